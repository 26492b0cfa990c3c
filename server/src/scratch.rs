//! Scratch directories of imports, and removing the ones killed imports left.
//!
//! An import parses its input into memory-mapped columns and spills sorted runs into a scratch
//! directory: about 20–30 MB for a shared scan, tens of gigabytes for a 10⁸-point city. Dropped,
//! a [`ScratchDir`] removes itself; but a process that is killed (SIGKILL, the OOM killer, a
//! power cut) runs no destructor, and each such import used to leave its directory in `/tmp`
//! for good.
//!
//! So every scratch directory holds an `owner.lock` file on which its import keeps an exclusive
//! lock (`flock`) for as long as the directory lives. The kernel releases the lock when the
//! process dies however it dies, so a directory whose lock can be taken has no owner: each new
//! scratch directory first removes those beside it ([`sweep_abandoned`]).
//!
//! Creating a directory and its lock file takes a few steps, and a process may be killed between
//! them. So creating and judging what to sweep both hold a lock on one file in the parent
//! ([`CREATE_LOCK`]): a sweep that holds it sees no directory half-created by a live import, and
//! a directory without its lock file that is empty or holds only the lock file still unnamed
//! (`owner.lock.new`) is what a process killed between those steps left; it goes at once.
//!
//! Removing is the slow part (a killed 10⁸-point import leaves tens of gigabytes), so it happens
//! after the creation lock is released, and no other import waits for it to start its own. A
//! sweep *claims* a directory under the lock: it keeps the directory's `owner.lock` locked and
//! renames the directory to [`REMOVING_PREFIX`]; an owner does the same with its own. The
//! removal unlinks the lock file last, so while it runs every other sweep finds the lock held
//! and leaves the directory to it; a removal cut short by a kill leaves the lock file unlocked
//! (or, killed at the very end, an empty directory: left for [`REMOVAL_GRACE`], in which its
//! remover would have removed it), and the next sweep finishes it.
//! Any other directory without the lock file is left alone while anything in it changed within
//! [`STALE_UNLOCKED`]: an Arbor from before the lock files may be writing it; older, it goes
//! too. Anything that is not a plain directory named `arbor-import-*` is left alone. The owner
//! holds the lock until its directory is gone, so a directory being removed is not taken for an
//! abandoned one either.

use std::fs::{File, TryLockError};
use std::io;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use tempfile::TempDir;

/// Prefix of scratch directory names.
pub const SCRATCH_PREFIX: &str = "arbor-import-";
/// The file in a scratch directory its owner keeps locked.
pub const OWNER_LOCK: &str = "owner.lock";
/// Prefix a scratch directory is renamed to just before it is removed, by its owner or a
/// sweep: whatever is left named so is a removal that did not finish. (A scratch directory's
/// own name is the prefix and six letters or digits, never this.)
pub const REMOVING_PREFIX: &str = "arbor-import-removing-";
/// The file in a scratch directories' parent that creating a scratch directory and judging what
/// to sweep lock (never removing, the slow part), so that a sweep never meets a directory a live
/// import is still creating. Kept (a few bytes of nothing); not named like a scratch directory.
pub const CREATE_LOCK: &str = ".arbor-import.lock";
/// The lock file's name until it is locked (a directory that has only this is half-created:
/// see [`half_created`]).
const OWNER_LOCK_NEW: &str = "owner.lock.new";
/// How long a directory named as a removal, empty and without its lock file, is left to its
/// remover (which removes it microseconds after unlinking the lock file) before a sweep takes
/// it for one whose remover was killed at its very end.
pub const REMOVAL_GRACE: Duration = Duration::from_secs(60);
/// How long a scratch directory without a lock file must have been unchanged (it and every
/// entry in it) before a sweep takes it for abandoned. A day: an import writes its columns and
/// runs continually, and the largest measured (10⁸ points) takes minutes.
pub const STALE_UNLOCKED: Duration = Duration::from_secs(24 * 60 * 60);

/// An import's scratch directory: removed on drop, locked by its owner while it lives.
#[derive(Debug)]
pub struct ScratchDir {
    /// `None` only once dropped (or abandoned in a test).
    dir: Option<TempDir>,
    /// Closed after `dir` is removed, so the lock is held until the directory is gone
    /// (unlinking an open file is fine on Unix): a sweep never sees a directory being removed
    /// as abandoned.
    _owner: Option<File>,
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        let Some(dir) = self.dir.take() else { return };
        let path = dir.keep();
        // The lock goes with the claim and is released once the lock file is unlinked, last:
        // a sweep never takes the directory for abandoned while it is being removed.
        let removed = claim(&path, self._owner.take()).and_then(Doomed::remove);
        if let Err(e) = removed {
            tracing::warn!(
                "could not remove the scratch directory {}: {e}",
                path.display()
            );
        }
    }
}

impl ScratchDir {
    /// A new scratch directory in `parent` (default: the system's temporary directory), after
    /// removing the abandoned ones there.
    pub fn new(parent: Option<&Path>) -> io::Result<ScratchDir> {
        let parent = parent.map_or_else(std::env::temp_dir, Path::to_path_buf);
        // Held until the directory and its lock file are made. Without it (a lock file nobody
        // may open) the import goes on, judging no half-made directory.
        let creating = lock_creation(&parent).ok();
        let doomed = claim_abandoned(&parent, creating.is_some());
        let made = create_locked(&parent);
        drop(creating);
        // Removed with the creation lock released: other imports start meanwhile.
        let removed = remove_all(doomed);
        if !removed.is_empty() {
            tracing::info!(
                parent = %parent.display(),
                "removed {} scratch directories of imports that did not finish: {}",
                removed.len(),
                removed
                    .iter()
                    .filter_map(|p| p.file_name()?.to_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        let (dir, owner) = made?;
        Ok(ScratchDir {
            dir: Some(dir),
            _owner: Some(owner),
        })
    }

    /// Where the scratch files go.
    pub fn path(&self) -> &Path {
        self.dir
            .as_ref()
            .expect("a scratch directory lives until dropped")
            .path()
    }
}

/// A new scratch directory in `parent` and its lock file, locked (call under [`CREATE_LOCK`]).
fn create_locked(parent: &Path) -> io::Result<(TempDir, File)> {
    let dir = tempfile::Builder::new()
        .prefix(SCRATCH_PREFIX)
        .tempdir_in(parent)?;
    // Locked under another name, then renamed: a sweep that sees `owner.lock` always finds it
    // locked, never in the instant between its creation and the lock.
    let unlocked = dir.path().join(OWNER_LOCK_NEW);
    let owner = File::create(&unlocked)?;
    owner.lock()?;
    std::fs::rename(&unlocked, dir.path().join(OWNER_LOCK))?;
    Ok((dir, owner))
}

/// Removes every scratch directory in `parent` whose owner is gone (its `owner.lock` exists and
/// can be locked, or it has none and nothing in it changed for [`STALE_UNLOCKED`]); returns the
/// ones removed, by the names they had. Best effort: what cannot be read, locked or removed
/// (another user's, one in use) stays, and a failure is logged, never returned.
pub fn sweep_abandoned(parent: &Path) -> Vec<PathBuf> {
    let doomed = {
        // A parent where the lock cannot be made (read-only, missing): no half-created
        // directory is judged, the rest as always.
        let creating = lock_creation(parent).ok();
        claim_abandoned(parent, creating.is_some())
    };
    remove_all(doomed)
}

/// [`CREATE_LOCK`] in `parent`, created if missing and locked exclusively (waiting for a
/// creation or sweep in progress); the lock goes when the file closes. Opened for reading
/// when it cannot be for writing (another user's in a shared `/tmp`: `flock` needs neither).
fn lock_creation(parent: &Path) -> io::Result<File> {
    let path = parent.join(CREATE_LOCK);
    let file = File::options()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .or_else(|_| File::open(&path))?;
    file.lock()?;
    Ok(file)
}

/// A scratch directory claimed for removal: renamed to [`REMOVING_PREFIX`], its lock file (when
/// it has one) held locked until [`Doomed::remove`] unlinks it.
#[derive(Debug)]
struct Doomed {
    /// The name it had when claimed (what a sweep reports).
    original: PathBuf,
    /// Its name now.
    path: PathBuf,
    /// The open, locked `owner.lock`; `None` for a directory that has none.
    _lock: Option<File>,
}

impl Doomed {
    /// Removes everything in the directory but its lock file, then the lock file, then the
    /// directory: a removal cut short leaves the lock file for the next sweep to find unlocked.
    /// Returns the name the directory had when claimed.
    fn remove(self) -> io::Result<PathBuf> {
        let gone_already = |r: io::Result<()>| match r {
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
            r => r,
        };
        for entry in std::fs::read_dir(&self.path)? {
            let entry = entry?;
            if entry.file_name() == OWNER_LOCK {
                continue;
            }
            // `file_type` does not follow a link: a link is unlinked, never entered.
            let removed = if entry.file_type()?.is_dir() {
                std::fs::remove_dir_all(entry.path())
            } else {
                std::fs::remove_file(entry.path())
            };
            gone_already(removed)?;
        }
        gone_already(std::fs::remove_file(self.path.join(OWNER_LOCK)))?;
        // Empty by now, unless another sweep finished it meanwhile (one without a lock file).
        gone_already(std::fs::remove_dir(&self.path))?;
        Ok(self.original)
    }
}

/// Claims `dir` for removal with its lock file `lock` (held locked, or `None` when it has none):
/// renamed to [`REMOVING_PREFIX`] unless it is so named already.
fn claim(dir: &Path, lock: Option<File>) -> io::Result<Doomed> {
    let path = if removal_cut_short(dir) {
        dir.to_path_buf()
    } else {
        let name = dir
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(|| io::Error::other("not a scratch directory's name"))?;
        let doomed = dir.with_file_name(format!(
            "{REMOVING_PREFIX}{}",
            name.strip_prefix(SCRATCH_PREFIX).unwrap_or(name)
        ));
        std::fs::rename(dir, &doomed)?;
        doomed
    };
    Ok(Doomed {
        original: dir.to_path_buf(),
        path,
        _lock: lock,
    })
}

/// Claims the abandoned scratch directories in `parent` (see [`sweep_abandoned`]);
/// `creators_locked_out` when the caller holds [`CREATE_LOCK`]. Quick: nothing is removed yet.
fn claim_abandoned(parent: &Path, creators_locked_out: bool) -> Vec<Doomed> {
    let Ok(entries) = std::fs::read_dir(parent) else {
        return Vec::new();
    };
    let mut doomed = Vec::new();
    for entry in entries.flatten() {
        let named = entry
            .file_name()
            .to_str()
            .is_some_and(|n| n.starts_with(SCRATCH_PREFIX));
        // `file_type` does not follow a symbolic link: a link is never entered or removed.
        let is_dir = entry.file_type().is_ok_and(|t| t.is_dir());
        if !named || !is_dir {
            continue;
        }
        let path = entry.path();
        let Some(lock) = abandoned(&path, SystemTime::now(), creators_locked_out) else {
            continue;
        };
        // Not found: removed by someone else meanwhile (its owner, as it finished, or another
        // sweep).
        doomed.extend(logged(claim(&path, lock), "claim", &path));
    }
    doomed
}

/// Removes the claimed directories; returns the names they had. Failures are logged.
fn remove_all(doomed: Vec<Doomed>) -> Vec<PathBuf> {
    let mut removed = Vec::new();
    for d in doomed {
        let path = d.path.clone();
        // Not found: finished by someone else meanwhile (a cut-short removal without a lock
        // file).
        removed.extend(logged(d.remove(), "remove", &path));
    }
    removed
}

/// `r`'s value; a failure to `doing` the abandoned directory `path` logged, unless it was not
/// found (someone else got there first).
fn logged<T>(r: io::Result<T>, doing: &str, path: &Path) -> Option<T> {
    match r {
        Ok(v) => Some(v),
        Err(e) if e.kind() == io::ErrorKind::NotFound => None,
        Err(e) => {
            tracing::warn!(
                "could not {doing} the abandoned scratch directory {}: {e}",
                path.display()
            );
            None
        }
    }
}

/// Whether `dir` is named as a removal in progress, or one its process did not finish.
fn removal_cut_short(dir: &Path) -> bool {
    dir.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.starts_with(REMOVING_PREFIX))
}

/// Whether `dir` is a scratch directory nobody holds at `now`, and if so its lock file, locked
/// (`Some(None)` when it has none): its lock file exists and the lock is free (a removal in
/// progress holds it too), or it has none and is a removal cut short (not one just finishing,
/// see [`removal_finishing`]), half-created while `creators_locked_out` (see
/// [`half_created`]), or stale.
fn abandoned(dir: &Path, now: SystemTime, creators_locked_out: bool) -> Option<Option<File>> {
    let lock = dir.join(OWNER_LOCK);
    // Not followed through a link: a link named like the lock file makes the directory
    // someone else's.
    match std::fs::symlink_metadata(&lock) {
        Ok(m) if m.is_file() => {}
        Ok(_) => return None,
        Err(e) if e.kind() == io::ErrorKind::NotFound => {
            let unowned = if removal_cut_short(dir) {
                !removal_finishing(dir, now)
            } else {
                (creators_locked_out && half_created(dir)) || unchanged_since(dir, now)
            };
            return unowned.then_some(None);
        }
        Err(_) => return None,
    }
    let file = File::open(&lock).ok()?;
    match file.try_lock() {
        Ok(()) => Some(Some(file)),
        Err(TryLockError::WouldBlock) => None,
        Err(TryLockError::Error(e)) => {
            tracing::debug!("{}: {e}", lock.display());
            None
        }
    }
}

/// Whether `dir`, named as a removal and without its lock file, is empty and changed within
/// [`REMOVAL_GRACE`] of `now`: its remover has just unlinked the lock file and is about to remove
/// the directory (a sweep would report it as its own). One left empty longer was cut short.
fn removal_finishing(dir: &Path, now: SystemTime) -> bool {
    let empty = std::fs::read_dir(dir).is_ok_and(|mut e| e.next().is_none());
    let recent = std::fs::symlink_metadata(dir)
        .and_then(|m| m.modified())
        .is_ok_and(|t| {
            now.duration_since(t)
                .map_or(true, |age| age < REMOVAL_GRACE)
        });
    empty && recent
}

/// Whether `dir` is as [`ScratchDir::new`] leaves it when killed before its lock file is named:
/// empty, or holding only the unnamed lock file (a plain file). Only meaningful while no
/// creation can be in progress, that is under [`CREATE_LOCK`].
fn half_created(dir: &Path) -> bool {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    let entries: Vec<_> = entries.take(2).collect();
    match entries.as_slice() {
        [] => true,
        [Ok(e)] => e.file_name() == OWNER_LOCK_NEW && e.file_type().is_ok_and(|t| t.is_file()),
        _ => false,
    }
}

/// Whether `dir` and every entry in it are plain files or directories unchanged for
/// [`STALE_UNLOCKED`] before `now` (a link or an unreadable entry: not stale, left alone).
fn unchanged_since(dir: &Path, now: SystemTime) -> bool {
    let stale = |m: &std::fs::Metadata| {
        m.modified()
            .is_ok_and(|t| now.duration_since(t).is_ok_and(|age| age >= STALE_UNLOCKED))
    };
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    if !std::fs::symlink_metadata(dir).is_ok_and(|m| stale(&m)) {
        return false;
    }
    entries.into_iter().all(|e| {
        e.and_then(|e| e.path().symlink_metadata())
            .is_ok_and(|m| !m.file_type().is_symlink() && stale(&m))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a killed import leaves: a scratch directory with its lock file and data, unlocked.
    fn abandoned_dir(parent: &Path, name: &str) -> PathBuf {
        let dir = parent.join(name);
        std::fs::create_dir(&dir).unwrap();
        std::fs::write(dir.join(OWNER_LOCK), b"").unwrap();
        std::fs::write(dir.join("src_positions.col"), [7u8; 4096]).unwrap();
        dir
    }

    #[test]
    fn a_new_scratch_dir_removes_the_abandoned_ones_and_nothing_else() {
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path();
        let dead = abandoned_dir(p, "arbor-import-dead1");
        let dead2 = abandoned_dir(p, "arbor-import-dead2");
        let live = ScratchDir::new(Some(p)).unwrap();
        assert!(!dead.exists() && !dead2.exists(), "abandoned dirs removed");
        std::fs::write(live.path().join("data.col"), b"x").unwrap();

        // Left alone: a recent scratch dir without a lock file but with data (an import from
        // before the lock files), another program's dir with a lock file, a link named like a
        // scratch dir, a plain file named like one.
        let unlocked = p.join("arbor-import-nolock");
        std::fs::create_dir(&unlocked).unwrap();
        std::fs::write(unlocked.join("src_positions.col"), b"x").unwrap();
        let other = abandoned_dir(p, "other-tool-dir");
        let target = abandoned_dir(p, "link-target");
        std::os::unix::fs::symlink(&target, p.join("arbor-import-link")).unwrap();
        std::fs::write(p.join("arbor-import-file"), b"not a dir").unwrap();
        // A lock file that is a link to a file nobody locks.
        let linked_lock = p.join("arbor-import-linked-lock");
        std::fs::create_dir(&linked_lock).unwrap();
        std::os::unix::fs::symlink(target.join(OWNER_LOCK), linked_lock.join(OWNER_LOCK)).unwrap();

        let second = ScratchDir::new(Some(p)).unwrap();
        assert!(
            live.path().join("data.col").exists(),
            "a live import's dir is kept"
        );
        for kept in [&unlocked, &other, &target, &linked_lock] {
            assert!(kept.exists(), "{} kept", kept.display());
        }
        assert!(p.join("arbor-import-link").exists());
        assert!(p.join("arbor-import-file").exists());
        assert!(
            target.join("src_positions.col").exists(),
            "nothing removed through the link"
        );

        // Dropped: removed with its lock file; the other live one stays.
        let gone = live.path().to_path_buf();
        drop(live);
        assert!(!gone.exists());
        assert!(second.path().exists());
        assert!(sweep_abandoned(p).is_empty(), "the live dir is locked");
    }

    #[test]
    fn a_scratch_dir_of_a_dead_owner_is_removed_by_the_sweep() {
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path();
        let dir = ScratchDir::new(Some(p)).unwrap();
        let path = dir.path().to_path_buf();
        // As a killed process leaves it: the lock released (the file closed), the directory kept.
        let mut dir = dir;
        dir._owner = None;
        let kept = dir.dir.take().unwrap().keep();
        drop(dir);
        assert_eq!(kept, path);
        assert_eq!(sweep_abandoned(p), vec![path.clone()]);
        assert!(!path.exists());
    }

    #[test]
    fn a_sweep_never_removes_a_scratch_dir_being_created() {
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path().to_path_buf();
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let sweeper = {
            let (p, stop) = (p.clone(), stop.clone());
            std::thread::spawn(move || {
                let mut removed = 0;
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    removed += sweep_abandoned(&p).len();
                }
                removed
            })
        };
        for i in 0..300 {
            let dir = ScratchDir::new(Some(&p)).unwrap();
            std::fs::write(dir.path().join("column"), [1u8; 64])
                .unwrap_or_else(|e| panic!("scratch dir {i} removed under its owner: {e}"));
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        assert_eq!(
            sweeper.join().unwrap(),
            0,
            "only live scratch dirs were there"
        );
    }

    /// Sets the modification time of `path` (a file or a directory) `age` into the past.
    fn age(path: &Path, age: Duration) {
        let t = SystemTime::now() - age;
        std::fs::File::open(path).unwrap().set_modified(t).unwrap();
    }

    #[test]
    fn a_stale_scratch_dir_without_a_lock_file_is_removed_and_a_recent_one_kept() {
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path();
        let old = STALE_UNLOCKED + Duration::from_secs(60);
        // What a process killed between creating the directory and naming its lock left, and
        // what an import from before the lock files left: both a day old.
        let half_made = p.join("arbor-import-halfmade");
        std::fs::create_dir(&half_made).unwrap();
        std::fs::write(half_made.join(OWNER_LOCK_NEW), b"").unwrap();
        age(&half_made.join(OWNER_LOCK_NEW), old);
        age(&half_made, old);
        let legacy = p.join("arbor-import-legacy");
        std::fs::create_dir(&legacy).unwrap();
        std::fs::write(legacy.join("src_positions.col"), [3u8; 256]).unwrap();
        age(&legacy.join("src_positions.col"), old);
        age(&legacy, old);
        // Kept: an old directory with one entry written recently (an import still writing),
        // a recent one with data (an import from before the lock files), an old one holding a
        // link, an old one of another name.
        let writing = p.join("arbor-import-writing");
        std::fs::create_dir(&writing).unwrap();
        std::fs::write(writing.join("run-0"), b"x").unwrap();
        age(&writing, old);
        let recent = p.join("arbor-import-recent");
        std::fs::create_dir(&recent).unwrap();
        std::fs::write(recent.join("src_positions.col"), [3u8; 256]).unwrap();
        let linked = p.join("arbor-import-linked");
        std::fs::create_dir(&linked).unwrap();
        std::os::unix::fs::symlink(&legacy, linked.join("elsewhere")).unwrap();
        age(&linked, old);
        let other = p.join("other-tool-dir");
        std::fs::create_dir(&other).unwrap();
        age(&other, old);

        let mut removed = sweep_abandoned(p);
        removed.sort();
        assert_eq!(removed, vec![half_made.clone(), legacy.clone()]);
        assert!(!half_made.exists() && !legacy.exists());
        for kept in [&writing, &recent, &linked, &other] {
            assert!(kept.exists(), "{} kept", kept.display());
        }
    }

    #[test]
    fn a_directory_half_created_by_a_killed_import_goes_at_once() {
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path();
        // Killed right after making the directory, and right after making the lock file
        // (unnamed, unlocked): both recent.
        let empty = p.join("arbor-import-empty");
        std::fs::create_dir(&empty).unwrap();
        let unnamed = p.join("arbor-import-unnamed");
        std::fs::create_dir(&unnamed).unwrap();
        std::fs::write(unnamed.join(OWNER_LOCK_NEW), b"").unwrap();
        // Kept: one with data and no lock file, one whose unnamed lock file is a directory.
        let data = p.join("arbor-import-data");
        std::fs::create_dir(&data).unwrap();
        std::fs::write(data.join("run-0"), b"x").unwrap();
        let odd = p.join("arbor-import-odd");
        std::fs::create_dir_all(odd.join(OWNER_LOCK_NEW)).unwrap();

        let live = ScratchDir::new(Some(p)).unwrap();
        assert!(
            !empty.exists() && !unnamed.exists(),
            "half-created dirs removed"
        );
        for kept in [&data, &odd] {
            assert!(kept.exists(), "{} kept", kept.display());
        }
        assert!(p.join(CREATE_LOCK).is_file());

        // While the creation lock is held elsewhere (an import making its directory), a sweep
        // waits for it rather than judge a half-made directory.
        let creating = lock_creation(p).unwrap();
        let half = p.join("arbor-import-half");
        std::fs::create_dir(&half).unwrap();
        let sweeper = {
            let p = p.to_path_buf();
            std::thread::spawn(move || sweep_abandoned(&p))
        };
        std::thread::sleep(Duration::from_millis(50));
        assert!(half.exists(), "not swept while the creation lock is held");
        std::fs::write(half.join(OWNER_LOCK), b"").unwrap();
        let locked = File::open(half.join(OWNER_LOCK)).unwrap();
        locked.lock().unwrap();
        drop(creating);
        assert!(sweeper.join().unwrap().is_empty(), "its owner holds it now");
        assert!(half.exists());
        drop(live);
    }

    #[test]
    fn a_creation_lock_file_that_cannot_be_written_still_locks() {
        use std::os::unix::fs::PermissionsExt as _;
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path();
        // As another user's lock file in a shared /tmp looks to this one (root ignores modes,
        // so the read-only open is what is checked here, the mode only where it applies).
        std::fs::write(p.join(CREATE_LOCK), b"").unwrap();
        std::fs::set_permissions(p.join(CREATE_LOCK), std::fs::Permissions::from_mode(0o444))
            .unwrap();
        let held = lock_creation(p).unwrap();
        let half = p.join("arbor-import-half");
        std::fs::create_dir(&half).unwrap();
        drop(held);
        let dir = ScratchDir::new(Some(p)).unwrap();
        assert!(!half.exists(), "swept under the lock");
        drop(dir);
    }

    #[test]
    fn a_removal_cut_short_is_finished_by_the_next_sweep() {
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path();
        // A sweep or an owner killed while removing: renamed, lock file gone, data left.
        let cut_short = p.join(format!("{REMOVING_PREFIX}abc123"));
        std::fs::create_dir(&cut_short).unwrap();
        std::fs::write(cut_short.join("src_positions.col"), [9u8; 512]).unwrap();
        // Empty, without a lock file: a remover about to remove it (left alone), or one killed
        // at the very end (removed once it is older than the grace).
        let finishing = p.join(format!("{REMOVING_PREFIX}fin123"));
        std::fs::create_dir(&finishing).unwrap();
        let finished_long_ago = p.join(format!("{REMOVING_PREFIX}old123"));
        std::fs::create_dir(&finished_long_ago).unwrap();
        age(&finished_long_ago, REMOVAL_GRACE + Duration::from_secs(1));
        let mut removed = sweep_abandoned(p);
        removed.sort();
        assert_eq!(removed, vec![cut_short.clone(), finished_long_ago]);
        assert!(!cut_short.exists());
        assert!(finishing.exists(), "left to its remover");
        std::fs::remove_dir(&finishing).unwrap();
        // An owner's own removal leaves nothing under either name.
        let dir = ScratchDir::new(Some(p)).unwrap();
        let name = dir.path().file_name().unwrap().to_str().unwrap().to_owned();
        std::fs::write(dir.path().join("data.col"), b"x").unwrap();
        drop(dir);
        let left = entries(p);
        assert!(left.is_empty(), "{name} removed, nothing left: {left:?}");
    }

    /// Names of what is in `parent` but the creation lock file.
    fn entries(parent: &Path) -> Vec<String> {
        let mut names: Vec<_> = std::fs::read_dir(parent)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .filter(|n| n != CREATE_LOCK)
            .collect();
        names.sort();
        names
    }

    #[test]
    fn removing_runs_with_the_creation_lock_released_and_is_left_to_its_remover() {
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path();
        let dead = abandoned_dir(p, "arbor-import-big");
        std::fs::create_dir(dead.join("runs")).unwrap();
        for i in 0..50 {
            std::fs::write(dead.join("runs").join(format!("run-{i}")), [1u8; 1024]).unwrap();
        }
        let doomed = {
            let _creating = lock_creation(p).unwrap();
            claim_abandoned(p, true)
        };
        let renamed = p.join(format!("{REMOVING_PREFIX}big"));
        assert_eq!(doomed.len(), 1);
        assert_eq!(doomed[0].path, renamed);
        assert!(!dead.exists() && renamed.join("runs/run-49").exists());

        // While it is being removed: the creation lock is free, another import makes its
        // directory, and neither it nor a sweep touches the one being removed.
        let lock = File::open(p.join(CREATE_LOCK)).unwrap();
        assert!(lock.try_lock().is_ok(), "the creation lock is free");
        drop(lock);
        let other = ScratchDir::new(Some(p)).unwrap();
        assert!(sweep_abandoned(p).is_empty(), "left to its remover");
        assert!(renamed.join("runs/run-49").exists());

        assert_eq!(remove_all(doomed), vec![dead]);
        assert!(!renamed.exists());
        drop(other);
        assert!(entries(p).is_empty(), "{:?}", entries(p));
    }

    #[test]
    fn a_removal_killed_halfway_is_finished_by_the_next_sweep() {
        let parent = tempfile::tempdir().unwrap();
        let p = parent.path();
        let dead = abandoned_dir(p, "arbor-import-half");
        std::fs::write(dead.join("run-0"), [2u8; 64]).unwrap();
        let mut doomed = claim_abandoned(p, true);
        let d = doomed.pop().unwrap();
        // Killed after one file went: the lock released, the lock file and the rest left.
        std::fs::remove_file(d.path.join("src_positions.col")).unwrap();
        let renamed = d.path.clone();
        drop(d);
        assert!(renamed.join(OWNER_LOCK).exists() && renamed.join("run-0").exists());
        assert_eq!(sweep_abandoned(p), vec![renamed]);
        assert!(entries(p).is_empty(), "{:?}", entries(p));
    }

    #[test]
    fn a_missing_parent_is_an_error_not_a_panic() {
        let parent = tempfile::tempdir().unwrap();
        let missing = parent.path().join("does-not-exist");
        assert!(sweep_abandoned(&missing).is_empty());
        assert!(ScratchDir::new(Some(&missing)).is_err());
    }
}
