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

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use arbor_proto::SceneDescription;

use super::{Pool, PoolError, StoredScene, channel_tree, decode_entry, nodes_tree, pack};

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
    /// The scenes to copy, by name; empty: every scene.
    pub scenes: &'a [String],
    /// Files of the source directory copied beside the pool when present: the server's state
    /// when its data directory is the pool directory (certificate, key, admin token, path
    /// memory), so that a server on the copy keeps its identity.
    pub carry_files: &'a [&'a str],
    /// Bytes of packs copied or compared between two openings of both pools
    /// ([`REOPEN_AFTER_BYTES`]; tests take less to reopen within a tree).
    pub reopen_after_bytes: u64,
}

impl Default for CopyOptions<'_> {
    fn default() -> Self {
        CopyOptions {
            scenes: &[],
            carry_files: &[],
            reopen_after_bytes: REOPEN_AFTER_BYTES,
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
#[derive(Debug, Clone, PartialEq, Eq)]
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

/// A scene to copy: its description and where its trees are in the source.
struct Planned {
    description: SceneDescription,
    generation: u64,
}

impl Planned {
    fn stored_bytes(&self) -> u64 {
        let st = &self.description.stats;
        st.node_bytes + st.channel_bytes.iter().sum::<u64>()
    }

    /// Each tree's label and its name in a pool where the scene is generation `generation`.
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
    if dest.symlink_metadata().is_ok() {
        return Err(CopyError::DestinationExists(dest.to_owned()));
    }
    let partial = partial_dir(dest)?;
    let (planned, planned_bytes, need, source_disk_bytes) = {
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
        let chosen_bytes: u64 = chosen.iter().map(Planned::stored_bytes).sum();
        let need = if all_bytes == 0 {
            0
        } else {
            (u128::from(disk) * u128::from(chosen_bytes) / u128::from(all_bytes)) as u64
        };
        (chosen, chosen_bytes, need, disk)
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
        std::fs::remove_dir_all(&partial).map_err(io("removing", &partial))?;
    }
    progress(CopyProgress::Planned {
        bytes: planned_bytes,
    });
    let mut copy = Copy {
        source_dir,
        planned_generations: planned
            .iter()
            .map(|p| (p.description.name.clone(), p.generation))
            .collect(),
        source_disk_bytes,
        partial: &partial,
        pools: None,
        reopen_after: options.reopen_after_bytes.max(1),
        since_reopen: 0,
        reopens: 0,
    };
    let result = copy.write_and_check(&planned, options, progress);
    drop(copy);
    match result {
        Ok(report) => {
            std::fs::rename(&partial, dest).map_err(io("renaming the copy to", dest))?;
            sync_dir(&parent)?;
            Ok(report)
        }
        Err(e) => {
            if let Err(r) = std::fs::remove_dir_all(&partial) {
                tracing::warn!(path = %partial.display(), "could not remove the failed copy: {r}");
            }
            Err(e)
        }
    }
}

/// Both pools of a copy in progress, opened again every `reopen_after` bytes.
struct Copy<'a> {
    source_dir: &'a Path,
    /// The planned scenes' names and generations in the source: checked at every opening.
    planned_generations: Vec<(String, u64)>,
    /// The source's database on disk when the copy began (for the report).
    source_disk_bytes: u64,
    partial: &'a Path,
    /// The source and the copy, while open.
    pools: Option<(Pool, Pool)>,
    reopen_after: u64,
    since_reopen: u64,
    reopens: u32,
}

impl Copy<'_> {
    /// The two pools, opened if they are not.
    fn pools(&mut self) -> Result<&(Pool, Pool), CopyError> {
        if self.pools.is_none() {
            let source = Pool::open_for_scan(self.source_dir)?;
            // Another process may have opened the source since the plan or the last opening.
            // A scene replaced or removed meanwhile has had its trees dropped: opening them by
            // name would make empty ones in the source and copy nothing, unnoticed.
            for (name, generation) in &self.planned_generations {
                source.scene_of_generation(name, *generation)?;
            }
            // Unpublished trees are the copy's own, written before the last reopening.
            let copy = Pool::open_for_scan(self.partial)?;
            self.pools = Some((source, copy));
        }
        Ok(self.pools.as_ref().expect("opened above"))
    }

    /// Counts `bytes` copied or compared; past `reopen_after` both pools are flushed and
    /// closed (the next [`Copy::pools`] opens them again).
    fn account(&mut self, bytes: u64) -> Result<(), CopyError> {
        self.since_reopen += bytes;
        if self.since_reopen >= self.reopen_after {
            self.close()?;
            self.reopens += 1;
        }
        Ok(())
    }

    fn close(&mut self) -> Result<(), CopyError> {
        if let Some((_, copy)) = self.pools.take() {
            copy.flush()?;
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
        for scene in planned {
            let (c, generation) = self.copy_scene(scene, progress)?;
            copied.push(c);
            generations.push(generation);
        }
        self.close()?;
        let copy_time = started.elapsed();
        let started = Instant::now();
        for (scene, &generation) in planned.iter().zip(&generations) {
            self.check_scene(scene, generation)?;
        }
        let (_, copy) = self.pools()?;
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
            let from = self.source_dir.join(name);
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
            source_disk_bytes: self.source_disk_bytes,
            copy_time,
            check_time,
            reopens: self.reopens,
        })
    }

    /// Copies one scene's packs unchanged, tree by tree in key order, then publishes it in the
    /// copy under a generation of the copy's own.
    fn copy_scene(
        &mut self,
        scene: &Planned,
        progress: &dyn Fn(CopyProgress),
    ) -> Result<(CopiedScene, u64), CopyError> {
        let name = &scene.description.name;
        let generation = self.pools()?.1.db.generate_id().map_err(PoolError::from)?;
        let mut done = CopiedScene {
            name: name.clone(),
            packs: 0,
            bytes: 0,
        };
        for ((label, from), (_, to)) in scene
            .trees(scene.generation)
            .into_iter()
            .zip(scene.trees(generation))
        {
            let mut after: Option<sled::IVec> = None;
            loop {
                let (source, copy) = self.pools()?;
                let (from_tree, to_tree) = (
                    source.db.open_tree(&from).map_err(PoolError::from)?,
                    copy.db.open_tree(&to).map_err(PoolError::from)?,
                );
                let mut stretch = 0;
                let mut finished = true;
                for entry in range_after(&from_tree, after.as_ref()) {
                    let (key, value) = entry.map_err(PoolError::from)?;
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
        let copy = &self.pools()?.1;
        copy.flush()?;
        copy.catalogue
            .insert(name.as_bytes(), entry)
            .map_err(PoolError::from)?;
        copy.catalogue.flush().map_err(PoolError::from)?;
        Ok((done, generation))
    }

    /// Compares one copied scene with its source: the catalogue entries' descriptions, then
    /// every tree pack by pack, in stretches between reopenings.
    fn check_scene(&mut self, scene: &Planned, generation: u64) -> Result<(), CopyError> {
        let name = &scene.description.name;
        let stored = self.pools()?.1.scene(name)?;
        if stored.generation != generation || stored.description != scene.description {
            return Err(CopyError::Mismatch {
                scene: name.clone(),
                what: "the catalogue entries differ".into(),
            });
        }
        drop(stored);
        for ((label, from), (_, to)) in scene
            .trees(scene.generation)
            .into_iter()
            .zip(scene.trees(generation))
        {
            let mut after = None;
            loop {
                let (source, copy) = self.pools()?;
                let (a, b) = (
                    source.db.open_tree(&from).map_err(PoolError::from)?,
                    copy.db.open_tree(&to).map_err(PoolError::from)?,
                );
                let budget = self.reopen_after.saturating_sub(self.since_reopen);
                let (compared, last) = compare_trees(name, label, &a, &b, after.as_ref(), budget)?;
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

/// Compares the packs of `a` (source) and `b` (copy) after `after`, until both end or `budget`
/// bytes of `a` are compared; returns the bytes compared and, when the budget ran out first, the
/// last key compared. Fails naming the first difference.
fn compare_trees(
    scene: &str,
    tree: &str,
    a: &sled::Tree,
    b: &sled::Tree,
    after: Option<&sled::IVec>,
    budget: u64,
) -> Result<(u64, Option<sled::IVec>), CopyError> {
    let mismatch = |what: String| CopyError::Mismatch {
        scene: scene.to_owned(),
        what: format!("{tree}: {what}"),
    };
    let (mut ia, mut ib) = (range_after(a, after), range_after(b, after));
    let mut compared = 0;
    loop {
        let next = |i: &mut sled::Iter| i.next().transpose().map_err(PoolError::from);
        match (next(&mut ia)?, next(&mut ib)?) {
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
    let mut pairs = vec![("nodes", &source.nodes, &copy.nodes)];
    pairs.extend(
        source
            .channels
            .iter()
            .zip(&copy.channels)
            .map(|((c, from), (_, to))| (c.name(), from, to)),
    );
    for (tree, a, b) in pairs {
        compare_trees(name, tree, a, b, None, u64::MAX)?;
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
