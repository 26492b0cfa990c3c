//! One client connection: handshake, `Hello`, request lists, treelet streams, closing.
//!
//! # Life of a connection
//!
//! 1. The TLS handshake, the client's control stream and a complete `Hello` must all arrive
//!    within `hello_timeout_ms` of the connection's first packet, else the connection is closed
//!    with `ProtocolViolation`.
//! 2. `Hello` is checked: version (`UnsupportedVersion`, decided by the frame decoder from the
//!    first field), scene and token ([`super::config::ServeConfig::access`]: `UnknownScene`,
//!    `Unauthorized`), channels stored by the scene (`UnknownChannel`; over the limit:
//!    `TooManyChannels`). Success: `SceneInfo` with the stored description.
//! 3. Request lists are read with [`FrameDecoder::for_server`]: an over-limit length is refused
//!    from its 4 length bytes (`FrameTooLarge`), undecodable bytes are `ProtocolViolation`, a
//!    list over the length limit is `ListTooLong`, an id ≥ the scene's treelet count is
//!    `UnknownTreelet`, any frame but `RequestList`/`Goodbye` after `Hello` is
//!    `ProtocolViolation`. Each list goes to the shared scheduler; treelets in flight that the
//!    new list no longer names have their streams reset (code [`CANCEL_CODE`]).
//! 4. Treelets the dispatcher hands over are sent each on its own server-opened unidirectional
//!    stream, at a QUIC priority from their rank (the first treelet started under the newest list
//!    highest). Streams are opened in rank order by one opener per connection, so when the
//!    client's stream credit runs out the best-ranked waiting treelet gets the next stream.
//!    Finishing a stream reports `handle_sent` (and the request-to-send latency), its
//!    acknowledgement `handle_delivered`, a reset or failure `handle_cancelled`. A stream that
//!    ends unfinished is always reset, never left looking complete.
//! 5. Every 50 ms the window is recomputed from quinn's RTT and congestion window
//!    (bandwidth ≈ cwnd / RTT, so the window is about one congestion window of treelets), and
//!    the slow-reader watchdog runs: treelets in flight and no stream progress (opened, written,
//!    acknowledged) for `slow_reader_timeout_ms` → `SlowReader`.
//! 6. Closing with a code first writes an `Error` (or `Goodbye`) frame on the control stream and
//!    waits up to [`CLOSE_FLUSH`] for it to be acknowledged, then closes the connection with the
//!    same code and counts it in `errors_total`.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use arbor_proto::frame::{FrameDecoder, encode};
use arbor_proto::limits::MAX_REQUEST_ITEMS;
use arbor_proto::wire::{ErrorCode, Frame, PROTOCOL_VERSION};
use arbor_proto::{Channel, TreeletId};
use bytes::Bytes;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;
use tracing::Instrument as _;

use super::schedule::{ConnectionConfig, ConnectionId, ListOutcome, window_for};
use super::shared::{CLOSE_FLUSH, Shared};
use super::shutdown::{Done, Shutdown};
use super::state::SessionInfo;
use super::treelets::ServedScene;
use crate::pool::PoolError;

/// Reset code of a treelet stream the client's latest list no longer wants (transport-level
/// cancel). `NoError`: nothing went wrong, the treelet is simply not coming.
pub const CANCEL_CODE: ErrorCode = ErrorCode::NoError;

/// How often the window and the slow-reader watchdog are updated.
const TICK: Duration = Duration::from_millis(50);
/// Mean treelet message size assumed before any was sent.
const DEFAULT_TREELET_BYTES: u64 = 4096;
/// Added to the RTT for the redelivery guard: about one client cycle.
const CLIENT_CYCLE: Duration = Duration::from_millis(50);

/// How a connection ends.
#[derive(Debug)]
enum End {
    /// We close it with `code`, after sending `frame` on the control stream if there is one.
    Close {
        code: ErrorCode,
        reason: String,
        goodbye: bool,
    },
    /// The peer closed it, it timed out, or it was lost.
    Lost(quinn::ConnectionError),
}

fn close(code: ErrorCode, reason: impl Into<String>) -> End {
    End::Close {
        code,
        reason: reason.into(),
        goodbye: false,
    }
}

/// The control stream's receive side with its frame decoder.
struct ControlReader {
    recv: quinn::RecvStream,
    decoder: FrameDecoder,
    pending: Bytes,
}

impl ControlReader {
    /// The next frame; `Ok(None)` at the end of the stream. Cancel-safe: the only await is
    /// quinn's cancel-safe `read_chunk`, and partial state lives in `self`.
    async fn read_frame(&mut self) -> Result<Option<Frame>, End> {
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

/// What a treelet stream task shares with its connection.
struct StreamCtx {
    shared: Arc<Shared>,
    id: ConnectionId,
    conn: quinn::Connection,
    scene: Arc<ServedScene>,
    /// Requested channels, ascending by id.
    channels: Vec<Channel>,
    base: Instant,
    /// Microseconds since `base` of the last progress of any stream.
    last_progress: AtomicU64,
    bytes_sent: AtomicU64,
    treelets_sent: AtomicU64,
}

impl StreamCtx {
    fn progress(&self) {
        let us = self.base.elapsed().as_micros().min(u128::from(u64::MAX)) as u64;
        self.last_progress.fetch_max(us, Ordering::Relaxed);
    }

    fn since_progress(&self) -> Duration {
        self.base.elapsed().saturating_sub(Duration::from_micros(
            self.last_progress.load(Ordering::Relaxed),
        ))
    }

    fn mean_treelet_bytes(&self) -> u64 {
        let n = self.treelets_sent.load(Ordering::Relaxed);
        self.bytes_sent
            .load(Ordering::Relaxed)
            .checked_div(n)
            .map_or(DEFAULT_TREELET_BYTES, |b| b.max(1))
    }
}

/// How one treelet's transfer ended.
#[derive(Debug)]
enum Outcome {
    /// Acknowledged by the peer.
    Delivered,
    /// Reset by us (cancel or shutdown), or never opened because it was cancelled first.
    Cancelled,
    /// The peer stopped the stream.
    StoppedByPeer,
    /// The connection went away.
    Lost,
    /// The treelet could not be read from the pool: the server's fault.
    Failed(String),
}

enum Step<T> {
    Done(T),
    Cancel(ErrorCode),
}

/// A treelet stream that is reset (with [`CANCEL_CODE`]) if dropped before it was finished, so
/// a client never sees an empty or cut stream ended as if complete (quinn's `SendStream` drop
/// finishes the stream).
struct OpenStream {
    stream: quinn::SendStream,
    finished: bool,
}

impl Drop for OpenStream {
    fn drop(&mut self) {
        if !self.finished {
            let _ = self
                .stream
                .reset(quinn::VarInt::from_u32(CANCEL_CODE.to_u32()));
        }
    }
}

/// Opens the connection's treelet streams one at a time, in the order the treelets were
/// started (their rank), and hands each to its stream task. With the client's stream credit
/// exhausted, the next stream to open is therefore always the best-ranked waiting treelet, not
/// whichever task happened to poll first. A task that was cancelled while waiting has dropped
/// its receiver and is skipped. Ends when the connection is lost (pending tasks then see their
/// sender dropped).
async fn open_in_order(
    ctx: Arc<StreamCtx>,
    mut requests: mpsc::UnboundedReceiver<oneshot::Sender<OpenStream>>,
) {
    while let Some(mut tx) = requests.recv().await {
        if tx.is_closed() {
            continue;
        }
        let opened = tokio::select! {
            s = ctx.conn.open_uni() => s,
            () = tx.closed() => continue,
        };
        let Ok(stream) = opened else { return };
        ctx.progress();
        // If the task is gone by now, the stream is reset on drop.
        let _ = tx.send(OpenStream {
            stream,
            finished: false,
        });
    }
}

async fn send_treelet(
    ctx: Arc<StreamCtx>,
    t: TreeletId,
    priority: i32,
    opened: oneshot::Receiver<OpenStream>,
    mut cancel: oneshot::Receiver<ErrorCode>,
) -> (TreeletId, Outcome) {
    let outcome = transfer(&ctx, t, priority, opened, &mut cancel).await;
    let now = Instant::now();
    {
        let mut core = ctx.shared.core();
        match outcome {
            Outcome::Delivered => {
                core.sched.handle_delivered(ctx.id, t, now);
            }
            _ => {
                core.sched.handle_cancelled(ctx.id, t);
            }
        }
    }
    if matches!(outcome, Outcome::Cancelled | Outcome::StoppedByPeer) {
        ctx.shared
            .state
            .metrics
            .treelets_cancelled
            .fetch_add(1, Ordering::Relaxed);
    }
    ctx.shared.wake.notify_one();
    (t, outcome)
}

async fn transfer(
    ctx: &StreamCtx,
    t: TreeletId,
    priority: i32,
    opened: oneshot::Receiver<OpenStream>,
    cancel: &mut oneshot::Receiver<ErrorCode>,
) -> Outcome {
    // Read from the pool while the stream is being opened.
    let message = match ctx.scene.message(t, &ctx.channels) {
        Ok(m) => m,
        Err(e) => return Outcome::Failed(e.to_string()),
    };
    let len = message.len() as u64;
    let cancelled = |r: Result<ErrorCode, oneshot::error::RecvError>| r.unwrap_or(CANCEL_CODE);
    let step = tokio::select! {
        biased;
        c = &mut *cancel => Step::Cancel(cancelled(c)),
        s = opened => Step::Done(s),
    };
    let mut open = match step {
        // Not opened yet: dropping the receiver tells the opener to skip it (a stream already
        // in the channel is reset on drop).
        Step::Cancel(_) => return Outcome::Cancelled,
        Step::Done(Ok(s)) => s,
        Step::Done(Err(_)) => return Outcome::Lost,
    };
    let stream = &mut open.stream;
    let _ = stream.set_priority(priority);
    let step = tokio::select! {
        biased;
        c = &mut *cancel => Step::Cancel(cancelled(c)),
        r = stream.write_chunk(Bytes::from(message)) => Step::Done(r),
    };
    match step {
        Step::Cancel(code) => {
            let _ = stream.reset(quinn::VarInt::from_u32(code.to_u32()));
            open.finished = true;
            return Outcome::Cancelled;
        }
        Step::Done(Err(quinn::WriteError::Stopped(_))) => return Outcome::StoppedByPeer,
        Step::Done(Err(_)) => return Outcome::Lost,
        Step::Done(Ok(())) => {}
    }
    let _ = stream.finish();
    open.finished = true;
    let stream = &mut open.stream;
    ctx.progress();
    let now = Instant::now();
    let latency = ctx.shared.core().sched.handle_sent(ctx.id, t, now);
    let m = &ctx.shared.state.metrics;
    if let Some(l) = latency {
        m.request_to_send.observe(l);
    }
    m.treelets_sent.fetch_add(1, Ordering::Relaxed);
    m.treelet_bytes_sent.fetch_add(len, Ordering::Relaxed);
    ctx.treelets_sent.fetch_add(1, Ordering::Relaxed);
    ctx.bytes_sent.fetch_add(len, Ordering::Relaxed);
    ctx.shared.state.update_session(ctx.id.0, |s| {
        s.treelets_sent += 1;
        s.bytes_sent += len;
    });
    let stopped = stream.stopped();
    let step = tokio::select! {
        biased;
        c = &mut *cancel => Step::Cancel(cancelled(c)),
        r = stopped => Step::Done(r),
    };
    match step {
        Step::Done(Ok(None)) => {
            ctx.progress();
            Outcome::Delivered
        }
        Step::Done(Ok(Some(_))) => Outcome::StoppedByPeer,
        Step::Done(Err(_)) => Outcome::Lost,
        Step::Cancel(code) => {
            if stream.reset(quinn::VarInt::from_u32(code.to_u32())).is_ok() {
                Outcome::Cancelled
            } else {
                // Already fully acknowledged: nothing left to cancel.
                Outcome::Delivered
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
        let connecting = match incoming.accept() {
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
        let end = serve(&shared, id, &conn, shutdown, deadline, &mut control).await;

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
                conn.close(
                    quinn::VarInt::from_u32(code.to_u32()),
                    code.name().as_bytes(),
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
async fn hello(
    shared: &Shared,
    conn: &quinn::Connection,
    control: &mut Option<quinn::SendStream>,
) -> Result<(ControlReader, Arc<ServedScene>, Vec<Channel>), End> {
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
    if let Err(code) = shared
        .config
        .access(&scene, &token, |s| pool.contains(s).unwrap_or(false))
    {
        let reason = match code {
            ErrorCode::UnknownScene => format!("no scene named {scene:?}"),
            _ => format!("access to scene {scene:?} denied"),
        };
        return Err(close(code, reason));
    }
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
    if let Some(c) = channels
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
    Ok((reader, served, channels))
}

/// The connection's whole service: `Hello`, then the main loop. Returns how it ends.
async fn serve(
    shared: &Arc<Shared>,
    id: ConnectionId,
    conn: &quinn::Connection,
    mut shutdown: Shutdown,
    hello_deadline: tokio::time::Instant,
    control: &mut Option<quinn::SendStream>,
) -> End {
    if shutdown.deadline().is_some() {
        return End::Close {
            code: ErrorCode::ShuttingDown,
            reason: "server shutting down".into(),
            goodbye: true,
        };
    }
    let greeted = tokio::select! {
        r = tokio::time::timeout_at(hello_deadline, hello(shared, conn, control)) => match r {
            Ok(r) => r,
            Err(_) => Err(close(
                ErrorCode::ProtocolViolation,
                format!("no Hello within {} ms", shared.config.hello_timeout_ms),
            )),
        },
        _ = shutdown.recv() => Err(End::Close {
            code: ErrorCode::ShuttingDown,
            reason: "server shutting down".into(),
            goodbye: true,
        }),
    };
    let (mut reader, scene, channels) = match greeted {
        Ok(g) => g,
        Err(end) => return end,
    };
    let scene_name = scene.stored.description.name.clone();
    shared.state.update_session(id.0, |s| {
        s.scene = scene_name.clone();
        s.set_channels(&channels);
    });
    tracing::info!(channels = ?channels.iter().map(|c| c.name()).collect::<Vec<_>>(), "hello accepted");

    let (route, mut jobs) = mpsc::unbounded_channel();
    let window_min = shared.config.window_min;
    {
        let mut core = shared.core();
        core.routes.insert(id, route);
        if let Err(e) = core.sched.add_connection(
            id,
            ConnectionConfig {
                window: window_min,
                max_queue: MAX_REQUEST_ITEMS,
                redelivery_guard: ConnectionConfig::default().redelivery_guard,
            },
        ) {
            tracing::error!("{e}");
            return close(ErrorCode::Internal, "connection registered twice");
        }
    }
    let ctx = Arc::new(StreamCtx {
        shared: shared.clone(),
        id,
        conn: conn.clone(),
        scene,
        channels,
        base: Instant::now(),
        last_progress: AtomicU64::new(0),
        bytes_sent: AtomicU64::new(0),
        treelets_sent: AtomicU64::new(0),
    });
    let (opens, open_requests) = mpsc::unbounded_channel();
    let opener = AbortOnDrop(tokio::spawn(open_in_order(ctx.clone(), open_requests)));
    let mut streams: JoinSet<(TreeletId, Outcome)> = JoinSet::new();
    let mut cancels: HashMap<TreeletId, oneshot::Sender<ErrorCode>> = HashMap::new();
    let mut rank: i32 = 0;
    let mut reading = true;
    let mut window = window_min;
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let treelet_count = ctx.scene.treelet_count();

    let end = loop {
        tokio::select! {
            frame = reader.read_frame(), if reading => match frame {
                Ok(Some(Frame::RequestList { seq, items })) => {
                    if let Some((t, _)) = items.iter().find(|(t, _)| t.0 >= treelet_count) {
                        break close(
                            ErrorCode::UnknownTreelet,
                            format!("treelet {} does not exist (the scene has {treelet_count})", t.0),
                        );
                    }
                    let m = &shared.state.metrics;
                    m.request_lists.fetch_add(1, Ordering::Relaxed);
                    m.request_items.fetch_add(items.len() as u64, Ordering::Relaxed);
                    let outcome = shared
                        .core()
                        .sched
                        .handle_request_list(id, seq, items, Instant::now());
                    match outcome {
                        Ok(ListOutcome::Applied { obsolete_in_flight, .. }) => {
                            rank = 0;
                            for t in obsolete_in_flight {
                                if let Some(tx) = cancels.remove(&t) {
                                    let _ = tx.send(CANCEL_CODE);
                                }
                            }
                        }
                        Ok(ListOutcome::Stale { last_seq }) => {
                            tracing::debug!(seq, last_seq, "stale request list ignored");
                        }
                        Err(e) => {
                            tracing::error!("{e}");
                            break close(ErrorCode::Internal, "scheduler lost the connection");
                        }
                    }
                    shared.state.update_session(id.0, |s| s.request_lists += 1);
                    shared.wake.notify_one();
                }
                Ok(Some(Frame::Goodbye { code })) => {
                    break close(ErrorCode::NoError, format!("client said goodbye ({code})"));
                }
                Ok(Some(Frame::Error { code, message })) => {
                    break close(
                        ErrorCode::NoError,
                        format!("client reported an error: {code}: {message}"),
                    );
                }
                Ok(Some(other)) => {
                    break close(
                        ErrorCode::ProtocolViolation,
                        format!("unexpected {:?} frame after Hello", other.frame_type()),
                    );
                }
                Ok(None) => {
                    // The client will send no more lists; keep serving the current one.
                    tracing::debug!("control stream finished by the client");
                    reading = false;
                }
                Err(end) => break end,
            },
            Some(t) = jobs.recv() => {
                if let Some(e) = conn.close_reason() {
                    // Lost under our feet: do not churn through the queue opening streams.
                    break End::Lost(e);
                }
                if streams.is_empty() {
                    // Idle until now: the watchdog counts from here.
                    ctx.progress();
                }
                let (tx, rx) = oneshot::channel();
                cancels.insert(t, tx);
                let (open_tx, open_rx) = oneshot::channel();
                let _ = opens.send(open_tx);
                let priority = rank.saturating_neg();
                rank = rank.saturating_add(1);
                streams.spawn(send_treelet(ctx.clone(), t, priority, open_rx, rx));
            }
            Some(joined) = streams.join_next(), if !streams.is_empty() => {
                let Ok((t, outcome)) = joined else { continue };
                cancels.remove(&t);
                match outcome {
                    Outcome::Failed(reason) => {
                        tracing::error!(treelet = t.0, "{reason}");
                        break close(ErrorCode::Internal, format!("treelet {} unavailable", t.0));
                    }
                    Outcome::Lost => {}
                    Outcome::Delivered | Outcome::Cancelled | Outcome::StoppedByPeer => {}
                }
            }
            _ = tick.tick() => {
                if !streams.is_empty() && ctx.since_progress() >= shared.config.slow_reader_timeout() {
                    break close(
                        ErrorCode::SlowReader,
                        format!(
                            "{} treelets in flight and no progress for {} ms",
                            streams.len(),
                            shared.config.slow_reader_timeout_ms
                        ),
                    );
                }
                let rtt = conn.rtt();
                let cwnd = conn.stats().path.cwnd;
                let bandwidth = cwnd as f64 / rtt.as_secs_f64().max(1e-6);
                let w = window_for(
                    bandwidth,
                    rtt,
                    ctx.mean_treelet_bytes() as usize,
                    shared.config.window_min,
                    shared.config.window_max,
                );
                let stats = {
                    let mut core = shared.core();
                    if w != window {
                        let _ = core.sched.set_window(id, w);
                    }
                    let _ = core.sched.set_redelivery_guard(id, rtt + CLIENT_CYCLE);
                    core.sched.stats(id)
                };
                if w != window {
                    tracing::trace!(window = w, rtt_us = rtt.as_micros() as u64, cwnd, "window");
                    window = w;
                    shared.wake.notify_one();
                }
                if let Some(st) = stats {
                    shared.state.update_session(id.0, |s| {
                        s.queue_depth = st.queue_depth as u64;
                        s.in_flight = st.in_flight as u64;
                    });
                }
            }
            deadline = shutdown.recv() => {
                break drain(shared, id, deadline, &mut streams, &mut cancels, &mut jobs).await;
            }
            e = conn.closed() => break End::Lost(e),
        }
    };
    // Whatever is still in flight ends with the connection.
    for (_, tx) in cancels.drain() {
        let code = match &end {
            End::Close { code, .. } => *code,
            End::Lost(_) => CANCEL_CODE,
        };
        let _ = tx.send(code);
    }
    let _ = tokio::time::timeout(Duration::from_millis(100), async {
        while streams.join_next().await.is_some() {}
    })
    .await;
    streams.abort_all();
    drop(opener);
    end
}

/// Aborts a task when dropped.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Shutdown of one connection: stop taking lists, let in-flight streams finish until the
/// deadline, reset the rest, then say goodbye.
async fn drain(
    shared: &Shared,
    id: ConnectionId,
    deadline: Instant,
    streams: &mut JoinSet<(TreeletId, Outcome)>,
    cancels: &mut HashMap<TreeletId, oneshot::Sender<ErrorCode>>,
    jobs: &mut mpsc::UnboundedReceiver<TreeletId>,
) -> End {
    // Treelets handed over but not started are not started now.
    {
        let mut core = shared.core();
        while let Ok(t) = jobs.try_recv() {
            core.sched.handle_cancelled(id, t);
        }
    }
    let deadline = tokio::time::Instant::from_std(deadline);
    let in_flight = streams.len();
    while !streams.is_empty() {
        tokio::select! {
            joined = streams.join_next() => {
                if let Some(Ok((t, _))) = joined {
                    cancels.remove(&t);
                }
            }
            _ = tokio::time::sleep_until(deadline) => break,
        }
    }
    let left = streams.len();
    for (_, tx) in cancels.drain() {
        let _ = tx.send(ErrorCode::ShuttingDown);
    }
    tracing::debug!(in_flight, reset = left, "drained for shutdown");
    End::Close {
        code: ErrorCode::ShuttingDown,
        reason: "server shutting down".into(),
        goodbye: true,
    }
}
