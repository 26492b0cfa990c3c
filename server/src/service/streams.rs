//! Treelet streams: one server-opened unidirectional stream per batch of treelets adjacent in
//! rank (a few per stream, so the per-stream cost of QUIC is shared), opened in rank order by one
//! opener per connection, written from the cached messages (one or a few buffers per stream,
//! see [`ServedScene::batch`]), reset when the latest list wants none of the batch.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use arbor_proto::wire::ErrorCode;
use arbor_proto::{Channel, TreeletId};
use tokio::sync::{mpsc, oneshot};

use super::readers::ReadFor;
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
    /// The slow-reader watchdog's clock.
    pub(super) clock: ProgressClock,
    pub(super) bytes_sent: AtomicU64,
    pub(super) treelets_sent: AtomicU64,
}

impl StreamCtx {
    /// A stream of the connection made progress (opened, written, acknowledged).
    pub(super) fn progress(&self) {
        self.clock.progress_at(Instant::now());
    }

    pub(super) fn mean_treelet_bytes(&self) -> u64 {
        let n = self.treelets_sent.load(Ordering::Relaxed);
        self.bytes_sent
            .load(Ordering::Relaxed)
            .checked_div(n)
            .map_or(DEFAULT_TREELET_BYTES, |b| b.max(1))
    }
}

/// When a connection's streams last made progress, for the slow-reader watchdog, and whether
/// the server itself is what they wait for.
///
/// Why the server's waits do not count: a stream whose batch waits for the pool's readers is
/// held up by the server's disk, not by the client. Counted, a pool read from a slow disk
/// closed readers as slow: the city's resting soak with its pool outside the page cache closed
/// 7 of 64 in 40 s before the readers (stop 66). One confined run after them closed 32, right
/// after builds, when this machine's disk drops from thousands of reads a second to a few
/// hundred (stop 68) (docs/measurements.md).
#[derive(Debug)]
pub(super) struct ProgressClock {
    base: Instant,
    /// Microseconds since `base` of the last progress.
    last_us: AtomicU64,
    /// Reads of this connection's batches queued for or running on the readers.
    reads_waited_for: AtomicUsize,
}

/// One read a stream waits for ([`ProgressClock::wait_for_read`]); its end, by result or by
/// cancel, is progress.
pub(super) struct ReadWait<'a>(&'a ProgressClock);

impl Drop for ReadWait<'_> {
    fn drop(&mut self) {
        self.0.reads_waited_for.fetch_sub(1, Ordering::Relaxed);
        self.0.progress_at(Instant::now());
    }
}

impl ProgressClock {
    /// A clock that counts from `base` as the last progress.
    pub(super) fn new(base: Instant) -> ProgressClock {
        ProgressClock {
            base,
            last_us: AtomicU64::new(0),
            reads_waited_for: AtomicUsize::new(0),
        }
    }

    /// Progress at `now` (a moment before the last one changes nothing).
    pub(super) fn progress_at(&self, now: Instant) {
        let us = now.saturating_duration_since(self.base).as_micros();
        self.last_us
            .fetch_max(us.min(u128::from(u64::MAX)) as u64, Ordering::Relaxed);
    }

    /// A stream starts waiting for a read of the pool; the clock stands still until it ends.
    pub(super) fn wait_for_read(&self) -> ReadWait<'_> {
        self.reads_waited_for.fetch_add(1, Ordering::Relaxed);
        ReadWait(self)
    }

    /// How long the connection has gone without progress at `now`, not counting the server's
    /// own waits: zero while a read is waited for.
    pub(super) fn stalled_for(&self, now: Instant) -> Duration {
        if self.reads_waited_for.load(Ordering::Relaxed) > 0 {
            return Duration::ZERO;
        }
        now.saturating_duration_since(self.base)
            .saturating_sub(Duration::from_micros(self.last_us.load(Ordering::Relaxed)))
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
            // The time waited is the server's, not the client's ([`ProgressClock`]).
            let _waiting = ctx.clock.wait_for_read();
            let read = ctx.shared.readers.read(ReadFor::Batch, move || {
                scene.complete_batch(partial, &channels)
            });
            // A batch cancelled while its read is queued is not read: its job is skipped
            // when its turn comes (`PoolReaders::read`), so a disk-bound server spends its
            // reads on what the lists still want.
            let step = tokio::select! {
                biased;
                _ = &mut *cancel => Step::Cancel(CANCEL_CODE),
                r = read => Step::Done(r),
            };
            match step {
                Step::Cancel(_) => return Outcome::Cancelled,
                Step::Done(Ok(read)) => read.map_err(|e| e.to_string()),
                Step::Done(Err(e)) => Err(e.to_string()),
            }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_watchdog_s_clock_stands_still_while_the_server_reads() {
        let base = Instant::now();
        let at = |ms| base + Duration::from_millis(ms);
        let clock = ProgressClock::new(base);
        assert_eq!(clock.stalled_for(at(300)), Duration::from_millis(300));
        {
            let first = clock.wait_for_read();
            let second = clock.wait_for_read();
            assert_eq!(clock.stalled_for(at(60_000)), Duration::ZERO);
            drop(first);
            assert_eq!(
                clock.stalled_for(at(60_000)),
                Duration::ZERO,
                "one read is still waited for"
            );
            drop(second);
        }
        // The last read's end was progress, at the real now: the client's time counts from
        // there.
        let stalled = clock.stalled_for(Instant::now() + Duration::from_secs(10));
        assert!(
            (Duration::from_secs(10)..Duration::from_secs(11)).contains(&stalled),
            "{stalled:?}"
        );
        clock.progress_at(at(1_000));
        clock.progress_at(at(400));
        assert_eq!(
            clock.stalled_for(at(1_500)),
            Duration::from_millis(500),
            "an earlier moment changes nothing"
        );
        assert_eq!(clock.stalled_for(base), Duration::ZERO, "never negative");
    }
}
