//! Copying a pool's scenes into a new pool directory (`arbor-server copy`), in this build's
//! layout.
//!
//! Why: sled keeps the segment size a database was made with, so a pool made before
//! [`POOL_SEGMENT_BYTES`](super::POOL_SEGMENT_BYTES) keeps 512 KiB segments, and with them an
//! open that reads one header per segment (6 s for the 10⁸-point city on a disk held to 500
//! reads a second, minutes for a 100 GB pool). A copy is made with this build's segments, holds
//! only the published scenes (none of the space that replaced or removed scenes left in the log),
//! and writes each tree's packs in key order.
//!
//! Guarantees: the source's scenes are only read (sled itself rewrites its snapshot file on every
//! open, and the copy's openings leave even unpublished trees alone). The copy is written into a sibling directory
//! `.{name}.copy-partial`, flushed, closed, opened again and compared with the source pack by pack
//! and description by description; only then is it renamed to the destination (and the parent
//! directory synced). A copy that fails or is killed leaves no pool at the destination; the next
//! copy to the same destination removes the partial directory first.
//!
//! Memory: iterating whole trees, sled keeps part of every page it has read or written since it
//! was opened, whatever its cache size (reading all of the city's 857 MB of packs left 480–600 MB
//! resident with caches of 16–512 MiB; writing them, about 300 MB more). So both pools are closed
//! and opened again after every [`REOPEN_AFTER_BYTES`] copied or compared, which bounds a copy's
//! memory whatever the pool's size. A process that opens the source meanwhile (a server started on it) makes the
//! copy fail naming the pool in use; a scene that process replaced or removed between two
//! openings fails it naming the scene ([`PoolError::ChangedWhileRead`]: its trees are gone);
//! nothing is renamed then.
//!
//! A served pool ([`copy_served`]) is read by a `get` per pack, counted as its scenes count their
//! reads and held to their pace ([`StoredScene::paced`]: the daemon's background read rate).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use arbor_proto::{ProtoError, SceneDescription};

use super::{
    Pool, PoolError, ReadAccount, StoredScene, channel_tree, decode_entry, nodes_tree, pack,
};

/// Bytes of packs copied or compared between two openings of both pools (module docs).
pub const REOPEN_AFTER_BYTES: u64 = 64 << 20;

/// Errors of a pool copy.
#[derive(Debug, thiserror::Error)]
pub enum CopyError {
    /// The destination already exists: a copy never writes into a directory it did not make.
    #[error("{0} already exists: a pool is copied into a new directory")]
    DestinationExists(PathBuf),
    /// The source is not a pool directory (no sled database in it).
    #[error("{0} is not a pool directory (no sled database `db` in it)")]
    NoSource(PathBuf),
    /// The destination has no file name (`/`, `..`), so no partial directory can sit beside it.
    #[error("{0} cannot be a pool directory to copy into (no file name)")]
    BadDestination(PathBuf),
    /// A scene asked for is not in the source pool (nothing was copied).
    #[error("no scene named {0:?} in the source pool")]
    NoSuchScene(String),
    /// The destination's file system has less room than the copy is expected to take: the
    /// source's file in the proportion of the scenes' stored bytes (sled's log holds about 1.75
    /// bytes of file per byte of packs, and a copy about as much as its source).
    #[error(
        "{dir} has {free} bytes free, a copy of these scenes takes about {need} bytes: free space or copy fewer scenes"
    )]
    NoRoom { dir: PathBuf, free: u64, need: u64 },
    /// Reading the source or writing the copy failed.
    #[error(transparent)]
    Pool(#[from] PoolError),
    /// The copy, opened again, differs from the source (nothing was renamed to the destination).
    #[error("the copy of scene {scene:?} differs from the source: {what}")]
    Mismatch { scene: String, what: String },
    /// Stopped on request ([`CopyOptions::stop`]); nothing was renamed to the destination.
    #[error("the copy was cancelled")]
    Cancelled,
    /// A file or directory operation failed.
    #[error("{what} {}: {source}", path.display())]
    Io {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

fn io(what: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> CopyError {
    let path = path.to_owned();
    move |source| CopyError::Io { what, path, source }
}

/// What to copy.
#[derive(Debug)]
pub struct CopyOptions<'a> {
    /// The scenes to copy, by name; empty: every scene ([`copy_pool`]; [`copy_served`] copies
    /// the scenes it is given).
    pub scenes: &'a [String],
    /// Files of the source directory ([`copy_served`]: of the state directory it is given)
    /// copied beside the pool when present: the server's state (certificate, key, admin token,
    /// path memory), so that a server on the copy keeps its identity.
    pub carry_files: &'a [&'a str],
    /// Bytes of packs copied or compared between two openings of the pools
    /// ([`REOPEN_AFTER_BYTES`]; tests take less to reopen within a tree).
    pub reopen_after_bytes: u64,
    /// Set from elsewhere to stop the copy after the pack in hand ([`CopyError::Cancelled`]).
    pub stop: Option<&'a AtomicBool>,
}

impl Default for CopyOptions<'_> {
    fn default() -> Self {
        CopyOptions {
            scenes: &[],
            carry_files: &[],
            reopen_after_bytes: REOPEN_AFTER_BYTES,
            stop: None,
        }
    }
}

/// What a copy reports while it runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CopyProgress {
    /// Once, before anything is written: the scenes' stored bytes (the descriptions' node and
    /// channel bytes), which the [`CopyProgress::Copied`] reports add up to.
    Planned { bytes: u64 },
    /// A pack copied: its blocks' bytes.
    Copied(u64),
}

/// One scene copied.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct CopiedScene {
    pub name: String,
    /// Packs written, over all of the scene's trees.
    pub packs: u64,
    /// Bytes of those packs.
    pub bytes: u64,
}

/// What a copy did.
#[derive(Debug)]
pub struct CopyReport {
    pub scenes: Vec<CopiedScene>,
    /// The carried files found and copied.
    pub carried: Vec<String>,
    /// The copy's database on disk.
    pub disk_bytes: u64,
    /// The source's database on disk, when the copy began.
    pub source_disk_bytes: u64,
    /// Writing (until flushed) and checking against the source.
    pub copy_time: Duration,
    pub check_time: Duration,
    /// Times both pools were opened again to let go of sled's memory.
    pub reopens: u32,
}

/// The partial directory of a copy to `dest`.
pub fn partial_dir(dest: &Path) -> Result<PathBuf, CopyError> {
    let name = dest
        .file_name()
        .filter(|n| !n.is_empty() && *n != "." && *n != "..")
        .ok_or_else(|| CopyError::BadDestination(dest.to_owned()))?;
    let mut partial = std::ffi::OsString::from(".");
    partial.push(name);
    partial.push(".copy-partial");
    Ok(dest.with_file_name(partial))
}

/// A scene to copy: its description and its generation in the source.
struct Planned {
    description: SceneDescription,
    generation: u64,
}

impl Planned {
    fn stored_bytes(&self) -> u64 {
        self.description.stats.stored_bytes()
    }

    /// Each tree's label and its name in a pool where the scene is generation `generation`
    /// (in [`StoredScene::trees`]'s order).
    fn trees(&self, generation: u64) -> Vec<(&'static str, String)> {
        let mut t = vec![("nodes", nodes_tree(generation))];
        t.extend(
            self.description
                .layout
                .channels()
                .iter()
                .map(|&c| (c.name(), channel_tree(generation, c))),
        );
        t
    }
}

/// Copies the scenes of the pool in `source_dir` into the new pool directory `dest`; see the
/// module docs. The source must not be open in this process. `progress` hears how many bytes
/// the scenes hold, then every pack copied.
pub fn copy_pool(
    source_dir: &Path,
    dest: &Path,
    options: &CopyOptions<'_>,
    progress: &dyn Fn(CopyProgress),
) -> Result<CopyReport, CopyError> {
    if !super::is_pool(source_dir) {
        return Err(CopyError::NoSource(source_dir.to_owned()));
    }
    let partial = new_destination(dest)?;
    let (planned, all_bytes, disk) = {
        let source = Pool::open_for_scan(source_dir)?;
        let disk = source.disk_bytes()?;
        let mut all = Vec::new();
        for entry in source.catalogue.iter() {
            let (k, v) = entry.map_err(PoolError::from)?;
            let (generation, description) = decode_entry(&k, &v)?;
            all.push(Planned {
                description,
                generation,
            });
        }
        let all_bytes: u64 = all.iter().map(Planned::stored_bytes).sum();
        let chosen = if options.scenes.is_empty() {
            all
        } else {
            let mut chosen: Vec<Planned> = Vec::new();
            for name in options.scenes {
                if chosen.iter().any(|p| p.description.name == *name) {
                    continue;
                }
                let i = all
                    .iter()
                    .position(|p| p.description.name == *name)
                    .ok_or_else(|| CopyError::NoSuchScene(name.clone()))?;
                chosen.push(all.swap_remove(i));
            }
            chosen
        };
        (chosen, all_bytes, disk)
    };
    let source = Source {
        reading: Reading::Closed(source_dir),
        dir: source_dir,
        disk_bytes: disk,
        all_bytes,
    };
    copy_planned(source, planned, dest, &partial, options, progress)
}

/// Copies `scenes`, opened from `pool`, which this process keeps open and serves from (the
/// daemon's live copy, [`crate::live_copy`]), into the new pool directory `dest`, as
/// [`copy_pool`] copies a closed pool: the same partial directory, check and rename. The caller
/// keeps the scenes' generations' trees until this returns, whatever replaces the scenes
/// meanwhile. The source is read by a `get` per pack, never by iterating a tree: sled keeps
/// what iteration reads far past its cache until the pool is closed (module docs), and a
/// served pool cannot be closed; reading the city's every pack by `get` left 96 MB resident,
/// iterating 503 MB (docs/measurements.md, stop 71). `options.carry_files` are read from
/// `state_dir`; `options.scenes` is not used.
pub fn copy_served(
    pool: &Pool,
    scenes: Vec<StoredScene>,
    state_dir: &Path,
    dest: &Path,
    options: &CopyOptions<'_>,
    progress: &dyn Fn(CopyProgress),
) -> Result<CopyReport, CopyError> {
    let partial = new_destination(dest)?;
    let planned: Vec<Planned> = scenes
        .iter()
        .map(|s| Planned {
            description: s.description.clone(),
            generation: s.generation,
        })
        .collect();
    // A held generation the catalogue no longer names (replaced since) counts too.
    let published: u64 = pool.scenes()?.iter().map(|d| d.stats.stored_bytes()).sum();
    let chosen: u64 = planned.iter().map(Planned::stored_bytes).sum();
    let source = Source {
        reading: Reading::Served(scenes),
        dir: state_dir,
        disk_bytes: pool.disk_bytes()?,
        all_bytes: published.max(chosen),
    };
    copy_planned(source, planned, dest, &partial, options, progress)
}

/// Refuses a destination that exists; the partial directory a copy to `dest` writes.
fn new_destination(dest: &Path) -> Result<PathBuf, CopyError> {
    if dest.symlink_metadata().is_ok() {
        return Err(CopyError::DestinationExists(dest.to_owned()));
    }
    partial_dir(dest)
}

/// Where a copy reads, and what it knows of the source before it starts.
struct Source<'a> {
    reading: Reading<'a>,
    /// Where the carried files are read.
    dir: &'a Path,
    /// The source's database on disk.
    disk_bytes: u64,
    /// Stored bytes of every scene of the source (the room a copy takes is estimated from the
    /// disk bytes in proportion to the chosen scenes' share).
    all_bytes: u64,
}

/// How the source's scenes are opened.
enum Reading<'a> {
    /// A pool directory no process has open: opened by the copy, and again after every
    /// `reopen_after` bytes; each opening checks that no other process replaced or removed
    /// the planned scenes meanwhile.
    Closed(&'a Path),
    /// Scenes of a pool this process keeps open, their trees kept by the caller.
    Served(Vec<StoredScene>),
}

/// Copies the planned scenes of `source` into `partial`, checks the copy, and renames it to
/// `dest`; removes `partial` when anything fails.
fn copy_planned(
    source: Source<'_>,
    planned: Vec<Planned>,
    dest: &Path,
    partial: &Path,
    options: &CopyOptions<'_>,
    progress: &dyn Fn(CopyProgress),
) -> Result<CopyReport, CopyError> {
    let planned_bytes: u64 = planned.iter().map(Planned::stored_bytes).sum();
    let need = if source.all_bytes == 0 {
        0
    } else {
        (u128::from(source.disk_bytes) * u128::from(planned_bytes) / u128::from(source.all_bytes))
            as u64
    };
    let parent = match partial.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_owned(),
        _ => PathBuf::from("."),
    };
    let free = free_bytes(&parent)?;
    if free < need {
        return Err(CopyError::NoRoom {
            dir: parent,
            free,
            need,
        });
    }
    if partial.symlink_metadata().is_ok() {
        tracing::warn!(
            path = %partial.display(),
            "removing the partial directory of an earlier copy that did not finish"
        );
        std::fs::remove_dir_all(partial).map_err(io("removing", partial))?;
    }
    progress(CopyProgress::Planned {
        bytes: planned_bytes,
    });
    let mut copy = Copy {
        planned_generations: planned
            .iter()
            .map(|p| (p.description.name.clone(), p.generation))
            .collect(),
        source,
        partial,
        opened: None,
        reopen_after: options.reopen_after_bytes.max(1),
        since_reopen: 0,
        reopens: 0,
        stop: options.stop,
    };
    let result = copy.write_and_check(&planned, options, progress);
    drop(copy);
    match result {
        Ok(report) => {
            std::fs::rename(partial, dest).map_err(io("renaming the copy to", dest))?;
            sync_dir(&parent)?;
            Ok(report)
        }
        Err(e) => {
            if let Err(r) = std::fs::remove_dir_all(partial) {
                tracing::warn!(path = %partial.display(), "could not remove the failed copy: {r}");
            }
            Err(e)
        }
    }
}

/// The source's planned scenes (in plan order) and the copy, while open.
struct Opened {
    /// A closed source's pool, opened by the copy; `None` for a served one.
    _source: Option<Pool>,
    scenes: Vec<StoredScene>,
    copy: Pool,
}

/// A copy in progress: the pools it opens again every `reopen_after` bytes.
struct Copy<'a> {
    source: Source<'a>,
    /// The planned scenes' names and generations in the source: checked at every opening of a
    /// closed source.
    planned_generations: Vec<(String, u64)>,
    partial: &'a Path,
    opened: Option<Opened>,
    reopen_after: u64,
    since_reopen: u64,
    reopens: u32,
    stop: Option<&'a AtomicBool>,
}

impl Copy<'_> {
    /// The source's scenes and the copy, opened if they are not.
    fn opened(&mut self) -> Result<&Opened, CopyError> {
        if self.opened.is_none() {
            let (source, scenes) = match &self.source.reading {
                Reading::Closed(dir) => {
                    let source = Pool::open_for_scan(dir)?;
                    // Another process may have opened the source since the plan or the last
                    // opening, and replaced or removed a scene: its trees are gone.
                    let scenes = self
                        .planned_generations
                        .iter()
                        .map(|(name, generation)| source.scene_of_generation(name, *generation))
                        .collect::<Result<Vec<_>, _>>()?;
                    (Some(source), scenes)
                }
                Reading::Served(scenes) => (None, scenes.clone()),
            };
            // Unpublished trees are the copy's own, written before the last reopening.
            let copy = Pool::open_for_scan(self.partial)?;
            self.opened = Some(Opened {
                _source: source,
                scenes,
                copy,
            });
        }
        Ok(self.opened.as_ref().expect("opened above"))
    }

    /// Tree `tree` (in [`StoredScene::trees`]'s order) of planned scene `scene` in the source,
    /// and the tree named `to` in the copy.
    fn tree_pair(
        &mut self,
        scene: usize,
        tree: usize,
        to: &str,
    ) -> Result<(sled::Tree, sled::Tree), CopyError> {
        let opened = self.opened()?;
        let from = opened.scenes[scene].trees()[tree].1.clone();
        let to = opened.copy.db.open_tree(to).map_err(PoolError::from)?;
        Ok((from, to))
    }

    /// The source's packs of `tree` (of planned scene `scene`) after `after`, read as this
    /// source is read.
    fn source_packs(
        &self,
        scene: usize,
        tree: &sled::Tree,
        after: Option<&sled::IVec>,
    ) -> Result<SourcePacks, CopyError> {
        let by_key = match &self.source.reading {
            Reading::Served(scenes) => Some(scenes[scene].reads().clone()),
            Reading::Closed(_) => None,
        };
        Ok(SourcePacks::after(tree, after, by_key)?)
    }

    fn check_stop(&self) -> Result<(), CopyError> {
        match self.stop {
            Some(stop) if stop.load(Ordering::Acquire) => Err(CopyError::Cancelled),
            _ => Ok(()),
        }
    }

    /// Counts `bytes` copied or compared; past `reopen_after` the pools are flushed and
    /// closed (the next [`Copy::opened`] opens them again).
    fn account(&mut self, bytes: u64) -> Result<(), CopyError> {
        self.since_reopen += bytes;
        if self.since_reopen >= self.reopen_after {
            self.close()?;
            self.reopens += 1;
        }
        Ok(())
    }

    fn close(&mut self) -> Result<(), CopyError> {
        if let Some(opened) = self.opened.take() {
            opened.copy.flush()?;
        }
        self.since_reopen = 0;
        Ok(())
    }

    /// Writes the planned scenes into the partial directory, closes it, opens it again and
    /// compares it with the source; then carries the state files.
    fn write_and_check(
        &mut self,
        planned: &[Planned],
        options: &CopyOptions<'_>,
        progress: &dyn Fn(CopyProgress),
    ) -> Result<CopyReport, CopyError> {
        let started = Instant::now();
        let mut copied = Vec::with_capacity(planned.len());
        let mut generations = Vec::with_capacity(planned.len());
        for (i, scene) in planned.iter().enumerate() {
            let (c, generation) = self.copy_scene(i, scene, progress)?;
            copied.push(c);
            generations.push(generation);
        }
        self.close()?;
        let copy_time = started.elapsed();
        let started = Instant::now();
        for (i, (scene, &generation)) in planned.iter().zip(&generations).enumerate() {
            self.check_scene(i, scene, generation)?;
        }
        let copy = &self.opened()?.copy;
        let found = copy.catalogue.len();
        if found != planned.len() {
            return Err(CopyError::Mismatch {
                scene: String::new(),
                what: format!("{found} scenes in the copy, {} copied", planned.len()),
            });
        }
        let disk_bytes = copy.disk_bytes()?;
        self.close()?;
        let check_time = started.elapsed();
        let mut carried = Vec::new();
        for name in options.carry_files {
            let from = self.source.dir.join(name);
            if from.is_file() {
                let to = self.partial.join(name);
                std::fs::copy(&from, &to).map_err(io("copying", &from))?;
                std::fs::File::open(&to)
                    .and_then(|f| f.sync_all())
                    .map_err(io("syncing", &to))?;
                carried.push((*name).to_owned());
            }
        }
        sync_dir(self.partial)?;
        Ok(CopyReport {
            scenes: copied,
            carried,
            disk_bytes,
            source_disk_bytes: self.source.disk_bytes,
            copy_time,
            check_time,
            reopens: self.reopens,
        })
    }

    /// Copies planned scene `index`'s packs unchanged, tree by tree in key order, then
    /// publishes it in the copy under a generation of the copy's own.
    fn copy_scene(
        &mut self,
        index: usize,
        scene: &Planned,
        progress: &dyn Fn(CopyProgress),
    ) -> Result<(CopiedScene, u64), CopyError> {
        let name = &scene.description.name;
        let generation = self
            .opened()?
            .copy
            .db
            .generate_id()
            .map_err(PoolError::from)?;
        let mut done = CopiedScene {
            name: name.clone(),
            packs: 0,
            bytes: 0,
        };
        for (tree, (label, to)) in scene.trees(generation).into_iter().enumerate() {
            let mut after: Option<sled::IVec> = None;
            loop {
                let (from_tree, to_tree) = self.tree_pair(index, tree, &to)?;
                let mut stretch = 0;
                let mut finished = true;
                for entry in self.source_packs(index, &from_tree, after.as_ref())? {
                    self.check_stop()?;
                    let (key, value) = entry?;
                    let blocks =
                        pack::block_bytes(&value).map_err(|source| PoolError::Corrupt {
                            what: format!("{label} pack {:?} of scene {name:?}", key.as_ref()),
                            source,
                        })?;
                    let n = value.len() as u64;
                    to_tree.insert(&key, value).map_err(PoolError::from)?;
                    done.packs += 1;
                    done.bytes += n;
                    stretch += n;
                    progress(CopyProgress::Copied(blocks as u64));
                    after = Some(key);
                    if self.since_reopen + stretch >= self.reopen_after {
                        finished = false;
                        break;
                    }
                }
                drop((from_tree, to_tree));
                self.account(stretch)?;
                if finished {
                    break;
                }
            }
        }
        let encoded = scene
            .description
            .encode()
            .map_err(|source| PoolError::Corrupt {
                what: format!("scene {name:?}"),
                source,
            })?;
        let mut entry = generation.to_be_bytes().to_vec();
        entry.extend_from_slice(&encoded);
        let copy = &self.opened()?.copy;
        copy.flush()?;
        copy.catalogue
            .insert(name.as_bytes(), entry)
            .map_err(PoolError::from)?;
        copy.catalogue.flush().map_err(PoolError::from)?;
        Ok((done, generation))
    }

    /// Compares planned scene `index`'s copy (generation `generation`) with its source: the
    /// catalogue entries' descriptions, then every tree pack by pack, in stretches between
    /// reopenings.
    fn check_scene(
        &mut self,
        index: usize,
        scene: &Planned,
        generation: u64,
    ) -> Result<(), CopyError> {
        let name = &scene.description.name;
        let stored = self.opened()?.copy.scene(name)?;
        if stored.generation != generation || stored.description != scene.description {
            return Err(CopyError::Mismatch {
                scene: name.clone(),
                what: "the catalogue entries differ".into(),
            });
        }
        drop(stored);
        for (tree, (label, to)) in scene.trees(generation).into_iter().enumerate() {
            let mut after = None;
            loop {
                self.check_stop()?;
                let (a, b) = self.tree_pair(index, tree, &to)?;
                let budget = self.reopen_after.saturating_sub(self.since_reopen);
                let packs = self.source_packs(index, &a, after.as_ref())?;
                let (compared, last) =
                    compare_trees(name, label, packs, &b, after.as_ref(), budget)?;
                drop((a, b));
                self.account(compared)?;
                match last {
                    Some(key) => after = Some(key),
                    None => break,
                }
            }
        }
        Ok(())
    }
}

/// The entries of `tree` after `key` (all of them without one), in key order.
fn range_after(tree: &sled::Tree, key: Option<&sled::IVec>) -> sled::Iter {
    match key {
        Some(k) => tree.range::<&[u8], _>((
            std::ops::Bound::Excluded(k.as_ref()),
            std::ops::Bound::Unbounded,
        )),
        None => tree.iter(),
    }
}

/// A source tree's packs after a key, in key order.
enum SourcePacks {
    /// Iterating the tree (a pool the copy opened itself, and closes every `reopen_after`).
    Iter(Box<sled::Iter>),
    /// A `get` per pack index from `next` to the tree's last key (a served pool,
    /// [`copy_served`]). A pool's pack keys are 4-byte indices; a tree whose last key is not
    /// one is named as corrupt.
    ByKey {
        tree: sled::Tree,
        next: u64,
        last: Option<u64>,
        /// The scene's read account: its pace, if any, holds these reads.
        reads: ReadAccount,
    },
}

impl SourcePacks {
    /// Iterating, or with `by_key`, a `get` per pack counted in that account.
    fn after(
        tree: &sled::Tree,
        after: Option<&sled::IVec>,
        by_key: Option<ReadAccount>,
    ) -> Result<SourcePacks, PoolError> {
        let Some(reads) = by_key else {
            return Ok(SourcePacks::Iter(Box::new(range_after(tree, after))));
        };
        let index = |key: &[u8]| -> Result<u64, PoolError> {
            let key: [u8; 4] = key.try_into().map_err(|_| PoolError::Corrupt {
                what: format!("pack key {key:?}"),
                source: ProtoError::OutOfRange {
                    what: "pack key",
                    detail: "not a 4-byte pack index".into(),
                },
            })?;
            Ok(u64::from(u32::from_be_bytes(key)))
        };
        let next = match after {
            Some(k) => index(k)? + 1,
            None => 0,
        };
        let last = match tree.last()? {
            Some((k, _)) => Some(index(&k)?),
            None => None,
        };
        Ok(SourcePacks::ByKey {
            tree: tree.clone(),
            next,
            last,
            reads,
        })
    }
}

impl Iterator for SourcePacks {
    type Item = Result<(sled::IVec, sled::IVec), PoolError>;

    fn next(&mut self) -> Option<Self::Item> {
        match self {
            SourcePacks::Iter(packs) => packs.next().map(|p| p.map_err(PoolError::from)),
            SourcePacks::ByKey {
                tree,
                next,
                last,
                reads,
            } => {
                let last = (*last)?;
                while *next <= last {
                    let key = u32::try_from(*next).ok()?.to_be_bytes();
                    *next += 1;
                    let began = Instant::now();
                    match tree.get(key) {
                        Ok(Some(pack)) => {
                            reads.observe(began, pack.len());
                            return Some(Ok((sled::IVec::from(&key[..]), pack)));
                        }
                        Ok(None) => {}
                        Err(e) => return Some(Err(e.into())),
                    }
                }
                None
            }
        }
    }
}

/// Compares the packs of `a` (the source's, in key order) with those of the copy's tree `b`
/// after `after`, until both end or `budget` bytes of `a` are compared; returns the bytes
/// compared and, when the budget ran out first, the last key compared. Fails naming the first
/// difference.
fn compare_trees(
    scene: &str,
    tree: &str,
    mut ia: SourcePacks,
    b: &sled::Tree,
    after: Option<&sled::IVec>,
    budget: u64,
) -> Result<(u64, Option<sled::IVec>), CopyError> {
    let mismatch = |what: String| CopyError::Mismatch {
        scene: scene.to_owned(),
        what: format!("{tree}: {what}"),
    };
    let mut ib = range_after(b, after);
    let mut compared = 0;
    loop {
        let a_next = ia.next().transpose()?;
        let b_next = ib.next().transpose().map_err(PoolError::from)?;
        match (a_next, b_next) {
            (None, None) => return Ok((compared, None)),
            (Some((k, _)), None) => {
                return Err(mismatch(format!("pack {k:?} missing in the copy")));
            }
            (None, Some((k, _))) => return Err(mismatch(format!("pack {k:?} only in the copy"))),
            (Some((ka, va)), Some((kb, vb))) => match ka.cmp(&kb) {
                std::cmp::Ordering::Less => {
                    return Err(mismatch(format!("pack {ka:?} missing in the copy")));
                }
                std::cmp::Ordering::Greater => {
                    return Err(mismatch(format!("pack {kb:?} only in the copy")));
                }
                std::cmp::Ordering::Equal if va != vb => {
                    return Err(mismatch(format!("pack {ka:?} differs")));
                }
                std::cmp::Ordering::Equal => {
                    compared += va.len() as u64;
                    if compared >= budget {
                        return Ok((compared, Some(ka)));
                    }
                }
            },
        }
    }
}

/// Fails naming the first difference between a source scene and its copy: the description,
/// or a tree's packs (keys and bytes). What a copy checks, for a scene at a time.
pub fn compare_scene(source: &StoredScene, copy: &StoredScene) -> Result<(), CopyError> {
    let name = &source.description.name;
    if source.description != copy.description {
        return Err(CopyError::Mismatch {
            scene: name.clone(),
            what: "the descriptions differ".into(),
        });
    }
    for ((tree, a), (_, b)) in source.trees().into_iter().zip(copy.trees()) {
        let packs = SourcePacks::after(a, None, None)?;
        compare_trees(name, tree, packs, b, None, u64::MAX)?;
    }
    Ok(())
}

fn free_bytes(dir: &Path) -> Result<u64, CopyError> {
    let s = rustix::fs::statvfs(dir)
        .map_err(|e| std::io::Error::from_raw_os_error(e.raw_os_error()))
        .map_err(io("reading the free space of", dir))?;
    Ok(s.f_bavail.saturating_mul(s.f_frsize))
}

fn sync_dir(dir: &Path) -> Result<(), CopyError> {
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io("syncing", dir))
}
