//! The treelet pool: every scene's treelets in one sled database, already compressed.
//!
//! Layout: a `catalogue` tree maps a scene name to its *generation* (a fresh id per import) and
//! encoded [`SceneDescription`]. A generation `g` owns the trees `g{g}:nodes` and
//! `g{g}:ch:{channel}`, so a channel is read without touching the others. Their values are
//! [`pack`]s of 16 consecutive treelets' blocks, keyed by big-endian pack index. The default tree
//! holds the pool's format number; a pool of another format is refused when opened, naming
//! both. An import writes its generation's trees, flushes them, and only then inserts the
//! catalogue entry (one atomic sled insert, then flushed): a scene is visible only when complete.
//! Trees of a generation that no catalogue entry names are leftovers of a killed import; they are
//! dropped when the pool is opened. sled holds an exclusive lock on the directory, so no live
//! import can be mistaken for a leftover.

pub mod copy;
pub mod pack;

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use arbor_proto::scene::validate_scene_name;
use arbor_proto::{AttributeLayout, Channel, ProtoError, SceneDescription, TreeletId};

use crate::octree::{BuildError, TreeletSink};
use crate::pace::ReadPace;
use crate::prometheus::{Buckets, Histogram};
use pack::PackWriter;

/// Errors of the pool.
#[derive(Debug, thiserror::Error)]
pub enum PoolError {
    /// sled failed (I/O or corruption).
    #[error("pool database: {0}")]
    Sled(#[from] sled::Error),
    /// Another process has the pool open: sled holds an exclusive lock on its file while a
    /// server serves it or an import writes it.
    #[error(
        "the pool {} is in use by another process (a server serving it, or an import): stop it \
         first, or ask the server through its admin API (`import --server`, `verify --server`, \
         `copy --server`)",
        .0.display()
    )]
    InUse(std::path::PathBuf),
    /// A stored value does not decode.
    #[error("pool entry {what}: {source}")]
    Corrupt {
        what: String,
        #[source]
        source: ProtoError,
    },
    /// The directory holds no pool (no sled database `db` in it): only an import or a server
    /// makes one.
    #[error("{} is not a pool directory (no sled database `db` in it)", .0.display())]
    NoPool(std::path::PathBuf),
    /// No scene of that name.
    #[error("no scene named {0:?} in the pool")]
    NoSuchScene(String),
    /// A scene of that name exists and replacing was not asked for.
    #[error("a scene named {0:?} already exists (remove it first or pass --replace)")]
    SceneExists(String),
    /// The scene name is not acceptable.
    #[error(transparent)]
    BadName(ProtoError),
    /// A generation still named by the catalogue cannot be dropped as retired.
    #[error("generation {0} is still published")]
    GenerationLive(u64),
    /// A scene read in stretches with the pool closed in between (`verify`, `copy`) was
    /// replaced or removed meanwhile: another process opened the pool between two stretches.
    #[error(
        "scene {0:?} was replaced or removed while it was being read (another process opened the pool meanwhile): run it again"
    )]
    ChangedWhileRead(String),
    /// The pool was written in a format this build does not read (format 1 kept one value per
    /// block; format 2 packs them).
    #[error(
        "pool format {found}, this build reads format {expected}: import the scenes again into a new pool directory"
    )]
    Format { found: u32, expected: u32 },
}

const CATALOGUE: &str = "catalogue";

/// Key of the pool's format number (u32, big-endian) in the default tree.
const FORMAT_KEY: &[u8] = b"arbor.pool.format";
/// The format this build writes and reads: 2, treelet blocks in packs. A pool without the key
/// but with scenes predates it (format 1).
const FORMAT: u32 = 2;

/// Bytes of one segment of the log of a pool made by this build (sled's `segment_size`; its
/// default is 512 KiB).
///
/// Why larger: sled's open reads the 20-byte header of every segment of its file, one read
/// each, before anything else. The 10⁸-point city's 1.47 GB pool in 512 KiB segments took 2,862
/// reads and 6.0 s to open on a disk held to 500 reads a second (cloud block storage past its
/// burst), during which the server served nobody; a 100 GB pool would take minutes. 8 MiB
/// segments make sixteen times fewer, and a leaf page of up to a quarter of a segment (2 MiB)
/// stays in the log instead of a blob file of its own. Each full segment is written from one
/// buffer of this size. A pool keeps the segment size it was made with (sled's `conf` file).
pub const POOL_SEGMENT_BYTES: usize = 8 << 20;

/// The segment size sled recorded in the pool directory `dir` (its `conf` file), if it has one
/// that sled would accept.
fn stored_segment_bytes(dir: &Path) -> Option<usize> {
    let conf = std::fs::read(dir.join("conf")).ok()?;
    let text = String::from_utf8_lossy(&conf);
    let bytes: usize = text
        .lines()
        .find_map(|l| l.strip_prefix("segment_size:"))?
        .trim()
        .parse()
        .ok()?;
    (bytes.is_power_of_two() && (256..=1 << 24).contains(&bytes)).then_some(bytes)
}

/// How long an opening waits for the pool's lock (a server's start, a copy's openings): a pool
/// handle dropped just before in the same process (an import, a test, the copy's own last
/// opening) lets go of sled's directory lock only when sled's flusher thread notices. A lock held
/// longer belongs to another live process (one process per pool).
pub const POOL_LOCK_WAIT: std::time::Duration = std::time::Duration::from_secs(2);

/// sled's page cache of a pool opened for a pass over whole trees ([`Pool::open_for_scan`]).
const SCAN_CACHE_BYTES: u64 = 16 << 20;

/// sled page cache size of [`Pool::open`]: imports and tools. A server sizes its own
/// (`pool_cache_bytes`, [`Pool::open_with_cache`]).
pub const POOL_CACHE_BYTES: u64 = 128 << 20;

fn nodes_tree(generation: u64) -> String {
    format!("g{generation}:nodes")
}

fn channel_tree(generation: u64, c: Channel) -> String {
    format!("g{generation}:ch:{}", c.name())
}

fn generation_of(tree_name: &[u8]) -> Option<u64> {
    let s = std::str::from_utf8(tree_name).ok()?;
    let rest = s.strip_prefix('g')?;
    rest.split(':').next()?.parse().ok()
}

/// The buckets of [`Pool::read_times`], 1 µs to 1 s: a pack read from sled's page cache takes a
/// few microseconds (0.3–2 µs on these machines), one whose page is decoded from the file again
/// tens, one the file must come from the disk for hundreds or more.
#[derive(Debug)]
pub struct PoolReadBuckets;

impl Buckets for PoolReadBuckets {
    const BOUNDS: &'static [f64] = &[
        0.000_001, 0.000_002, 0.000_005, 0.000_01, 0.000_02, 0.000_05, 0.000_1, 0.000_2, 0.000_5,
        0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 1.0,
    ];
}

/// An open pool.
#[derive(Debug, Clone)]
pub struct Pool {
    db: sled::Db,
    catalogue: sled::Tree,
    /// Times of the treelet-block reads of every scene opened from this pool (its clones
    /// share it).
    reads: Arc<Histogram<PoolReadBuckets>>,
    /// The size of the log segments the pool was made with.
    segment_bytes: usize,
}

/// A stored scene: its description and the trees holding its blocks.
#[derive(Debug, Clone)]
pub struct StoredScene {
    pub description: SceneDescription,
    pub generation: u64,
    nodes: sled::Tree,
    channels: Vec<(Channel, sled::Tree)>,
    reads: ReadAccount,
}

/// Where a scene's block reads are counted, and the pace they keep.
#[derive(Debug, Clone)]
pub(crate) struct ReadAccount {
    /// The pool's serving histogram, or one of the scene's own ([`StoredScene::with_reads_apart`]).
    times: Arc<Histogram<PoolReadBuckets>>,
    /// A background job's pace and stop flag ([`StoredScene::paced`]).
    paced: Option<(Arc<ReadPace>, Arc<AtomicBool>)>,
}

impl ReadAccount {
    /// Counts one sled read of `bytes` that took from `began` until now, and waits for the pace.
    pub(crate) fn observe(&self, began: Instant, bytes: usize) {
        self.times.observe(began.elapsed());
        if let Some((pace, stop)) = &self.paced {
            pace.take(bytes as u64, Some(stop));
        }
    }
}

impl StoredScene {
    /// The compressed node block of a treelet.
    pub fn nodes(&self, id: TreeletId) -> Result<Option<sled::IVec>, PoolError> {
        packed_block(&self.nodes, "nodes", id, &self.reads)
    }

    /// The compressed attribute block of one channel of a treelet; `None` if the scene lacks the
    /// channel or the treelet.
    pub fn channel(
        &self,
        channel: Channel,
        id: TreeletId,
    ) -> Result<Option<sled::IVec>, PoolError> {
        match self.channels.iter().find(|(c, _)| *c == channel) {
            Some((c, t)) => packed_block(t, c.name(), id, &self.reads),
            None => Ok(None),
        }
    }

    /// The compressed node blocks of `ids`, in order, as [`StoredScene::nodes`] reads each, but
    /// with one sled read per pack while consecutive ids stay in it.
    pub fn nodes_of(&self, ids: &[TreeletId]) -> Result<Vec<Option<sled::IVec>>, PoolError> {
        packed_blocks(&self.nodes, "nodes", ids, &self.reads)
    }

    /// The compressed `channel` blocks of `ids`, in order, as [`StoredScene::channel`] reads
    /// each, but with one sled read per pack while consecutive ids stay in it.
    pub fn channel_of(
        &self,
        channel: Channel,
        ids: &[TreeletId],
    ) -> Result<Vec<Option<sled::IVec>>, PoolError> {
        match self.channels.iter().find(|(c, _)| *c == channel) {
            Some((c, t)) => packed_blocks(t, c.name(), ids, &self.reads),
            None => Ok(vec![None; ids.len()]),
        }
    }

    /// The scene's trees with their names in reports: the nodes, then each channel of its
    /// layout, in the layout's order.
    pub fn trees(&self) -> Vec<(&'static str, &sled::Tree)> {
        let mut trees = vec![("nodes", &self.nodes)];
        trees.extend(self.channels.iter().map(|(c, t)| (c.name(), t)));
        trees
    }

    /// This scene with its reads counted apart from the pool's read histogram (what
    /// `arbor_pool_read_seconds` reports), so that a whole-scene check in the daemon does not
    /// show as serving latency.
    pub fn with_reads_apart(mut self) -> StoredScene {
        self.reads.times = Arc::default();
        self
    }

    /// This scene with every block read keeping `pace` (shared by a daemon's background jobs),
    /// until `stop` is set: what a check reads while the daemon serves ([`crate::pace`]).
    pub fn paced(mut self, pace: Arc<ReadPace>, stop: Arc<AtomicBool>) -> StoredScene {
        self.reads.paced = Some((pace, stop));
        self
    }

    /// Where this scene's reads are counted, and their pace (a copy reading its packs by key).
    pub(crate) fn reads(&self) -> &ReadAccount {
        &self.reads
    }

    /// Number of node blocks stored.
    pub fn stored_treelets(&self) -> Result<usize, PoolError> {
        self.stored_ids().try_fold(0, |n, id| id.map(|_| n + 1))
    }

    /// Ids of the stored node blocks, ascending.
    pub fn stored_ids(&self) -> impl Iterator<Item = Result<TreeletId, PoolError>> + '_ {
        self.stored_ids_from(TreeletId(0))
    }

    /// Ids of the stored node blocks from `start` on, ascending (a pass over the scene that
    /// was interrupted resumes there).
    pub fn stored_ids_from(
        &self,
        start: TreeletId,
    ) -> impl Iterator<Item = Result<TreeletId, PoolError>> + '_ {
        let (first_key, _) = pack::locate(start);
        let ids = self.nodes.range(first_key..).flat_map(|entry| {
            let ids = entry.map_err(PoolError::from).and_then(|(k, v)| {
                let corrupt = |source| PoolError::Corrupt {
                    what: format!("nodes pack key {:?}", k.as_ref()),
                    source,
                };
                let first = pack::first_id(&k).ok_or_else(|| {
                    corrupt(ProtoError::OutOfRange {
                        what: "pack key",
                        detail: "not a 4-byte pack index of ids below 2³²".into(),
                    })
                })?;
                let slots = pack::present(&v).map_err(corrupt)?;
                Ok(slots
                    .into_iter()
                    .map(move |s| Ok(TreeletId(first + s as u32)))
                    .collect::<Vec<_>>())
            });
            match ids {
                Ok(ids) => ids,
                Err(e) => vec![Err(e)],
            }
        });
        ids.filter(move |id| id.as_ref().map_or(true, |id| id.0 >= start.0))
    }
}

/// Whether `dir` holds a pool (sled's database file).
pub fn is_pool(dir: &Path) -> bool {
    dir.join("db").is_file()
}

/// Removes the `snap.*.generating` files in the sled directory `dir`, if no process holds the
/// database, and returns how many went.
///
/// sled 0.34 writes a snapshot to `snap.<lsn>.generating`, syncs it and only then renames it to
/// `snap.<lsn>`. A process killed in between leaves the `.generating` file, which sled's open
/// then takes for the newest snapshot and refuses as corrupt (spacejam/sled#1527): a pool
/// killed mid-import could not be opened again (seen once in `cli.rs`'s SIGKILL test). Such a
/// file was never a finished snapshot, so removing it loses nothing: sled reads the previous
/// snapshot and replays its log. The lock sled itself takes (an exclusive `flock` on the `db`
/// file) is taken first, so a snapshot another live process is writing is never touched.
fn remove_unfinished_snapshots(dir: &Path) -> usize {
    let Ok(lock) = std::fs::File::open(dir.join("db")) else {
        return 0;
    };
    if lock.try_lock().is_err() {
        return 0;
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .filter(|e| {
            let name = e.file_name();
            let name = name.to_string_lossy();
            name.starts_with("snap.") && name.ends_with(".generating")
        })
        .filter(|e| std::fs::remove_file(e.path()).is_ok())
        .count()
}

/// The block of `id` in a tree of packs (`stream` names the tree in errors).
fn packed_block(
    tree: &sled::Tree,
    stream: &str,
    id: TreeletId,
    reads: &ReadAccount,
) -> Result<Option<sled::IVec>, PoolError> {
    PackCursor::default().block(tree, stream, id, reads)
}

/// The blocks of `ids` in order, through one [`PackCursor`].
fn packed_blocks(
    tree: &sled::Tree,
    stream: &str,
    ids: &[TreeletId],
    reads: &ReadAccount,
) -> Result<Vec<Option<sled::IVec>>, PoolError> {
    let mut cursor = PackCursor::default();
    ids.iter()
        .map(|&id| cursor.block(tree, stream, id, reads))
        .collect()
}

/// Reads blocks of one tree holding on to the last pack read, so that consecutive ids in one
/// pack cost one sled `get` between them. A stream's batch is treelets adjacent in rank, mostly
/// siblings with consecutive ids: a `get` per block took 1.5–1.7× as long as one per pack (2.6–2.9
/// against 1.7 µs per treelet on the 10⁸-point city, 0.76 against 0.28 on lion-4k;
/// `server/benches/messages.rs`, docs/measurements.md, stop 59).
#[derive(Default)]
struct PackCursor {
    /// The key of the pack last read, and the pack (`None`: not stored).
    held: Option<([u8; 4], Option<sled::IVec>)>,
}

impl PackCursor {
    fn block(
        &mut self,
        tree: &sled::Tree,
        stream: &str,
        id: TreeletId,
        reads: &ReadAccount,
    ) -> Result<Option<sled::IVec>, PoolError> {
        let (key, slot) = pack::locate(id);
        let pack = match &self.held {
            Some((held, pack)) if *held == key => pack,
            _ => {
                let began = Instant::now();
                let pack = tree.get(key)?;
                reads.observe(began, pack.as_ref().map_or(0, |p| p.len()));
                &self.held.insert((key, pack)).1
            }
        };
        let Some(p) = pack else {
            return Ok(None);
        };
        pack::block(p, slot).map_err(|source| PoolError::Corrupt {
            what: format!("{stream} pack of treelet {}", id.0),
            source,
        })
    }
}

/// Tells the kernel that this process reads the sled file of the pool in `dir` at random
/// (`POSIX_FADV_RANDOM` on sled's own descriptors, found in `/proc/self/fd`), and returns how
/// many descriptors it advised.
///
/// Why: a treelet's read is one page of a few KiB somewhere in the file, and the kernel reads
/// ahead of every read it does not find cached (up to `read_ahead_kb`, 8 MiB on this machine's
/// disk). With the 1.47 GB city pool outside the page cache (the soak's server in a 600 MB
/// memory cgroup) each read fetched about 113 KB: 600 MB/s from the disk for 18 MB/s of
/// treelets, the disk's bandwidth the bound, and the read-ahead pages evicted before use.
/// Without read-ahead the same load read 4 KiB a read and was served at the page cache's rate
/// (docs/measurements.md, stop 66). sled opens its file itself, so the advice goes to its
/// descriptors; the advice belongs to the open file, not the inode, so a descriptor of our own
/// would not do.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
fn advise_random_reads(dir: &Path) -> usize {
    use std::os::fd::BorrowedFd;
    let Ok(file) = dir.join("db").canonicalize() else {
        return 0;
    };
    let Ok(descriptors) = std::fs::read_dir("/proc/self/fd") else {
        return 0;
    };
    let mut advised = 0;
    for entry in descriptors.flatten() {
        let Some(fd) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<i32>().ok())
        else {
            continue;
        };
        if std::fs::read_link(entry.path()).ok().as_deref() != Some(file.as_path()) {
            continue;
        }
        // SAFETY: `fd` is open and refers to the pool's file (its link was just read): sled
        // opened it and holds it as long as the database is open, and it is borrowed only for
        // this one call, which changes how the kernel reads ahead on it and nothing else.
        let fd = unsafe { BorrowedFd::borrow_raw(fd) };
        if rustix::fs::fadvise(fd, 0, None, rustix::fs::Advice::Random).is_ok() {
            advised += 1;
        }
    }
    advised
}

/// Read-ahead advice is Linux's here; elsewhere the kernel's default stands.
#[cfg(not(target_os = "linux"))]
fn advise_random_reads(_dir: &Path) -> usize {
    0
}

impl Pool {
    /// Opens (creating if needed) the pool in `dir` and drops leftovers of killed imports, with
    /// a page cache of [`POOL_CACHE_BYTES`].
    pub fn open(dir: &Path) -> Result<Pool, PoolError> {
        // sled's page cache defaults to 1 GiB of anonymous memory; an import writes each block
        // once, so a modest cache keeps it lean.
        Self::open_with_cache(dir, POOL_CACHE_BYTES)
    }

    /// [`Pool::open`] of a pool that exists: a command that only reads or removes (`list`,
    /// `info`, `remove`) must not leave an empty pool at a mistyped path.
    pub fn open_existing(dir: &Path) -> Result<Pool, PoolError> {
        if !is_pool(dir) {
            return Err(PoolError::NoPool(dir.to_owned()));
        }
        Self::open(dir)
    }

    /// [`Pool::open`] with a page cache of `cache_bytes`: sled keeps that much of the pool's
    /// pages decoded. A read whose page is not among them decodes the page from the file again;
    /// on the 10⁸-point city (1.4 GB of pool) the reads for building messages that missed the
    /// message cache took 1.7–2.4 µs per treelet with 128 MiB and 0.54–0.67 µs with 1 GiB
    /// (`server/benches/messages.rs`, docs/measurements.md, stop 59).
    pub fn open_with_cache(dir: &Path, cache_bytes: u64) -> Result<Pool, PoolError> {
        Self::open_inner(dir, cache_bytes, false)
    }

    /// [`Pool::open_with_cache`], or, `for_scan`, [`Pool::open_for_scan`]'s opening.
    fn open_inner(dir: &Path, cache_bytes: u64, for_scan: bool) -> Result<Pool, PoolError> {
        // sled refuses a segment size other than the one its directory was made with; a new
        // pool gets POOL_SEGMENT_BYTES, one made before (512 KiB, sled's default) keeps its own.
        let segment_bytes = stored_segment_bytes(dir).unwrap_or(POOL_SEGMENT_BYTES);
        let config = sled::Config::new()
            .path(dir)
            .cache_capacity(cache_bytes)
            .segment_size(segment_bytes);
        let in_use = |e: sled::Error| match e {
            sled::Error::Io(e) if e.to_string().contains("could not acquire lock") => {
                PoolError::InUse(dir.to_owned())
            }
            e => PoolError::Sled(e),
        };
        let db = match config.open() {
            Err(sled::Error::Corruption { .. }) if remove_unfinished_snapshots(dir) > 0 => {
                tracing::warn!(
                    "removed an unfinished sled snapshot left by a killed process; the pool \
                     recovers from its log"
                );
                config.open().map_err(in_use)?
            }
            opened => opened.map_err(in_use)?,
        };
        if !for_scan {
            let advised = advise_random_reads(dir);
            tracing::debug!(descriptors = advised, "pool file advised for random reads");
        }
        let catalogue = db.open_tree(CATALOGUE)?;
        check_format(&db, &catalogue)?;
        let pool = Pool {
            db,
            catalogue,
            reads: Arc::default(),
            segment_bytes,
        };
        let cleaned = if for_scan { 0 } else { pool.drop_leftovers()? };
        if cleaned > 0 {
            tracing::warn!(
                trees = cleaned,
                "dropped leftovers of an interrupted import"
            );
        }
        Ok(pool)
    }

    /// Opens the pool in `dir` for a command that reads or writes whole trees in key order
    /// (`copy`, `verify`): a small page cache (each page is read once), the trees no catalogue
    /// entry names kept (a copy's own, unpublished while it writes them; such a command changes
    /// nothing it does not own), and no random-read advice (the kernel's read-ahead serves a
    /// pass in key order: the city's cold copy took 68 s with the advice). A handle this
    /// process just dropped lets go of sled's lock when its flusher thread ends, shortly after:
    /// the opening waits for it up to [`POOL_LOCK_WAIT`].
    pub fn open_for_scan(dir: &Path) -> Result<Pool, PoolError> {
        let deadline = std::time::Instant::now() + POOL_LOCK_WAIT;
        loop {
            match Pool::open_inner(dir, SCAN_CACHE_BYTES, true) {
                Err(PoolError::InUse(_)) if std::time::Instant::now() < deadline => {
                    std::thread::sleep(std::time::Duration::from_millis(20));
                }
                opened => return opened,
            }
        }
    }

    fn live_generations(&self) -> Result<Vec<u64>, PoolError> {
        let mut g = Vec::new();
        for entry in self.catalogue.iter() {
            let (k, v) = entry?;
            g.push(decode_entry(&k, &v)?.0);
        }
        Ok(g)
    }

    fn drop_leftovers(&self) -> Result<usize, PoolError> {
        let live = self.live_generations()?;
        let mut dropped = 0;
        for name in self.db.tree_names() {
            if let Some(g) = generation_of(&name)
                && !live.contains(&g)
            {
                self.db.drop_tree(&name)?;
                dropped += 1;
            }
        }
        if dropped > 0 {
            self.db.flush()?;
        }
        Ok(dropped)
    }

    /// All scenes, by name.
    pub fn scenes(&self) -> Result<Vec<SceneDescription>, PoolError> {
        Ok(self.published()?.into_iter().map(|(_, d)| d).collect())
    }

    /// Every published scene's generation and description, by name.
    pub fn published(&self) -> Result<Vec<(u64, SceneDescription)>, PoolError> {
        let mut out = Vec::new();
        for entry in self.catalogue.iter() {
            let (k, v) = entry?;
            out.push(decode_entry(&k, &v)?);
        }
        Ok(out)
    }

    /// Each published scene's name and generation, by name (the catalogue's descriptions left
    /// undecoded).
    pub fn generations(&self) -> Result<Vec<(String, u64)>, PoolError> {
        let mut out = Vec::new();
        for entry in self.catalogue.iter() {
            let (k, v) = entry?;
            let generation = entry_generation(&k, &v)?;
            let name = String::from_utf8(k.to_vec()).map_err(|_| PoolError::Corrupt {
                what: format!("catalogue {:?}", String::from_utf8_lossy(&k)),
                source: ProtoError::OutOfRange {
                    what: "catalogue entry",
                    detail: "its name is not UTF-8".into(),
                },
            })?;
            out.push((name, generation));
        }
        Ok(out)
    }

    /// One scene.
    pub fn scene(&self, name: &str) -> Result<StoredScene, PoolError> {
        let v = self
            .catalogue
            .get(name.as_bytes())?
            .ok_or_else(|| PoolError::NoSuchScene(name.to_owned()))?;
        let (generation, description) = decode_entry(name.as_bytes(), &v)?;
        let nodes = self.db.open_tree(nodes_tree(generation))?;
        let channels = description
            .layout
            .channels()
            .iter()
            .map(|&c| Ok((c, self.db.open_tree(channel_tree(generation, c))?)))
            .collect::<Result<_, PoolError>>()?;
        Ok(StoredScene {
            description,
            generation,
            nodes,
            channels,
            reads: ReadAccount {
                times: Arc::clone(&self.reads),
                paced: None,
            },
        })
    }

    /// The scene `name` if it is still generation `generation`: a command that reads a scene in
    /// stretches with the pool closed in between (`verify`, `copy`) checks at every opening that
    /// no other process replaced or removed it meanwhile ([`PoolError::ChangedWhileRead`]).
    pub fn scene_of_generation(
        &self,
        name: &str,
        generation: u64,
    ) -> Result<StoredScene, PoolError> {
        match self.scene(name) {
            Ok(s) if s.generation == generation => Ok(s),
            Ok(_) | Err(PoolError::NoSuchScene(_)) => {
                Err(PoolError::ChangedWhileRead(name.to_owned()))
            }
            Err(e) => Err(e),
        }
    }

    /// How long each read of a pack of treelet blocks took, for every scene opened from this
    /// pool or its clones (a block read from the pack last read costs no read): what tells an
    /// operator whether `pool_cache_bytes` holds the pages clients ask for.
    pub fn read_times(&self) -> &Histogram<PoolReadBuckets> {
        &self.reads
    }

    /// Whether a scene of that name exists.
    pub fn contains(&self, name: &str) -> Result<bool, PoolError> {
        Ok(self.catalogue.contains_key(name.as_bytes())?)
    }

    /// Starts an import. Fails early if the name is taken and `replace` is false.
    pub fn begin_import(&self, name: &str, replace: bool) -> Result<PoolImport, PoolError> {
        validate_scene_name(name).map_err(PoolError::BadName)?;
        if !replace && self.catalogue.contains_key(name.as_bytes())? {
            return Err(PoolError::SceneExists(name.to_owned()));
        }
        let generation = self.db.generate_id()?;
        let nodes = PackWriter::new(self.db.open_tree(nodes_tree(generation))?);
        Ok(PoolImport {
            pool: self.clone(),
            name: name.to_owned(),
            replace,
            generation,
            nodes,
            channels: Vec::new(),
            committed: false,
        })
    }

    /// Removes a scene: the catalogue entry first (atomic), then its trees.
    pub fn remove(&self, name: &str) -> Result<(), PoolError> {
        let generation = self.unpublish(name)?;
        self.drop_generation(generation)?;
        Ok(())
    }

    /// Removes a scene's catalogue entry (atomic, flushed) and returns its generation, whose
    /// trees stay until [`Pool::drop_retired`] (readers that opened the scene before keep
    /// reading it; the next [`Pool::open`] drops them too).
    pub fn unpublish(&self, name: &str) -> Result<u64, PoolError> {
        let v = self
            .catalogue
            .remove(name.as_bytes())?
            .ok_or_else(|| PoolError::NoSuchScene(name.to_owned()))?;
        self.catalogue.flush()?;
        Ok(decode_entry(name.as_bytes(), &v)?.0)
    }

    /// Drops the trees of a generation that no catalogue entry names any more (one retired by
    /// [`Pool::unpublish`] or [`PoolImport::commit_retaining`]). A live generation is refused.
    pub fn drop_retired(&self, generation: u64) -> Result<(), PoolError> {
        if self.live_generations()?.contains(&generation) {
            return Err(PoolError::GenerationLive(generation));
        }
        self.drop_generation(generation)
    }

    fn drop_generation(&self, generation: u64) -> Result<(), PoolError> {
        for name in self.db.tree_names() {
            if generation_of(&name) == Some(generation) {
                self.db.drop_tree(&name)?;
            }
        }
        self.db.flush()?;
        Ok(())
    }

    /// Generations that have trees on disk (live scenes, or an import in progress).
    pub fn stored_generations(&self) -> Vec<u64> {
        let mut g: Vec<u64> = self
            .db
            .tree_names()
            .iter()
            .filter_map(|n| generation_of(n))
            .collect();
        g.sort_unstable();
        g.dedup();
        g
    }

    /// The size of the log segments this pool was made with: [`POOL_SEGMENT_BYTES`] for a pool
    /// made by this build, 512 KiB for one made before (sled reads one header per segment
    /// whenever the pool opens; `arbor-server copy` makes a copy with this build's).
    pub fn segment_bytes(&self) -> usize {
        self.segment_bytes
    }

    /// Bytes the database occupies on disk.
    pub fn disk_bytes(&self) -> Result<u64, PoolError> {
        Ok(self.db.size_on_disk()?)
    }

    /// Flushes everything to disk.
    pub fn flush(&self) -> Result<(), PoolError> {
        self.db.flush()?;
        Ok(())
    }
}

/// Refuses a pool of another format; marks a new one with this build's.
fn check_format(db: &sled::Db, catalogue: &sled::Tree) -> Result<(), PoolError> {
    let found = match db.get(FORMAT_KEY)? {
        Some(v) => match <[u8; 4]>::try_from(v.as_ref()) {
            Ok(b) => u32::from_be_bytes(b),
            Err(_) => {
                return Err(PoolError::Corrupt {
                    what: "pool format".into(),
                    source: ProtoError::Truncated {
                        what: "pool format",
                        need: 4,
                        have: v.len(),
                    },
                });
            }
        },
        None if catalogue.is_empty() => {
            db.insert(FORMAT_KEY, &FORMAT.to_be_bytes())?;
            db.flush()?;
            FORMAT
        }
        None => 1,
    };
    if found != FORMAT {
        return Err(PoolError::Format {
            found,
            expected: FORMAT,
        });
    }
    Ok(())
}

fn decode_entry(key: &[u8], v: &[u8]) -> Result<(u64, SceneDescription), PoolError> {
    let generation = entry_generation(key, v)?;
    let d = SceneDescription::decode(&v[8..]).map_err(|source| PoolError::Corrupt {
        what: format!("catalogue {:?}", String::from_utf8_lossy(key)),
        source,
    })?;
    Ok((generation, d))
}

/// The generation of a catalogue entry (its first 8 bytes), the description left undecoded.
fn entry_generation(key: &[u8], v: &[u8]) -> Result<u64, PoolError> {
    let g = v.get(..8).ok_or_else(|| PoolError::Corrupt {
        what: format!("catalogue {:?}", String::from_utf8_lossy(key)),
        source: ProtoError::Truncated {
            what: "catalogue entry",
            need: 8,
            have: v.len(),
        },
    })?;
    Ok(u64::from_be_bytes(g.try_into().expect("8 bytes")))
}

/// An import in progress. Receives treelets as a [`TreeletSink`]; [`PoolImport::commit`] makes
/// the scene visible. Dropped without commit, it removes what it wrote.
#[derive(Debug)]
pub struct PoolImport {
    pool: Pool,
    name: String,
    replace: bool,
    generation: u64,
    nodes: PackWriter,
    channels: Vec<PackWriter>,
    committed: bool,
}

impl PoolImport {
    /// Opens the channel trees for a layout (call before the first `put`).
    pub fn set_channels(&mut self, channels: &[Channel]) -> Result<(), PoolError> {
        self.channels = channels
            .iter()
            .map(|&c| {
                let tree = self.pool.db.open_tree(channel_tree(self.generation, c))?;
                Ok::<_, PoolError>(PackWriter::new(tree))
            })
            .collect::<Result<_, _>>()?;
        Ok(())
    }

    /// Ends the import as a crash would: what was written stays on disk, unpublished, for the
    /// next [`Pool::open`] to drop. For recovery tests and tools; normal code drops or commits.
    pub fn abandon_as_if_crashed(mut self) -> Result<(), PoolError> {
        self.pool.db.flush()?;
        self.committed = true;
        Ok(())
    }

    /// Flushes the data, then publishes the catalogue entry atomically; a replaced scene's
    /// generation is dropped at once.
    pub fn commit(self, description: &SceneDescription) -> Result<(), PoolError> {
        let pool = self.pool.clone();
        if let Some(old) = self.commit_retaining(description)? {
            pool.drop_generation(old)?;
        }
        Ok(())
    }

    /// As [`PoolImport::commit`], but a replaced scene's generation is returned instead of
    /// dropped, so that readers that opened it finish on it; drop it with
    /// [`Pool::drop_retired`].
    pub fn commit_retaining(
        mut self,
        description: &SceneDescription,
    ) -> Result<Option<u64>, PoolError> {
        let encoded = description.encode().map_err(|source| PoolError::Corrupt {
            what: format!("new scene {:?}", self.name),
            source,
        })?;
        self.nodes.finish()?;
        for c in &mut self.channels {
            c.finish()?;
        }
        self.pool.db.flush()?;
        let mut entry = self.generation.to_be_bytes().to_vec();
        entry.extend_from_slice(&encoded);
        let previous = if self.replace {
            self.pool.catalogue.insert(self.name.as_bytes(), entry)?
        } else {
            match self.pool.catalogue.compare_and_swap(
                self.name.as_bytes(),
                None as Option<&[u8]>,
                Some(entry),
            )? {
                Ok(()) => None,
                Err(_) => return Err(PoolError::SceneExists(self.name.clone())),
            }
        };
        self.pool.catalogue.flush()?;
        self.committed = true;
        match previous {
            Some(old) => Ok(Some(decode_entry(self.name.as_bytes(), &old)?.0)),
            None => Ok(None),
        }
    }
}

impl Drop for PoolImport {
    fn drop(&mut self) {
        if !self.committed
            && let Err(e) = self.pool.drop_generation(self.generation)
        {
            tracing::warn!("could not drop an abandoned import: {e}");
        }
    }
}

impl TreeletSink for PoolImport {
    fn start(&mut self, layout: &AttributeLayout) -> Result<(), BuildError> {
        self.set_channels(layout.channels())
            .map_err(|e| BuildError::Sink(e.to_string()))
    }

    fn put_nodes(&mut self, blocks: Vec<(TreeletId, Vec<u8>)>) -> Result<(), BuildError> {
        write_column(&mut self.nodes, blocks)
    }

    /// Each channel's tree is written by a thread of its own: sled's inserts were the import's
    /// slowest serial step, and its trees take concurrent writers.
    fn put_channels(&mut self, blocks: Vec<(TreeletId, Vec<Vec<u8>>)>) -> Result<(), BuildError> {
        if let Some((id, b)) = blocks.iter().find(|(_, b)| b.len() != self.channels.len()) {
            return Err(BuildError::Sink(format!(
                "treelet {}: {} channel blocks for {} channel trees",
                id.0,
                b.len(),
                self.channels.len()
            )));
        }
        let mut columns: Vec<Vec<(TreeletId, Vec<u8>)>> =
            vec![Vec::with_capacity(blocks.len()); self.channels.len()];
        for (id, per_channel) in blocks {
            for (column, b) in columns.iter_mut().zip(per_channel) {
                column.push((id, b));
            }
        }
        std::thread::scope(|scope| {
            let mut pairs = self.channels.iter_mut().zip(columns);
            let first = pairs.next();
            let others: Vec<_> = pairs
                .map(|(tree, column)| scope.spawn(move || write_column(tree, column)))
                .collect();
            let mut result = first.map_or(Ok(()), |(tree, column)| write_column(tree, column));
            for h in others {
                let r = h
                    .join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
                result = result.and(r);
            }
            result
        })
    }
}

/// Hands `(treelet, block)` pairs to one of an import's pack writers.
fn write_column(
    packs: &mut PackWriter,
    column: Vec<(TreeletId, Vec<u8>)>,
) -> Result<(), BuildError> {
    for (id, block) in column {
        packs
            .put(id, block)
            .map_err(|e| BuildError::Sink(e.to_string()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(target_os = "linux")]
    #[test]
    fn sled_s_descriptor_of_the_pool_file_is_advised_and_no_other() {
        let dir = tempfile::tempdir().unwrap();
        let pool = Pool::open(dir.path()).unwrap();
        // Opening advised it already; it is still open, so it is found again.
        assert!(
            advise_random_reads(dir.path()) >= 1,
            "sled's descriptor of {}/db was not found",
            dir.path().display()
        );
        let other = tempfile::tempdir().unwrap();
        assert_eq!(advise_random_reads(other.path()), 0);
        drop(pool);
    }
}
