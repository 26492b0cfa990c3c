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

use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};

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

/// The reader threads and the queue they take jobs from. Dropping it ends them once the jobs
/// queued so far are done.
#[derive(Debug)]
pub(crate) struct PoolReaders {
    jobs: Mutex<mpsc::Sender<Job>>,
    figures: Arc<ReadFigures>,
}

/// The read gave no result: it panicked (a bug; the reader goes on with the next read), or the
/// readers are gone (the process is ending).
#[derive(Debug, thiserror::Error)]
#[error("the pool read gave no result: it panicked, or the reader threads are gone")]
pub(crate) struct ReadFailed;

impl PoolReaders {
    /// Starts `threads` readers (at least one), counting what they do in `figures`.
    pub(crate) fn start(threads: usize, figures: Arc<ReadFigures>) -> std::io::Result<Self> {
        let (tx, rx) = mpsc::channel::<Job>();
        let rx = Arc::new(Mutex::new(rx));
        for i in 0..threads.max(1) {
            let rx = rx.clone();
            std::thread::Builder::new()
                .name(format!("arbor-read-{i}"))
                .spawn(move || {
                    loop {
                        // One reader waits for the next job while the others wait for the lock:
                        // the lock is let go before the job runs.
                        let job = match rx.lock() {
                            Ok(rx) => rx.recv(),
                            Err(_) => return,
                        };
                        match job {
                            // A panicking read drops its result's sender, which tells its
                            // caller; the reader stays for the next one.
                            Ok(job) => {
                                let _ = std::panic::catch_unwind(AssertUnwindSafe(job));
                            }
                            Err(_) => return,
                        }
                    }
                })?;
        }
        Ok(Self {
            jobs: Mutex::new(tx),
            figures,
        })
    }

    /// Runs `read` on a reader thread and waits for its result without holding the caller's
    /// worker. A caller that stops waiting (its future dropped: a cancelled batch, a
    /// connection gone) before its read's turn has the read skipped.
    pub(crate) async fn read<T: Send + 'static>(
        &self,
        read: impl FnOnce() -> T + Send + 'static,
    ) -> Result<T, ReadFailed> {
        let (done, result) = oneshot::channel();
        let figures = self.figures.clone();
        let job: Job = Box::new(move || {
            // Counted before the read, so a read that panics is no longer waiting either.
            figures.waiting.fetch_sub(1, Ordering::Relaxed);
            if done.is_closed() {
                figures.skipped.fetch_add(1, Ordering::Relaxed);
            } else {
                figures.run.fetch_add(1, Ordering::Relaxed);
                let _ = done.send(read());
            }
        });
        self.figures.waiting.fetch_add(1, Ordering::Relaxed);
        let queued = match self.jobs.lock() {
            Ok(jobs) => jobs.send(job).is_ok(),
            Err(_) => false,
        };
        if !queued {
            self.figures.waiting.fetch_sub(1, Ordering::Relaxed);
            return Err(ReadFailed);
        }
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
                        .read(move || {
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

    #[tokio::test(flavor = "current_thread")]
    async fn a_read_nobody_waits_for_any_more_is_skipped() {
        let figures = Arc::new(ReadFigures::default());
        let readers = Arc::new(PoolReaders::start(1, figures.clone()).unwrap());
        // The only reader is held by a read that waits for `release`.
        let (release, wait) = std::sync::mpsc::channel::<()>();
        let busy = {
            let readers = readers.clone();
            tokio::spawn(async move { readers.read(move || wait.recv().is_ok()).await })
        };
        let ran = Arc::new(AtomicUsize::new(0));
        let abandoned = {
            let (readers, ran) = (readers.clone(), ran.clone());
            tokio::spawn(async move {
                readers
                    .read(move || ran.fetch_add(1, Ordering::SeqCst))
                    .await
            })
        };
        // Both reads are queued once the tasks have run; then the second one's caller goes.
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert_eq!(
            figures.waiting.load(Ordering::SeqCst),
            1,
            "the second waits"
        );
        abandoned.abort();
        assert!(abandoned.await.unwrap_err().is_cancelled());
        release.send(()).unwrap();
        assert!(busy.await.unwrap().unwrap());
        let ran_after = {
            let ran = ran.clone();
            readers
                .read(move || ran.load(Ordering::SeqCst))
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
    async fn a_read_that_panics_is_an_error_and_its_reader_reads_on() {
        let readers = PoolReaders::start(1, Arc::default()).unwrap();
        let failed = readers.read(|| -> u32 { panic!("a read failed") }).await;
        assert!(failed.is_err());
        assert_eq!(
            readers.read(|| 7).await.unwrap(),
            7,
            "the only reader is still there"
        );
    }
}
