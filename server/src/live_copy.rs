//! Copies of the pool a running daemon serves (`POST /v1/copies`): a backup, or the pool for
//! a new replica, made without stopping the server. sled locks a pool per process, so the
//! stand-alone `arbor-server copy` needs the daemon stopped; this copy reads through the
//! daemon's open pool instead.
//!
//! * **Where copies go**: only into a new directory directly under the configured copy root
//!   (`serve --copy-root DIR`), named by the request (a plain directory name, never a path); a
//!   destination that exists, or that another copy queued or running writes, is refused.
//! * **What is copied**: the generations published when the copy was asked for (every scene,
//!   or the ones named), whatever replaces them meanwhile; their trees are opened at submission
//!   and a generation retired while a copy holds it is kept until the copy ends
//!   ([`Copies::holds`], asked by the scene manager's reaper). The daemon's state files
//!   (certificate, key, admin token, path memory) go with it, so a server on the copy keeps the
//!   fingerprint clients pinned.
//! * **The same guarantees as the stand-alone copy** ([`crate::pool::copy`]): written into a
//!   partial directory beside the destination, opened again and compared with the source pack
//!   by pack, renamed into place only then; a copy that fails, is cancelled or is killed leaves
//!   no pool at the destination. The partial directories of copies killed with the daemon are
//!   removed when it starts again.
//! * **Memory**: the source is read by a `get` per pack ([`copy_served`]), which sled's page
//!   cache bounds; the copy's own pool is closed and opened again every 64 MiB.
//! * **CPU**: one copy at a time, queued, on a worker thread at the import priority
//!   ([`ImportPriority`]: `SCHED_IDLE` by default), so streaming keeps its rate.
//! * **Disk**: every source pack read, for the copy and for the compare, takes its bytes from the
//!   daemon's [`ReadPace`] (`serve --background-read-rate`, shared with checks); a cancelled
//!   copy stops waiting.
//! * **Cancellation**: `DELETE /v1/copies/{id}` ([`Copies::cancel`]), and every copy queued or
//!   running when the scene manager is dropped, stops after the pack in hand and removes its
//!   partial directory.
//! * **Scheduled copies**: with `serve --copy-every`, every published scene is copied each
//!   period into `scheduled-<UTC time>` ([`Copies::submit_scheduled`]; skipped while the last
//!   one runs), and after each that succeeds the oldest scheduled copies beyond `--copy-keep`
//!   are removed ([`prune_scheduled`]: only directories named exactly so).
//! * **Metrics**: copies ended by outcome, and when the last one succeeded
//!   ([`Copies::figures`]): what an alert on a missing backup reads.

use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Instant, SystemTime};

use serde::{Deserialize, Serialize};

use crate::daemon::ADMIN_TOKEN_FILE;
use crate::jobs::{BackgroundJob, JobBoard};
use crate::live_import::{ImportPriority, lock, lower_priority, unix_seconds};
use crate::pace::ReadPace;
use crate::periodic::{ScheduleFigures, utc_fields, utc_time};
use crate::pool::copy::{
    CopiedScene, CopyError, CopyOptions, CopyProgress, CopyReport, copy_served,
};
use crate::pool::{Pool, PoolError, StoredScene};
use crate::service::path_memory::PATHS_FILE;
use crate::service::tls::{CERT_FILE, KEY_FILE};

/// The daemon's state files a copy carries (read from its data directory).
pub const CARRIED_FILES: [&str; 4] = [CERT_FILE, KEY_FILE, ADMIN_TOKEN_FILE, PATHS_FILE];

/// Longest destination name.
const MAX_NAME_BYTES: usize = 128;

/// Why a copy request was refused before it was queued. Each maps to an HTTP status in the
/// admin API.
#[derive(Debug, thiserror::Error)]
pub enum LiveCopyError {
    /// The daemon was started without a copy root.
    #[error("copies are disabled: start the daemon with --copy-root DIR")]
    Disabled,
    /// The destination is not a plain directory name.
    #[error(
        "copy destination {0:?}: a directory name of 1 to 128 letters, digits, '-', '_' or '.', not starting with '.'"
    )]
    BadName(String),
    /// The destination of a copy asked for is named as scheduled copies are, which
    /// `--copy-keep` removes.
    #[error(
        "copy destination {0:?} is named as scheduled copies are (scheduled-<UTC time>), which --copy-keep removes: choose another name"
    )]
    Reserved(String),
    /// The destination exists under the copy root (a copy never writes into a directory it did
    /// not make), or a copy queued or running writes it.
    #[error("copy destination {0:?} {1}")]
    DestinationTaken(String, &'static str),
    /// A scene asked for is not published, or the pool could not be read.
    #[error(transparent)]
    Pool(#[from] PoolError),
}

/// `POST /v1/copies`'s body.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CopyRequest {
    /// The new directory's name under the copy root.
    pub to: String,
    /// Scenes to copy; empty or absent: every published scene.
    #[serde(default)]
    pub scenes: Vec<String>,
}

/// Where a copy stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CopyPhase {
    /// Waiting for the copy before it.
    Queued,
    Running,
    /// Done: the copy is in place, compared with the source.
    Done,
    /// Nothing is left at the destination (the error says why).
    Failed,
    /// Cancelled before it ended; nothing is left at the destination.
    Cancelled,
}

impl CopyPhase {
    /// The phase as the API and `/metrics` name it.
    pub fn as_str(self) -> &'static str {
        match self {
            CopyPhase::Queued => "queued",
            CopyPhase::Running => "running",
            CopyPhase::Done => "done",
            CopyPhase::Failed => "failed",
            CopyPhase::Cancelled => "cancelled",
        }
    }
}

/// The outcomes a copy can end with, as `/metrics` labels them.
pub const OUTCOMES: [CopyPhase; 3] = [CopyPhase::Done, CopyPhase::Failed, CopyPhase::Cancelled];

/// A scene a copy holds: its name and the generation copied.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CopySceneRef {
    pub name: String,
    pub generation: u64,
}

/// What a copy that ended wrote.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CopySummary {
    /// Packs and bytes per scene.
    pub scenes: Vec<CopiedScene>,
    /// The state files carried.
    pub carried: Vec<String>,
    /// The copy's database on disk.
    pub disk_bytes: u64,
    /// Writing, then comparing with the source.
    pub copy_seconds: f64,
    pub check_seconds: f64,
}

impl From<CopyReport> for CopySummary {
    fn from(r: CopyReport) -> Self {
        CopySummary {
            scenes: r.scenes,
            carried: r.carried,
            disk_bytes: r.disk_bytes,
            copy_seconds: r.copy_time.as_secs_f64(),
            check_seconds: r.check_time.as_secs_f64(),
        }
    }
}

/// What `GET /v1/copies/{id}` answers.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CopyStatus {
    pub id: u64,
    /// The destination's name under the copy root, and its path.
    pub to: String,
    pub path: String,
    /// Made by `serve --copy-every` (named [`SCHEDULED_PREFIX`] and its time, pruned to
    /// `--copy-keep`), not asked for.
    pub scheduled: bool,
    pub scenes: Vec<CopySceneRef>,
    pub phase: CopyPhase,
    /// Bytes of treelet blocks the scenes hold, and how many are copied so far.
    pub bytes_planned: u64,
    pub bytes_copied: u64,
    /// Seconds since submission (until it ended, when it did).
    pub seconds: f64,
    /// Submission time, seconds since the Unix epoch.
    pub submitted_unix: f64,
    /// Why it failed.
    pub error: Option<String>,
    /// What was written, when done.
    pub report: Option<CopySummary>,
}

#[derive(Debug)]
struct Job {
    id: u64,
    to: String,
    path: PathBuf,
    scheduled: bool,
    scenes: Vec<CopySceneRef>,
    /// The scenes' trees, until the worker takes them.
    stored: Mutex<Option<Vec<StoredScene>>>,
    started: AtomicBool,
    /// Shared with the scenes' reads: a cancelled copy stops waiting for the pace.
    cancelled: Arc<AtomicBool>,
    planned: u64,
    copied: AtomicU64,
    submitted: SystemTime,
    clock: Instant,
    outcome: Mutex<Option<Outcome>>,
}

#[derive(Clone, Debug)]
struct Outcome {
    seconds: f64,
    phase: CopyPhase,
    error: Option<String>,
    report: Option<CopySummary>,
}

impl BackgroundJob for Job {
    type Status = CopyStatus;

    fn finished(&self) -> bool {
        lock(&self.outcome).is_some()
    }

    fn request_cancel(&self) {
        self.cancelled.store(true, Ordering::Release);
        tracing::info!(id = self.id, to = %self.to, "copy cancelled");
    }

    fn status(&self) -> CopyStatus {
        let outcome = lock(&self.outcome).clone();
        let (phase, seconds, error, report) = match outcome {
            Some(o) => (o.phase, o.seconds, o.error, o.report),
            None => (
                if self.started.load(Ordering::Acquire) {
                    CopyPhase::Running
                } else {
                    CopyPhase::Queued
                },
                self.clock.elapsed().as_secs_f64(),
                None,
                None,
            ),
        };
        CopyStatus {
            id: self.id,
            to: self.to.clone(),
            path: self.path.display().to_string(),
            scheduled: self.scheduled,
            scenes: self.scenes.clone(),
            phase,
            bytes_planned: self.planned,
            bytes_copied: self.copied.load(Ordering::Relaxed),
            seconds,
            submitted_unix: unix_seconds(self.submitted),
            error,
            report,
        }
    }
}

/// What `/metrics` reports of the copies.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CopyFigures {
    /// Copies ended since the daemon started, in [`OUTCOMES`] order.
    pub ended: [u64; 3],
    /// When the last successful copy ended, seconds since the Unix epoch.
    pub last_done_unix: Option<f64>,
    /// Scheduled copies skipped because the last one had not ended.
    pub skipped: u64,
    /// The copies by `--copy-every`/`--copy-at`, if scheduled.
    pub scheduled: Option<ScheduleFigures>,
}

/// Where copies are written and what they carry.
#[derive(Clone, Debug)]
struct Places {
    /// The copy root, canonicalized; `None`: copies disabled.
    root: Option<PathBuf>,
    /// The daemon's data directory (its state files).
    state_dir: PathBuf,
    /// Scheduled copies kept once one succeeds (`None`: every one).
    keep_scheduled: Option<NonZeroUsize>,
}

/// The daemon's pool copies: a queue, its worker, and the copies kept for status. Held by the
/// scene manager ([`crate::live_import::LiveImports`]), whose routes reach it.
#[derive(Debug)]
pub struct Copies {
    pool: Pool,
    places: Places,
    board: JobBoard<Job>,
    figures: Arc<Mutex<CopyFigures>>,
    /// The pace the copies' reads keep (shared with the daemon's checks).
    pace: Arc<ReadPace>,
}

impl Copies {
    /// Copies of `pool`'s scenes into new directories under `root` (`None`: copies refused),
    /// carrying the state files of `state_dir`, run one at a time on a worker thread at
    /// `priority`, their reads held to `pace`; after each scheduled copy that succeeds, the
    /// newest `keep_scheduled` scheduled copies are kept ([`prune_scheduled`]). The partial
    /// directories copies left under `root` when the daemon was killed are removed first.
    pub fn new(
        pool: Pool,
        root: Option<&Path>,
        state_dir: &Path,
        priority: ImportPriority,
        pace: Arc<ReadPace>,
        keep_scheduled: Option<NonZeroUsize>,
    ) -> std::io::Result<Copies> {
        let root = root.map(std::fs::canonicalize).transpose()?;
        if let Some(root) = &root {
            remove_partial_copies(root)?;
        }
        let (tx, rx) = mpsc::channel::<Arc<Job>>();
        let figures = Arc::new(Mutex::new(CopyFigures::default()));
        let places = Places {
            root,
            state_dir: state_dir.to_owned(),
            keep_scheduled,
        };
        let worker = (pool.clone(), places.clone(), figures.clone());
        std::thread::Builder::new()
            .name("arbor-copy".into())
            .spawn(move || {
                lower_priority(priority);
                let (pool, places, figures) = worker;
                while let Ok(job) = rx.recv() {
                    run_job(&pool, &places, &job, &figures);
                }
            })?;
        Ok(Copies {
            pool,
            places,
            board: JobBoard::new(tx),
            figures,
            pace,
        })
    }

    /// Whether copies are enabled (a copy root is configured).
    pub fn enabled(&self) -> bool {
        self.places.root.is_some()
    }

    /// Checks and queues a copy; returns its id.
    pub fn submit(&self, req: &CopyRequest) -> Result<u64, LiveCopyError> {
        if is_scheduled_name(&req.to) {
            return Err(LiveCopyError::Reserved(req.to.clone()));
        }
        self.submit_job(req, false)
    }

    /// Queues the scheduled copy due at `due` (`serve --copy-every/--copy-at`): every published
    /// scene into [`scheduled_name`]`(due)`. `None`: a scheduled copy is still queued or
    /// running, and this one is skipped (and counted) rather than piled behind it.
    pub fn submit_scheduled(&self, due: SystemTime) -> Result<Option<u64>, LiveCopyError> {
        if self
            .board
            .any_running(|j| j.scheduled && !j.cancelled.load(Ordering::Acquire))
        {
            lock(&self.figures).skipped += 1;
            return Ok(None);
        }
        let to = scheduled_name(due);
        self.submit_job(&CopyRequest { to, scenes: vec![] }, true)
            .map(Some)
    }

    fn submit_job(&self, req: &CopyRequest, scheduled: bool) -> Result<u64, LiveCopyError> {
        let root = self.places.root.as_ref().ok_or(LiveCopyError::Disabled)?;
        validate_destination(&req.to)?;
        let path = root.join(&req.to);
        // The scenes are opened under the jobs' lock: the reaper asks `holds` under it too, so
        // a generation it finds unheld cannot be opened here afterwards.
        let jobs = self.board.lock();
        if jobs.values().any(|j| j.to == req.to && !j.finished()) {
            return Err(LiveCopyError::DestinationTaken(
                req.to.clone(),
                "is being written by another copy",
            ));
        }
        if path.symlink_metadata().is_ok() {
            return Err(LiveCopyError::DestinationTaken(
                req.to.clone(),
                "already exists under the copy root: a copy is made into a new directory",
            ));
        }
        let names: Vec<String> = if req.scenes.is_empty() {
            self.pool
                .generations()?
                .into_iter()
                .map(|(n, _)| n)
                .collect()
        } else {
            let mut names = req.scenes.clone();
            names.sort();
            names.dedup();
            names
        };
        let cancelled = Arc::new(AtomicBool::new(false));
        let stored = names
            .iter()
            .map(|n| {
                let scene = self.pool.scene(n)?.with_reads_apart();
                Ok(scene.paced(self.pace.clone(), cancelled.clone()))
            })
            .collect::<Result<Vec<StoredScene>, PoolError>>()?;
        let id = self.board.next_id();
        let scenes: Vec<CopySceneRef> = stored
            .iter()
            .map(|s| CopySceneRef {
                name: s.description.name.clone(),
                generation: s.generation,
            })
            .collect();
        let planned = stored
            .iter()
            .map(|s| s.description.stats.stored_bytes())
            .sum();
        let job = Arc::new(Job {
            id,
            to: req.to.clone(),
            path,
            scheduled,
            scenes,
            stored: Mutex::new(Some(stored)),
            started: AtomicBool::new(false),
            cancelled,
            planned,
            copied: AtomicU64::new(0),
            submitted: SystemTime::now(),
            clock: Instant::now(),
            outcome: Mutex::new(None),
        });
        tracing::info!(
            id,
            to = %req.to,
            scenes = job.scenes.len(),
            scheduled,
            "copy queued"
        );
        if !self.board.add(jobs, id, job.clone()) {
            *lock(&job.outcome) = Some(Outcome {
                seconds: 0.0,
                phase: CopyPhase::Failed,
                error: Some("the copy worker has stopped".into()),
                report: None,
            });
        }
        Ok(id)
    }

    /// One copy's status.
    pub fn status(&self, id: u64) -> Option<CopyStatus> {
        self.board.status(id)
    }

    /// Every copy kept (queued, running, and the last finished ones), by id.
    pub fn list(&self) -> Vec<CopyStatus> {
        self.board.list()
    }

    /// Asks a queued or running copy to stop (after the pack in hand); its status then says
    /// `cancelled`. `None`: no such copy. A finished copy is left as it is.
    pub fn cancel(&self, id: u64) -> Option<CopyStatus> {
        self.board.cancel(id)
    }

    /// Whether a copy that has not ended reads `generation` (the reaper keeps it meanwhile).
    pub fn holds(&self, generation: u64) -> bool {
        self.board
            .any_running(|j| j.scenes.iter().any(|s| s.generation == generation))
    }

    /// When the newest scheduled copy under the copy root was due (its name says it; only
    /// whole copies, renamed into place, count). `None`: none, or copies disabled.
    pub fn last_scheduled(&self) -> Option<SystemTime> {
        let root = self.places.root.as_ref()?;
        std::fs::read_dir(root)
            .ok()?
            .filter_map(|e| e.ok())
            .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
            .filter_map(|e| scheduled_time(&e.file_name().to_string_lossy()))
            .max()
    }

    /// Says when the scheduled copy is next due (`/metrics`, the page).
    pub fn schedule_next(&self, figures: ScheduleFigures) {
        lock(&self.figures).scheduled = Some(figures);
    }

    /// Copies ended by outcome, when the last successful one ended, and the schedule's figures.
    pub fn figures(&self) -> CopyFigures {
        lock(&self.figures).clone()
    }
}

impl Drop for Copies {
    fn drop(&mut self) {
        self.board.cancel_all();
    }
}

/// Removes the partial directories (`.NAME.copy-partial`) of copies that did not end under
/// `root`: nothing else writes there, and no copy runs before the manager starts.
fn remove_partial_copies(root: &Path) -> std::io::Result<()> {
    for entry in std::fs::read_dir(root)? {
        let entry = entry?;
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if name.starts_with('.') && name.ends_with(".copy-partial") && entry.file_type()?.is_dir() {
            tracing::warn!(
                path = %entry.path().display(),
                "removing the partial directory of a copy that did not end"
            );
            std::fs::remove_dir_all(entry.path())?;
        }
    }
    Ok(())
}

/// The name of scheduled copies: this prefix, then the UTC time it was due, `YYYY-MM-DDTHHMMSSZ`
/// (names sort as times do). Only directories named so are ever pruned.
pub const SCHEDULED_PREFIX: &str = "scheduled-";

/// The destination of the scheduled copy due at `t`: [`SCHEDULED_PREFIX`] and its UTC time.
pub fn scheduled_name(t: SystemTime) -> String {
    let (year, month, day, hour, minute, second) = utc_fields(t);
    format!("{SCHEDULED_PREFIX}{year:04}-{month:02}-{day:02}T{hour:02}{minute:02}{second:02}Z")
}

/// The time a scheduled copy was due, read back from its name; `None` for any other name.
pub fn scheduled_time(name: &str) -> Option<SystemTime> {
    if !is_scheduled_name(name) {
        return None;
    }
    let t = &name[SCHEDULED_PREFIX.len()..];
    let field = |range: std::ops::Range<usize>| t[range].parse::<u64>().ok();
    utc_time(
        field(0..4)?,
        field(5..7)?,
        field(8..10)?,
        field(11..13)?,
        field(13..15)?,
        field(15..17)?,
    )
}

/// Whether `name` is a scheduled copy's name, exactly as [`scheduled_name`] writes one.
fn is_scheduled_name(name: &str) -> bool {
    let Some(time) = name.strip_prefix(SCHEDULED_PREFIX) else {
        return false;
    };
    let b = time.as_bytes();
    b.len() == 18
        && b.iter().enumerate().all(|(i, &c)| match i {
            4 | 7 => c == b'-',
            10 => c == b'T',
            17 => c == b'Z',
            _ => c.is_ascii_digit(),
        })
}

/// Removes all but the newest `keep` scheduled copies under `root` (directories named as
/// [`scheduled_name`] names them; nothing else is touched), and returns the names removed.
pub fn prune_scheduled(root: &Path, keep: NonZeroUsize) -> std::io::Result<Vec<String>> {
    let mut scheduled = Vec::new();
    for entry in std::fs::read_dir(root)? {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if is_scheduled_name(&name) && entry.file_type()?.is_dir() {
            scheduled.push(name);
        }
    }
    scheduled.sort();
    let old = scheduled.len().saturating_sub(keep.get());
    let removed: Vec<String> = scheduled.into_iter().take(old).collect();
    for name in &removed {
        std::fs::remove_dir_all(root.join(name))?;
        tracing::info!(name, "old scheduled copy removed (--copy-keep)");
    }
    Ok(removed)
}

/// Refuses a destination that is not a plain directory name (no separator, no `..`, no hidden
/// or partial directory of a copy).
pub fn validate_destination(to: &str) -> Result<(), LiveCopyError> {
    let plain = !to.is_empty()
        && to.len() <= MAX_NAME_BYTES
        && !to.starts_with('.')
        && to
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.'));
    if plain {
        Ok(())
    } else {
        Err(LiveCopyError::BadName(to.to_owned()))
    }
}

/// Runs one copy (or records it cancelled, if it was before it started), and counts its
/// outcome in `figures`.
fn run_job(pool: &Pool, places: &Places, job: &Job, figures: &Mutex<CopyFigures>) {
    // Taken once: a job is queued once, and the trees are let go when it ends.
    let Some(scenes) = lock(&job.stored).take() else {
        return;
    };
    let result = if job.cancelled.load(Ordering::Acquire) {
        Err(CopyError::Cancelled)
    } else {
        job.started.store(true, Ordering::Release);
        tracing::info!(id = job.id, to = %job.to, "copy started");
        let options = CopyOptions {
            carry_files: &CARRIED_FILES,
            stop: Some(&job.cancelled),
            ..CopyOptions::default()
        };
        copy_served(pool, scenes, &places.state_dir, &job.path, &options, &|p| {
            if let CopyProgress::Copied(n) = p {
                job.copied.fetch_add(n, Ordering::Relaxed);
            }
        })
    };
    let seconds = job.clock.elapsed().as_secs_f64();
    let outcome = match result {
        Ok(report) => {
            tracing::info!(
                id = job.id,
                to = %job.to,
                disk_bytes = report.disk_bytes,
                seconds,
                "copy done: compared with the source"
            );
            if let (true, Some(root), Some(keep)) =
                (job.scheduled, &places.root, places.keep_scheduled)
            {
                // After the new copy is whole, so a failed one never costs a good one.
                if let Err(e) = prune_scheduled(root, keep) {
                    tracing::error!(
                        "removing old scheduled copies under {}: {e}",
                        root.display()
                    );
                }
            }
            Outcome {
                seconds,
                phase: CopyPhase::Done,
                error: None,
                report: Some(report.into()),
            }
        }
        Err(CopyError::Cancelled) => {
            tracing::info!(id = job.id, to = %job.to, "copy stopped");
            Outcome {
                seconds,
                phase: CopyPhase::Cancelled,
                error: None,
                report: None,
            }
        }
        Err(e) => {
            tracing::error!(id = job.id, to = %job.to, "copy failed: {e}");
            Outcome {
                seconds,
                phase: CopyPhase::Failed,
                error: Some(e.to_string()),
                report: None,
            }
        }
    };
    {
        let mut f = lock(figures);
        if let Some(i) = OUTCOMES.iter().position(|&o| o == outcome.phase) {
            f.ended[i] += 1;
        }
        if outcome.phase == CopyPhase::Done {
            f.last_done_unix = Some(unix_seconds(SystemTime::now()));
        }
    }
    *lock(&job.outcome) = Some(outcome);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::{BuildOptions, DepthChoice};
    use crate::pipeline::{SceneImport, Superseded, import_scene, import_scene_observed};
    use crate::pool::copy::compare_scene;
    use crate::progress::ImportProgress;
    use std::time::UNIX_EPOCH;

    fn bunny_import(replace: bool) -> SceneImport {
        let request = SceneImport {
            name: "bunny".into(),
            input: Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../shared/data/meshes/stanford-bunny.obj"),
            build: BuildOptions {
                depth: DepthChoice::Fixed(6),
                treelet_bytes: 1024,
                progress: false,
                ..BuildOptions::default()
            },
            replace,
            ..SceneImport::default()
        };
        assert!(
            request.input.exists(),
            "the real scans in ../shared/data are required"
        );
        request
    }

    /// A pool holding the bunny, a copy root and a state directory, and copies whose queue
    /// this test drains itself (no worker: every step is the test's).
    struct Unstarted {
        dir: tempfile::TempDir,
        copies: Copies,
        rx: mpsc::Receiver<Arc<Job>>,
        pace: Arc<ReadPace>,
    }

    fn unstarted() -> Unstarted {
        let dir = tempfile::tempdir().unwrap();
        let pool = Pool::open(&dir.path().join("pool")).unwrap();
        import_scene(&pool, &bunny_import(false)).unwrap();
        let root = dir.path().join("copies");
        std::fs::create_dir(&root).unwrap();
        std::fs::write(dir.path().join("pool").join(CERT_FILE), "certificate").unwrap();
        let (tx, rx) = mpsc::channel();
        let copies = Copies {
            pool,
            places: Places {
                root: Some(std::fs::canonicalize(&root).unwrap()),
                state_dir: dir.path().join("pool"),
                keep_scheduled: None,
            },
            board: JobBoard::new(tx),
            figures: Arc::default(),
            pace: Arc::new(ReadPace::new(None)),
        };
        let pace = copies.pace.clone();
        Unstarted {
            dir,
            copies,
            rx,
            pace,
        }
    }

    impl Unstarted {
        fn run_next(&self) -> Arc<Job> {
            let job = self.rx.try_recv().expect("a copy queued");
            run_job(
                &self.copies.pool,
                &self.copies.places,
                &job,
                &self.copies.figures,
            );
            job
        }
    }

    /// The names in `dir`, sorted.
    fn names_in(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    fn request(to: &str) -> CopyRequest {
        CopyRequest {
            to: to.into(),
            scenes: Vec::new(),
        }
    }

    #[test]
    fn phases_are_named_as_serde_names_them() {
        for phase in [CopyPhase::Queued, CopyPhase::Running]
            .into_iter()
            .chain(OUTCOMES)
        {
            assert_eq!(serde_json::to_value(phase).unwrap(), phase.as_str());
        }
    }

    #[test]
    fn scheduled_copies_are_named_by_their_utc_time() {
        let at = |secs: u64| scheduled_name(UNIX_EPOCH + std::time::Duration::from_secs(secs));
        assert_eq!(at(0), "scheduled-1970-01-01T000000Z");
        // 2024-02-29 23:59:59 UTC (a leap day), then the next second.
        assert_eq!(at(1_709_251_199), "scheduled-2024-02-29T235959Z");
        assert_eq!(at(1_709_251_200), "scheduled-2024-03-01T000000Z");
        // 2000-12-31 (a leap year divisible by 400: day 366), 2100-03-01 (not a leap year).
        assert_eq!(at(978_220_800), "scheduled-2000-12-31T000000Z");
        assert_eq!(at(4_107_542_400), "scheduled-2100-03-01T000000Z");
        assert_eq!(at(1_764_646_245), "scheduled-2025-12-02T033045Z");
        for secs in [0, 1_709_251_199, 4_107_542_400] {
            let name = at(secs);
            assert!(is_scheduled_name(&name), "{name}");
            validate_destination(&name).unwrap();
        }
        for other in [
            "scheduled-",
            "scheduled-2024-02-29T235959",
            "scheduled-2024-02-29T235959Zx",
            "scheduled-2024-02-29 235959Z",
            "scheduled-2024_02-29T235959Z",
            "Scheduled-2024-02-29T235959Z",
            "nightly-2024-02-29",
        ] {
            assert!(!is_scheduled_name(other), "{other}");
        }
        // Names sort as times do.
        let mut names: Vec<String> = [4_107_542_400, 0, 1_709_251_200, 1_709_251_199]
            .into_iter()
            .map(at)
            .collect();
        names.sort();
        assert_eq!(names[0], at(0));
        assert_eq!(names[3], at(4_107_542_400));
    }

    #[test]
    fn pruning_keeps_the_newest_scheduled_copies_and_touches_nothing_else() {
        let root = tempfile::tempdir().unwrap();
        let dirs = [
            "scheduled-2026-11-28T030000Z",
            "scheduled-2026-11-30T030000Z",
            "scheduled-2026-11-29T030000Z",
            "scheduled-2026-12-01T030000Z",
            "scheduled-bogus",
            "nightly-2026-11-01",
            ".scheduled-2026-12-02T030000Z.copy-partial",
        ];
        for d in dirs {
            std::fs::create_dir(root.path().join(d)).unwrap();
            std::fs::write(root.path().join(d).join("db"), "a pool").unwrap();
        }
        // A file with a scheduled name is not a copy.
        std::fs::write(root.path().join("scheduled-2000-01-01T000000Z"), "").unwrap();
        let keep = NonZeroUsize::new(2).unwrap();
        let removed = prune_scheduled(root.path(), keep).unwrap();
        assert_eq!(
            removed,
            [
                "scheduled-2026-11-28T030000Z",
                "scheduled-2026-11-29T030000Z"
            ]
        );
        let left = names_in(root.path());
        assert_eq!(
            left,
            [
                ".scheduled-2026-12-02T030000Z.copy-partial",
                "nightly-2026-11-01",
                "scheduled-2000-01-01T000000Z",
                "scheduled-2026-11-30T030000Z",
                "scheduled-2026-12-01T030000Z",
                "scheduled-bogus",
            ]
        );
        // Fewer than kept: nothing goes.
        assert!(prune_scheduled(root.path(), keep).unwrap().is_empty());
    }

    /// A scheduled copy is skipped while the last one is queued; once one is done, the oldest
    /// scheduled copies beyond the number kept go, and copies asked for stay.
    #[test]
    fn scheduled_copies_do_not_pile_up_and_are_pruned_after_one_succeeds() {
        let mut t = unstarted();
        t.copies.places.keep_scheduled = NonZeroUsize::new(2);
        let root = t.dir.path().join("copies");
        for old in [
            "scheduled-2020-01-01T000000Z",
            "scheduled-2020-01-02T000000Z",
        ] {
            std::fs::create_dir(root.join(old)).unwrap();
        }
        let copies = &t.copies;
        let day = |d: u64| UNIX_EPOCH + std::time::Duration::from_secs(1_764_633_600 + d * 86_400);
        let first = copies.submit_scheduled(day(0)).unwrap().expect("queued");
        assert_eq!(copies.submit_scheduled(day(1)).unwrap(), None, "piled up");
        assert_eq!(copies.figures().skipped, 1, "a skipped copy not counted");
        let asked = copies.submit(&request("asked")).unwrap();
        assert!(matches!(
            copies.submit(&request("scheduled-2030-01-01T000000Z")),
            Err(LiveCopyError::Reserved(_))
        ));
        assert!(copies.status(first).unwrap().scheduled);
        assert!(!copies.status(asked).unwrap().scheduled);
        t.run_next();
        assert_eq!(t.copies.status(first).unwrap().phase, CopyPhase::Done);
        t.run_next();
        let left = names_in(&root);
        assert_eq!(
            left,
            [
                "asked",
                "scheduled-2020-01-02T000000Z",
                "scheduled-2025-12-02T000000Z"
            ]
        );
        // A scheduled copy cancelled while queued does not hold the next one back.
        let third = t.copies.submit_scheduled(day(2)).unwrap().expect("queued");
        t.copies.cancel(third);
        assert!(t.copies.submit_scheduled(day(3)).unwrap().is_some());
    }

    #[test]
    fn a_scheduled_copy_says_when_it_was_due_and_the_newest_whole_one_counts() {
        for t in [0, 951_782_400, 1_764_658_800, 4_107_542_399] {
            let t = std::time::UNIX_EPOCH + std::time::Duration::from_secs(t);
            assert_eq!(scheduled_time(&scheduled_name(t)), Some(t));
        }
        for other in [
            "scheduled-2026-02-30T000000Z",
            "scheduled-2026-12-02T250000Z",
            "scheduled-bogus",
            "manual",
        ] {
            assert_eq!(scheduled_time(other), None, "{other}");
        }
        let t = unstarted();
        let root = t.dir.path().join("copies");
        assert_eq!(t.copies.last_scheduled(), None);
        std::fs::create_dir(root.join("scheduled-2026-12-01T030000Z")).unwrap();
        std::fs::create_dir(root.join("scheduled-2025-12-01T030000Z")).unwrap();
        std::fs::create_dir(root.join(".scheduled-2027-01-01T030000Z.copy-partial")).unwrap();
        std::fs::create_dir(root.join("scheduled-2026-13-01T030000Z")).unwrap();
        std::fs::write(root.join("scheduled-2028-01-01T030000Z"), "a file").unwrap();
        assert_eq!(
            t.copies.last_scheduled().map(scheduled_name).as_deref(),
            Some("scheduled-2026-12-01T030000Z")
        );
    }

    #[test]
    fn destinations_are_plain_names_under_the_root() {
        for bad in [
            "",
            ".",
            "..",
            ".hidden",
            "a/b",
            "../up",
            "/abs",
            "a b",
            "a\\b",
            "ü",
            &"x".repeat(129),
        ] {
            assert!(
                matches!(validate_destination(bad), Err(LiveCopyError::BadName(_))),
                "{bad:?} accepted"
            );
        }
        for good in ["backup", "pool-2026-12-02", "a.b_c", &"x".repeat(128)] {
            validate_destination(good).unwrap();
        }
    }

    /// What a copy holds is what was published when it was asked for: the bunny replaced
    /// before the copy runs is copied as it was, pack for pack, and its old generation is held
    /// until the copy ends. Destinations are taken once; a copy cancelled while queued writes
    /// nothing; the figures count each outcome; dropping the manager cancels what is queued.
    #[test]
    fn copies_hold_the_generations_published_when_asked_and_end_as_counted() {
        let t = unstarted();
        let copies = &t.copies;
        let disabled = Copies::new(
            copies.pool.clone(),
            None,
            t.dir.path(),
            ImportPriority::Idle,
            t.pace.clone(),
            None,
        )
        .unwrap();
        assert!(!disabled.enabled() && copies.enabled());
        // A manager starting removes what copies killed with the daemon left, and only that.
        let root = t.dir.path().join("copies");
        for left in [".killed.copy-partial", ".other.copy-partial/db"] {
            std::fs::create_dir_all(root.join(left)).unwrap();
        }
        std::fs::create_dir(root.join("kept")).unwrap();
        std::fs::write(root.join(".note.copy-partial"), "a file, not a copy").unwrap();
        let restarted = Copies::new(
            copies.pool.clone(),
            Some(&root),
            t.dir.path(),
            ImportPriority::Idle,
            t.pace.clone(),
            None,
        )
        .unwrap();
        let left = names_in(&root);
        assert_eq!(left, [".note.copy-partial", "kept"]);
        std::fs::remove_dir(root.join("kept")).unwrap();
        std::fs::remove_file(root.join(".note.copy-partial")).unwrap();
        drop(restarted);
        assert!(matches!(
            disabled.submit(&request("a")),
            Err(LiveCopyError::Disabled)
        ));
        assert!(matches!(
            copies.submit(&CopyRequest {
                to: "a".into(),
                scenes: vec!["nope".into()],
            }),
            Err(LiveCopyError::Pool(PoolError::NoSuchScene(_)))
        ));
        assert!(matches!(
            copies.submit(&request("../a")),
            Err(LiveCopyError::BadName(_))
        ));

        let old = copies.pool.scene("bunny").unwrap();
        let first = copies.submit(&request("first")).unwrap();
        assert!(matches!(
            copies.submit(&request("first")),
            Err(LiveCopyError::DestinationTaken(..))
        ));
        assert!(copies.holds(old.generation));
        let s = copies.status(first).unwrap();
        assert_eq!(s.phase, CopyPhase::Queued);
        assert_eq!(
            s.scenes,
            [CopySceneRef {
                name: "bunny".into(),
                generation: old.generation
            }]
        );

        // Replaced before the copy runs; the old generation's trees kept (as the daemon's
        // reaper keeps them while `holds` says so).
        let (_, retired) = import_scene_observed(
            &copies.pool,
            &bunny_import(true),
            &ImportProgress::default(),
            Superseded::Keep,
        )
        .unwrap();
        assert_eq!(retired, Some(old.generation));
        let job = t.run_next();
        let s = job.status();
        assert_eq!(s.phase, CopyPhase::Done, "{s:?}");
        assert!(!copies.holds(old.generation));
        assert_eq!(s.bytes_copied, s.bytes_planned);
        let report = s.report.unwrap();
        assert_eq!(report.carried, [CERT_FILE]);
        assert_eq!(report.scenes[0].name, "bunny");
        let dest = t.dir.path().join("copies").join("first");
        {
            let copied = Pool::open(&dest).unwrap();
            let scene = copied.scene("bunny").unwrap();
            compare_scene(&old, &scene).unwrap();
            assert_ne!(
                scene.description,
                copies.pool.scene("bunny").unwrap().description,
                "the replacement was copied"
            );
        }
        assert!(matches!(
            copies.submit(&request("first")),
            Err(LiveCopyError::DestinationTaken(..))
        ));

        // Cancelled while queued: nothing written.
        let second = copies.submit(&request("second")).unwrap();
        assert_eq!(copies.cancel(second).unwrap().phase, CopyPhase::Queued);
        t.run_next();
        let s = copies.status(second).unwrap();
        assert_eq!((s.phase, s.bytes_copied), (CopyPhase::Cancelled, 0));
        assert!(!t.dir.path().join("copies").join("second").exists());
        assert_eq!(copies.cancel(first).unwrap().phase, CopyPhase::Done);
        assert!(copies.cancel(99).is_none());
        let f = copies.figures();
        assert_eq!(f.ended, [1, 0, 1]);
        assert!(f.last_done_unix.is_some_and(|t| t > 1.7e9));
        assert_eq!(
            copies.list().iter().map(|s| s.id).collect::<Vec<_>>(),
            [first, second]
        );

        // A copy that fails leaves nothing and says why; dropping the manager cancels.
        let third = copies.submit(&request("third")).unwrap();
        std::fs::create_dir(t.dir.path().join("copies").join("third")).unwrap();
        t.run_next();
        let s = copies.status(third).unwrap();
        assert_eq!(s.phase, CopyPhase::Failed);
        assert!(s.error.unwrap().contains("already exists"));
        copies.submit(&request("fourth")).unwrap();
        let Unstarted {
            dir,
            copies,
            rx,
            pace,
        } = t;
        let (pool, places, figures) = (
            copies.pool.clone(),
            copies.places.clone(),
            copies.figures.clone(),
        );
        drop((copies, pace));
        let job = rx.try_recv().unwrap();
        run_job(&pool, &places, &job, &figures);
        assert_eq!(job.status().phase, CopyPhase::Cancelled);
        assert!(!dir.path().join("copies").join("fourth").exists());
        assert_eq!(lock(&figures).ended, [1, 1, 2]);
    }
}
