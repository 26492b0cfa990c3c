//! Treelet streams: one server-opened unidirectional stream per batch of treelets adjacent in
//! rank (a few per stream, so the per-stream cost of QUIC is shared), opened in rank order by one
//! opener per connection, written from the cached messages (one or a few buffers per stream,
//! see [`ServedScene::batch`]), reset when the latest list wants none of the batch.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use arbor_proto::wire::ErrorCode;
use arbor_proto::{Channel, TreeletId};
use tokio::sync::{mpsc, oneshot};

use super::schedule::ConnectionId;
use super::shared::Shared;
use super::timeline::Event;
use super::treelets::{CachedBatch, ServedScene};

/// Reset code of a treelet stream the client's latest list no longer wants (transport-level
/// cancel). `NoError`: nothing went wrong, the treelet is simply not coming.
pub const CANCEL_CODE: ErrorCode = ErrorCode::NoError;

/// Mean treelet message size assumed before any was sent.
pub(super) const DEFAULT_TREELET_BYTES: u64 = 4096;

/// What a treelet stream task shares with its connection.
pub(super) struct StreamCtx {
    pub(super) shared: Arc<Shared>,
    pub(super) id: ConnectionId,
    pub(super) conn: quinn::Connection,
    pub(super) scene: Arc<ServedScene>,
    /// Requested channels, ascending by id.
    pub(super) channels: Vec<Channel>,
    pub(super) base: Instant,
    /// Microseconds since `base` of the last progress of any stream.
    pub(super) last_progress: AtomicU64,
    pub(super) bytes_sent: AtomicU64,
    pub(super) treelets_sent: AtomicU64,
}

impl StreamCtx {
    pub(super) fn progress(&self) {
        let us = self.base.elapsed().as_micros().min(u128::from(u64::MAX)) as u64;
        self.last_progress.fetch_max(us, Ordering::Relaxed);
    }

    pub(super) fn since_progress(&self) -> Duration {
        self.base.elapsed().saturating_sub(Duration::from_micros(
            self.last_progress.load(Ordering::Relaxed),
        ))
    }

    pub(super) fn mean_treelet_bytes(&self) -> u64 {
        let n = self.treelets_sent.load(Ordering::Relaxed);
        self.bytes_sent
            .load(Ordering::Relaxed)
            .checked_div(n)
            .map_or(DEFAULT_TREELET_BYTES, |b| b.max(1))
    }
}

/// How one treelet's transfer ended.
#[derive(Debug)]
pub(super) enum Outcome {
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
pub(super) struct OpenStream {
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
pub(super) async fn open_in_order(
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

/// Sends a batch of treelets, adjacent in rank, on one stream: their messages back to back,
/// the stream finished, then waits until the client has all of it. The batch is cancelled as a
/// whole (its stream reset) when the connection's latest list no longer wants any of it; the
/// scheduler then hears of every treelet of the batch.
pub(super) async fn send_batch(
    ctx: Arc<StreamCtx>,
    batch: Vec<TreeletId>,
    priority: i32,
    opened: oneshot::Receiver<OpenStream>,
    mut cancel: oneshot::Receiver<ErrorCode>,
) -> (Vec<TreeletId>, Outcome) {
    let timeline = &ctx.shared.state.timeline;
    timeline.record(|| Event::Dispatched {
        session: ctx.id.0,
        at: Instant::now(),
        batch: batch.clone(),
    });
    let outcome = transfer(&ctx, &batch, priority, opened, &mut cancel).await;
    let now = Instant::now();
    timeline.record(|| Event::Ended {
        session: ctx.id.0,
        at: now,
        batch: batch.clone(),
        delivered: matches!(outcome, Outcome::Delivered),
    });
    {
        let mut core = ctx.shared.core();
        if matches!(outcome, Outcome::Delivered) {
            core.sched.handle_delivered_all(ctx.id, &batch, now);
        } else {
            for &t in &batch {
                core.sched.handle_cancelled(ctx.id, t);
            }
        }
    }
    if matches!(outcome, Outcome::Cancelled | Outcome::StoppedByPeer) {
        ctx.shared
            .state
            .metrics
            .treelets_cancelled
            .fetch_add(batch.len() as u64, Ordering::Relaxed);
    }
    ctx.shared.wake.notify_one();
    (batch, outcome)
}

async fn transfer(
    ctx: &StreamCtx,
    batch: &[TreeletId],
    priority: i32,
    opened: oneshot::Receiver<OpenStream>,
    cancel: &mut oneshot::Receiver<ErrorCode>,
) -> Outcome {
    // Read (or take from the cache) while the stream is being opened. What the cache lacks is
    // read by the pool's readers, not on this worker: a pool larger than the page cache reads
    // from disk (`super::readers`).
    let chunks = match ctx.scene.cached_batch(batch, &ctx.channels) {
        CachedBatch::Whole(chunks) => Ok(chunks),
        CachedBatch::Partial(partial) => {
            let (scene, channels) = (ctx.scene.clone(), ctx.channels.clone());
            let read = match ctx
                .shared
                .readers
                .read(move || scene.complete_batch(partial, &channels))
                .await
            {
                Ok(read) => read.map_err(|e| e.to_string()),
                Err(e) => Err(e.to_string()),
            };
            // The server's own progress: time its streams waited for the disk is not the
            // client's. Without this a pool read from a slow disk closed readers as slow (the
            // city's resting soak with its pool outside the page cache: 7 of 64 in 40 s).
            ctx.progress();
            read
        }
    };
    let mut chunks = match chunks {
        Ok(b) => b,
        Err(e) => return Outcome::Failed(e),
    };
    let len = chunks.iter().map(|c| c.len() as u64).sum();
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
        r = stream.write_all_chunks(&mut chunks) => Step::Done(r),
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
    ctx.progress();
    record_sent(ctx, batch, len);
    // Every byte is with the transport now: a cancel no longer resets the stream. A reset
    // would abandon what is still unsent or unacknowledged, and the client would drop the
    // messages it had not read yet, while the scheduler, believing them mostly delivered,
    // would not send them again for a redelivery guard (measured over the link emulator:
    // the last listed treelets of a view arrived 80–150 ms late). What is written is at most
    // the connection's window.
    match open.stream.stopped().await {
        Ok(None) => {
            ctx.progress();
            Outcome::Delivered
        }
        Ok(Some(_)) => Outcome::StoppedByPeer,
        Err(_) => Outcome::Lost,
    }
}

/// The scheduler, the metrics and the session hear that a batch was written.
fn record_sent(ctx: &StreamCtx, batch: &[TreeletId], len: u64) {
    let now = Instant::now();
    let mut latencies = Vec::with_capacity(batch.len());
    ctx.shared
        .core()
        .sched
        .handle_sent_all(ctx.id, batch, now, &mut latencies);
    let m = &ctx.shared.state.metrics;
    m.request_to_send.observe_all(latencies);
    let n = batch.len() as u64;
    m.treelets_sent.fetch_add(n, Ordering::Relaxed);
    m.treelet_bytes_sent.fetch_add(len, Ordering::Relaxed);
    m.treelet_streams.fetch_add(1, Ordering::Relaxed);
    ctx.treelets_sent.fetch_add(n, Ordering::Relaxed);
    ctx.bytes_sent.fetch_add(len, Ordering::Relaxed);
    ctx.shared.state.update_session(ctx.id.0, |s| {
        s.treelets_sent += n;
        s.bytes_sent += len;
    });
}
