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
    t
}

/// The quinn client configuration for `trust` (TLS from [`rustls_client_config`]) with
/// `idle_timeout` (see [`transport_config`]).
pub fn quinn_client_config(
    trust: &Trust,
    idle_timeout: Duration,
) -> Result<quinn::ClientConfig, ClientError> {
    let tls = rustls_client_config(trust)?;
    let quic = QuicClientConfig::try_from(Arc::new(tls))
        .map_err(|e| ClientError::InvalidConfig(format!("QUIC TLS configuration: {e}")))?;
    let mut config = quinn::ClientConfig::new(Arc::new(quic));
    config.transport_config(Arc::new(transport_config(idle_timeout)));
    Ok(config)
}
