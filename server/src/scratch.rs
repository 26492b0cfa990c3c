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
//! them. So creating and sweeping both hold a lock on one file in the parent ([`CREATE_LOCK`]):
//! a sweep that holds it sees no directory half-created by a live import, and a directory
//! without its lock file that is empty or holds only the lock file still unnamed
//! (`owner.lock.new`) is what a process killed between those steps left; it goes at once.
//! Removing one is cut short by a kill as easily (its lock file may go first), so an owner or
//! a sweep renames a directory to [`REMOVING_PREFIX`] before removing it, and a sweep removes
//! what is left so named. (Before, both stayed for a day, and `server/tests/cli.rs`' kills now
//! and then landed there.)
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
/// The file in a scratch directories' parent that creating a scratch directory and sweeping
/// lock, so that a sweep never meets a directory a live import is still creating. Kept (a few
/// bytes of nothing); not named like a scratch directory.
pub const CREATE_LOCK: &str = ".arbor-import.lock";
/// The lock file's name until it is locked (a directory that has only this is half-created:
/// see [`half_created`]).
const OWNER_LOCK_NEW: &str = "owner.lock.new";
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
    /// Where [`CREATE_LOCK`] lies.
    parent: PathBuf,
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        // Removed under the creation lock: a sweep never meets it half removed, empty with its
        // lock file already unlinked, which it would take for half-created.
        let _creating = lock_creation(&self.parent).ok();
        if let Some(dir) = self.dir.take() {
            let path = dir.keep();
            if let Err(e) = remove_scratch(&path) {
                tracing::warn!(
                    "could not remove the scratch directory {}: {e}",
                    path.display()
                );
            }
        }
    }
}

impl ScratchDir {
    /// A new scratch directory in `parent` (default: the system's temporary directory), after
    /// removing the abandoned ones there.
    pub fn new(parent: Option<&Path>) -> io::Result<ScratchDir> {
        let parent = parent.map_or_else(std::env::temp_dir, Path::to_path_buf);
        // Held until the directory and its lock file are made (released as it drops). Without
        // it (a lock file nobody may open) the import goes on, judging no half-made directory.
        let creating = lock_creation(&parent).ok();
        let removed = sweep(&parent, creating.is_some());
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
        let dir = tempfile::Builder::new()
            .prefix(SCRATCH_PREFIX)
            .tempdir_in(&parent)?;
        // Locked under another name, then renamed: a sweep that sees `owner.lock` always finds
        // it locked, never in the instant between its creation and the lock.
        let unlocked = dir.path().join(OWNER_LOCK_NEW);
        let owner = File::create(&unlocked)?;
        owner.lock()?;
        std::fs::rename(&unlocked, dir.path().join(OWNER_LOCK))?;
        drop(creating);
        Ok(ScratchDir {
            dir: Some(dir),
            _owner: Some(owner),
            parent,
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

/// Removes every scratch directory in `parent` whose owner is gone (its `owner.lock` exists and
/// can be locked, or it has none and nothing in it changed for [`STALE_UNLOCKED`]); returns the
/// ones removed. Best effort: what cannot be read, locked or removed
/// (another user's, one in use) stays, and a failure is logged, never returned.
pub fn sweep_abandoned(parent: &Path) -> Vec<PathBuf> {
    match lock_creation(parent) {
        Ok(_creating) => sweep(parent, true),
        // A parent where the lock cannot be made (read-only, missing): no half-created
        // directory is judged, the rest as always.
        Err(_) => sweep(parent, false),
    }
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

/// [`sweep_abandoned`]; `creators_locked_out` when the caller holds [`CREATE_LOCK`].
fn sweep(parent: &Path, creators_locked_out: bool) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(parent) else {
        return Vec::new();
    };
    let mut removed = Vec::new();
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
        if !abandoned(&path, SystemTime::now(), creators_locked_out) {
            continue;
        }
        match remove_scratch(&path) {
            Ok(()) => removed.push(path),
            // Removed by someone else meanwhile (its owner, as it finished, or another sweep).
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => tracing::warn!(
                "could not remove the abandoned scratch directory {}: {e}",
                path.display()
            ),
        }
    }
    removed
}

/// Removes scratch directory `path`, renamed first to [`REMOVING_PREFIX`]: a process killed
/// while removing it (its lock file may already be gone) leaves a directory named as such,
/// which the next sweep removes. One already so named is removed as it is.
fn remove_scratch(path: &Path) -> io::Result<()> {
    if removal_cut_short(path) {
        return std::fs::remove_dir_all(path);
    }
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| io::Error::other("not a scratch directory's name"))?;
    let doomed = path.with_file_name(format!(
        "{REMOVING_PREFIX}{}",
        name.strip_prefix(SCRATCH_PREFIX).unwrap_or(name)
    ));
    std::fs::rename(path, &doomed)?;
    std::fs::remove_dir_all(&doomed)
}

/// Whether `dir` is named as a removal in progress, or one its process did not finish.
fn removal_cut_short(dir: &Path) -> bool {
    dir.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.starts_with(REMOVING_PREFIX))
}

/// Whether `dir` is a scratch directory nobody holds at `now`: its lock file exists and the
/// lock is free, or it has none and is half-created while `creators_locked_out` (see
/// [`half_created`]) or stale.
fn abandoned(dir: &Path, now: SystemTime, creators_locked_out: bool) -> bool {
    // Removing it again, alongside a removal still running, does no harm.
    if removal_cut_short(dir) {
        return true;
    }
    let lock = dir.join(OWNER_LOCK);
    // Not followed through a link: a link named like the lock file makes the directory
    // someone else's.
    match std::fs::symlink_metadata(&lock) {
        Ok(m) if m.is_file() => {}
        Ok(_) => return false,
        Err(e) if e.kind() == io::ErrorKind::NotFound => {
            return (creators_locked_out && half_created(dir)) || unchanged_since(dir, now);
        }
        Err(_) => return false,
    }
    let Ok(file) = File::open(&lock) else {
        return false;
    };
    match file.try_lock() {
        // Released as `file` closes, before the directory goes.
        Ok(()) => true,
        Err(TryLockError::WouldBlock) => false,
        Err(TryLockError::Error(e)) => {
            tracing::debug!("{}: {e}", lock.display());
            false
        }
    }
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
        assert_eq!(sweep_abandoned(p), vec![cut_short.clone()]);
        assert!(!cut_short.exists());
        // An owner's own removal leaves nothing under either name.
        let dir = ScratchDir::new(Some(p)).unwrap();
        let name = dir.path().file_name().unwrap().to_str().unwrap().to_owned();
        std::fs::write(dir.path().join("data.col"), b"x").unwrap();
        drop(dir);
        let left: Vec<_> = std::fs::read_dir(p)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .filter(|n| n != CREATE_LOCK)
            .collect();
        assert!(left.is_empty(), "{name} removed, nothing left: {left:?}");
    }

    #[test]
    fn a_missing_parent_is_an_error_not_a_panic() {
        let parent = tempfile::tempdir().unwrap();
        let missing = parent.path().join("does-not-exist");
        assert!(sweep_abandoned(&missing).is_empty());
        assert!(ScratchDir::new(Some(&missing)).is_err());
    }
}
