//! Checks of published scenes in a running daemon (`POST /v1/scenes/{name}/verify`): the
//! invariants `arbor-server verify` checks, without stopping the server (sled locks the pool
//! per process, so the stand-alone command needs the daemon stopped).
//!
//! * **What is checked**: the generation published when the check was asked for, whatever
//!   replaces it meanwhile. The scene's trees are opened at submission; a generation retired
//!   while a check holds it is kept until the check ends ([`Verifications::holds`], asked by the
//!   scene manager's reaper).
//! * **Memory**: the pass reads through the daemon's open pool by `get`, a batch of
//!   [`BATCH_TREELETS`] at a time, and holds nothing that grows with the scene
//!   ([`crate::verify`]); sled's page cache is the daemon's own, so a check pushes serving pages
//!   out of it while it runs. Its reads are counted apart from the serving read histogram.
//! * **CPU**: one check at a time, queued, on a worker thread whose rayon pool runs at the
//!   import priority ([`ImportPriority`]: `SCHED_IDLE` by default), so streaming keeps its rate.
//! * **Disk**: every pack a check reads takes its bytes from the daemon's [`ReadPace`]
//!   (`serve --background-read-rate`, shared with copies); a cancelled check stops waiting.
//! * **Cancellation**: `DELETE /v1/verifications/{id}` ([`Verifications::cancel`]), and every
//!   check queued or running when the daemon's scene manager is dropped, stops after the batch
//!   in hand.
//! * Asking again for a scene whose same generation is queued or running answers that check.
//! * **Scrubbing**: with `serve --check-every`, every published scene is checked again each
//!   period ([`Verifications::check_all`], from the scene manager's timer), so damage that
//!   appears on disk is found without anyone asking.
//! * **Metrics**: checks ended, by outcome, and each published scene's last check
//!   ([`Verifications::figures`], written to `/metrics`): what an alert on a damaged or
//!   unchecked scene reads.

use std::collections::BTreeMap;
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Instant, SystemTime};

use serde::Serialize;

use crate::jobs::{BackgroundJob, JobBoard};
use crate::live_import::{ImportPriority, background_threads, lock, unix_seconds};
use crate::pace::ReadPace;
use crate::periodic::ScheduleFigures;
use crate::pool::{Pool, PoolError, StoredScene};
use crate::verify::{BATCH_TREELETS, VerifyProgress, VerifyReport, verify_scene_observed};

/// Where a check stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum VerifyPhase {
    /// Waiting for the check before it.
    Queued,
    Running,
    /// Done: every invariant holds.
    Ok,
    /// Done: some invariant is broken (the report lists them).
    Problems,
    /// The pool could not be read (the error says why).
    Failed,
    /// Cancelled before it ended.
    Cancelled,
}

impl VerifyPhase {
    /// The phase as the API and `/metrics` name it.
    pub fn as_str(self) -> &'static str {
        match self {
            VerifyPhase::Queued => "queued",
            VerifyPhase::Running => "running",
            VerifyPhase::Ok => "ok",
            VerifyPhase::Problems => "problems",
            VerifyPhase::Failed => "failed",
            VerifyPhase::Cancelled => "cancelled",
        }
    }
}

/// What `GET /v1/verifications/{id}` answers.
#[derive(Clone, Debug, Serialize)]
pub struct VerifyStatus {
    pub id: u64,
    pub scene: String,
    /// The generation checked: the one published at submission.
    pub generation: u64,
    pub phase: VerifyPhase,
    /// Treelets the scene's description counts.
    pub treelets_planned: u64,
    /// Treelets checked so far.
    pub treelets_checked: u64,
    /// Seconds since submission (until it ended, when it did).
    pub seconds: f64,
    /// Submission time, seconds since the Unix epoch.
    pub submitted_unix: f64,
    /// Why it failed.
    pub error: Option<String>,
    /// The report, when done.
    pub report: Option<VerifyReport>,
}

#[derive(Debug)]
struct Job {
    id: u64,
    scene: String,
    generation: u64,
    /// The scene's trees, until the worker takes them.
    stored: Mutex<Option<StoredScene>>,
    started: AtomicBool,
    /// Shared with the scene's reads: a cancelled check stops waiting for the pace.
    cancelled: Arc<AtomicBool>,
    /// Treelets the scene's description counts.
    planned: u64,
    checked: AtomicU64,
    submitted: SystemTime,
    clock: Instant,
    outcome: Mutex<Option<Outcome>>,
}

#[derive(Clone, Debug)]
struct Outcome {
    seconds: f64,
    /// `Ok(None)`: cancelled.
    result: Result<Option<VerifyReport>, String>,
}

impl BackgroundJob for Job {
    type Status = VerifyStatus;

    fn finished(&self) -> bool {
        lock(&self.outcome).is_some()
    }

    fn request_cancel(&self) {
        self.cancelled.store(true, Ordering::Release);
        tracing::info!(id = self.id, scene = %self.scene, "verification cancelled");
    }

    fn status(&self) -> VerifyStatus {
        let outcome = lock(&self.outcome).clone();
        let phase = match &outcome {
            None if self.started.load(Ordering::Acquire) => VerifyPhase::Running,
            None => VerifyPhase::Queued,
            Some(o) => outcome_of(&o.result),
        };
        let seconds = outcome
            .as_ref()
            .map_or_else(|| self.clock.elapsed().as_secs_f64(), |o| o.seconds);
        let (error, report) = match outcome.map(|o| o.result) {
            Some(Err(e)) => (Some(e), None),
            Some(Ok(report)) => (None, report),
            None => (None, None),
        };
        VerifyStatus {
            id: self.id,
            scene: self.scene.clone(),
            generation: self.generation,
            phase,
            treelets_planned: self.planned,
            treelets_checked: self.checked.load(Ordering::Relaxed),
            seconds,
            submitted_unix: unix_seconds(self.submitted),
            error,
            report,
        }
    }
}

/// The daemon's scene checks: a queue, its worker, and the checks kept for status. Held by the
/// scene manager ([`crate::live_import::LiveImports`]), whose routes reach it.
#[derive(Debug)]
pub struct Verifications {
    pool: Pool,
    pace: Arc<ReadPace>,
    board: JobBoard<Job>,
    tally: Arc<Tally>,
}

/// The outcomes a check can end with, as `/metrics` labels them.
pub const OUTCOMES: [VerifyPhase; 4] = [
    VerifyPhase::Ok,
    VerifyPhase::Problems,
    VerifyPhase::Failed,
    VerifyPhase::Cancelled,
];

/// The last check of a scene that ran to its end (or failed reading).
#[derive(Clone, Debug, PartialEq)]
pub struct LastCheck {
    pub generation: u64,
    /// [`VerifyPhase::Ok`], [`VerifyPhase::Problems`] or [`VerifyPhase::Failed`].
    pub outcome: VerifyPhase,
    pub problems: u64,
    /// When it ended, seconds since the Unix epoch.
    pub ended_unix: f64,
}

/// What `/metrics` reports of the checks.
#[derive(Clone, Debug, Default)]
pub struct CheckFigures {
    /// Checks ended since the daemon started, in [`OUTCOMES`] order.
    pub ended: [u64; 4],
    /// Each scene's last check, while the generation it checked is published.
    pub last: BTreeMap<String, LastCheck>,
    /// The checks of every scene by `--check-every`/`--check-at`, if scheduled.
    pub scheduled: Option<ScheduleFigures>,
}

/// How a check that ended ended: `Ok(None)` is cancelled.
fn outcome_of(result: &Result<Option<VerifyReport>, String>) -> VerifyPhase {
    match result {
        Ok(Some(r)) if r.is_ok() => VerifyPhase::Ok,
        Ok(Some(_)) => VerifyPhase::Problems,
        Ok(None) => VerifyPhase::Cancelled,
        Err(_) => VerifyPhase::Failed,
    }
}

/// Counts kept over every check, whatever the list of kept checks forgets.
#[derive(Debug, Default)]
struct Tally {
    figures: Mutex<CheckFigures>,
}

impl Tally {
    fn record(&self, job: &Job, result: &Result<Option<VerifyReport>, String>) {
        let outcome = outcome_of(result);
        let problems = match result {
            Ok(Some(r)) => r.problem_count,
            _ => 0,
        };
        let mut f = lock(&self.figures);
        if let Some(i) = OUTCOMES.iter().position(|&o| o == outcome) {
            f.ended[i] += 1;
        }
        if outcome != VerifyPhase::Cancelled {
            let ended_unix = unix_seconds(SystemTime::now());
            f.last.insert(
                job.scene.clone(),
                LastCheck {
                    generation: job.generation,
                    outcome,
                    problems,
                    ended_unix,
                },
            );
        }
    }
}

impl Verifications {
    /// Checks of `pool`'s scenes, run one at a time on a worker thread at `priority`, their
    /// reads held to `pace`.
    pub fn new(
        pool: Pool,
        priority: ImportPriority,
        pace: Arc<ReadPace>,
    ) -> std::io::Result<Verifications> {
        let (tx, rx) = mpsc::channel::<Arc<Job>>();
        let tally = Arc::new(Tally::default());
        let worker_tally = tally.clone();
        std::thread::Builder::new()
            .name("arbor-verify".into())
            .spawn(move || run_worker(rx, priority, &worker_tally))?;
        Ok(Verifications {
            pool,
            pace,
            board: JobBoard::new(tx),
            tally,
        })
    }

    /// Says when the scheduled checks of every scene are next due (`/metrics`, the page).
    pub fn schedule_next(&self, figures: ScheduleFigures) {
        lock(&self.tally.figures).scheduled = Some(figures);
    }

    /// The scheduled checks' figures, if they are scheduled.
    pub fn scheduled(&self) -> Option<ScheduleFigures> {
        lock(&self.tally.figures).scheduled.clone()
    }

    /// Queues a check of every published scene (one already queued or running is not queued
    /// twice); returns how many were asked for.
    pub fn check_all(&self) -> Result<usize, PoolError> {
        let scenes = self.pool.generations()?;
        for (name, _) in &scenes {
            match self.submit(name) {
                // Removed since the catalogue was read.
                Err(PoolError::NoSuchScene(_)) => {}
                other => {
                    other?;
                }
            }
        }
        Ok(scenes.len())
    }

    /// Checks ended by outcome, and each published scene's last check of the generation
    /// published now (a replaced or removed scene's checks say nothing of what is served).
    pub fn figures(&self) -> Result<CheckFigures, PoolError> {
        Ok(self.figures_of(&self.pool.generations()?))
    }

    /// [`Verifications::figures`], with the published scenes' names and generations already
    /// read (`/metrics` reads the catalogue once per scrape).
    pub fn figures_of(&self, published: &[(String, u64)]) -> CheckFigures {
        let mut f = lock(&self.tally.figures).clone();
        f.last
            .retain(|scene, last| published.contains(&(scene.clone(), last.generation)));
        f
    }

    /// Queues a check of the generation of `scene` published now; returns its id (the id of
    /// the check of that generation already queued or running, if there is one).
    pub fn submit(&self, scene: &str) -> Result<u64, PoolError> {
        // The scene is opened under the jobs' lock: the reaper asks `holds` under it too, so a
        // generation it finds unheld cannot be opened here afterwards (it was unpublished before
        // it was retired).
        let jobs = self.board.lock();
        let cancelled = Arc::new(AtomicBool::new(false));
        let stored = self
            .pool
            .scene(scene)?
            .with_reads_apart()
            .paced(self.pace.clone(), cancelled.clone());
        if let Some(j) = jobs.values().find(|j| {
            j.scene == scene
                && j.generation == stored.generation
                && !j.finished()
                && !j.cancelled.load(Ordering::Acquire)
        }) {
            return Ok(j.id);
        }
        let id = self.board.next_id();
        let job = Arc::new(Job {
            id,
            scene: scene.to_owned(),
            generation: stored.generation,
            planned: u64::from(stored.description.treelet_count),
            stored: Mutex::new(Some(stored)),
            started: AtomicBool::new(false),
            cancelled,
            checked: AtomicU64::new(0),
            submitted: SystemTime::now(),
            clock: Instant::now(),
            outcome: Mutex::new(None),
        });
        tracing::info!(
            id,
            scene,
            generation = job.generation,
            "verification queued"
        );
        if !self.board.add(jobs, id, job.clone()) {
            *lock(&job.outcome) = Some(Outcome {
                seconds: 0.0,
                result: Err("the verification worker has stopped".into()),
            });
        }
        Ok(id)
    }

    /// One check's status.
    pub fn status(&self, id: u64) -> Option<VerifyStatus> {
        self.board.status(id)
    }

    /// Every check kept (queued, running, and the last finished ones), by id.
    pub fn list(&self) -> Vec<VerifyStatus> {
        self.board.list()
    }

    /// Asks a queued or running check to stop (after the batch in hand); its status then says
    /// `cancelled`. `None`: no such check. A finished check is left as it is.
    pub fn cancel(&self, id: u64) -> Option<VerifyStatus> {
        self.board.cancel(id)
    }

    /// Whether a check that has not ended reads `generation` (the reaper keeps it meanwhile).
    pub fn holds(&self, generation: u64) -> bool {
        self.board.any_running(|j| j.generation == generation)
    }
}

impl Drop for Verifications {
    fn drop(&mut self) {
        self.board.cancel_all();
    }
}

fn run_worker(rx: mpsc::Receiver<Arc<Job>>, priority: ImportPriority, tally: &Tally) {
    let Some(pool) = background_threads("arbor-verify", priority) else {
        return;
    };
    while let Ok(job) = rx.recv() {
        run_job(&pool, &job, tally);
    }
}

/// Runs one check on `threads` (or records it cancelled, if it was before it started), and
/// counts its outcome in `tally`.
fn run_job(threads: &rayon::ThreadPool, job: &Job, tally: &Tally) {
    let stored = lock(&job.stored).take();
    let result = match stored {
        Some(_) if job.cancelled.load(Ordering::Acquire) => Ok(None),
        None => Err("the scene's trees were already taken".to_owned()),
        Some(scene) => {
            job.started.store(true, Ordering::Release);
            tracing::info!(id = job.id, scene = %job.scene, "verification started");
            let mut progress = |p: VerifyProgress| {
                if let VerifyProgress::Checked(n) = p {
                    job.checked.fetch_add(n, Ordering::Relaxed);
                }
                if job.cancelled.load(Ordering::Acquire) {
                    ControlFlow::Break(())
                } else {
                    ControlFlow::Continue(())
                }
            };
            let result =
                threads.install(|| verify_scene_observed(&scene, BATCH_TREELETS, &mut progress));
            result.map_err(|e| e.to_string())
        }
    };
    let seconds = job.clock.elapsed().as_secs_f64();
    match &result {
        Ok(Some(r)) if r.is_ok() => tracing::info!(
            id = job.id,
            scene = %job.scene,
            treelets = r.treelets,
            seconds,
            "verification done: every invariant holds"
        ),
        Ok(Some(r)) => tracing::error!(
            id = job.id,
            scene = %job.scene,
            generation = job.generation,
            problems = r.problem_count,
            first = r.problems.first().map_or("", String::as_str),
            seconds,
            "a published scene breaks its invariants"
        ),
        Ok(None) => tracing::info!(id = job.id, scene = %job.scene, "verification stopped"),
        Err(e) => tracing::warn!(id = job.id, scene = %job.scene, "verification failed: {e}"),
    }
    tally.record(job, &result);
    *lock(&job.outcome) = Some(Outcome { seconds, result });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::{BuildOptions, DepthChoice};
    use crate::pipeline::{SceneImport, import_scene};
    use crate::verify::verify_scene;

    /// A pool holding the bunny as `bunny`, and checks of it whose queue this test drains
    /// itself (no worker: every step is the test's).
    fn unstarted() -> (
        tempfile::TempDir,
        Verifications,
        mpsc::Receiver<Arc<Job>>,
        rayon::ThreadPool,
    ) {
        let dir = tempfile::tempdir().unwrap();
        let pool = Pool::open(dir.path()).unwrap();
        let request = SceneImport {
            name: "bunny".into(),
            input: std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../shared/data/meshes/stanford-bunny.obj"),
            build: BuildOptions {
                depth: DepthChoice::Fixed(6),
                treelet_bytes: 1024,
                progress: false,
                ..BuildOptions::default()
            },
            ..SceneImport::default()
        };
        assert!(
            request.input.exists(),
            "the real scans in ../shared/data are required"
        );
        import_scene(&pool, &request).unwrap();
        let (tx, rx) = mpsc::channel();
        let checks = Verifications {
            pool,
            pace: Arc::new(ReadPace::new(None)),
            board: JobBoard::new(tx),
            tally: Arc::default(),
        };
        let threads = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        (dir, checks, rx, threads)
    }

    #[test]
    fn phases_are_named_as_serde_names_them() {
        for phase in [VerifyPhase::Queued, VerifyPhase::Running]
            .into_iter()
            .chain(OUTCOMES)
        {
            assert_eq!(serde_json::to_value(phase).unwrap(), phase.as_str());
        }
    }

    #[test]
    fn checks_are_queued_once_cancelled_and_hold_their_generation() {
        let (_dir, checks, rx, threads) = unstarted();
        let generation = checks.pool.scene("bunny").unwrap().generation;
        assert!(matches!(
            checks.submit("nope"),
            Err(PoolError::NoSuchScene(_))
        ));
        let first = checks.submit("bunny").unwrap();
        assert_eq!(
            checks.submit("bunny").unwrap(),
            first,
            "a second check queued"
        );
        assert_eq!(checks.status(first).unwrap().phase, VerifyPhase::Queued);
        assert!(checks.holds(generation));
        assert!(!checks.holds(generation + 1));

        // Cancelled while queued: it never reads, and asking again queues a new check.
        assert_eq!(checks.cancel(first).unwrap().phase, VerifyPhase::Queued);
        let second = checks.submit("bunny").unwrap();
        assert_ne!(second, first, "answered with the cancelled check");
        run_job(&threads, &rx.try_recv().unwrap(), &checks.tally);
        let s = checks.status(first).unwrap();
        assert_eq!(
            (s.phase, s.treelets_checked, s.report),
            (VerifyPhase::Cancelled, 0, None)
        );
        assert!(checks.holds(generation), "the second check reads it");

        // The new check runs to the report `verify_scene` gives.
        run_job(&threads, &rx.try_recv().unwrap(), &checks.tally);
        assert!(rx.try_recv().is_err(), "a check queued twice");
        assert!(!checks.holds(generation));
        let s = checks.status(second).unwrap();
        assert_eq!(s.phase, VerifyPhase::Ok, "{s:?}");
        let expected = verify_scene(&checks.pool.scene("bunny").unwrap()).unwrap();
        assert_eq!(s.report.as_ref(), Some(&expected));
        assert_eq!(s.treelets_planned, expected.treelets);
        assert_eq!(s.treelets_checked, expected.treelets);
        // Counted: one cancelled, one ok; the scene's last check is the one that ran.
        let f = checks.figures().unwrap();
        assert_eq!(f.ended, [1, 0, 0, 1]);
        let last = &f.last["bunny"];
        assert_eq!(
            (last.generation, last.outcome, last.problems),
            (generation, VerifyPhase::Ok, 0)
        );
        // Cancelling a finished check changes nothing; an unknown id is `None`.
        assert_eq!(checks.cancel(second).unwrap().phase, VerifyPhase::Ok);
        assert!(checks.cancel(99).is_none());
        assert_eq!(
            checks.list().iter().map(|s| s.id).collect::<Vec<_>>(),
            [first, second]
        );

        // Dropping the manager (the daemon stopping) cancels what is queued.
        assert_eq!(checks.check_all().unwrap(), 1, "every published scene");
        assert_eq!(checks.check_all().unwrap(), 1);
        let job = rx.try_recv().unwrap();
        assert!(rx.try_recv().is_err(), "a scene queued twice by check_all");
        let tally = checks.tally.clone();
        let pool = checks.pool.clone();
        drop(checks);
        run_job(&threads, &job, &tally);
        assert_eq!(job.status().phase, VerifyPhase::Cancelled);

        // A scene no longer published has no last check to report.
        let checks = Verifications::new(
            pool.clone(),
            ImportPriority::Idle,
            Arc::new(ReadPace::new(None)),
        )
        .unwrap();
        *lock(&checks.tally.figures) = lock(&tally.figures).clone();
        assert!(checks.figures().unwrap().last.contains_key("bunny"));
        pool.remove("bunny").unwrap();
        assert!(checks.figures().unwrap().last.is_empty());
        assert_eq!(checks.figures().unwrap().ended, [1, 0, 0, 2]);
    }
}
