//! One client connection: handshake, `Hello`, request lists, treelet streams, closing. This
//! file owns the handshake, `Hello` and the close; `handler.rs` the main loop after
//! `Hello`, `streams.rs` the treelet streams.
//!
//! # Life of a connection
//!
//! 1. The TLS handshake, the client's control stream and a complete `Hello` must all arrive
//!    within `hello_timeout_ms` of the connection's first packet, else the connection is closed
//!    with `ProtocolViolation`.
//! 2. `Hello` is checked: version (`UnsupportedVersion`, decided by the frame decoder from the
//!    first field), scene and token ([`super::access::AccessPolicy::admit`]: `UnknownScene`,
//!    `Unauthorized`), channels stored by the scene (`UnknownChannel`; over the limit:
//!    `TooManyChannels`). Success: `SceneInfo` with the stored description.
//! 3. Request lists are read with [`FrameDecoder::for_server`]: an over-limit length is refused
//!    from its 4 length bytes (`FrameTooLarge`), undecodable bytes are `ProtocolViolation`, a
//!    list over the length limit is `ListTooLong`, an id ≥ the scene's treelet count is
//!    `UnknownTreelet`, any frame but `RequestList`/`Goodbye` after `Hello` is
//!    `ProtocolViolation`. Each list goes to the shared scheduler; treelets in flight that the
//!    new list no longer names have their streams reset (code `CANCEL_CODE`: `NoError`).
//! 4. Treelets the dispatcher hands over are sent each on its own server-opened unidirectional
//!    stream, at a QUIC priority from their rank (the first treelet started under the newest list
//!    highest). Streams are opened in rank order by one opener per connection, so when the
//!    client's stream credit runs out the best-ranked waiting treelet gets the next stream.
//!    Finishing a stream reports `handle_sent` (and the request-to-send latency), its
//!    acknowledgement `handle_delivered`, a reset or failure `handle_cancelled`. A stream that
//!    ends unfinished is always reset, never left looking complete.
//! 5. On every delivered batch and every 50 ms the window is recomputed from quinn's RTT and
//!    congestion window (bandwidth ≈ cwnd / RTT, so the window is about one congestion window of
//!    treelets); every 50 ms the slow-reader watchdog runs: treelets in flight and no stream
//!    progress (opened, written, acknowledged) for `slow_reader_timeout_ms` → `SlowReader`.
//! 6. Closing with a code first writes an `Error` (or `Goodbye`) frame on the control stream and
//!    waits up to `CLOSE_FLUSH` (300 ms) for it to be acknowledged, then closes the connection with the
//!    same code and counts it in `errors_total`.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use arbor_proto::Channel;
use arbor_proto::frame::{FrameDecoder, encode};
use arbor_proto::wire::{
    ErrorCode, Frame, HELLO_GRANT_AVAILABLE, HELLO_SEND_ROOT, PROTOCOL_VERSION, ViewHint,
    error_message,
};
use bytes::Bytes;
use tracing::Instrument as _;

use super::access::Grant;
use super::handler;
use super::shared::{CLOSE_FLUSH, Shared};
use super::shutdown::{Done, Shutdown};
use super::state::SessionInfo;
use super::treelets::ServedScene;
use crate::pool::PoolError;

/// How a connection ends.
#[derive(Debug)]
pub(super) enum End {
    /// We close it with `code`, after sending `frame` on the control stream if there is one.
    Close {
        code: ErrorCode,
        reason: String,
        goodbye: bool,
    },
    /// The peer closed it, it timed out, or it was lost.
    Lost(quinn::ConnectionError),
}

pub(super) fn close(code: ErrorCode, reason: impl Into<String>) -> End {
    End::Close {
        code,
        reason: reason.into(),
        goodbye: false,
    }
}

/// The control stream's receive side with its frame decoder.
pub(super) struct ControlReader {
    recv: quinn::RecvStream,
    decoder: FrameDecoder,
    pending: Bytes,
}

impl ControlReader {
    /// The next frame; `Ok(None)` at the end of the stream. Cancel-safe: the only await is
    /// quinn's cancel-safe `read_chunk`, and partial state lives in `self`.
    pub(super) async fn read_frame(&mut self) -> Result<Option<Frame>, End> {
        loop {
            let mut took = 0;
            if !self.pending.is_empty() {
                took = self.decoder.push(&self.pending);
                let _ = self.pending.split_to(took);
            }
            match self.decoder.next() {
                Ok(Some(f)) => return Ok(Some(f)),
                Err(e) => return Err(close(e.code(), e.to_string())),
                Ok(None) if !self.pending.is_empty() && took == 0 => {
                    // The decoder neither took bytes nor produced a frame; it never does this,
                    // but a stuck stream must not spin.
                    return Err(close(
                        ErrorCode::ProtocolViolation,
                        "control stream stalled",
                    ));
                }
                Ok(None) if !self.pending.is_empty() => {}
                Ok(None) => match self.recv.read_chunk(64 * 1024, true).await {
                    Ok(Some(chunk)) => self.pending = chunk.bytes,
                    Ok(None) => {
                        return if self.decoder.buffered() > 0 {
                            Err(close(
                                ErrorCode::ProtocolViolation,
                                "control stream ended inside a frame",
                            ))
                        } else {
                            Ok(None)
                        };
                    }
                    Err(quinn::ReadError::ConnectionLost(e)) => return Err(End::Lost(e)),
                    Err(quinn::ReadError::Reset(code)) => {
                        return Err(close(
                            ErrorCode::ProtocolViolation,
                            format!("control stream reset by the client (code {code})"),
                        ));
                    }
                    Err(e) => {
                        return Err(close(
                            ErrorCode::ProtocolViolation,
                            format!("control stream: {e}"),
                        ));
                    }
                },
            }
        }
    }
}

/// Serves one incoming connection to its end. Holds `_done` until then (drop-to-finish).
pub(crate) async fn run(
    shared: Arc<Shared>,
    incoming: quinn::Incoming,
    shutdown: Shutdown,
    _done: Done,
) {
    let id = shared.next_connection_id();
    let peer = incoming.remote_address();
    let span = tracing::info_span!("conn", id = id.0, %peer, scene = tracing::field::Empty);
    async move {
        let deadline = tokio::time::Instant::now() + shared.config.hello_timeout();
        let (accepted, observer) = match shared.server_config_for(peer.ip()) {
            Some((own, observer)) => (incoming.accept_with(own), Some(observer)),
            None => (incoming.accept(), None),
        };
        let connecting = match accepted {
            Ok(c) => c,
            Err(e) => {
                tracing::debug!("accept failed: {e}");
                return;
            }
        };
        let conn = match tokio::time::timeout_at(deadline, connecting).await {
            Ok(Ok(c)) => c,
            Ok(Err(e)) => {
                tracing::info!("handshake failed: {e}");
                return;
            }
            Err(_) => {
                tracing::info!("handshake not complete within the hello timeout");
                return;
            }
        };
        let m = &shared.state.metrics;
        m.connections_accepted.fetch_add(1, Ordering::Relaxed);
        m.connections_open.fetch_add(1, Ordering::Relaxed);
        shared.state.add_session(SessionInfo::new(id.0, peer));
        tracing::debug!("connected");

        let mut control = None;
        let end = handler::serve(&shared, id, &conn, shutdown, deadline, &mut control).await;
        shared.handle_close(peer.ip(), &conn, observer.as_deref());

        // Unregister before closing so no treelet is offered to a dying connection.
        {
            let mut core = shared.core();
            core.sched.remove_connection(id);
            core.routes.remove(&id);
        }
        shared.wake.notify_one();
        match end {
            End::Close {
                code,
                reason,
                goodbye,
            } => {
                if let Some(mut send) = control {
                    let frame = if goodbye {
                        Frame::Goodbye { code }
                    } else {
                        Frame::error(code, reason.clone())
                    };
                    if let Ok(bytes) = encode(&frame) {
                        let _ = tokio::time::timeout(CLOSE_FLUSH, async {
                            send.write_all(&bytes).await.ok()?;
                            send.finish().ok()?;
                            send.stopped().await.ok()
                        })
                        .await;
                    }
                }
                // The reason in the close frame too: a client that has not read the `Error`
                // frame when the connection closes (a busy one: the flush above is bounded)
                // still learns why, not just the code. Quinn cuts it to fit a packet.
                conn.close(
                    quinn::VarInt::from_u32(code.to_u32()),
                    error_message(reason.as_str()).as_bytes(),
                );
                shared.state.metrics.error(code);
                if matches!(code, ErrorCode::NoError | ErrorCode::ShuttingDown) {
                    tracing::info!(%code, "closed: {reason}");
                } else {
                    tracing::warn!(%code, "closed: {reason}");
                }
            }
            End::Lost(e) => tracing::info!("connection ended: {e}"),
        }
        shared.access.leave(id.0);
        if let Some(s) = shared.state.remove_session(id.0) {
            tracing::debug!(
                lists = s.request_lists,
                treelets = s.treelets_sent,
                bytes = s.bytes_sent,
                "session summary"
            );
        }
        m.connections_open.fetch_sub(1, Ordering::Relaxed);
    }
    .instrument(span)
    .await
}

/// Waits for the control stream and `Hello`, then answers `SceneInfo`.
/// A client that passed `Hello`.
pub(super) struct Greeting {
    /// The control stream's receive side.
    pub reader: ControlReader,
    /// The scene it is served.
    pub scene: Arc<ServedScene>,
    /// The channels it receives, ascending by id.
    pub channels: Vec<Channel>,
    /// It asked for the root treelet unasked ([`HELLO_SEND_ROOT`]).
    pub send_root: bool,
    /// The view to push the root's refinement for ([`arbor_proto::wire::HELLO_VIEW`]; the
    /// decoder checked it and that it comes with [`HELLO_SEND_ROOT`]).
    pub view: Option<ViewHint>,
    /// What it was let in with, for the scene rules that may replace these.
    pub grant: Grant,
}

pub(super) async fn hello(
    shared: &Shared,
    conn: &quinn::Connection,
    control: &mut Option<quinn::SendStream>,
) -> Result<Greeting, End> {
    let (send, recv) = conn.accept_bi().await.map_err(End::Lost)?;
    *control = Some(send);
    let mut reader = ControlReader {
        recv,
        decoder: FrameDecoder::for_server(),
        pending: Bytes::new(),
    };
    let frame = match reader.read_frame().await? {
        Some(f) => f,
        None => {
            return Err(close(
                ErrorCode::ProtocolViolation,
                "control stream ended before Hello",
            ));
        }
    };
    let Frame::Hello {
        version,
        scene,
        mut channels,
        token,
        flags,
        view,
    } = frame
    else {
        return Err(close(
            ErrorCode::ProtocolViolation,
            format!("expected Hello, got {:?}", frame.frame_type()),
        ));
    };
    if version != PROTOCOL_VERSION {
        return Err(close(
            ErrorCode::UnsupportedVersion,
            format!("protocol version {version}, this server speaks {PROTOCOL_VERSION}"),
        ));
    }
    let pool = &shared.pool;
    let admitted = shared
        .access
        .policy()
        .admit(&scene, &token, |s| pool.contains(s).unwrap_or(false));
    let grant = match admitted {
        Ok(grant) => grant,
        Err(code) => {
            let reason = match code {
                ErrorCode::UnknownScene => format!("no scene named {scene:?}"),
                _ => format!("access to scene {scene:?} denied"),
            };
            return Err(close(code, reason));
        }
    };
    let stored = match pool.scene(&scene) {
        Ok(s) => s,
        Err(PoolError::NoSuchScene(_)) => {
            return Err(close(
                ErrorCode::UnknownScene,
                format!("no scene named {scene:?}"),
            ));
        }
        Err(e) => {
            tracing::error!("reading scene {scene:?}: {e}");
            return Err(close(ErrorCode::Internal, "the pool failed to read"));
        }
    };
    if flags & HELLO_GRANT_AVAILABLE != 0 {
        channels.retain(|c| stored.description.layout.contains(*c));
    } else if let Some(c) = channels
        .iter()
        .find(|c| !stored.description.layout.contains(**c))
    {
        return Err(close(
            ErrorCode::UnknownChannel,
            format!("scene {scene:?} has no {} channel", c.name()),
        ));
    }
    channels.sort_by_key(|c| c.id());
    let description = Box::new(stored.description.clone());
    let served = shared.served_scene(stored);
    let bytes = encode(&Frame::SceneInfo { description }).map_err(|e| {
        tracing::error!("encoding SceneInfo: {e}");
        close(ErrorCode::Internal, "scene description does not encode")
    })?;
    let send = control
        .as_mut()
        .ok_or_else(|| close(ErrorCode::Internal, "no control stream"))?;
    send.write_all(&bytes).await.map_err(|e| match e {
        quinn::WriteError::ConnectionLost(e) => End::Lost(e),
        e => close(ErrorCode::ProtocolViolation, format!("control stream: {e}")),
    })?;
    tracing::Span::current().record("scene", scene.as_str());
    Ok(Greeting {
        reader,
        scene: served,
        channels,
        send_root: flags & HELLO_SEND_ROOT != 0,
        view,
        grant,
    })
}
