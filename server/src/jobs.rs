//! The background jobs a daemon keeps for its admin API ([`crate::live_verify`]'s checks,
//! [`crate::live_copy`]'s copies): ids, one queue to one worker, status by id, cancellation,
//! and the last finished jobs kept while older ones are forgotten.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, mpsc};

use crate::live_import::{forget_oldest_finished, lock};

/// Finished jobs of one kind kept for status.
pub(crate) const KEEP_FINISHED: usize = 64;

/// A job on a [`JobBoard`].
pub(crate) trait BackgroundJob {
    /// What its status route answers.
    type Status;
    /// Whether it ended (however it ended).
    fn finished(&self) -> bool;
    /// Asks it (not finished) to stop; it ends `cancelled` once its worker sees the request.
    fn request_cancel(&self);
    fn status(&self) -> Self::Status;
}

/// Jobs by id (so oldest first), and the queue to their worker.
#[derive(Debug)]
pub(crate) struct JobBoard<J> {
    jobs: Mutex<BTreeMap<u64, Arc<J>>>,
    next: AtomicU64,
    queue: Mutex<mpsc::Sender<Arc<J>>>,
}

impl<J: BackgroundJob> JobBoard<J> {
    /// A board whose jobs go to the worker receiving from `queue`.
    pub(crate) fn new(queue: mpsc::Sender<Arc<J>>) -> Self {
        JobBoard {
            jobs: Mutex::new(BTreeMap::new()),
            next: AtomicU64::new(1),
            queue: Mutex::new(queue),
        }
    }

    /// The jobs, locked: a submission checks them and adds its job under one lock.
    pub(crate) fn lock(&self) -> MutexGuard<'_, BTreeMap<u64, Arc<J>>> {
        lock(&self.jobs)
    }

    /// The id the next job gets.
    pub(crate) fn next_id(&self) -> u64 {
        self.next.fetch_add(1, Ordering::Relaxed)
    }

    /// Adds `job` under the lock `jobs` holds (forgetting the oldest finished jobs beyond
    /// [`KEEP_FINISHED`]), lets the lock go, and queues it; `false` when the worker has stopped.
    pub(crate) fn add(
        &self,
        mut jobs: MutexGuard<'_, BTreeMap<u64, Arc<J>>>,
        id: u64,
        job: Arc<J>,
    ) -> bool {
        jobs.insert(id, job.clone());
        forget_oldest_finished(&mut jobs, KEEP_FINISHED, J::finished);
        drop(jobs);
        lock(&self.queue).send(job).is_ok()
    }

    /// One job's status.
    pub(crate) fn status(&self, id: u64) -> Option<J::Status> {
        lock(&self.jobs).get(&id).map(|j| j.status())
    }

    /// Every job kept (queued, running, and the last finished ones), by id.
    pub(crate) fn list(&self) -> Vec<J::Status> {
        lock(&self.jobs).values().map(|j| j.status()).collect()
    }

    /// Asks a queued or running job to stop; `None`: no such job. A finished job is left as
    /// it ended.
    pub(crate) fn cancel(&self, id: u64) -> Option<J::Status> {
        let jobs = lock(&self.jobs);
        let job = jobs.get(&id)?;
        if !job.finished() {
            job.request_cancel();
        }
        Some(job.status())
    }

    /// Whether a job that has not ended matches `which`.
    pub(crate) fn any_running(&self, which: impl Fn(&J) -> bool) -> bool {
        lock(&self.jobs).values().any(|j| !j.finished() && which(j))
    }

    /// Asks every job to stop (the manager is going away).
    pub(crate) fn cancel_all(&self) {
        for job in lock(&self.jobs).values() {
            if !job.finished() {
                job.request_cancel();
            }
        }
    }
}
