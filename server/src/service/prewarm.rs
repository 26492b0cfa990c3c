//! Reading the pool's files into the page cache once at start (`pool_prewarm`), front to back
//! in large reads, so that a fresh server's treelet reads find their pages in memory instead of
//! waiting for the disk one page at a time.
//!
//! Why: a treelet read is a page or two somewhere in the pool's file. A disk that limits
//! operations per second (cloud block storage: a burst, then a baseline of a few hundred)
//! serves those one at a time: with the server held to 500 reads/s, a fresh server's first
//! view of the 10⁸-point city (some 10,000 such reads; about 1 s otherwise) did not converge in
//! 3.1–3.9 s. The city's 1.47 GB pool read front to back is a few hundred reads of about a MiB
//! (6–7 s at that limit, under 1 s without it); a client that came 12 s after the start then
//! converged in 0.89–0.98 s (docs/measurements.md, stop 68).
//!
//! It runs on a thread of its own beside the service, which serves from the start, and reads a
//! chunk only once the pool's readers have been quiet for a while ([`QuietReaders`]), so a
//! client's reads never wait behind it. What it costs: page cache, not the server's own memory.
//! So by default (`auto`) it runs only when the pool's files fit in half of the memory the
//! process may still use (`MemAvailable`, and the room below its cgroups' limits): a pool larger
//! than that would evict its own pages before clients asked for them, and the server reads at
//! random as before. `/metrics` shows its progress (`arbor_pool_prewarm_*`).
//!
//! What the last run's clients had in the page cache comes first ([`super::hot_pages`], saved
//! in the data directory while the server runs and when it stops): the whole pool after it when
//! it fits, and only those pages, up to half the room, when it does not.

use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Mutex, mpsc};
use std::time::{Duration, Instant};

use serde::Deserialize;

use super::hot_pages;
use super::readers::ReadFigures;

/// Whether the pool's files are read into the page cache at start (`pool_prewarm`, CLI
/// `--pool-prewarm`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum PoolPrewarm {
    /// The last run's hot pages, then the rest of the files when they fit in half of the memory
    /// the process may still use; only the hot pages, up to that half, when they do not.
    #[default]
    Auto,
    /// The last run's hot pages, then every file, however large (a pool larger than memory
    /// evicts its own pages as it goes).
    Always,
    /// Never: every page is read from the disk when a treelet first needs it.
    Off,
}

/// How many bytes one read takes: large enough that a disk limited in operations per second
/// reads the pool at its bandwidth.
pub const PREWARM_READ_BYTES: usize = 4 << 20;

/// What the prewarm did, for `/metrics`.
#[derive(Debug, Default)]
pub struct PrewarmFigures {
    /// Bytes it set out to read (0: it did not run).
    pub total: AtomicU64,
    /// Of those, the bytes of the last run's hot pages, read first.
    pub hot: AtomicU64,
    /// Bytes read so far.
    pub read: AtomicU64,
    /// 1 once it ended (all read, stopped, or failed), else 0.
    pub done: AtomicU64,
}

/// One read of the prewarm: `len` bytes of the file at `path` from `offset`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WarmRead {
    pub path: PathBuf,
    pub offset: u64,
    pub len: u64,
}

/// What the prewarm reads, in order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Plan {
    pub reads: Vec<WarmRead>,
    /// Bytes of the last run's hot pages among them (the first reads).
    pub hot_bytes: u64,
    /// Whether every file is read whole after them.
    pub whole: bool,
}

/// What the prewarm of the pool's `files` reads under `mode`, with the last run's `hot` pages
/// and `room` bytes of memory the process may still use (`None`: unknown); `Err` says why it
/// reads nothing, for the log.
pub fn plan(
    mode: PoolPrewarm,
    files: &[(PathBuf, u64)],
    hot: Vec<WarmRead>,
    room: Option<u64>,
) -> Result<Plan, String> {
    let pool_bytes: u64 = files.iter().map(|f| f.1).sum();
    let hot_bytes: u64 = hot.iter().map(|r| r.len).sum();
    let whole = |hot: Vec<WarmRead>| {
        let rest = the_rest(files, &hot);
        Plan {
            reads: [hot, rest].concat(),
            hot_bytes,
            whole: true,
        }
    };
    match (mode, room) {
        (PoolPrewarm::Off, _) => Err("pool_prewarm is off".into()),
        (PoolPrewarm::Always, _) => Ok(whole(hot)),
        (PoolPrewarm::Auto, None) => Err(
            "the memory the process may use is unknown (set pool_prewarm = \"always\" to read it anyway)"
                .into(),
        ),
        (PoolPrewarm::Auto, Some(room)) if pool_bytes <= room / 2 => Ok(whole(hot)),
        (PoolPrewarm::Auto, Some(room)) => {
            let too_large = format!(
                "the pool's {} MiB exceed half of the {} MiB of memory left",
                pool_bytes >> 20,
                room >> 20
            );
            let mut budget = room / 2;
            let mut reads = Vec::new();
            for mut r in hot {
                if budget == 0 {
                    break;
                }
                r.len = r.len.min(budget);
                budget -= r.len;
                reads.push(r);
            }
            if reads.is_empty() {
                let why = if hot_bytes == 0 {
                    "no earlier run left a list of its hot pages"
                } else {
                    "there is no room for its hot pages either"
                };
                return Err(format!(
                    "{too_large}, and {why} (set pool_prewarm = \"always\" to read it anyway)"
                ));
            }
            Ok(Plan {
                hot_bytes: reads.iter().map(|r| r.len).sum(),
                reads,
                whole: false,
            })
        }
    }
}

/// What is left of the `files` once the `hot` reads are done: each file's parts they do not
/// cover, front to back, so the pool is read once in all.
fn the_rest(files: &[(PathBuf, u64)], hot: &[WarmRead]) -> Vec<WarmRead> {
    let mut rest = Vec::new();
    for (path, len) in files {
        let mut covered: Vec<(u64, u64)> = hot
            .iter()
            .filter(|r| r.path == *path)
            .map(|r| (r.offset, r.offset.saturating_add(r.len)))
            .collect();
        covered.sort_unstable();
        let mut at = 0;
        for (start, end) in covered.into_iter().chain([(*len, *len)]) {
            let start = start.min(*len);
            if start > at {
                rest.push(WarmRead {
                    path: path.clone(),
                    offset: at,
                    len: start - at,
                });
            }
            at = at.max(end);
        }
    }
    rest
}

/// `MemAvailable` of a `/proc/meminfo` text, bytes.
pub fn mem_available(meminfo: &str) -> Option<u64> {
    let kib: u64 = meminfo
        .lines()
        .find_map(|l| l.strip_prefix("MemAvailable:"))?
        .trim()
        .strip_suffix("kB")?
        .trim()
        .parse()
        .ok()?;
    kib.checked_mul(1024)
}

/// The room below the memory limits of the process's cgroup and its ancestors, bytes (the
/// least of them): `proc_cgroup` is the text of `/proc/self/cgroup`, `read` reads a file of the
/// cgroup hierarchy by its path. Cgroup v1's memory controller (`memory.limit_in_bytes`,
/// `memory.usage_in_bytes` under `/sys/fs/cgroup/memory`) or v2's (`memory.max`,
/// `memory.current` under `/sys/fs/cgroup`). `None`: no limit, or none could be read.
pub fn cgroup_room(proc_cgroup: &str, read: impl Fn(&Path) -> Option<String>) -> Option<u64> {
    let number = |path: PathBuf| -> Option<u64> { read(&path)?.trim().parse().ok() };
    for line in proc_cgroup.lines() {
        let mut fields = line.splitn(3, ':');
        let (_, controllers, path) = (fields.next()?, fields.next()?, fields.next()?);
        let (root, limit, usage) = if controllers.split(',').any(|c| c == "memory") {
            (
                "/sys/fs/cgroup/memory",
                "memory.limit_in_bytes",
                "memory.usage_in_bytes",
            )
        } else if controllers.is_empty() {
            ("/sys/fs/cgroup", "memory.max", "memory.current")
        } else {
            continue;
        };
        // The cgroup, then each parent up to the root: a limit set on a parent (a systemd
        // slice, a Kubernetes pod) binds its children too.
        let own = Path::new(root).join(path.trim_start_matches('/'));
        let room = own
            .ancestors()
            .take_while(|dir| dir.starts_with(root))
            .filter_map(|dir| {
                // "max" (v2) or a number near 2⁶³ (v1) is no limit.
                let limit = number(dir.join(limit)).filter(|&l| l < 1 << 62)?;
                Some(limit.saturating_sub(number(dir.join(usage)).unwrap_or(0)))
            })
            .min();
        if room.is_some() {
            return room;
        }
    }
    None
}

/// The memory this process may still use: `MemAvailable`, less where a cgroup's limit
/// ([`cgroup_room`]) is nearer. `None` where neither can be read (not Linux).
pub fn memory_room() -> Option<u64> {
    let read = |p: &Path| std::fs::read_to_string(p).ok();
    let available = read(Path::new("/proc/meminfo")).and_then(|m| mem_available(&m));
    let cgroup = read(Path::new("/proc/self/cgroup")).and_then(|c| cgroup_room(&c, read));
    match (available, cgroup) {
        (Some(a), Some(c)) => Some(a.min(c)),
        (a, c) => a.or(c),
    }
}

/// The regular files under `dir` (the pool: sled's `db`, its snapshots and blobs), each with
/// its length, in a stable order.
pub fn pool_files(dir: &Path) -> std::io::Result<Vec<(PathBuf, u64)>> {
    let mut files = Vec::new();
    let mut dirs = vec![dir.to_owned()];
    while let Some(d) = dirs.pop() {
        for entry in std::fs::read_dir(&d)? {
            let entry = entry?;
            let kind = entry.file_type()?;
            if kind.is_dir() {
                dirs.push(entry.path());
            } else if kind.is_file() {
                files.push((entry.path(), entry.metadata()?.len()));
            }
        }
    }
    files.sort();
    Ok(files)
}

/// Where the warming reads go: `/dev/null` by `sendfile` (Linux), so the kernel reads each
/// chunk into the page cache without copying it to the process (1.47 GB: 0.1 s of CPU instead
/// of 1.1–2.6 s through a buffer on this machine); else a buffer of [`PREWARM_READ_BYTES`].
enum Sink {
    #[cfg(target_os = "linux")]
    Null(File),
    Buffer(Vec<u8>),
}

impl Sink {
    fn new() -> Sink {
        #[cfg(target_os = "linux")]
        if let Ok(null) = File::options().write(true).open("/dev/null") {
            return Sink::Null(null);
        }
        Sink::Buffer(vec![0u8; PREWARM_READ_BYTES])
    }

    /// The next chunk of `file` from `offset`, at most `max` bytes and
    /// [`PREWARM_READ_BYTES`], into the page cache; its length (0 at the end).
    fn warm(&mut self, file: &mut File, offset: &mut u64, max: u64) -> std::io::Result<usize> {
        let want = usize::try_from(max).map_or(PREWARM_READ_BYTES, |m| m.min(PREWARM_READ_BYTES));
        match self {
            #[cfg(target_os = "linux")]
            Sink::Null(null) => match rustix::fs::sendfile(&*null, &*file, Some(offset), want) {
                Ok(n) => Ok(n),
                // A file system that cannot splice: read through a buffer from here on.
                Err(rustix::io::Errno::INVAL | rustix::io::Errno::NOSYS) => {
                    *self = Sink::Buffer(vec![0u8; PREWARM_READ_BYTES]);
                    self.warm(file, offset, max)
                }
                Err(e) => Err(e.into()),
            },
            Sink::Buffer(buffer) => {
                use std::io::{Seek, SeekFrom};
                file.seek(SeekFrom::Start(*offset))?;
                let n = file.read(&mut buffer[..want])?;
                *offset += n as u64;
                Ok(n)
            }
        }
    }
}

/// How long the prewarm waits before it looks again whether the readers are idle.
pub const PREWARM_YIELD: Duration = Duration::from_millis(10);

/// Least time the pool's readers must have read nothing before the prewarm reads a chunk.
pub const PREWARM_QUIET: Duration = Duration::from_millis(50);

/// How long they must have read nothing before the first chunk: a client that comes right
/// after the start finds the disk to itself.
pub const PREWARM_START_QUIET: Duration = Duration::from_secs(1);

/// How many times its own duration the readers must be quiet after a chunk before the next:
/// a slow disk (a chunk that took long) is left alone longer.
pub const PREWARM_QUIET_PER_CHUNK: u32 = 4;

/// Whether the pool's readers have been quiet long enough for the prewarm's next chunk:
/// nothing queued or running, and no read started since, for [`PREWARM_START_QUIET`] before the
/// first chunk and then [`PREWARM_QUIET_PER_CHUNK`] times the last chunk's duration, at least
/// [`PREWARM_QUIET`]; told the readers' figures and the time.
///
/// Why not only "nothing queued now": a view's reads come in bursts, a batch at a time, and
/// between two of them the readers are idle for moments; a chunk read then held the disk when
/// the next batch came. A fresh server's first view of the 10⁸-point city, its client there at
/// once, took 1.31–1.42 s with the prewarm reading in those moments, 0.91–0.98 s without
/// (docs/measurements.md, stop 68).
#[derive(Debug)]
pub struct QuietReaders {
    runs: u64,
    since: Instant,
    quiet_for: Duration,
}

impl QuietReaders {
    /// Readers seen with `runs` reads run so far, at `now`, before the first chunk.
    pub fn new(runs: u64, now: Instant) -> QuietReaders {
        QuietReaders {
            runs,
            since: now,
            quiet_for: PREWARM_START_QUIET,
        }
    }

    /// The last chunk took `took`.
    pub fn chunk_took(&mut self, took: Duration) {
        self.quiet_for = took
            .saturating_mul(PREWARM_QUIET_PER_CHUNK)
            .max(PREWARM_QUIET);
    }

    /// Whether the readers, with `waiting` reads queued or running and `runs` run so far at
    /// `now`, have been quiet long enough.
    pub fn quiet(&mut self, waiting: u64, runs: u64, now: Instant) -> bool {
        if waiting > 0 || runs != self.runs {
            self.runs = runs;
            self.since = now;
            return false;
        }
        now.saturating_duration_since(self.since) >= self.quiet_for
    }
}

/// Does `reads` in order, each in chunks of at most [`PREWARM_READ_BYTES`], into the page
/// cache, each chunk only once `idle` says the treelet reads leave the disk alone (told how
/// long the last chunk took, zero before the first; it is asked again every
/// [`PREWARM_YIELD`]), adding each chunk's bytes to `figures.read`, until all are done or
/// `stop` is set; returns the bytes read. A file that cannot be opened or read (removed since)
/// is left, the rest are read.
///
/// Why wait: a client's reads want the disk now, and the prewarm's only later. A fresh
/// server's first view of the 10⁸-point city, its client there at once, took 1.23–1.34 s with
/// the prewarm reading beside it and 0.96–1.12 s without (docs/measurements.md, stop 68).
pub fn read_files(
    reads: &[WarmRead],
    stop: &AtomicBool,
    mut idle: impl FnMut(Duration) -> bool,
    figures: &PrewarmFigures,
) -> u64 {
    let mut sink = Sink::new();
    let (mut total, mut last) = (0, Duration::ZERO);
    let mut open: Option<(&Path, File)> = None;
    for r in reads {
        if open.as_ref().is_none_or(|(path, _)| *path != r.path) {
            open = File::open(&r.path).ok().map(|f| (r.path.as_path(), f));
        }
        let Some((_, file)) = open.as_mut() else {
            continue;
        };
        let (mut offset, end) = (r.offset, r.offset.saturating_add(r.len));
        while offset < end {
            while !idle(last) && !stop.load(Ordering::Relaxed) {
                std::thread::sleep(PREWARM_YIELD);
            }
            if stop.load(Ordering::Relaxed) {
                return total;
            }
            let t0 = Instant::now();
            let left = end - offset;
            let warmed = sink.warm(file, &mut offset, left);
            last = t0.elapsed();
            match warmed {
                Ok(0) => break,
                Ok(n) => {
                    total += n as u64;
                    figures.read.fetch_add(n as u64, Ordering::Relaxed);
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    tracing::warn!(file = %r.path.display(), "prewarming the pool: {e}");
                    break;
                }
            }
        }
    }
    total
}

/// The prewarm's threads: the reads, and the saving of the hot-page list. Dropping it stops
/// the reads at the next one and the saving (the service ended).
#[derive(Debug)]
pub struct Prewarm {
    stop: Arc<AtomicBool>,
    /// Dropped with it: the saving thread ends.
    _saver: mpsc::Sender<()>,
    pool: PathBuf,
    list: PathBuf,
    /// Held while the list is saved: the saving thread's tick and the shutdown's save never
    /// write the same temporary file at once. It holds what the last save wrote.
    saving: Arc<Mutex<LastSave>>,
}

/// A hash of the hot pages the list was last written with: a save whose snapshot hashes the
/// same, while the list is still there, writes nothing (a server whose clients keep to the
/// same pages would otherwise rewrite and sync an unchanged file every minute).
type LastSave = Option<u64>;

impl Prewarm {
    /// Saves the list of the pool's pages now in the page cache for the next start (when the
    /// service stops); a failure is logged.
    pub fn save_hot_pages(&self) {
        save_hot_pages(&self.pool, &self.list, &self.saving);
    }
}

impl Drop for Prewarm {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// Saves the hot-page list of the pool in `pool` to `list` under `saving` unless it would be
/// written as it was last time ([`LastSave`]), logging what it did.
fn save_hot_pages(pool: &Path, list: &Path, saving: &Mutex<LastSave>) {
    use std::hash::{Hash, Hasher};
    let mut last = saving.lock().unwrap_or_else(|e| e.into_inner());
    let t0 = Instant::now();
    let hot = match hot_pages::snapshot(pool) {
        Ok(hot) => hot,
        Err(e) => {
            tracing::warn!("the pool's hot pages not saved: {e}");
            return;
        }
    };
    let mut hasher = std::hash::DefaultHasher::new();
    hot.hash(&mut hasher);
    let hash = hasher.finish();
    if *last == Some(hash) && list.exists() {
        tracing::debug!(list = %list.display(), "the pool's hot pages unchanged: not saved");
        return;
    }
    match hot_pages::save(list, pool, &hot) {
        Ok(bytes) => {
            *last = Some(hash);
            tracing::debug!(
                list = %list.display(),
                mib = bytes >> 20,
                ms = t0.elapsed().as_millis() as u64,
                "saved the pool's hot pages"
            );
        }
        Err(e) => tracing::warn!("the pool's hot pages not saved: {e}"),
    }
}

/// The last run's hot pages of the pool in `dir` (its `files`), as reads; a list that cannot
/// be read is logged and left.
fn last_hot_pages(dir: &Path, list: &Path, files: &[(PathBuf, u64)]) -> Vec<WarmRead> {
    match hot_pages::load(list, dir) {
        Ok(hot) => hot_pages::reads(&hot, dir, files),
        Err(e) => {
            tracing::warn!("the last run's hot pages not used: {e}");
            Vec::new()
        }
    }
}

/// Plans by `mode` (with [`memory_room`] and the hot-page list in `data_dir`) what to read of
/// the pool in `dir` into the page cache, logs why nothing or starts a thread that reads it,
/// reporting in `figures`; it reads while the pool's `readers` are quiet ([`QuietReaders`]).
/// Unless `mode` is off, a second thread saves the hot-page list every
/// [`hot_pages::HOT_PAGES_SAVE_INTERVAL`], and the handle saves it once more when told.
pub fn start(
    dir: &Path,
    data_dir: &Path,
    mode: PoolPrewarm,
    readers: Arc<ReadFigures>,
    figures: Arc<PrewarmFigures>,
) -> Option<Prewarm> {
    start_saving_every(
        dir,
        data_dir,
        mode,
        readers,
        figures,
        hot_pages::HOT_PAGES_SAVE_INTERVAL,
    )
}

/// [`start`], the list saved every `save_every`.
fn start_saving_every(
    dir: &Path,
    data_dir: &Path,
    mode: PoolPrewarm,
    readers: Arc<ReadFigures>,
    figures: Arc<PrewarmFigures>,
    save_every: Duration,
) -> Option<Prewarm> {
    let finish = |figures: &PrewarmFigures| figures.done.store(1, Ordering::Relaxed);
    if mode == PoolPrewarm::Off {
        tracing::info!(db = %dir.display(), "not prewarming the pool: pool_prewarm is off");
        finish(&figures);
        return None;
    }
    let list = data_dir.join(hot_pages::HOT_PAGES_FILE);
    let stop = Arc::new(AtomicBool::new(false));
    let (saver, saves) = mpsc::channel::<()>();
    let saving = Arc::new(Mutex::new(LastSave::None));
    let (pool, saved, lock) = (dir.to_owned(), list.clone(), saving.clone());
    let saver_thread = std::thread::Builder::new()
        .name("arbor-hot-pages".into())
        .spawn(move || {
            while let Err(mpsc::RecvTimeoutError::Timeout) = saves.recv_timeout(save_every) {
                save_hot_pages(&pool, &saved, &lock);
            }
        });
    if let Err(e) = saver_thread {
        tracing::warn!("the pool's hot pages will not be saved: starting its thread: {e}");
    }
    let handle = Prewarm {
        stop: stop.clone(),
        _saver: saver,
        pool: dir.to_owned(),
        list: list.clone(),
        saving,
    };
    let files = match pool_files(dir) {
        Ok(f) => f,
        Err(e) => {
            tracing::warn!(db = %dir.display(), "not prewarming the pool: listing its files: {e}");
            finish(&figures);
            return Some(handle);
        }
    };
    let hot = last_hot_pages(dir, &list, &files);
    let room = if mode == PoolPrewarm::Auto {
        memory_room()
    } else {
        None
    };
    let plan = match plan(mode, &files, hot, room) {
        Ok(p) => p,
        Err(why) => {
            tracing::info!(db = %dir.display(), "not prewarming the pool: {why}");
            finish(&figures);
            return Some(handle);
        }
    };
    let bytes: u64 = plan.reads.iter().map(|r| r.len).sum();
    figures.total.store(bytes, Ordering::Relaxed);
    figures.hot.store(plan.hot_bytes, Ordering::Relaxed);
    let db = dir.to_owned();
    let reported = figures.clone();
    let spawned = std::thread::Builder::new()
        .name("arbor-prewarm".into())
        .spawn(move || {
            let t0 = Instant::now();
            tracing::info!(
                db = %db.display(),
                mib = bytes >> 20,
                hot_mib = plan.hot_bytes >> 20,
                whole = plan.whole,
                "prewarming the pool's page cache ({})",
                match (plan.hot_bytes, plan.whole) {
                    (0, _) => "every file",
                    (_, true) => "the last run's hot pages first, then the rest",
                    (_, false) => "only the last run's hot pages: the pool does not fit",
                }
            );
            let runs = || readers.run.load(Ordering::Relaxed);
            let mut quiet = QuietReaders::new(runs(), Instant::now());
            let idle = |last: Duration| {
                if !last.is_zero() {
                    quiet.chunk_took(last);
                }
                let waiting = readers.waiting.load(Ordering::Relaxed);
                quiet.quiet(waiting, runs(), Instant::now())
            };
            let read = read_files(&plan.reads, &stop, idle, &figures);
            finish(&figures);
            tracing::info!(
                db = %db.display(),
                mib = read >> 20,
                secs = format!("{:.2}", t0.elapsed().as_secs_f64()),
                stopped = stop.load(Ordering::Relaxed),
                "pool prewarmed"
            );
        });
    if let Err(e) = spawned {
        tracing::warn!("not prewarming the pool: starting its thread: {e}");
        finish(&reported);
    }
    Some(handle)
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIB: u64 = 1 << 20;

    /// A read of `len` bytes of `name` from `offset`.
    fn read(name: &str, offset: u64, len: u64) -> WarmRead {
        WarmRead {
            path: PathBuf::from(name),
            offset,
            len,
        }
    }

    #[test]
    fn auto_warms_a_pool_within_half_the_room_or_only_its_hot_pages() {
        let auto = PoolPrewarm::Auto;
        let files = vec![
            (PathBuf::from("db"), 90 * MIB),
            (PathBuf::from("conf"), 10 * MIB),
        ];
        let hot = vec![read("db", 0, 30 * MIB), read("db", 50 * MIB, 40 * MIB)];
        let whole = [read("db", 0, 90 * MIB), read("conf", 0, 10 * MIB)];
        let hot_then_rest = [
            hot.clone(),
            vec![read("db", 30 * MIB, 20 * MIB), read("conf", 0, 10 * MIB)],
        ]
        .concat();

        // It fits: the hot pages first, then the rest of every file.
        let p = plan(auto, &files, hot.clone(), Some(200 * MIB)).unwrap();
        assert_eq!(p.reads, hot_then_rest);
        assert_eq!((p.hot_bytes, p.whole), (70 * MIB, true));
        let p = plan(auto, &files, Vec::new(), Some(1000 * MIB)).unwrap();
        assert_eq!((p.reads.as_slice(), p.hot_bytes), (whole.as_slice(), 0));
        assert_eq!(plan(auto, &[], Vec::new(), Some(0)).unwrap().reads, []);

        // It does not: the hot pages only, up to half the room, the last one cut.
        let p = plan(auto, &files, hot.clone(), Some(199 * MIB)).unwrap();
        assert_eq!(p.reads, hot);
        assert!(!p.whole);
        let p = plan(auto, &files, hot.clone(), Some(100 * MIB)).unwrap();
        assert_eq!(
            p.reads,
            [read("db", 0, 30 * MIB), read("db", 50 * MIB, 20 * MIB)]
        );
        assert_eq!(p.hot_bytes, 50 * MIB);
        let p = plan(auto, &files, hot.clone(), Some(60 * MIB)).unwrap();
        assert_eq!(p.reads, [read("db", 0, 30 * MIB)]);
        // Without hot pages, or no room for any: nothing, and the log says why.
        let why = plan(auto, &files, Vec::new(), Some(199 * MIB)).unwrap_err();
        assert!(why.contains("100 MiB") && why.contains("199 MiB"), "{why}");
        assert!(why.contains("hot pages"), "{why}");
        assert!(plan(auto, &files, hot.clone(), Some(1)).is_err());
        assert!(plan(auto, &files, hot.clone(), None).is_err());

        // Always: everything, however large; off: nothing.
        let p = plan(PoolPrewarm::Always, &files, hot.clone(), Some(0)).unwrap();
        assert_eq!(p.reads, hot_then_rest);
        let p = plan(PoolPrewarm::Always, &files, Vec::new(), None).unwrap();
        assert_eq!(p.reads, whole);
        assert!(plan(PoolPrewarm::Off, &files, hot, Some(u64::MAX)).is_err());
    }

    #[test]
    fn the_rest_is_what_the_hot_reads_leave_of_each_file() {
        let files = vec![(PathBuf::from("db"), 100), (PathBuf::from("conf"), 10)];
        assert_eq!(
            the_rest(&files, &[]),
            [read("db", 0, 100), read("conf", 0, 10)]
        );
        // Out of order, overlapping, touching, past the end: each byte once.
        let hot = [
            read("db", 50, 10),
            read("db", 0, 5),
            read("db", 55, 10),
            read("db", 65, 5),
            read("db", 90, 50),
            read("gone", 0, 5),
        ];
        assert_eq!(
            the_rest(&files, &hot),
            [read("db", 5, 45), read("db", 70, 20), read("conf", 0, 10)]
        );
        assert_eq!(the_rest(&files[..1], &[read("db", 0, 100)]), []);
    }

    #[test]
    fn meminfo_gives_the_available_bytes() {
        let text = "MemTotal:       24595860 kB\nMemFree:        20000000 kB\nMemAvailable:   22719384 kB\nBuffers: 1 kB\n";
        assert_eq!(mem_available(text), Some(22_719_384 * 1024));
        assert_eq!(mem_available("MemTotal: 1 kB\n"), None);
        assert_eq!(mem_available("MemAvailable: lots kB\n"), None);
        assert_eq!(
            mem_available("MemAvailable: 18446744073709551615 kB\n"),
            None
        );
    }

    /// A cgroup hierarchy of `files` (path → text).
    fn hierarchy(files: &[(&str, &str)]) -> impl Fn(&Path) -> Option<String> {
        let files: Vec<(PathBuf, String)> = files
            .iter()
            .map(|(p, t)| (PathBuf::from(p), t.to_string()))
            .collect();
        move |p| files.iter().find(|f| f.0 == p).map(|f| f.1.clone())
    }

    #[test]
    fn the_cgroup_limit_less_its_usage_is_the_room() {
        let v1 = "12:pids:/x\n4:memory:/arbor-soak-7\n1:name=systemd:/x\n";
        let read = hierarchy(&[
            (
                "/sys/fs/cgroup/memory/arbor-soak-7/memory.limit_in_bytes",
                "943718400\n",
            ),
            (
                "/sys/fs/cgroup/memory/arbor-soak-7/memory.usage_in_bytes",
                "143718400\n",
            ),
        ]);
        assert_eq!(cgroup_room(v1, &read), Some(800_000_000));
        let unlimited = hierarchy(&[(
            "/sys/fs/cgroup/memory/arbor-soak-7/memory.limit_in_bytes",
            "9223372036854771712\n",
        )]);
        assert_eq!(cgroup_room(v1, unlimited), None);

        let v2 = "0::/system.slice/arbor.service\n";
        let read = hierarchy(&[
            (
                "/sys/fs/cgroup/system.slice/arbor.service/memory.max",
                "2147483648\n",
            ),
            (
                "/sys/fs/cgroup/system.slice/arbor.service/memory.current",
                "1073741824\n",
            ),
        ]);
        assert_eq!(cgroup_room(v2, &read), Some(1 << 30));
        let max = hierarchy(&[(
            "/sys/fs/cgroup/system.slice/arbor.service/memory.max",
            "max\n",
        )]);
        assert_eq!(cgroup_room(v2, max), None);
        // Usage above the limit (possible briefly in v1) leaves no room, not a wrapped number.
        let over = hierarchy(&[
            ("/sys/fs/cgroup/memory.max", "100\n"),
            ("/sys/fs/cgroup/memory.current", "200\n"),
        ]);
        assert_eq!(cgroup_room("0::/\n", over), Some(0));
        // A limit on a parent (a slice, a pod) binds the child: the least room counts.
        let nested = hierarchy(&[
            ("/sys/fs/cgroup/kubepods/pod1/memory.max", "1000\n"),
            ("/sys/fs/cgroup/kubepods/pod1/memory.current", "400\n"),
            ("/sys/fs/cgroup/kubepods/pod1/app/memory.max", "max\n"),
            ("/sys/fs/cgroup/kubepods/pod1/app/memory.current", "300\n"),
            ("/sys/fs/cgroup/kubepods/memory.max", "5000\n"),
            ("/sys/fs/cgroup/kubepods/memory.current", "4700\n"),
        ]);
        assert_eq!(cgroup_room("0::/kubepods/pod1/app\n", &nested), Some(300));
        let v1_parent = hierarchy(&[(
            "/sys/fs/cgroup/memory/system.slice/memory.limit_in_bytes",
            "2048\n",
        )]);
        assert_eq!(
            cgroup_room("9:memory:/system.slice/arbor.service\n", v1_parent),
            Some(2048)
        );
        assert_eq!(cgroup_room("", hierarchy(&[])), None);
        assert_eq!(cgroup_room("garbage", hierarchy(&[])), None);
    }

    #[test]
    fn every_file_is_read_whole_unless_stopped() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("blobs")).unwrap();
        let sizes = [
            ("db", PREWARM_READ_BYTES * 2 + 5),
            ("conf", 62),
            ("blobs/1", 1000),
        ];
        for (name, len) in sizes {
            std::fs::write(dir.path().join(name), vec![7u8; len]).unwrap();
        }
        let files = pool_files(dir.path()).unwrap();
        assert_eq!(files.len(), 3);
        let whole: u64 = sizes.iter().map(|s| s.1 as u64).sum();
        assert_eq!(files.iter().map(|f| f.1).sum::<u64>(), whole);
        let files: Vec<WarmRead> = files
            .into_iter()
            .map(|(path, len)| WarmRead {
                path,
                offset: 0,
                len,
            })
            .collect();

        let figures = PrewarmFigures::default();
        assert_eq!(
            read_files(&files, &AtomicBool::new(false), |_| true, &figures),
            whole
        );
        assert_eq!(figures.read.load(Ordering::Relaxed), whole);

        let figures = PrewarmFigures::default();
        assert_eq!(
            read_files(&files, &AtomicBool::new(true), |_| true, &figures),
            0
        );
        assert_eq!(figures.read.load(Ordering::Relaxed), 0);

        // Both sinks read a file whole, chunk by chunk.
        for mut sink in [Sink::new(), Sink::Buffer(vec![0u8; PREWARM_READ_BYTES])] {
            let mut file = File::open(dir.path().join("db")).unwrap();
            let (mut offset, mut chunks) = (0u64, Vec::new());
            loop {
                match sink.warm(&mut file, &mut offset, u64::MAX).unwrap() {
                    0 => break,
                    n => chunks.push(n),
                }
            }
            assert_eq!(chunks, [PREWARM_READ_BYTES, PREWARM_READ_BYTES, 5]);
            assert_eq!(offset, (PREWARM_READ_BYTES * 2 + 5) as u64);
            // A part of a file: no more than asked, nothing past the end.
            let mut offset = 10;
            assert_eq!(sink.warm(&mut file, &mut offset, 300).unwrap(), 300);
            assert_eq!(offset, 310);
            let mut offset = (PREWARM_READ_BYTES * 2) as u64;
            assert_eq!(sink.warm(&mut file, &mut offset, 300).unwrap(), 5);
        }

        // Ranges of files: each read to its length, in order.
        let parts = [
            read_part(&dir, "db", 1, 99),
            read_part(&dir, "db", PREWARM_READ_BYTES as u64, 5000),
            read_part(&dir, "conf", 60, 10),
        ];
        let figures = PrewarmFigures::default();
        let mut chunks = 0;
        let idle = |_| {
            chunks += 1;
            true
        };
        assert_eq!(
            read_files(&parts, &AtomicBool::new(false), idle, &figures),
            99 + 5000 + 2
        );
        assert_eq!(
            chunks, 4,
            "one chunk each, and one more that finds conf's end"
        );

        // A file gone since it was listed is left; the others are read.
        std::fs::remove_file(dir.path().join("conf")).unwrap();
        let figures = PrewarmFigures::default();
        assert_eq!(
            read_files(&files, &AtomicBool::new(false), |_| true, &figures),
            whole - 62
        );
    }

    /// A read of `len` bytes of the file `name` in `dir` from `offset`.
    fn read_part(dir: &tempfile::TempDir, name: &str, offset: u64, len: u64) -> WarmRead {
        WarmRead {
            path: dir.path().join(name),
            offset,
            len,
        }
    }

    /// [`start`] with `always` on the pool in `dir`, its data directory the same.
    fn start_always(
        dir: &tempfile::TempDir,
        readers: &Arc<ReadFigures>,
        figures: &Arc<PrewarmFigures>,
    ) -> Option<Prewarm> {
        start(
            dir.path(),
            dir.path(),
            PoolPrewarm::Always,
            readers.clone(),
            figures.clone(),
        )
    }

    /// Waits until `figures` says the prewarm ended.
    fn wait_done(figures: &PrewarmFigures) {
        let t0 = Instant::now();
        while figures.done.load(Ordering::Relaxed) == 0 {
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "the prewarm did not end in 30 s"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    #[test]
    fn readers_are_quiet_once_nothing_ran_for_a_while() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let start_ms = PREWARM_START_QUIET.as_millis() as u64;
        let quiet_ms = PREWARM_QUIET.as_millis() as u64;
        let mut q = QuietReaders::new(5, t0);
        assert!(
            !q.quiet(0, 5, at(start_ms - 1)),
            "the first chunk waits longer"
        );
        assert!(q.quiet(0, 5, at(start_ms)));
        // After a quick chunk: the least quiet.
        q.chunk_took(Duration::from_millis(1));
        let base = start_ms + 1;
        assert!(!q.quiet(1, 5, at(base)), "a read queued");
        assert!(!q.quiet(0, 5, at(base + quiet_ms - 1)));
        assert!(q.quiet(0, 5, at(base + quiet_ms)));
        // A read that came and went between two looks counts too.
        let base = base + quiet_ms + 1;
        assert!(!q.quiet(0, 6, at(base)));
        assert!(!q.quiet(0, 6, at(base + quiet_ms - 1)));
        assert!(q.quiet(0, 6, at(base + quiet_ms)));
        // After a slow chunk: four times its time.
        q.chunk_took(Duration::from_millis(40));
        let base = base + quiet_ms + 1;
        assert!(!q.quiet(0, 7, at(base)));
        assert!(!q.quiet(0, 7, at(base + 159)));
        assert!(q.quiet(0, 7, at(base + 160)));
        // A clock that went back (another thread's instant) is not quiet, and not a panic.
        assert!(!q.quiet(0, 7, t0));
    }

    #[test]
    fn the_prewarm_reads_nothing_while_a_treelet_read_waits() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("db"), vec![1u8; 1 << 20]).unwrap();
        let readers = Arc::new(ReadFigures::default());
        readers.waiting.store(1, Ordering::Relaxed);
        let figures = Arc::new(PrewarmFigures::default());
        let handle = start_always(&dir, &readers, &figures);
        std::thread::sleep(PREWARM_START_QUIET + Duration::from_millis(300));
        assert_eq!(figures.read.load(Ordering::Relaxed), 0);
        assert_eq!(figures.done.load(Ordering::Relaxed), 0);
        readers.waiting.store(0, Ordering::Relaxed);
        wait_done(&figures);
        assert_eq!(figures.read.load(Ordering::Relaxed), 1 << 20);
        drop(handle);

        // Stopped (the service ended) while it waits: it ends without reading.
        readers.waiting.store(1, Ordering::Relaxed);
        let figures = Arc::new(PrewarmFigures::default());
        let handle = start_always(&dir, &readers, &figures);
        drop(handle);
        wait_done(&figures);
        assert_eq!(figures.read.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn a_running_prewarm_saves_the_hot_pages_on_its_own_until_dropped() {
        let pool = tempfile::tempdir().unwrap();
        let data = tempfile::tempdir().unwrap();
        std::fs::write(pool.path().join("db"), vec![1u8; 1 << 20]).unwrap();
        let list = data.path().join(hot_pages::HOT_PAGES_FILE);
        let handle = start_saving_every(
            pool.path(),
            data.path(),
            PoolPrewarm::Always,
            Arc::new(ReadFigures::default()),
            Arc::new(PrewarmFigures::default()),
            Duration::from_millis(20),
        );
        let t0 = Instant::now();
        while !list.exists() {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "no list saved in 10 s"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
        drop(handle);
        // The saving thread has ended by its next tick: the list, removed, stays away.
        std::thread::sleep(Duration::from_millis(100));
        std::fs::remove_file(&list).unwrap();
        std::thread::sleep(Duration::from_millis(100));
        assert!(!list.exists(), "saved after the prewarm was dropped");
    }

    /// A save whose pages are those of the last one writes nothing; a list removed meanwhile, or
    /// pages that changed, are written again.
    #[cfg(target_os = "linux")]
    #[test]
    fn an_unchanged_list_is_not_written_again() {
        use std::os::unix::fs::MetadataExt as _;
        let pool = tempfile::tempdir().unwrap();
        let data = tempfile::tempdir().unwrap();
        std::fs::write(pool.path().join("db"), vec![1u8; 1 << 20]).unwrap();
        let list = data.path().join(hot_pages::HOT_PAGES_FILE);
        let inode = || std::fs::metadata(&list).unwrap().ino();
        let saving = Mutex::new(LastSave::None);
        save_hot_pages(pool.path(), &list, &saving);
        let first = inode();
        save_hot_pages(pool.path(), &list, &saving);
        assert_eq!(inode(), first, "an unchanged list was written again");
        std::fs::remove_file(&list).unwrap();
        save_hot_pages(pool.path(), &list, &saving);
        assert!(list.exists(), "a removed list was not written again");
        let second = inode();
        // A new file of the pool, its pages in the page cache as written.
        std::fs::write(pool.path().join("blob"), vec![2u8; 1 << 16]).unwrap();
        save_hot_pages(pool.path(), &list, &saving);
        assert_ne!(inode(), second, "changed pages were not saved");
        let saved = hot_pages::load(&list, pool.path()).unwrap();
        assert!(saved.iter().any(|f| f.name == "blob"), "{saved:?}");
    }

    #[test]
    fn a_started_prewarm_reads_the_pool_and_says_it_is_done() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("db"), vec![1u8; 3 * 1024 * 1024]).unwrap();
        let figures = Arc::new(PrewarmFigures::default());
        let readers = Arc::new(ReadFigures::default());
        let handle = start_always(&dir, &readers, &figures);
        assert!(handle.is_some());
        wait_done(&figures);
        assert_eq!(figures.total.load(Ordering::Relaxed), 3 << 20);
        assert_eq!(figures.read.load(Ordering::Relaxed), 3 << 20);

        let off = Arc::new(PrewarmFigures::default());
        assert!(
            start(
                dir.path(),
                dir.path(),
                PoolPrewarm::Off,
                readers,
                off.clone()
            )
            .is_none()
        );
        assert_eq!(off.total.load(Ordering::Relaxed), 0);
        assert_eq!(off.read.load(Ordering::Relaxed), 0);
        assert_eq!(off.done.load(Ordering::Relaxed), 1);
    }
}
