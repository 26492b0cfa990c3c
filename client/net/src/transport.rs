//! The QUIC side of the client configuration: quinn transport parameters and timeouts.

use std::sync::Arc;
use std::time::Duration;

use quinn::crypto::rustls::QuicClientConfig;
use quinn::{IdleTimeout, TransportConfig, VarInt};

use super::error::ClientError;
use super::tls::{Trust, rustls_client_config};

/// Server-opened unidirectional streams (one or a few treelets each) the server may have open at
/// once. Generous, so the server's in-flight window is never limited by stream credit.
pub const MAX_INCOMING_UNI_STREAMS: u32 = 1024;
/// Flow-control window of one treelet stream: more than a largest treelet message
/// ([`arbor_proto::limits::MAX_TREELET_MESSAGE_BYTES`]).
pub const STREAM_RECEIVE_WINDOW: u32 = 4 << 20;
/// Flow-control window of the whole connection: what the server may have sent that the client
/// has not read yet. Enough for a 1 Gbit/s × 100 ms path; it also bounds what QUIC buffers while
/// the client applies backpressure.
pub const RECEIVE_WINDOW: u32 = 16 << 20;
/// Receive buffer the client asks the kernel for on its UDP socket (granted up to the system's
/// limit, `net.core.rmem_max` on Linux). The default (about 208 KiB on Linux) overflowed while
/// the client was busy: a whole lion-4k fetched on loopback lost 5–20 % of its packets, each
/// loss a retransmission and a congestion-window cut; with 4 MiB none was lost.
pub const SOCKET_RECEIVE_BUFFER: usize = 4 << 20;
/// Initial congestion window of the client's own sending, which is request lists. A deep list
/// of a thousand items is 12 KB and one goes out every cycle. From quinn's default of about
/// 14 KB, the window grew too slowly over a 50 ms round trip, and lists queued in the send
/// buffer: measured over the link emulator after a camera jump, they reached the server up to
/// 125 ms late instead of 25 ms. Stale lists make the server resend what the client already holds
/// and react late to what it needs. The server's default is the same.
pub const INITIAL_WINDOW: u64 = 128 << 10;
/// Most bytes of request lists the client has written and the server not yet acknowledged
/// (QUIC's send window; lists are all the client sends), or the list's own size when larger.
/// A newer list waits until the ones before are acknowledged, and the lists the view went
/// through meanwhile are skipped: only the latest is sent. With quinn's default (about 10 MB)
/// lists queued in the send buffer whenever the uplink carried less than they came to: over a
/// 10 Mbit/s link with 1 % loss, where Cubic holds the uplink near 1.4 Mbit/s, lists reached
/// the server up to 30 s late and the server resent what the client already held, 78 % of the
/// treelets received (docs/measurements.md, stop 62). 32 KiB is about two ranked lists of the
/// client's default 4,096 items; with 16 KiB (one list in flight) the city's lists waited a
/// round trip behind each other on a clean 80 ms link, long enough for the server to resend
/// 5–8 % of the treelets. Where lists still wait here long, they get shorter
/// ([`crate::list_cap`]).
pub const LIST_SEND_WINDOW: u64 = 32 << 10;
/// A connection with nothing received for this long is lost.
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(30);
/// Keep-alive pings, so a quiet but healthy connection is never idle.
pub const KEEP_ALIVE: Duration = Duration::from_secs(5);
/// Longest wait for the QUIC/TLS handshake.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Longest wait for the server's answer (`SceneInfo` or `Error`) to `Hello`.
pub const HELLO_TIMEOUT: Duration = Duration::from_secs(10);
/// How long a graceful close waits for the `Goodbye` to be written and the close to be sent.
pub const CLOSE_TIMEOUT: Duration = Duration::from_secs(2);

/// The transport parameters the client offers, with `idle_timeout` (keep-alives every third
/// of it, at most every [`KEEP_ALIVE`]).
pub fn transport_config(idle_timeout: Duration) -> TransportConfig {
    let mut t = TransportConfig::default();
    let mut cubic = quinn::congestion::CubicConfig::default();
    cubic.initial_window(INITIAL_WINDOW);
    t.congestion_controller_factory(Arc::new(cubic));
    t.max_concurrent_uni_streams(VarInt::from_u32(MAX_INCOMING_UNI_STREAMS))
        // The client opens the only bidirectional stream; the server opens none.
        .max_concurrent_bidi_streams(VarInt::from_u32(0))
        .stream_receive_window(VarInt::from_u32(STREAM_RECEIVE_WINDOW))
        .receive_window(VarInt::from_u32(RECEIVE_WINDOW))
        .keep_alive_interval(Some(KEEP_ALIVE.min(idle_timeout / 3)))
        .max_idle_timeout(Some(
            IdleTimeout::try_from(idle_timeout.min(IDLE_TIMEOUT))
                .expect("at most 30 s fits a QUIC idle timeout"),
        ));
    t.send_window(LIST_SEND_WINDOW);
    t
}

/// The client's UDP socket on `bind`, with a receive buffer of [`SOCKET_RECEIVE_BUFFER`] or as
/// much of it as the system allows (less is not an error: the connection works, it just drops
/// more under bursts).
fn client_socket(bind: std::net::SocketAddr) -> std::io::Result<std::net::UdpSocket> {
    let socket = std::net::UdpSocket::bind(bind)?;
    let state = quinn::udp::UdpSocketState::new((&socket).into())?;
    if let Err(e) = state.set_recv_buffer_size((&socket).into(), SOCKET_RECEIVE_BUFFER) {
        tracing::debug!("the UDP receive buffer stays at the system default: {e}");
    }
    Ok(socket)
}

/// A client endpoint on `bind` over `client_socket`'s socket (quinn's `Endpoint::client` with a
/// larger receive buffer). Needs a tokio runtime.
pub fn client_endpoint(bind: std::net::SocketAddr) -> std::io::Result<quinn::Endpoint> {
    let runtime =
        quinn::default_runtime().ok_or_else(|| std::io::Error::other("no async runtime"))?;
    quinn::Endpoint::new(
        quinn::EndpointConfig::default(),
        None,
        client_socket(bind)?,
        runtime,
    )
}

/// The quinn client configuration for `trust` (TLS from [`rustls_client_config`]) with
/// `idle_timeout` (see [`transport_config`]) and `list_send_window` (see [`LIST_SEND_WINDOW`]).
pub fn quinn_client_config(
    trust: &Trust,
    idle_timeout: Duration,
    list_send_window: u64,
) -> Result<quinn::ClientConfig, ClientError> {
    let tls = rustls_client_config(trust)?;
    let quic = QuicClientConfig::try_from(Arc::new(tls))
        .map_err(|e| ClientError::InvalidConfig(format!("QUIC TLS configuration: {e}")))?;
    let mut config = quinn::ClientConfig::new(Arc::new(quic));
    let mut transport = transport_config(idle_timeout);
    transport.send_window(list_send_window);
    config.transport_config(Arc::new(transport));
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_client_socket_asks_for_a_larger_receive_buffer() {
        let socket = client_socket("127.0.0.1:0".parse().unwrap()).unwrap();
        let state = quinn::udp::UdpSocketState::new((&socket).into()).unwrap();
        let got = state.recv_buffer_size((&socket).into()).unwrap();
        let plain = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let default = state.recv_buffer_size((&plain).into()).unwrap();
        // Linux grants up to `net.core.rmem_max` (and reports twice what was set).
        let max: usize = std::fs::read_to_string("/proc/sys/net/core/rmem_max")
            .expect("net.core.rmem_max is readable")
            .trim()
            .parse()
            .expect("net.core.rmem_max is a number");
        assert!(
            max > default,
            "net.core.rmem_max ({max}) allows no receive buffer above the default ({default}): \
             nothing to check here"
        );
        assert!(
            got > default,
            "receive buffer {got} bytes, default {default}"
        );
    }
}
