//! The connection task: connect, say `Hello`, then send request lists, read treelet streams
//! and control frames concurrently until the connection ends; reconnect with backoff unless the
//! end is final.

use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr};
use std::sync::Arc;
use std::time::Instant;

use arbor_proto::frame::{FrameDecoder, encode};
use arbor_proto::wire::{ErrorCode, Frame, ViewHint};
use arbor_proto::{SceneDescription, TreeletId};
use bytes::{Buf, Bytes};
use quinn::{ConnectError, Connection, ConnectionError, Endpoint, RecvStream, SendStream, VarInt};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;
use tokio::time::timeout;

use super::backoff::Jitter;
use super::config::ClientConfig;
use super::event::ClientEvent;
use super::list_cap::ListCap;
use super::replicas::Replicas;
use super::shared::{Queued, Shared};
use super::stream::{LocalClose, StreamContext, close_locally, read_stream};
use super::transport::{CLOSE_TIMEOUT, HANDSHAKE_TIMEOUT, HELLO_TIMEOUT, client_endpoint};
use super::url::ServerUrl;

/// The latest request list, shared between the handle and the task.
pub(crate) type RequestList = Arc<Wishes>;

/// What a request list says: the items, and for a deep list the view and each item's error.
#[derive(Debug)]
pub(crate) struct Wishes {
    pub items: Vec<(TreeletId, f32)>,
    /// The view, the errors (one per item) and the index of the first prefetch item of a
    /// [`Frame::DeepRequestList`].
    pub deep: Option<(ViewHint, Vec<f32>, usize)>,
}

impl Wishes {
    /// Whether `other` says exactly the same, bit for bit: sending it again would change
    /// nothing at the server (it keeps the last list's order, errors and view) and only cost
    /// upstream bytes — a deep list of a thousand items is 12 KB, and in a view's tail the
    /// same list comes every cycle until its treelets arrive.
    fn same_as(&self, other: &Wishes) -> bool {
        let same = |a: f32, b: f32| a.to_bits() == b.to_bits();
        self.items.len() == other.items.len()
            && self
                .items
                .iter()
                .zip(&other.items)
                .all(|(a, b)| a.0 == b.0 && same(a.1, b.1))
            && match (&self.deep, &other.deep) {
                (None, None) => true,
                // Views are checked finite, so `==` is exact (the free slots included); the
                // errors come one per item, so their lengths already agree.
                (Some((va, ea, pa)), Some((vb, eb, pb))) => {
                    va == vb && pa == pb && ea.iter().zip(eb).all(|(&a, &b)| same(a, b))
                }
                _ => false,
            }
    }
}

/// Whether a close code means reconnecting cannot help (the configuration is wrong): the scene,
/// the token, the protocol version or the channels. Every other code, and a connection lost
/// without a code, leads to a reconnect with backoff.
pub fn is_final_code(code: ErrorCode) -> bool {
    matches!(
        code,
        ErrorCode::Unauthorized
            | ErrorCode::UnknownScene
            | ErrorCode::UnsupportedVersion
            | ErrorCode::UnknownChannel
            | ErrorCode::TooManyChannels
    )
}

/// How one connection (or attempt) ended.
#[derive(Debug)]
struct Ending {
    code: Option<ErrorCode>,
    reason: String,
    retry: bool,
    connected: bool,
}

enum Outcome {
    Ended(Ending),
    /// The caller closed the client.
    Shutdown,
}

fn failed(reason: String, retry: bool) -> Outcome {
    Outcome::Ended(Ending {
        code: None,
        reason,
        retry,
        connected: false,
    })
}

/// Resolves once the caller asked to close (or dropped the handle).
async fn shutdown_requested(rx: &mut watch::Receiver<bool>) {
    let _ = rx.wait_for(|&stop| stop).await;
}

pub(crate) struct Task {
    pub config: ClientConfig,
    /// The URL and its replicas, and which one is in use.
    pub replicas: Replicas,
    pub quinn_config: quinn::ClientConfig,
    /// The encoded `Hello` frame with the view, for connections until one is established.
    pub first_hello: Option<Vec<u8>>,
    /// The encoded `Hello` frame.
    pub hello: Vec<u8>,
    pub shared: Arc<Shared>,
    pub events: mpsc::UnboundedSender<Queued>,
    pub lists: watch::Receiver<Option<RequestList>>,
    pub shutdown: watch::Receiver<bool>,
    pub jitter: Jitter,
    /// Index of the resolved address to try next; kept while connections succeed.
    pub next_addr: usize,
    /// The server of the last established connection, to count failovers.
    pub last_server: Option<ServerUrl>,
}

impl Task {
    pub async fn run(mut self) {
        let mut endpoint: Option<Endpoint> = None;
        let mut attempt = 0u32;
        let mut next_seq = 1u64;
        loop {
            let ending = match self.session(&mut endpoint, &mut next_seq).await {
                Outcome::Shutdown => break,
                Outcome::Ended(e) => e,
            };
            if ending.connected {
                attempt = 0;
            }
            // A lost connection moves to the next replica at once; failed attempts move on too,
            // with backoff.
            let lost = ending.connected && self.replicas.can_fail_over();
            if ending.retry && self.replicas.advance() {
                self.next_addr = 0;
            }
            let reconnect_in = ending.retry.then(|| {
                if lost {
                    return std::time::Duration::ZERO;
                }
                let d = self.config.backoff.delay(attempt, &mut self.jitter);
                attempt = attempt.saturating_add(1);
                d
            });
            {
                let mut s = self.shared.stats();
                s.disconnects += 1;
                if ending.code.is_some() {
                    s.last_close_code = ending.code;
                }
            }
            tracing::info!(
                url = %self.last_server.as_ref().unwrap_or(&self.config.url),
                next = %self.replicas.current(),
                code = ?ending.code,
                reason = %ending.reason,
                ?reconnect_in,
                "disconnected"
            );
            let _ = self.events.send(Queued::plain(ClientEvent::Disconnected {
                code: ending.code,
                reason: ending.reason,
                reconnect_in,
            }));
            let Some(delay) = reconnect_in else { break };
            tokio::select! {
                _ = tokio::time::sleep(delay) => {}
                _ = shutdown_requested(&mut self.shutdown) => break,
            }
        }
        if let Some(ep) = endpoint {
            ep.close(VarInt::from_u32(ErrorCode::NoError.to_u32()), b"");
            let _ = timeout(CLOSE_TIMEOUT, ep.wait_idle()).await;
        }
    }

    /// One connection attempt and, if it succeeds, the connection's life.
    async fn session(&mut self, endpoint: &mut Option<Endpoint>, next_seq: &mut u64) -> Outcome {
        let url = &self.replicas.current().clone();
        let resolved = tokio::select! {
            r = tokio::net::lookup_host((url.host.as_str(), url.port)) => r,
            _ = shutdown_requested(&mut self.shutdown) => return Outcome::Shutdown,
        };
        let addrs: Vec<SocketAddr> = match resolved {
            Ok(a) => a.collect(),
            Err(e) => return failed(format!("cannot resolve {}: {e}", url.host), true),
        };
        if addrs.is_empty() {
            return failed(format!("{} has no address", url.host), true);
        }
        // Each failed attempt moves on to the host's next address.
        let addr = addrs[self.next_addr % addrs.len()];
        self.next_addr = self.next_addr.wrapping_add(1);
        let ep = match endpoint_for(endpoint, addr) {
            Ok(ep) => ep,
            Err(e) => return failed(format!("cannot open a UDP socket: {e}"), true),
        };
        let connecting = match ep.connect_with(self.quinn_config.clone(), addr, &url.host) {
            Ok(c) => c,
            Err(ConnectError::InvalidServerName(name)) => {
                return failed(format!("{name:?} is not a valid TLS server name"), false);
            }
            Err(e) => return failed(format!("cannot connect to {addr}: {e}"), true),
        };
        let conn = tokio::select! {
            r = timeout(HANDSHAKE_TIMEOUT, connecting) => match r {
                Ok(Ok(conn)) => conn,
                Ok(Err(e)) => {
                    return Outcome::Ended(ending_from(e, &LocalClose::default(), None, false));
                }
                Err(_) => {
                    return failed(
                        format!("no QUIC handshake with {addr} within {HANDSHAKE_TIMEOUT:?}"),
                        true,
                    );
                }
            },
            _ = shutdown_requested(&mut self.shutdown) => return Outcome::Shutdown,
        };
        tracing::debug!(%addr, "QUIC connection established");

        let local_close = LocalClose::default();
        let mut remote: Option<(ErrorCode, String)> = None;
        let setup = tokio::select! {
            r = setup(&conn, self.first_hello.as_ref().unwrap_or(&self.hello)) => r,
            _ = shutdown_requested(&mut self.shutdown) => {
                close_gracefully(&conn, None).await;
                return Outcome::Shutdown;
            }
        };
        let (mut send, mut control, scene) = match setup {
            Ok(ok) => ok,
            Err(SetupError::Refused(code, message)) => {
                remote = Some((code, message));
                let err = wait_closed(&conn, &local_close, true).await;
                return Outcome::Ended(ending_from(err, &local_close, remote, false));
            }
            Err(SetupError::Violation(reason)) => {
                close_locally(&conn, &local_close, ErrorCode::ProtocolViolation, reason);
                return Outcome::Ended(ending_from(conn.closed().await, &local_close, None, false));
            }
            Err(SetupError::Ended) => {
                let err = wait_closed(&conn, &local_close, false).await;
                return Outcome::Ended(ending_from(err, &local_close, None, false));
            }
        };

        // Connected: stay with this address next time.
        self.next_addr = self.next_addr.wrapping_sub(1);
        if let Err(reason) = self.replicas.admit(&scene) {
            tracing::error!(%reason, "refusing a replica");
            close_gracefully(&conn, Some(&mut send)).await;
            return failed(reason, true);
        }
        self.note_connected(url, &scene);

        let ctx = Arc::new(StreamContext {
            shared: self.shared.clone(),
            events: self.events.clone(),
            conn: conn.clone(),
            local_close: local_close.clone(),
            channels: self.config.channels.clone(),
            treelet_count: scene.treelet_count,
            treelet_nodes: scene.treelet_nodes,
        });
        let mut readers = JoinSet::new();
        let stopped = tokio::select! {
            why = send_lists(&conn, &mut send, &mut self.lists, &self.shared, &scene, next_seq, &self.config) => Some(why),
            end = read_control(&mut control, &mut remote) => match end {
                ControlEnd::Violation(reason) => {
                    close_locally(&conn, &local_close, ErrorCode::ProtocolViolation, reason.clone());
                    Some(reason)
                }
                ControlEnd::Ended(why) => Some(why),
            },
            err = accept_streams(&conn, &mut readers, ctx) => Some(err.to_string()),
            _ = shutdown_requested(&mut self.shutdown) => None,
        };
        let Some(why) = stopped else {
            close_gracefully(&conn, Some(&mut send)).await;
            readers.shutdown().await;
            return Outcome::Shutdown;
        };
        tracing::debug!(%why, "connection ending");
        let err = wait_closed(&conn, &local_close, remote.is_some()).await;
        // No treelet event may follow the Disconnected event.
        readers.shutdown().await;
        Outcome::Ended(ending_from(err, &local_close, remote, true))
    }

    /// Records a greeted connection to `url` (counting a failover when the server changed) and
    /// tells the application.
    fn note_connected(&mut self, url: &ServerUrl, scene: &Arc<SceneDescription>) {
        // A reconnection keeps the slot buffer: the root's refinement is not pushed again.
        self.first_hello = None;
        {
            let mut stats = self.shared.stats();
            if self.last_server.as_ref().is_some_and(|s| s != url) {
                stats.failovers += 1;
            }
            stats.server = Some(url.clone());
            stats.connects += 1;
        }
        self.last_server = Some(url.clone());
        if scene.name != url.scene {
            tracing::warn!(asked = %url.scene, got = %scene.name, "server named the scene differently");
        }
        self.shared.set_scene(scene.clone());
        tracing::info!(url = %url, treelets = scene.treelet_count, "connected");
        let _ = self
            .events
            .send(Queued::plain(ClientEvent::Connected(scene.clone())));
    }
}

/// The client endpoint for `addr`'s address family, reused while the family stays the same.
fn endpoint_for(slot: &mut Option<Endpoint>, addr: SocketAddr) -> std::io::Result<Endpoint> {
    if let Some(ep) = slot
        && ep.local_addr()?.is_ipv6() == addr.is_ipv6()
    {
        return Ok(ep.clone());
    }
    let bind: SocketAddr = if addr.is_ipv6() {
        (Ipv6Addr::UNSPECIFIED, 0).into()
    } else {
        (Ipv4Addr::UNSPECIFIED, 0).into()
    };
    let ep = client_endpoint(bind)?;
    if let Some(old) = slot.replace(ep.clone()) {
        old.close(VarInt::from_u32(ErrorCode::NoError.to_u32()), b"");
    }
    Ok(ep)
}

/// The server's control stream: bytes in, frames out.
struct Control {
    recv: RecvStream,
    decoder: FrameDecoder,
    pending: Bytes,
}

enum ControlEnd {
    /// The server sent something it must not.
    Violation(String),
    /// The stream finished or the connection is going away.
    Ended(String),
}

impl Control {
    fn new(recv: RecvStream) -> Self {
        Self {
            recv,
            decoder: FrameDecoder::for_client(),
            pending: Bytes::new(),
        }
    }

    async fn next_frame(&mut self) -> Result<Frame, ControlEnd> {
        loop {
            match self.decoder.next() {
                Ok(Some(frame)) => return Ok(frame),
                Ok(None) => {}
                Err(e) => return Err(ControlEnd::Violation(format!("control stream: {e}"))),
            }
            if self.pending.is_empty() {
                match self.recv.read_chunk(64 * 1024, true).await {
                    Ok(Some(chunk)) => self.pending = chunk.bytes,
                    Ok(None) => return Err(ControlEnd::Ended("control stream finished".into())),
                    Err(e) => return Err(ControlEnd::Ended(format!("control stream: {e}"))),
                }
            }
            // The decoder holds at most one maximal frame, so when it takes nothing it has a
            // whole frame (or an error) for the next turn.
            let n = self.decoder.push(&self.pending);
            self.pending.advance(n);
        }
    }
}

enum SetupError {
    /// The server answered `Hello` with an `Error` frame.
    Refused(ErrorCode, String),
    Violation(String),
    /// The connection went away.
    Ended,
}

/// Opens the control stream, sends `Hello` and waits for `SceneInfo`.
async fn setup(
    conn: &Connection,
    hello: &[u8],
) -> Result<(SendStream, Control, Arc<SceneDescription>), SetupError> {
    let (mut send, recv) = conn.open_bi().await.map_err(|_| SetupError::Ended)?;
    send.write_all(hello).await.map_err(|_| SetupError::Ended)?;
    let mut control = Control::new(recv);
    let frame = match timeout(HELLO_TIMEOUT, control.next_frame()).await {
        Ok(Ok(frame)) => frame,
        Ok(Err(ControlEnd::Violation(reason))) => return Err(SetupError::Violation(reason)),
        Ok(Err(ControlEnd::Ended(_))) => return Err(SetupError::Ended),
        Err(_) => {
            return Err(SetupError::Violation(format!(
                "no answer to Hello within {HELLO_TIMEOUT:?}"
            )));
        }
    };
    match frame {
        Frame::SceneInfo { description } => Ok((send, control, Arc::from(description))),
        Frame::Error { code, message } => Err(SetupError::Refused(code, message)),
        Frame::Goodbye { code } => Err(SetupError::Refused(code, "server said goodbye".into())),
        other => Err(SetupError::Violation(format!(
            "expected SceneInfo, got a {:?} frame",
            other.frame_type()
        ))),
    }
}

/// Sends the latest request list now and whenever it changes, with at most the config's
/// `list_send_window` bytes of lists unacknowledged (or the list's own size when larger, so that
/// a large list still leaves in one flight; see [`crate::transport::LIST_SEND_WINDOW`]). A list
/// waits for those before to be acknowledged; the lists the view goes through meanwhile are
/// skipped and the latest goes next. While lists wait long, ranked ones carry only their head
/// (`adaptive_list_cap`, [`crate::list_cap`]). Returns only when writing fails.
async fn send_lists(
    conn: &quinn::Connection,
    send: &mut SendStream,
    lists: &mut watch::Receiver<Option<RequestList>>,
    shared: &Shared,
    scene: &SceneDescription,
    next_seq: &mut u64,
    config: &ClientConfig,
) -> String {
    // A new connection gets the latest list at once.
    lists.mark_changed();
    let mut last: Option<RequestList> = None;
    let mut cap = config.adaptive_list_cap.then(ListCap::default);
    loop {
        if lists.changed().await.is_err() {
            // The handle is gone; the shutdown signal ends the session.
            std::future::pending::<()>().await;
        }
        // Compared while borrowed: an unchanged list is neither copied nor sent, and a new one
        // is copied once, into `last`, and sent from there.
        let list = {
            let latest = lists.borrow_and_update();
            let Some(list) = latest.as_ref() else {
                continue;
            };
            if last.as_ref().is_some_and(|l| l.same_as(list)) {
                shared.stats().lists_unchanged += 1;
                continue;
            }
            list.clone()
        };
        let list = &*last.insert(list);
        let keep = |id: TreeletId| id.0 < scene.treelet_count;
        let kept = list.items.iter().filter(|(id, _)| keep(*id)).count();
        if kept < list.items.len() {
            tracing::warn!(
                dropped = list.items.len() - kept,
                treelets = scene.treelet_count,
                "request list names treelets the scene does not have; not sending them"
            );
        }
        let seq = *next_seq;
        *next_seq += 1;
        // Plain lists (the thesis's loop) go whole; ranked ones, in serving order, at most the
        // cap's head (`list_cap`).
        let full = kept;
        let frame = match &list.deep {
            None => Frame::RequestList {
                seq,
                items: list
                    .items
                    .iter()
                    .copied()
                    .filter(|(id, _)| keep(*id))
                    .collect(),
            },
            Some((view, errors, prefetch_from)) => {
                let (mut items, prefetch_from) =
                    ranked_items(&list.items, errors, *prefetch_from, keep);
                items.truncate(cap.as_ref().map_or(full, |c| c.apply(full)));
                Frame::RankedRequestList {
                    seq,
                    view: *view,
                    prefetch_from: prefetch_from.min(items.len() as u32),
                    items,
                }
            }
        };
        let bytes = match encode(&frame) {
            Ok(b) => b,
            Err(e) => {
                // `request` validated the list, so this is a bug; skip the list, keep going.
                tracing::error!(error = %e, "cannot encode a request list");
                continue;
            }
        };
        let now = Instant::now();
        // What the server is asked for: a ranked list's head, or every kept item.
        let sent = match &frame {
            Frame::RankedRequestList { items, .. } => {
                shared.latency().list_sent(items.iter().map(|i| i.0), now);
                items.len()
            }
            _ => {
                let ids = list.items.iter().map(|i| i.0).filter(|id| keep(*id));
                shared.latency().list_sent(ids, now);
                full
            }
        };
        conn.set_send_window(config.list_send_window.max(bytes.len() as u64));
        if let Err(e) = send.write_all(&bytes).await {
            return format!("writing request list {seq}: {e}");
        }
        if let Some(cap) = &mut cap {
            let before = cap.cap();
            cap.handle_written(Instant::now(), full, sent, now.elapsed(), conn.rtt());
            if cap.cap() != before {
                tracing::debug!(cap = ?cap.cap(), full, "request list cap");
            }
        }
        {
            let mut stats = shared.stats();
            stats.lists_sent += 1;
            if sent < full {
                stats.lists_capped += 1;
            }
        }
        tracing::trace!(seq, sent, full, "request list sent");
    }
}

/// A deep list's items as a [`Frame::RankedRequestList`] carries them, and its prefetch start:
/// those `keep` accepts, in the order the server would serve them (priority, highest first,
/// ties by lower id; the items before `prefetch_from` ahead of the prefetch), errors in steps.
/// The rank then says what the priorities said, in a third of a deep list's bytes: lists go up
/// every cycle, and an uplink may be a tenth of the downlink.
fn ranked_items(
    items: &[(TreeletId, f32)],
    errors: &[f32],
    prefetch_from: usize,
    keep: impl Fn(TreeletId) -> bool,
) -> (Vec<(TreeletId, i16)>, u32) {
    let mut kept: Vec<(bool, TreeletId, f32, f32)> = items
        .iter()
        .zip(errors)
        .enumerate()
        .filter(|(_, ((id, _), _))| keep(*id))
        .map(|(i, (&(id, p), &e))| (i >= prefetch_from, id, p, e))
        .collect();
    kept.sort_by(|a, b| {
        (a.0.cmp(&b.0))
            .then(b.2.total_cmp(&a.2))
            .then(a.1.cmp(&b.1))
    });
    let prefetch_from = kept.iter().take_while(|k| !k.0).count() as u32;
    let ranked = kept
        .into_iter()
        .map(|(_, id, _, e)| (id, arbor_proto::wire::error_steps(e)))
        .collect();
    (ranked, prefetch_from)
}

/// Reads control frames after `SceneInfo`: `Error` and `Goodbye` are remembered (the close
/// follows); anything else is a violation.
async fn read_control(
    control: &mut Control,
    remote: &mut Option<(ErrorCode, String)>,
) -> ControlEnd {
    loop {
        match control.next_frame().await {
            Ok(Frame::Error { code, message }) => {
                tracing::info!(%code, %message, "server sent an error");
                *remote = Some((code, message));
            }
            Ok(Frame::Goodbye { code }) => {
                tracing::info!(%code, "server said goodbye");
                remote.get_or_insert((code, "server said goodbye".into()));
            }
            Ok(other) => {
                return ControlEnd::Violation(format!(
                    "unexpected {:?} frame from the server",
                    other.frame_type()
                ));
            }
            Err(end) => return end,
        }
    }
}

/// Accepts treelet streams while the buffer has room, one reader task each.
async fn accept_streams(
    conn: &Connection,
    readers: &mut JoinSet<()>,
    ctx: Arc<StreamContext>,
) -> ConnectionError {
    loop {
        // Backpressure: no new stream while the caller's buffer is full.
        ctx.shared.wait_for_room().await;
        match conn.accept_uni().await {
            Ok(recv) => {
                readers.spawn(read_stream(recv, ctx.clone()));
            }
            Err(e) => return e,
        }
        while readers.try_join_next().is_some() {}
    }
}

/// Waits for the connection to close. A server that said why (`Error`, `Goodbye`) or ended
/// the control stream gets [`CLOSE_TIMEOUT`] to close it; then the client closes.
async fn wait_closed(conn: &Connection, local: &LocalClose, said_why: bool) -> ConnectionError {
    if let Ok(err) = timeout(CLOSE_TIMEOUT, conn.closed()).await {
        return err;
    }
    let (code, reason) = if said_why {
        (
            ErrorCode::NoError,
            "server did not close after its last frame",
        )
    } else {
        (
            ErrorCode::ProtocolViolation,
            "server ended the control stream without closing",
        )
    };
    close_locally(conn, local, code, reason.into());
    conn.closed().await
}

/// The caller closes: `Goodbye`, finish the control stream, wait (bounded) until the server
/// has it — a close discards stream data not yet delivered — and close with `NoError`.
async fn close_gracefully(conn: &Connection, send: Option<&mut SendStream>) {
    if let Some(send) = send {
        let goodbye = encode(&Frame::Goodbye {
            code: ErrorCode::NoError,
        });
        let _ = timeout(CLOSE_TIMEOUT, async {
            if let Ok(bytes) = goodbye {
                send.write_all(&bytes).await.ok()?;
            }
            send.finish().ok()?;
            send.stopped().await.ok()
        })
        .await;
    }
    conn.close(
        VarInt::from_u32(ErrorCode::NoError.to_u32()),
        b"client closed",
    );
}

/// Turns how a connection closed into the caller's terms.
fn ending_from(
    err: ConnectionError,
    local: &LocalClose,
    remote: Option<(ErrorCode, String)>,
    connected: bool,
) -> Ending {
    let local = local.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let remote_code = remote.as_ref().map(|r| r.0);
    let is_crypto = |code: u64| (0x100..0x200).contains(&code);
    let (code, reason, mut retry) = match err {
        ConnectionError::ApplicationClosed(close) => {
            let number = close.error_code.into_inner();
            let code = u32::try_from(number).ok().and_then(ErrorCode::from_u32);
            let mut text = String::from_utf8_lossy(&close.reason).into_owned();
            if let Some((_, message)) = &remote {
                if text.is_empty() || text == *message {
                    text = message.clone();
                } else {
                    text = format!("{text} ({message})");
                }
            }
            let name = code.map_or_else(|| format!("unknown code {number}"), |c| c.to_string());
            (
                code,
                format!("server closed the connection: {name}: {text}"),
                true,
            )
        }
        ConnectionError::LocallyClosed => match local {
            Some((code, why)) => (
                Some(code),
                format!("client closed the connection: {code}: {why}"),
                true,
            ),
            None => (None, "connection closed by the client".into(), true),
        },
        ConnectionError::TimedOut => (
            remote_code,
            "connection timed out: no answer from the server".into(),
            true,
        ),
        ConnectionError::Reset => (
            remote_code,
            "connection reset by the server (it may have restarted)".into(),
            true,
        ),
        ConnectionError::TransportError(e) => {
            let crypto = is_crypto(e.code.into());
            let what = if crypto {
                "TLS handshake failed"
            } else {
                "transport error"
            };
            (None, format!("{what}: {e}"), !crypto)
        }
        ConnectionError::ConnectionClosed(close) => {
            let crypto = is_crypto(close.error_code.into());
            // An application close before the handshake completes travels as this transport
            // code (RFC 9000 §10.2.3): the server gave up on the handshake, which it does when
            // its hello timeout runs out.
            let unfinished_handshake =
                !connected && close.error_code == quinn::TransportErrorCode::APPLICATION_ERROR;
            let what = if crypto {
                "server refused the TLS handshake"
            } else if unfinished_handshake {
                "server closed the connection before the handshake completed (its hello \
                 timeout ran out: a slow or very lossy link?)"
            } else {
                "server aborted the connection"
            };
            (None, format!("{what}: {close}"), !crypto)
        }
        ConnectionError::VersionMismatch => (
            None,
            "server supports no QUIC version this client speaks".into(),
            false,
        ),
        ConnectionError::CidsExhausted => (None, "connection ids exhausted".into(), true),
    };
    let code = code.or(remote_code);
    if code.is_some_and(is_final_code) {
        retry = false;
    }
    Ending {
        code,
        reason,
        retry,
        connected,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranked_items_are_in_serving_order_with_the_prefetch_after() {
        let items = [
            (TreeletId(9), 1.0),
            (TreeletId(4), 3.0),
            (TreeletId(7), 3.0),
            (TreeletId(99), 9.0),
            (TreeletId(2), -5.0),
            // The prefetch: its priorities may exceed the listed ones; it still comes after.
            (TreeletId(30), 0.5),
            (TreeletId(20), 8.0),
            (TreeletId(25), 8.0),
        ];
        let errors = [1.0, 2.0, 3.0, 4.0, -64.0, 0.25, 63.0, 0.0];
        let keep = |id: TreeletId| id.0 < 50;
        let (ranked, prefetch_from) = ranked_items(&items, &errors, 5, keep);
        let ids: Vec<u32> = ranked.iter().map(|(id, _)| id.0).collect();
        assert_eq!(ids, [4, 7, 9, 2, 20, 25, 30], "99 is not in the scene");
        assert_eq!(prefetch_from, 4);
        let steps: Vec<i16> = ranked.iter().map(|&(_, e)| e).collect();
        assert_eq!(steps, [1024, 1536, 512, -i16::MAX, 32256, 0, 128]);
        // Nothing prefetched, or everything.
        assert_eq!(ranked_items(&items, &errors, 8, keep).1, 7);
        assert_eq!(ranked_items(&items, &errors, 0, keep).1, 0);
    }

    #[test]
    fn a_handshake_the_server_gave_up_on_is_named() {
        let closed = |error_code| {
            ConnectionError::ConnectionClosed(quinn::ConnectionClose {
                error_code,
                frame_type: None,
                reason: Bytes::new(),
            })
        };
        let app = quinn::TransportErrorCode::APPLICATION_ERROR;
        let ending = ending_from(closed(app), &LocalClose::default(), None, false);
        assert!(
            ending.reason.contains("before the handshake completed") && ending.retry,
            "{}",
            ending.reason
        );
        let other = quinn::TransportErrorCode::PROTOCOL_VIOLATION;
        let ending = ending_from(closed(other), &LocalClose::default(), None, false);
        assert!(
            ending.reason.starts_with("server aborted the connection"),
            "{}",
            ending.reason
        );
    }
}
