//! The pool's readers: a fixed set of threads that build treelet messages from the pool for
//! the stream tasks, so that a read that waits for the disk waits on one of them and not on an
//! async worker.
//!
//! Why: a pool larger than the page cache is read from disk, a few KiB at random per treelet.
//! Read on the runtime's two workers, each read held a worker — and every task queued behind it:
//! lists, acknowledgements, the other connections' streams — for its duration, and the disk was
//! never more than two reads deep. The city soak with its pool outside the page cache served
//! 31k treelets/s instead of 63k, with a list's first treelet 188 ms after it (p50) instead of
//! 2 ms (docs/measurements.md, stop 66).
//!
//! Why a fixed set and not tokio's blocking pool: that pool starts a thread whenever none is
//! idle at the moment a job comes, and under 64 clients it kept about 40 for reads alone; each
//! keeps an allocator heap of its own, and the server's resident memory grew by 100–190 MB.
//! `pool_readers` threads (8 by default, [`super::config::ServeConfig::pool_readers`]) keep a
//! disk's queue busy and their memory bounded.

use std::collections::VecDeque;
use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

type Job = Box<dyn FnOnce() + Send>;

/// What the readers did, for `/metrics`.
#[derive(Debug, Default)]
pub struct ReadFigures {
    /// Reads queued or running now.
    pub waiting: AtomicU64,
    /// Reads run: a batch's messages the message cache lacked, or a push plan that needed a
    /// shape the shape cache lacked.
    pub run: AtomicU64,
    /// Reads skipped because nobody waited for them any more when their turn came (a batch
    /// cancelled by a newer list, a connection gone).
    pub skipped: AtomicU64,
}

/// What a read is for, which decides its turn: the readers take every queued batch before any
/// plan, unless the plan has waited [`PLAN_MAX_WAIT`].
///
/// Why: a batch was handed to a stream and the link waits for it (a list's first treelet, in
/// the resting city soak from a cold pool, came only after the plans queued before it), while a
/// plan only adds pushes, which rank below every listed treelet anyway.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ReadFor {
    /// The messages of a batch of treelets handed to a stream.
    Batch,
    /// A deep list's push plan.
    Plan,
}

/// How long a queued plan may wait behind batches: past this it goes first. Without a bound,
/// a disk too slow for the batches alone would never plan, and pushes would stop.
pub(crate) const PLAN_MAX_WAIT: Duration = Duration::from_millis(250);

/// The queued jobs, batches before plans younger than [`PLAN_MAX_WAIT`].
#[derive(Default)]
struct Queues {
    batches: VecDeque<Job>,
    /// Each with when it was queued.
    plans: VecDeque<(Instant, Job)>,
    /// No more jobs come: readers end once the queues are empty.
    closed: bool,
}

struct Jobs {
    /// [`PLAN_MAX_WAIT`] (tests set their own).
    plan_max_wait: Duration,
    queues: Mutex<Queues>,
    /// Signalled when a job is queued or the queues are closed.
    queued: Condvar,
}

impl Jobs {
    fn queues(&self) -> MutexGuard<'_, Queues> {
        // Jobs run outside the lock, and every critical section leaves the queues whole.
        self.queues.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The next job: a plan that has waited [`PLAN_MAX_WAIT`], else a batch, else a plan;
    /// `None` once the queues are closed and empty.
    fn next(&self) -> Option<Job> {
        let mut q = self.queues();
        loop {
            let overdue = q
                .plans
                .front()
                .is_some_and(|(queued, _)| queued.elapsed() >= self.plan_max_wait);
            let job = if overdue {
                q.plans.pop_front().map(|(_, job)| job)
            } else {
                q.batches
                    .pop_front()
                    .or_else(|| q.plans.pop_front().map(|(_, job)| job))
            };
            if let Some(job) = job {
                return Some(job);
            }
            if q.closed {
                return None;
            }
            q = self.queued.wait(q).unwrap_or_else(|p| p.into_inner());
        }
    }
}

/// The reader threads and the queues they take jobs from. Dropping it ends them once the jobs
/// queued so far are done.
pub(crate) struct PoolReaders {
    jobs: Arc<Jobs>,
    figures: Arc<ReadFigures>,
}

impl std::fmt::Debug for PoolReaders {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PoolReaders")
            .field("figures", &self.figures)
            .finish_non_exhaustive()
    }
}

impl Drop for PoolReaders {
    fn drop(&mut self) {
        self.jobs.queues().closed = true;
        self.jobs.queued.notify_all();
    }
}

/// One read counted in [`ReadFigures::waiting`] from when it is queued until it has run, was
/// skipped, panicked (the unwinding drops it) or was dropped unrun.
struct Waiting(Arc<ReadFigures>);

impl Waiting {
    fn count(figures: &Arc<ReadFigures>) -> Waiting {
        figures.waiting.fetch_add(1, Ordering::Relaxed);
        Waiting(figures.clone())
    }
}

impl Drop for Waiting {
    fn drop(&mut self) {
        self.0.waiting.fetch_sub(1, Ordering::Relaxed);
    }
}

/// The read gave no result: it panicked (a bug; the reader goes on with the next read), or the
/// readers are gone (the process is ending).
#[derive(Debug, thiserror::Error)]
#[error("the pool read gave no result: it panicked, or the reader threads are gone")]
pub(crate) struct ReadFailed;

impl PoolReaders {
    /// Starts `threads` readers (at least one), counting what they do in `figures`.
    pub(crate) fn start(threads: usize, figures: Arc<ReadFigures>) -> std::io::Result<Self> {
        Self::start_with(threads, figures, PLAN_MAX_WAIT)
    }

    /// [`Self::start`] with plans waiting at most `plan_max_wait` behind batches.
    fn start_with(
        threads: usize,
        figures: Arc<ReadFigures>,
        plan_max_wait: Duration,
    ) -> std::io::Result<Self> {
        let jobs = Arc::new(Jobs {
            plan_max_wait,
            queues: Mutex::default(),
            queued: Condvar::new(),
        });
        for i in 0..threads.max(1) {
            let queues = jobs.clone();
            let started = std::thread::Builder::new()
                .name(format!("arbor-read-{i}"))
                .spawn(move || {
                    while let Some(job) = queues.next() {
                        // A panicking read drops its result's sender, which tells its caller;
                        // the reader stays for the next one.
                        let _ = std::panic::catch_unwind(AssertUnwindSafe(job));
                    }
                });
            if let Err(e) = started {
                // The readers started so far end with the queues closed.
                jobs.queues().closed = true;
                jobs.queued.notify_all();
                return Err(e);
            }
        }
        Ok(Self { jobs, figures })
    }

    /// Runs `read` on a reader thread, in its turn ([`ReadFor`]), and waits for its result
    /// without holding the caller's worker. A caller that stops waiting (its future dropped: a
    /// cancelled batch, a connection gone) before its read's turn has the read skipped.
    pub(crate) async fn read<T: Send + 'static>(
        &self,
        purpose: ReadFor,
        read: impl FnOnce() -> T + Send + 'static,
    ) -> Result<T, ReadFailed> {
        let (done, result) = oneshot::channel();
        {
            let mut q = self.jobs.queues();
            if q.closed {
                return Err(ReadFailed);
            }
            let counted = Waiting::count(&self.figures);
            let job: Job = Box::new(move || {
                let figures = &counted.0;
                if done.is_closed() {
                    figures.skipped.fetch_add(1, Ordering::Relaxed);
                    return;
                }
                figures.run.fetch_add(1, Ordering::Relaxed);
                let value = read();
                // No longer waiting once its caller can have the result.
                drop(counted);
                let _ = done.send(value);
            });
            match purpose {
                ReadFor::Batch => q.batches.push_back(job),
                ReadFor::Plan => q.plans.push_back((Instant::now(), job)),
            }
        }
        self.jobs.queued.notify_one();
        result.await.map_err(|_| ReadFailed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::time::Duration;

    #[tokio::test(flavor = "current_thread")]
    async fn reads_run_on_the_readers_at_most_as_many_at_once_as_there_are_readers() {
        let readers = Arc::new(PoolReaders::start(3, Arc::default()).unwrap());
        let running = Arc::new(AtomicUsize::new(0));
        let most = Arc::new(AtomicUsize::new(0));
        let reads: Vec<_> = (0..9)
            .map(|i| {
                let (readers, running, most) = (readers.clone(), running.clone(), most.clone());
                tokio::spawn(async move {
                    readers
                        .read(ReadFor::Batch, move || {
                            let now = running.fetch_add(1, Ordering::SeqCst) + 1;
                            most.fetch_max(now, Ordering::SeqCst);
                            // A slow disk, on a reader: the runtime's only thread stays free.
                            std::thread::sleep(Duration::from_millis(50));
                            running.fetch_sub(1, Ordering::SeqCst);
                            let name = std::thread::current().name().map(str::to_owned);
                            (i, name)
                        })
                        .await
                        .unwrap()
                })
            })
            .collect();
        for (k, r) in reads.into_iter().enumerate() {
            let (i, name) = r.await.unwrap();
            assert_eq!(i, k);
            assert!(name.unwrap().starts_with("arbor-read-"));
        }
        // Never more than the readers at once; more than one (all three, unless a thread was
        // held up for a whole read).
        let most = most.load(Ordering::SeqCst);
        assert!(
            (2..=3).contains(&most),
            "{most} reads at once with three readers"
        );
    }

    /// Holds the one reader of `readers` with a read that waits for the returned sender; the
    /// task ends `Ok(true)` once released.
    fn hold_the_only_reader(
        readers: &Arc<PoolReaders>,
    ) -> (
        std::sync::mpsc::Sender<()>,
        tokio::task::JoinHandle<Result<bool, ReadFailed>>,
    ) {
        let (release, wait) = std::sync::mpsc::channel::<()>();
        let readers = readers.clone();
        let busy = tokio::spawn(async move {
            readers
                .read(ReadFor::Batch, move || wait.recv().is_ok())
                .await
        });
        (release, busy)
    }

    /// Spawns a read for `purpose` that adds `name` to `order` when it runs.
    fn read_in_turn(
        readers: &Arc<PoolReaders>,
        order: &Arc<Mutex<Vec<&'static str>>>,
        purpose: ReadFor,
        name: &'static str,
    ) -> tokio::task::JoinHandle<Result<(), ReadFailed>> {
        let (readers, order) = (readers.clone(), order.clone());
        tokio::spawn(async move {
            readers
                .read(purpose, move || order.lock().unwrap().push(name))
                .await
        })
    }

    #[tokio::test(flavor = "current_thread")]
    async fn a_read_nobody_waits_for_any_more_is_skipped() {
        let figures = Arc::new(ReadFigures::default());
        let readers = Arc::new(PoolReaders::start(1, figures.clone()).unwrap());
        let (release, busy) = hold_the_only_reader(&readers);
        let ran = Arc::new(AtomicUsize::new(0));
        let abandoned = {
            let (readers, ran) = (readers.clone(), ran.clone());
            tokio::spawn(async move {
                readers
                    .read(ReadFor::Batch, move || ran.fetch_add(1, Ordering::SeqCst))
                    .await
            })
        };
        // Both reads are queued once the tasks have run; then the second one's caller goes.
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert_eq!(
            figures.waiting.load(Ordering::SeqCst),
            2,
            "the held read runs, the second waits"
        );
        abandoned.abort();
        assert!(abandoned.await.unwrap_err().is_cancelled());
        release.send(()).unwrap();
        assert!(busy.await.unwrap().unwrap());
        let ran_after = {
            let ran = ran.clone();
            readers
                .read(ReadFor::Batch, move || ran.load(Ordering::SeqCst))
                .await
                .unwrap()
        };
        assert_eq!(ran_after, 0, "the abandoned read ran");
        let count = |n: &AtomicU64| n.load(Ordering::SeqCst);
        assert_eq!(
            (
                count(&figures.waiting),
                count(&figures.run),
                count(&figures.skipped)
            ),
            (0, 2, 1)
        );
    }

    #[tokio::test(flavor = "current_thread")]
    async fn queued_batches_are_read_before_queued_plans() {
        // Plans never overdue here, however slow the machine.
        let hour = Duration::from_secs(3_600);
        let readers = Arc::new(PoolReaders::start_with(1, Arc::default(), hour).unwrap());
        let (release, busy) = hold_the_only_reader(&readers);
        tokio::time::sleep(Duration::from_millis(20)).await;
        let order = Arc::new(Mutex::new(Vec::new()));
        // This runtime's one thread runs the tasks in the order they were spawned, so they
        // queue their reads in it.
        let queued: Vec<_> = [
            (ReadFor::Plan, "plan 1"),
            (ReadFor::Batch, "batch 1"),
            (ReadFor::Plan, "plan 2"),
            (ReadFor::Batch, "batch 2"),
        ]
        .into_iter()
        .map(|(purpose, name)| read_in_turn(&readers, &order, purpose, name))
        .collect();
        tokio::time::sleep(Duration::from_millis(20)).await;
        release.send(()).unwrap();
        assert!(busy.await.unwrap().unwrap());
        for read in queued {
            read.await.unwrap().unwrap();
        }
        assert_eq!(
            *order.lock().unwrap(),
            ["batch 1", "batch 2", "plan 1", "plan 2"]
        );
    }

    #[tokio::test(flavor = "current_thread")]
    async fn a_plan_that_waited_too_long_goes_before_the_batches() {
        let max_wait = Duration::from_millis(50);
        let readers = Arc::new(PoolReaders::start_with(1, Arc::default(), max_wait).unwrap());
        let (release, busy) = hold_the_only_reader(&readers);
        tokio::time::sleep(Duration::from_millis(20)).await;
        let order = Arc::new(Mutex::new(Vec::new()));
        let read = |purpose, name| read_in_turn(&readers, &order, purpose, name);
        let plan = read(ReadFor::Plan, "plan");
        tokio::time::sleep(max_wait + Duration::from_millis(20)).await;
        let batch = read(ReadFor::Batch, "batch");
        tokio::time::sleep(Duration::from_millis(20)).await;
        release.send(()).unwrap();
        assert!(busy.await.unwrap().unwrap());
        plan.await.unwrap().unwrap();
        batch.await.unwrap().unwrap();
        assert_eq!(*order.lock().unwrap(), ["plan", "batch"]);
    }

    #[tokio::test(flavor = "current_thread")]
    async fn a_read_that_panics_is_an_error_and_its_reader_reads_on() {
        let readers = PoolReaders::start(1, Arc::default()).unwrap();
        let failed = readers
            .read(ReadFor::Batch, || -> u32 { panic!("a read failed") })
            .await;
        assert!(failed.is_err());
        assert_eq!(
            readers.read(ReadFor::Batch, || 7).await.unwrap(),
            7,
            "the only reader is still there"
        );
    }
}
