//! Scene management in a running daemon: imports of server-side files into the pool the daemon
//! serves, and removals, without stopping it (sled locks the pool per process, so the daemon is
//! the only one that can write it).
//!
//! * **Where files may come from**: only under the configured import root. Every input is
//!   resolved (`..` refused outright, then the path and every file it expands to canonicalized,
//!   symlinks followed) and must stay inside the canonical root ([`resolve_inputs`]).
//! * **One import at a time**, queued, on a worker thread whose build runs in its own rayon pool
//!   at the lowest CPU priority (`SCHED_IDLE`, else nice 10; [`ImportPriority`]), so the QUIC
//!   service's threads get the cores whenever they want them and clients of other scenes keep
//!   streaming. Progress is readable at any time
//!   ([`LiveImports::status`]).
//! * **Generations**: a replacing import publishes the new generation atomically; sessions that
//!   opened the old one keep reading it (never a mix: a session holds one generation's trees).
//!   The old generation is dropped once every session that could have opened it has ended — the
//!   sessions of that scene (or not yet greeted) live at the commit. Removal is the same:
//!   unpublished at once, dropped when its last session ends. What is left at a crash is dropped
//!   by the next `Pool::open`.
//! * **Checks** of published scenes run beside imports, one at a time ([`crate::live_verify`]);
//!   a retired generation a check reads is kept until the check ends.

use std::collections::BTreeMap;
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak, mpsc};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use crate::daemon::DaemonOptions;
use crate::import::tiles::{TileOptions, expand_inputs};
use crate::import::{Format, ImportOptions};
use crate::live_copy::Copies;
use crate::live_verify::Verifications;
use crate::octree::{BuildOptions, DepthChoice};
use crate::pace::{self, PaceError, ReadPace};
use crate::periodic::{self, Schedule, ScheduleError, ScheduleFigures, Timer};
use crate::pipeline::{SceneImport, Superseded, import_scene_observed};
use crate::pool::{Pool, PoolError};
use crate::progress::{ImportProgress, Phase, ProgressSnapshot};
use crate::service::state::ServiceState;

/// CPU priority (nice value) of the import threads at [`ImportPriority::Low`], and where
/// `SCHED_IDLE` is refused: the service's threads go first.
pub const IMPORT_NICE: i32 = 10;

/// How the import threads share the CPU with the service (`arbor-server serve
/// --import-priority`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum ImportPriority {
    /// `SCHED_IDLE`: only CPU time no service thread wants. Streaming keeps its rate during an
    /// import; on cores that streaming saturates, the import waits.
    #[default]
    Idle,
    /// Nice [`IMPORT_NICE`]: the service goes first, but an import still gets about a tenth of
    /// a busy core, so it finishes on a saturated server (streaming measured at 74 % of its
    /// idle rate on two shared cores).
    Low,
}
/// Why the scene manager could not start.
#[derive(Debug, thiserror::Error)]
pub enum ManagerError {
    /// A configured directory (import root, copy root) cannot be read.
    #[error("{key} {}: {source}", path.display())]
    Root {
        key: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A worker thread could not be started.
    #[error("starting the scene manager's threads: {0}")]
    Threads(#[from] std::io::Error),
    /// The background read rate is out of range.
    #[error(transparent)]
    Pace(#[from] PaceError),
    /// Scheduled copies were asked for without a copy root to put them in.
    #[error("--copy-every and --copy-at need --copy-root (where the scheduled copies go)")]
    ScheduleWithoutRoot,
    /// A periodic check's or copy's schedule cannot be kept.
    #[error("{key}: {source}")]
    Schedule {
        key: &'static str,
        #[source]
        source: ScheduleError,
    },
}

fn root_error(
    key: &'static str,
    path: &Option<PathBuf>,
) -> impl FnOnce(std::io::Error) -> ManagerError {
    let path = path.clone().unwrap_or_default();
    move |source| ManagerError::Root { key, path, source }
}

/// How often retired generations are checked for sessions still reading them.
const REAP_EVERY: Duration = Duration::from_millis(250);
/// Finished imports kept for `GET /v1/imports`.
const KEEP_FINISHED: usize = 64;

/// Why an import request was refused before it started. Each maps to an HTTP status in the
/// admin API.
#[derive(Debug, thiserror::Error)]
pub enum LiveImportError {
    /// The daemon was started without an import root.
    #[error("imports are disabled: start the daemon with --import-root DIR")]
    Disabled,
    /// An input names a parent directory (`..`).
    #[error("{input:?}: '..' is not allowed in import paths")]
    Traversal { input: String },
    /// An input resolves (symlinks followed) outside the import root.
    #[error("{input:?} resolves to {resolved} outside the import root")]
    OutsideRoot { input: String, resolved: String },
    /// An input does not exist or cannot be read.
    #[error("{input:?}: {error}")]
    NotFound { input: String, error: String },
    /// The request itself is malformed (empty inputs, bad depth, bad name...).
    #[error("{0}")]
    BadRequest(String),
    /// The scene exists and `replace` was not asked for.
    #[error("a scene named {0:?} already exists (pass \"replace\": true)")]
    SceneExists(String),
    /// The pool could not be read.
    #[error(transparent)]
    Pool(#[from] PoolError),
}

/// `POST /v1/scenes`: what to import. Paths are relative to the import root (or absolute
/// inside it); several inputs, directories or patterns make a tile set.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImportRequest {
    pub scene: String,
    pub inputs: Vec<String>,
    #[serde(default)]
    pub replace: bool,
    /// `"auto"` (default) or a depth.
    #[serde(default)]
    pub depth: Option<serde_json::Value>,
    #[serde(default)]
    pub treelet_bytes: Option<u32>,
    #[serde(default)]
    pub iso: Option<f32>,
    #[serde(default)]
    pub format: Option<String>,
    #[serde(default)]
    pub memory_budget_mib: Option<u64>,
    #[serde(default)]
    pub allow_mixed_crs: bool,
}

/// What `GET /v1/imports/{id}` answers.
#[derive(Clone, Debug, Serialize)]
pub struct ImportStatus {
    pub id: u64,
    pub scene: String,
    pub inputs: Vec<String>,
    #[serde(flatten)]
    pub progress: ProgressSnapshot,
    /// Seconds since the import was submitted (until it finished, when it did).
    pub seconds: f64,
    /// Submission time, seconds since the Unix epoch.
    pub submitted_unix: f64,
    /// The error, when it failed (names the file and the place).
    pub error: Option<String>,
    /// Figures of the stored scene, when done.
    pub treelets: Option<u32>,
    pub voxels: Option<u64>,
    pub primitives: Option<u64>,
}

#[derive(Debug)]
struct Job {
    id: u64,
    request: SceneImport,
    inputs: Vec<String>,
    progress: ImportProgress,
    submitted: SystemTime,
    clock: Instant,
    outcome: Mutex<Option<Outcome>>,
}

#[derive(Debug, Clone)]
struct Outcome {
    seconds: f64,
    result: Result<(u32, u64, u64), String>,
}

/// A generation no longer published, kept while sessions may read it.
#[derive(Debug)]
struct Retired {
    generation: u64,
    scene: String,
    /// Sessions live when it was retired that may hold it.
    sessions: Vec<u64>,
}

#[derive(Debug)]
struct Inner {
    pool: Pool,
    root: Option<PathBuf>,
    scratch: Option<PathBuf>,
    state: Arc<ServiceState>,
    jobs: Mutex<BTreeMap<u64, Arc<Job>>>,
    next: AtomicU64,
    queue: Mutex<mpsc::Sender<Arc<Job>>>,
    retired: Mutex<Vec<Retired>>,
    verifications: Verifications,
    copies: Copies,
    pace: Arc<ReadPace>,
    /// The daemon's data directory: the scheduled checks' record goes there.
    state_dir: PathBuf,
}

/// The guarded value, whether or not a thread panicked holding it (the jobs' state stays
/// readable).
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// `t` in seconds since the Unix epoch (0 before it).
pub(crate) fn unix_seconds(t: SystemTime) -> f64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// Of the background jobs kept for status (by id, so oldest first), removes the oldest finished
/// ones beyond `keep`.
pub(crate) fn forget_oldest_finished<J>(
    jobs: &mut BTreeMap<u64, Arc<J>>,
    keep: usize,
    finished: impl Fn(&J) -> bool,
) {
    let done: Vec<u64> = jobs
        .iter()
        .filter(|(_, j)| finished(j))
        .map(|(&id, _)| id)
        .collect();
    for id in &done[..done.len().saturating_sub(keep)] {
        jobs.remove(id);
    }
}

/// The daemon's scene manager (cheap to clone).
#[derive(Clone, Debug)]
pub struct LiveImports {
    inner: Arc<Inner>,
}

impl LiveImports {
    /// A manager for `pool`, configured by `options`: the import root (`None`: imports
    /// disabled, removal still works) and scratch; the periods of checks of every published
    /// scene and of scheduled copies (`None`: only those asked for); the copy root and how many
    /// scheduled copies are kept; the background read rate. `state_dir` holds the files a copy
    /// carries.
    pub fn new(
        pool: Pool,
        state: Arc<ServiceState>,
        options: &DaemonOptions,
        state_dir: &Path,
    ) -> Result<LiveImports, ManagerError> {
        let priority = options.import_priority;
        let schedule = |key, every, at| {
            Schedule::new(every, at).map_err(|source| ManagerError::Schedule { key, source })
        };
        let check_schedule = schedule(
            "--check-every/--check-at",
            options.check_every,
            options.check_at.clone(),
        )?;
        let copy_schedule = schedule(
            "--copy-every/--copy-at",
            options.copy_every,
            options.copy_at.clone(),
        )?;
        if copy_schedule.is_some() && options.copy_root.is_none() {
            return Err(ManagerError::ScheduleWithoutRoot);
        }
        let pace = Arc::new(ReadPace::new(pace::validate(options.background_read_rate)?));
        if let Some(rate) = options.background_read_rate {
            tracing::info!(
                rate = %pace::describe_rate(Some(rate)),
                "checks and copies read the pool at most at this rate"
            );
        }
        let root = options
            .import_root
            .as_deref()
            .map(std::fs::canonicalize)
            .transpose()
            .map_err(root_error("--import-root", &options.import_root))?;
        let copies = Copies::new(
            pool.clone(),
            options.copy_root.as_deref(),
            state_dir,
            priority,
            pace.clone(),
            options.copy_keep,
        )
        .map_err(root_error("--copy-root", &options.copy_root))?;
        let (tx, rx) = mpsc::channel::<Arc<Job>>();
        let verifications = Verifications::new(pool.clone(), priority, pace.clone())?;
        let inner = Arc::new(Inner {
            pool,
            root,
            scratch: options.import_scratch.clone(),
            state,
            jobs: Mutex::new(BTreeMap::new()),
            next: AtomicU64::new(1),
            queue: Mutex::new(tx),
            retired: Mutex::new(Vec::new()),
            verifications,
            copies,
            pace,
            state_dir: state_dir.to_owned(),
        });
        let weak = Arc::downgrade(&inner);
        std::thread::Builder::new()
            .name("arbor-import".into())
            .spawn(move || run_worker(rx, weak, priority))?;
        let weak = Arc::downgrade(&inner);
        std::thread::Builder::new()
            .name("arbor-reaper".into())
            .spawn(move || run_reaper(weak))?;
        if let Some(schedule) = check_schedule {
            tracing::info!(schedule = %schedule.describe(), "every scene is checked");
            let weak = Arc::downgrade(&inner);
            std::thread::Builder::new()
                .name("arbor-scrub".into())
                .spawn(move || every(weak, schedule, &CHECK_EVERY_SCENE))?;
        }
        if let Some(schedule) = copy_schedule {
            tracing::info!(schedule = %schedule.describe(), "the pool is copied");
            let weak = Arc::downgrade(&inner);
            std::thread::Builder::new()
                .name("arbor-backup".into())
                .spawn(move || every(weak, schedule, &COPY_THE_POOL))?;
        }
        Ok(LiveImports { inner })
    }

    /// Whether imports are enabled (an import root is configured).
    pub fn enabled(&self) -> bool {
        self.inner.root.is_some()
    }

    /// Checks and queues an import; returns its id. Paths, the name and the parameters are
    /// checked here; parsing errors come later, in the import's status.
    pub fn submit(&self, req: ImportRequest) -> Result<u64, LiveImportError> {
        let root = self
            .inner
            .root
            .as_deref()
            .ok_or(LiveImportError::Disabled)?;
        arbor_proto::scene::validate_scene_name(&req.scene)
            .map_err(|e| LiveImportError::BadRequest(e.to_string()))?;
        if !req.replace && self.inner.pool.contains(&req.scene)? {
            return Err(LiveImportError::SceneExists(req.scene));
        }
        let files = resolve_inputs(root, &req.inputs)?;
        let request = scene_import(&req, files, self.inner.scratch.clone())?;
        let id = self.inner.next.fetch_add(1, Ordering::Relaxed);
        let job = Arc::new(Job {
            id,
            inputs: std::iter::once(&request.input)
                .chain(&request.more_tiles)
                .map(|p| p.display().to_string())
                .collect(),
            request,
            progress: ImportProgress::default(),
            submitted: SystemTime::now(),
            clock: Instant::now(),
            outcome: Mutex::new(None),
        });
        {
            let mut jobs = lock(&self.inner.jobs);
            jobs.insert(id, job.clone());
            forget_oldest_finished(&mut jobs, KEEP_FINISHED, |j| lock(&j.outcome).is_some());
        }
        tracing::info!(id, scene = %job.request.name, files = job.inputs.len(), "import queued");
        lock(&self.inner.queue)
            .send(job)
            .map_err(|_| LiveImportError::BadRequest("the import worker has stopped".into()))?;
        Ok(id)
    }

    /// One import's status.
    pub fn status(&self, id: u64) -> Option<ImportStatus> {
        lock(&self.inner.jobs).get(&id).map(|j| status_of(j))
    }

    /// Every import kept (running, queued, and the last finished ones), by id.
    pub fn list(&self) -> Vec<ImportStatus> {
        lock(&self.inner.jobs)
            .values()
            .map(|j| status_of(j))
            .collect()
    }

    /// Removes a scene: unpublished now; its trees dropped when its last session ended.
    pub fn remove_scene(&self, name: &str) -> Result<(), PoolError> {
        let generation = self.inner.pool.unpublish(name)?;
        tracing::info!(scene = name, generation, "scene removed");
        self.inner.retire(generation, name);
        Ok(())
    }

    /// Checks of published scenes ([`crate::live_verify`]).
    pub fn verifications(&self) -> &Verifications {
        &self.inner.verifications
    }

    /// The pool copies ([`crate::live_copy`]).
    pub fn copies(&self) -> &Copies {
        &self.inner.copies
    }

    /// The pace the checks' and copies' reads keep ([`crate::pace`]).
    pub fn background_reads(&self) -> &ReadPace {
        &self.inner.pace
    }

    /// Generations retired but still read by live sessions or checks.
    pub fn retired_generations(&self) -> Vec<u64> {
        lock(&self.inner.retired)
            .iter()
            .map(|r| r.generation)
            .collect()
    }
}

impl Inner {
    fn retire(&self, generation: u64, scene: &str) {
        let sessions = self
            .state
            .sessions()
            .into_iter()
            .filter(|s| s.scene == scene || s.scene.is_empty())
            .map(|s| s.id)
            .collect();
        lock(&self.retired).push(Retired {
            generation,
            scene: scene.to_owned(),
            sessions,
        });
        self.reap();
    }

    /// Drops every retired generation none of whose sessions is still live and no check reads.
    fn reap(&self) {
        let live: Vec<u64> = self.state.sessions().iter().map(|s| s.id).collect();
        let mut retired = lock(&self.retired);
        retired.retain_mut(|r| {
            r.sessions.retain(|s| live.contains(s));
            if !r.sessions.is_empty()
                || self.verifications.holds(r.generation)
                || self.copies.holds(r.generation)
            {
                return true;
            }
            match self.pool.drop_retired(r.generation) {
                Ok(()) => {
                    tracing::info!(scene = %r.scene, generation = r.generation, "old generation dropped");
                    false
                }
                Err(e) => {
                    tracing::warn!(scene = %r.scene, generation = r.generation, "dropping an old generation: {e}");
                    false
                }
            }
        });
    }
}

fn status_of(j: &Job) -> ImportStatus {
    // The phase first: the worker records the outcome before it enters the final phase, so a
    // final phase read here always comes with its outcome.
    let progress = j.progress.snapshot();
    let outcome = lock(&j.outcome).clone();
    let seconds = outcome
        .as_ref()
        .map_or_else(|| j.clock.elapsed().as_secs_f64(), |o| o.seconds);
    let figures = outcome
        .as_ref()
        .and_then(|o| o.result.as_ref().ok())
        .copied();
    ImportStatus {
        id: j.id,
        scene: j.request.name.clone(),
        inputs: j.inputs.clone(),
        progress,
        seconds,
        submitted_unix: unix_seconds(j.submitted),
        error: outcome.and_then(|o| o.result.err()),
        treelets: figures.map(|f| f.0),
        voxels: figures.map(|f| f.1),
        primitives: figures.map(|f| f.2),
    }
}

/// Lowers the calling thread's CPU priority to `priority` (best effort: an unprivileged process
/// may always lower its own). Threads it starts inherit the setting.
///
/// [`ImportPriority::Idle`] asks for `SCHED_IDLE`: the thread runs only on CPU time no other
/// thread of normal priority wants, so streaming keeps its rate however busy the import is (at
/// nice 10 the import still took a tenth of a core the service wanted; the live-import bench
/// showed clients at 74 % of their idle rate). Where `SCHED_IDLE` is refused, and for
/// [`ImportPriority::Low`], nice [`IMPORT_NICE`].
#[allow(unsafe_code)]
/// Lowers the calling thread's CPU priority to `priority`.
pub(crate) fn lower_priority(priority: ImportPriority) {
    if priority == ImportPriority::Low {
        set_nice(None);
        return;
    }
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: `sched_setscheduler` reads `param` (a valid, initialized value on the stack) and
    // changes only the scheduling policy of the calling thread (pid 0).
    if unsafe { libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) } == 0 {
        return;
    }
    set_nice(Some(std::io::Error::last_os_error()));
}

/// Nice [`IMPORT_NICE`] for the calling thread; `idle_error`: why `SCHED_IDLE` was refused.
fn set_nice(idle_error: Option<std::io::Error>) {
    let tid = rustix::thread::gettid();
    match rustix::process::setpriority_process(Some(tid), IMPORT_NICE) {
        Ok(()) => {
            if let Some(e) = idle_error {
                tracing::debug!(
                    "SCHED_IDLE refused ({e}); import threads run at nice {IMPORT_NICE}"
                );
            }
        }
        Err(e) => tracing::warn!(
            "could not lower the import thread's priority (SCHED_IDLE: {}; nice: {e})",
            idle_error.map_or_else(|| "not asked".to_owned(), |e| e.to_string())
        ),
    }
}

/// Lowers the calling worker thread to `priority` and makes the rayon pool its work runs on:
/// a thread per core, each at `priority` too, named `{name}-N`. `None` (logged) when the
/// threads cannot be started.
pub(crate) fn background_threads(
    name: &'static str,
    priority: ImportPriority,
) -> Option<rayon::ThreadPool> {
    lower_priority(priority);
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(move |i| format!("{name}-{i}"))
        .start_handler(move |_| lower_priority(priority))
        .build()
        .inspect_err(|e| tracing::error!("no {name} thread pool: {e}"))
        .ok()
}

fn run_worker(rx: mpsc::Receiver<Arc<Job>>, inner: Weak<Inner>, priority: ImportPriority) {
    let Some(pool) = background_threads("arbor-import", priority) else {
        return;
    };
    while let Ok(job) = rx.recv() {
        let Some(inner) = inner.upgrade() else { return };
        tracing::info!(id = job.id, scene = %job.request.name, "import started");
        job.progress.enter(Phase::Reading, 0);
        let result = pool.install(|| {
            import_scene_observed(&inner.pool, &job.request, &job.progress, Superseded::Keep)
        });
        let seconds = job.clock.elapsed().as_secs_f64();
        let (result, phase) = match result {
            Ok((scene, retired)) => {
                let d = &scene.description;
                tracing::info!(id = job.id, scene = %d.name, treelets = d.treelet_count, seconds, "import done");
                if let Some(g) = retired {
                    inner.retire(g, &d.name);
                }
                (
                    Ok((d.treelet_count, d.stats.voxels, d.primitives)),
                    Phase::Done,
                )
            }
            Err(e) => {
                tracing::warn!(id = job.id, scene = %job.request.name, "import failed: {e}");
                (Err(e.to_string()), Phase::Failed)
            }
        };
        *lock(&job.outcome) = Some(Outcome { seconds, result });
        // Last: a watcher that sees the final phase also sees the outcome and the retirement.
        job.progress.enter(phase, 0);
    }
}

/// A periodic job: what it does when due (given the time it was due), and where it says when it
/// is next due.
struct Periodic {
    work: fn(&Inner, SystemTime),
    publish: fn(&Inner, ScheduleFigures),
    /// When it was last due, as the daemon's files say (`None`: not known).
    last_due: fn(&Inner) -> Option<SystemTime>,
}

/// Where the daemon keeps the time the last scheduled check of every scene was due (seconds
/// since the Unix epoch), so a restart knows whether it missed one.
pub const LAST_SCHEDULED_CHECK_FILE: &str = "last-scheduled-check";

/// `serve --check-every/--check-at`'s job: a check of every published scene queued, and the
/// time it was due recorded.
const CHECK_EVERY_SCENE: Periodic = Periodic {
    work: |inner, due| match inner.verifications.check_all() {
        Ok(n) => {
            tracing::info!(scenes = n, "periodic check of every scene queued");
            record_check(&inner.state_dir, due);
        }
        Err(e) => tracing::warn!("periodic check: reading the catalogue: {e}"),
    },
    publish: |inner, figures| inner.verifications.schedule_next(figures),
    last_due: |inner| {
        let file = inner.state_dir.join(LAST_SCHEDULED_CHECK_FILE);
        let text = std::fs::read_to_string(&file).ok()?;
        match text.trim().parse::<u64>() {
            Ok(seconds) => Some(UNIX_EPOCH + Duration::from_secs(seconds)),
            Err(_) => {
                tracing::warn!(
                    path = %file.display(),
                    "not a time (seconds since the epoch): a missed check is not made up"
                );
                None
            }
        }
    },
};

/// Writes the time the last scheduled check was due, whole or not at all (a sibling renamed
/// over it); a failure is logged, and costs at most a repeated check after a restart.
fn record_check(state_dir: &Path, due: SystemTime) {
    let file = state_dir.join(LAST_SCHEDULED_CHECK_FILE);
    let partial = state_dir.join(format!(".{LAST_SCHEDULED_CHECK_FILE}.partial"));
    let written = std::fs::write(&partial, format!("{}\n", periodic::seconds(due)))
        .and_then(|()| std::fs::rename(&partial, &file));
    if let Err(e) = written {
        tracing::warn!(path = %file.display(), "recording the scheduled check's time: {e}");
    }
}

/// `serve --copy-every/--copy-at`'s job: the scheduled copy queued, named by the time it was
/// due, unless the last one still runs.
const COPY_THE_POOL: Periodic = Periodic {
    work: |inner, due| match inner.copies.submit_scheduled(due) {
        Ok(Some(id)) => tracing::info!(id, "scheduled copy of the pool queued"),
        Ok(None) => tracing::warn!(
            "scheduled copy skipped: the last one has not ended (a period shorter than a copy?)"
        ),
        Err(e) => tracing::error!("scheduled copy: {e}"),
    },
    publish: |inner, figures| inner.copies.schedule_next(figures),
    last_due: |inner| inner.copies.last_scheduled(),
};

/// Runs `job` each time `schedule` is due (the first time one period after the start, or at
/// the next clock time, or at once for a clock time missed since it last ran), until the
/// scene manager is dropped.
fn every(inner: Weak<Inner>, schedule: Schedule, job: &Periodic) {
    let Some(last) = inner.upgrade().map(|i| (job.last_due)(&i)) else {
        return;
    };
    let (wall, mono) = (SystemTime::now(), Instant::now());
    let mut timer = Timer::resume(&schedule, wall, mono, last);
    let describe = schedule.describe();
    let period_seconds = schedule.period().as_secs_f64();
    if timer.next_due(wall, mono) <= wall {
        tracing::info!(
            schedule = %describe,
            "a scheduled time passed since the job last ran (the daemon was down): it runs now"
        );
    } else if let Some(last) = last.filter(|&l| l > wall) {
        // A clock set back, or a copy named in the future brought in by hand: either way no
        // time is made up at this start, which the operator should know.
        tracing::warn!(
            schedule = %describe,
            last = %crate::periodic::utc_text(last),
            "the job's last scheduled time is later than now (a clock set back, or a scheduled \
             copy named in the future): nothing missed is made up at this start"
        );
    }
    let mut published = None;
    loop {
        let (wall, mono) = (SystemTime::now(), Instant::now());
        let due = timer.poll(wall, mono);
        let next = timer.next_due(wall, mono);
        {
            let Some(inner) = inner.upgrade() else { return };
            if let Some(due) = due {
                (job.work)(&inner, due);
            }
            // Said again only when it changed, to the second (a period counted from the start
            // is projected on the wall clock anew at each wake-up).
            let next_unix = unix_seconds(next).round();
            if published != Some(next_unix) {
                published = Some(next_unix);
                (job.publish)(
                    &inner,
                    ScheduleFigures {
                        schedule: describe.clone(),
                        next_due_unix: next_unix,
                        period_seconds,
                    },
                );
            }
        }
        // Short sleeps: the manager's drop is seen soon, and a clock stepped is followed.
        let wait = next.duration_since(SystemTime::now()).unwrap_or_default();
        std::thread::sleep(REAP_EVERY.min(wait));
    }
}

fn run_reaper(inner: Weak<Inner>) {
    loop {
        std::thread::sleep(REAP_EVERY);
        let Some(inner) = inner.upgrade() else { return };
        if !lock(&inner.retired).is_empty() {
            inner.reap();
        }
    }
}

/// The build and read options of a request.
fn scene_import(
    req: &ImportRequest,
    files: Vec<PathBuf>,
    scratch: Option<PathBuf>,
) -> Result<SceneImport, LiveImportError> {
    let bad = LiveImportError::BadRequest;
    let depth = match &req.depth {
        None => DepthChoice::Auto,
        Some(serde_json::Value::String(s)) if s.eq_ignore_ascii_case("auto") => DepthChoice::Auto,
        Some(serde_json::Value::Number(n)) => match n.as_u64() {
            Some(d) if d <= u64::from(arbor_proto::limits::MAX_DEPTH) => {
                DepthChoice::Fixed(d as u8)
            }
            _ => return Err(bad(format!("depth {n} is not 0..=31"))),
        },
        Some(v) => return Err(bad(format!("depth {v} is neither \"auto\" nor a number"))),
    };
    let defaults = BuildOptions::default();
    let treelet_bytes = req.treelet_bytes.unwrap_or(defaults.treelet_bytes);
    arbor_proto::treelet::nodes_for_bytes(treelet_bytes).map_err(|e| bad(e.to_string()))?;
    if let Some(i) = req.iso
        && !i.is_finite()
    {
        return Err(bad(format!("iso {i} is not finite")));
    }
    let memory_budget = match req.memory_budget_mib {
        None => defaults.memory_budget,
        Some(m @ 1..=1_048_576) => (m as usize) << 20,
        Some(m) => return Err(bad(format!("memory_budget_mib {m} is not 1..=1048576"))),
    };
    let format = match &req.format {
        None => None,
        Some(f) => Some(f.parse::<Format>().map_err(bad)?),
    };
    let mut files = files.into_iter();
    let input = files
        .next()
        .ok_or_else(|| bad("\"inputs\" names no file".into()))?;
    Ok(SceneImport {
        name: req.scene.clone(),
        input,
        more_tiles: files.collect(),
        import: ImportOptions {
            format,
            raw: None,
            tiles: TileOptions {
                allow_mixed_crs: req.allow_mixed_crs,
            },
        },
        build: BuildOptions {
            depth,
            treelet_bytes,
            iso: req.iso,
            memory_budget,
            ..defaults
        },
        replace: req.replace,
        scratch_parent: scratch,
    })
}

/// Resolves the inputs of a request against the canonical import `root`: no `..`, and every
/// path and every file it expands to (directories, patterns) must lie inside the root once
/// symlinks are followed. Returns canonical file paths, in reading order.
pub fn resolve_inputs(root: &Path, inputs: &[String]) -> Result<Vec<PathBuf>, LiveImportError> {
    if inputs.is_empty() {
        return Err(LiveImportError::BadRequest(
            "\"inputs\" is empty: name at least one file, directory or pattern".into(),
        ));
    }
    let mut files = Vec::new();
    for input in inputs {
        let path = Path::new(input);
        if input.is_empty() || input.contains('\0') {
            return Err(LiveImportError::BadRequest(format!(
                "{input:?} is not a path"
            )));
        }
        if path.components().any(|c| c == Component::ParentDir) {
            return Err(LiveImportError::Traversal {
                input: input.clone(),
            });
        }
        let joined = root.join(path);
        let name = joined
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let inside = |p: &Path| -> Result<PathBuf, LiveImportError> {
            let canonical = std::fs::canonicalize(p).map_err(|e| LiveImportError::NotFound {
                input: input.clone(),
                error: e.to_string(),
            })?;
            if canonical.starts_with(root) {
                Ok(canonical)
            } else {
                Err(LiveImportError::OutsideRoot {
                    input: input.clone(),
                    resolved: canonical.display().to_string(),
                })
            }
        };
        let start = if name.contains(['*', '?']) {
            let parent = joined.parent().unwrap_or(root);
            inside(parent)?.join(&name)
        } else {
            inside(&joined)?
        };
        let expanded = expand_inputs(&[start]).map_err(|e| LiveImportError::NotFound {
            input: input.clone(),
            error: e.to_string(),
        })?;
        for f in expanded {
            files.push(inside(&f)?);
        }
    }
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The policy and nice value of the calling thread.
    #[allow(unsafe_code)]
    fn scheduling() -> (i32, i32) {
        // SAFETY: `sched_getscheduler(0)` only reads the calling thread's policy.
        let policy = unsafe { libc::sched_getscheduler(0) };
        let tid = rustix::thread::gettid();
        (
            policy,
            rustix::process::getpriority_process(Some(tid)).unwrap(),
        )
    }

    /// By default the import threads run under `SCHED_IDLE` (Linux lets any thread lower itself
    /// to it), and the threads they start inherit it, so the whole build yields to the service.
    /// `--import-priority low` keeps the normal policy at nice 10 instead.
    #[test]
    fn import_threads_run_only_on_idle_cpu_unless_asked_otherwise() {
        let on_a_thread = |priority| {
            std::thread::spawn(move || {
                lower_priority(priority);
                (scheduling(), std::thread::spawn(scheduling).join().unwrap())
            })
            .join()
            .unwrap()
        };
        let (own, child) = on_a_thread(ImportPriority::default());
        assert_eq!(own.0, libc::SCHED_IDLE, "the import thread's policy");
        assert_eq!(
            child.0,
            libc::SCHED_IDLE,
            "a thread the import thread started"
        );
        let (own, child) = on_a_thread(ImportPriority::Low);
        assert_eq!(
            own,
            (libc::SCHED_OTHER, IMPORT_NICE),
            "policy and nice at low"
        );
        assert_eq!(child, (libc::SCHED_OTHER, IMPORT_NICE), "inherited at low");
        assert_eq!(
            scheduling().0,
            libc::SCHED_OTHER,
            "the test thread was not touched"
        );
    }

    #[test]
    fn inputs_stay_inside_the_root() {
        let top = tempfile::tempdir().unwrap();
        let root = top.path().join("root");
        let outside = top.path().join("outside");
        std::fs::create_dir_all(root.join("tiles")).unwrap();
        std::fs::create_dir_all(&outside).unwrap();
        for f in ["tiles/a.laz", "tiles/b.laz", "one.las"] {
            std::fs::write(root.join(f), b"x").unwrap();
        }
        std::fs::write(outside.join("secret.las"), b"x").unwrap();
        std::os::unix::fs::symlink(outside.join("secret.las"), root.join("link.las")).unwrap();
        std::os::unix::fs::symlink(&outside, root.join("linkdir")).unwrap();
        let root = std::fs::canonicalize(&root).unwrap();
        let ok = |inputs: &[&str]| {
            let v: Vec<String> = inputs.iter().map(|s| s.to_string()).collect();
            resolve_inputs(&root, &v)
        };
        let names = |v: Vec<PathBuf>| -> Vec<String> {
            v.iter()
                .map(|p| p.strip_prefix(&root).unwrap().display().to_string())
                .collect()
        };
        assert_eq!(
            names(ok(&["tiles"]).unwrap()),
            ["tiles/a.laz", "tiles/b.laz"]
        );
        assert_eq!(
            names(ok(&["tiles/*.laz", "one.las"]).unwrap()),
            ["tiles/a.laz", "tiles/b.laz", "one.las"]
        );
        let absolute = root.join("one.las").display().to_string();
        assert_eq!(names(ok(&[&absolute]).unwrap()), ["one.las"]);
        for (input, want) in [
            ("../outside/secret.las", "'..' is not allowed"),
            ("tiles/../../outside", "'..' is not allowed"),
            ("link.las", "outside the import root"),
            ("linkdir", "outside the import root"),
            ("linkdir/*.las", "outside the import root"),
            ("/etc/passwd", "outside the import root"),
            ("missing.las", "No such file"),
            ("", "is not a path"),
        ] {
            let e = ok(&[input]).unwrap_err().to_string();
            assert!(e.contains(want), "{input}: {e}");
        }
        assert!(ok(&[]).unwrap_err().to_string().contains("empty"));
    }
}
