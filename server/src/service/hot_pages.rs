//! The pool's hot pages: which parts of the pool's files were in the page cache while the server
//! last ran, saved in its data directory ([`HOT_PAGES_FILE`]) and read back first by the next
//! start's prewarm ([`super::prewarm`]).
//!
//! Why: after a restart the page cache holds whatever the machine kept, often nothing of the
//! pool, and the first clients wait for the disk page by page (a fresh server's first view of
//! the 10⁸-point city reads some 2,400 scattered pieces of its file, ~140 MB; on a disk held to
//! 500 reads a second that view took 5–6 s instead of 1 s). The whole pool is read at start only
//! when it fits in memory; a pool larger than memory was not read at all. What the last run's
//! clients had in the page cache is what the next run's will most likely ask for again, and it
//! fits, since it did (the same idea as a database's buffer pool dump).
//!
//! What is saved: for each file of the pool, the byte ranges of its pages in the page cache
//! (`mincore` on a read-only mapping: nothing is read, nothing faulted in), runs of pages closer
//! than [`HOT_GAP_BYTES`] joined so that reading them back takes one read per run rather than
//! one per page. Saved every [`HOT_PAGES_SAVE_INTERVAL`] and when the service stops (unless the
//! pages are those of the last save and its list is still there); a list of
//! another pool, of another format, or naming a file the pool no longer has is ignored (the
//! log says why), and the pool is never written.

use std::path::{Component, Path, PathBuf};
use std::time::{Duration, SystemTime};

use serde::{Deserialize, Serialize};

use super::prewarm::WarmRead;
use super::state_file::{ReadState, read_json, write_json};

/// The hot-page list's file in the data directory.
pub const HOT_PAGES_FILE: &str = "pool-hot-pages.json";

/// The list's format.
const HOT_PAGES_VERSION: u32 = 1;

/// The largest list read back: some 2.5 M ranges, far more than any page cache holds runs.
pub const MAX_HOT_PAGES_FILE_BYTES: u64 = 64 << 20;

/// Resident runs at most this far apart are saved as one range: reading the gap costs bytes,
/// a separate read costs one of the disk's operations (a few hundred a second on cloud block
/// storage past its burst, where 256 KiB take about a millisecond of its bandwidth).
pub const HOT_GAP_BYTES: u64 = 256 << 10;

/// How often a running server saves the list (and once more when it stops): a server killed
/// without its shutdown leaves a list at most this old.
pub const HOT_PAGES_SAVE_INTERVAL: Duration = Duration::from_secs(60);

/// How much of a file one `mincore` looks at: its vector holds a byte per page (256 KiB for
/// 1 GiB), so a pool of terabytes is looked at a window at a time.
const WINDOW_BYTES: u64 = 1 << 30;

/// Errors reading or writing the hot-page list.
#[derive(Debug, thiserror::Error)]
pub enum HotPagesError {
    /// The file could not be read or written, or the pool's pages could not be looked at.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is larger than [`MAX_HOT_PAGES_FILE_BYTES`].
    #[error("{}: {bytes} bytes, more than the {MAX_HOT_PAGES_FILE_BYTES} a hot-page list takes", path.display())]
    TooLarge { path: PathBuf, bytes: u64 },
    /// The file is not a hot-page list of this format, or not of this pool.
    #[error("{}: not a hot-page list of this pool: {reason}", path.display())]
    Format { path: PathBuf, reason: String },
}

/// The hot ranges of one file of the pool.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HotFile {
    /// The file's path below the pool directory, `/`-separated (`db`, `blobs/123`).
    pub name: String,
    /// `[offset, length]` byte ranges, ascending and apart.
    pub ranges: Vec<[u64; 2]>,
}

impl HotFile {
    /// Bytes of its ranges.
    pub fn bytes(&self) -> u64 {
        self.ranges.iter().map(|r| r[1]).sum()
    }
}

/// [`HOT_PAGES_FILE`]'s contents.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SavedHotPages {
    version: u32,
    /// The pool directory it was saved for (canonical).
    pool: PathBuf,
    /// When it was written, milliseconds since the Unix epoch.
    saved_at_unix_ms: u64,
    files: Vec<HotFile>,
}

/// Appends to `out` the byte ranges of the pages `resident` marks (a `mincore` vector: bit 0
/// of each byte), page `i` lying at `base + i × page`, joining a range to the one before when
/// at most `gap` bytes lie between them.
pub fn join_runs(resident: &[u8], base: u64, page: u64, gap: u64, out: &mut Vec<[u64; 2]>) {
    let mut i = 0;
    while i < resident.len() {
        if resident[i] & 1 == 0 {
            i += 1;
            continue;
        }
        let first = i;
        while i < resident.len() && resident[i] & 1 == 1 {
            i += 1;
        }
        let (start, len) = (base + first as u64 * page, (i - first) as u64 * page);
        match out.last_mut() {
            Some(last) if start.saturating_sub(last[0] + last[1]) <= gap => {
                last[1] = start + len - last[0];
            }
            _ => out.push([start, len]),
        }
    }
}

/// The ranges of `path`'s pages in the page cache, runs at most `gap` apart joined, the last
/// ending at the file's end.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
pub fn resident_ranges(path: &Path, gap: u64) -> std::io::Result<Vec<[u64; 2]>> {
    let file = std::fs::File::open(path)?;
    let len = file.metadata()?.len();
    // SAFETY: sysconf has no preconditions.
    let page = u64::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) })
        .ok()
        .filter(|&p| p > 0)
        .unwrap_or(4096);
    let mut out = Vec::new();
    let mut offset = 0;
    while offset < len {
        let span = (len - offset).min(WINDOW_BYTES);
        // SAFETY: a read-only shared mapping that is only looked at by `mincore`, never read
        // through, so a file truncated under it (sled does not truncate its file while open)
        // cannot fault this process; it is dropped before the next window.
        let map = unsafe {
            memmap2::MmapOptions::new()
                .offset(offset)
                .len(span as usize)
                .map(&file)?
        };
        let mut vector = vec![0u8; span.div_ceil(page) as usize];
        // SAFETY: the range is the mapping, page-aligned (mmap returns it so) and `span` long;
        // the vector holds one byte per page of it.
        let rc = unsafe {
            libc::mincore(
                map.as_ptr() as *mut libc::c_void,
                span as usize,
                vector.as_mut_ptr(),
            )
        };
        if rc != 0 {
            return Err(std::io::Error::last_os_error());
        }
        join_runs(&vector, offset, page, gap, &mut out);
        offset += span;
    }
    if let Some(last) = out.last_mut() {
        last[1] = last[1].min(len - last[0]);
    }
    Ok(out)
}

/// Which pages are cached is Linux's to say here; elsewhere nothing is saved.
#[cfg(not(target_os = "linux"))]
pub fn resident_ranges(_path: &Path, _gap: u64) -> std::io::Result<Vec<[u64; 2]>> {
    Ok(Vec::new())
}

/// `path`'s name below `dir`, `/`-separated; `None` outside it or not UTF-8.
fn name_below(dir: &Path, path: &Path) -> Option<String> {
    let rest = path.strip_prefix(dir).ok()?;
    let parts: Option<Vec<&str>> = rest.components().map(|c| c.as_os_str().to_str()).collect();
    Some(parts?.join("/"))
}

/// The hot ranges of every file of the pool in `dir` (those with any), in the order of
/// [`super::prewarm::pool_files`], leaving out the list itself should it lie in the pool's
/// directory (the data directory defaults to it).
pub fn snapshot(dir: &Path) -> Result<Vec<HotFile>, HotPagesError> {
    let io = |path: &Path| {
        let path = path.to_owned();
        move |source| HotPagesError::Io { path, source }
    };
    let mut hot = Vec::new();
    for (path, _) in super::prewarm::pool_files(dir).map_err(io(dir))? {
        let Some(name) = name_below(dir, &path) else {
            continue;
        };
        if name.starts_with(HOT_PAGES_FILE) {
            continue;
        }
        let ranges = match resident_ranges(&path, HOT_GAP_BYTES) {
            Ok(r) => r,
            // Removed since it was listed (a sled blob, a snapshot replaced).
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(io(&path)(e)),
        };
        if !ranges.is_empty() {
            hot.push(HotFile { name, ranges });
        }
    }
    Ok(hot)
}

/// Writes `files` as the hot-page list of the pool in `pool` to `path` (a temporary file, then
/// renamed, so a list is whole or absent); returns the bytes the list names.
pub fn save(path: &Path, pool: &Path, files: &[HotFile]) -> Result<u64, HotPagesError> {
    let io = |source| HotPagesError::Io {
        path: path.to_owned(),
        source,
    };
    let saved = SavedHotPages {
        version: HOT_PAGES_VERSION,
        pool: pool.canonicalize().map_err(io)?,
        saved_at_unix_ms: SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX)),
        files: files.to_vec(),
    };
    write_json(path, &saved).map_err(io)?;
    Ok(files.iter().map(HotFile::bytes).sum())
}

/// Reads the hot-page list at `path` saved for the pool in `pool`; none (a missing file) is an
/// empty list. Refused, naming why: a file over [`MAX_HOT_PAGES_FILE_BYTES`], not JSON of this
/// format, saved for another pool directory, a name that leaves the pool's directory, or ranges
/// empty, out of order or overlapping.
pub fn load(path: &Path, pool: &Path) -> Result<Vec<HotFile>, HotPagesError> {
    let io = |source| HotPagesError::Io {
        path: path.to_owned(),
        source,
    };
    let format = |reason: String| HotPagesError::Format {
        path: path.to_owned(),
        reason,
    };
    let saved: SavedHotPages = match read_json(path, MAX_HOT_PAGES_FILE_BYTES).map_err(io)? {
        ReadState::Missing => return Ok(Vec::new()),
        ReadState::TooLarge(bytes) => {
            return Err(HotPagesError::TooLarge {
                path: path.to_owned(),
                bytes,
            });
        }
        ReadState::Malformed(reason) => return Err(format(reason)),
        ReadState::Read(saved) => saved,
    };
    if saved.version != HOT_PAGES_VERSION {
        return Err(format(format!(
            "version {}, this build reads {HOT_PAGES_VERSION}",
            saved.version
        )));
    }
    let pool = pool.canonicalize().map_err(io)?;
    if saved.pool != pool {
        return Err(format(format!(
            "saved for the pool in {}, this server serves {}",
            saved.pool.display(),
            pool.display()
        )));
    }
    for f in &saved.files {
        let inside = !f.name.is_empty()
            && Path::new(&f.name)
                .components()
                .all(|c| matches!(c, Component::Normal(_)));
        if !inside {
            return Err(format(format!(
                "file name {:?} is not a path below the pool's directory",
                f.name
            )));
        }
        let mut end = 0;
        for (i, &[offset, len]) in f.ranges.iter().enumerate() {
            let Some(next) = offset.checked_add(len).filter(|_| len > 0) else {
                return Err(format(format!(
                    "{}: range {i} [{offset}, {len}] is empty or passes 2⁶⁴",
                    f.name
                )));
            };
            if i > 0 && offset < end {
                return Err(format(format!(
                    "{}: range {i} at {offset} overlaps or precedes the one before (ending at {end})",
                    f.name
                )));
            }
            end = next;
        }
    }
    Ok(saved.files)
}

/// The reads that bring `hot` back into the page cache: each range of a file the pool in `dir`
/// has now (`files`, as [`super::prewarm::pool_files`] lists them), cut at the file's length
/// now; ranges of files it no longer has are left.
pub fn reads(hot: &[HotFile], dir: &Path, files: &[(PathBuf, u64)]) -> Vec<WarmRead> {
    let mut out = Vec::new();
    for h in hot {
        let Some((path, len)) = files
            .iter()
            .find(|(p, _)| name_below(dir, p).as_deref() == Some(h.name.as_str()))
        else {
            continue;
        };
        for &[offset, n] in &h.ranges {
            let n = n.min(len.saturating_sub(offset));
            if n > 0 {
                out.push(WarmRead {
                    path: path.clone(),
                    offset,
                    len: n,
                });
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const PAGE: u64 = 4096;

    #[test]
    fn resident_runs_become_ranges_joined_across_small_gaps() {
        let mut out = Vec::new();
        join_runs(&[0, 1, 1, 0, 0, 0, 1, 0], 0, PAGE, 0, &mut out);
        assert_eq!(out, [[PAGE, 2 * PAGE], [6 * PAGE, PAGE]]);

        // Gaps of up to `gap` bytes are read through.
        let mut out = Vec::new();
        join_runs(&[1, 0, 0, 1, 0, 0, 0, 1], 0, PAGE, 2 * PAGE, &mut out);
        assert_eq!(out, [[0, 4 * PAGE], [7 * PAGE, PAGE]]);

        // Only bit 0 counts (the kernel may set others); a window continues the last range.
        let mut out = vec![[0, PAGE]];
        join_runs(&[0xfe, 0x81, 3], 10 * PAGE, PAGE, 0, &mut out);
        assert_eq!(out, [[0, PAGE], [11 * PAGE, 2 * PAGE]]);
        join_runs(&[1], 13 * PAGE, PAGE, 0, &mut out);
        assert_eq!(out, [[0, PAGE], [11 * PAGE, 3 * PAGE]]);

        let mut out = Vec::new();
        join_runs(&[], 0, PAGE, 0, &mut out);
        join_runs(&[0, 0], 0, PAGE, u64::MAX, &mut out);
        assert!(out.is_empty());
    }

    /// Evicts `path`'s clean pages from the page cache.
    #[cfg(target_os = "linux")]
    fn evict(path: &Path) {
        let f = std::fs::File::open(path).unwrap();
        f.sync_all().unwrap();
        rustix::fs::fadvise(&f, 0, None, rustix::fs::Advice::DontNeed).unwrap();
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn the_ranges_are_the_pages_read_since_eviction() {
        use std::os::unix::fs::FileExt;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("db");
        // 600 pages and a part: the last range ends at the file's end, not the page's.
        std::fs::write(&path, vec![9u8; 600 * PAGE as usize + 100]).unwrap();
        evict(&path);
        assert_eq!(
            resident_ranges(&path, 0).unwrap(),
            Vec::<[u64; 2]>::new(),
            "the file system kept the evicted pages: this test needs one that drops them"
        );
        let f = std::fs::File::open(&path).unwrap();
        // No read-ahead: only the pages read become resident.
        rustix::fs::fadvise(&f, 0, None, rustix::fs::Advice::Random).unwrap();
        let mut buf = vec![0u8; 3 * PAGE as usize];
        f.read_exact_at(&mut buf, 10 * PAGE).unwrap();
        f.read_exact_at(&mut buf[..1], 200 * PAGE + 5).unwrap();
        f.read_exact_at(&mut buf[..1], 600 * PAGE + 50).unwrap();
        assert_eq!(
            resident_ranges(&path, 0).unwrap(),
            [[10 * PAGE, 3 * PAGE], [200 * PAGE, PAGE], [600 * PAGE, 100]]
        );
        // The default gap joins runs 47 pages (188 KiB) apart, not 139 (556 KiB).
        f.read_exact_at(&mut buf[..1], 60 * PAGE).unwrap();
        assert_eq!(
            resident_ranges(&path, HOT_GAP_BYTES).unwrap(),
            [
                [10 * PAGE, 51 * PAGE],
                [200 * PAGE, PAGE],
                [600 * PAGE, 100]
            ]
        );
        let hot = snapshot(dir.path()).unwrap();
        assert_eq!(hot.len(), 1);
        assert_eq!(hot[0].name, "db");
        assert_eq!(hot[0].bytes(), 52 * PAGE + 100);
        std::fs::write(dir.path().join("empty"), b"").unwrap();
        assert_eq!(snapshot(dir.path()).unwrap().len(), 1, "no pages, no entry");
    }

    #[test]
    fn a_saved_list_comes_back_for_its_pool_only() {
        let pool = tempfile::tempdir().unwrap();
        std::fs::create_dir(pool.path().join("blobs")).unwrap();
        std::fs::write(pool.path().join("db"), vec![0u8; 40_000]).unwrap();
        std::fs::write(pool.path().join("blobs/7"), vec![0u8; 100]).unwrap();
        let file = pool.path().join(HOT_PAGES_FILE);
        assert_eq!(load(&file, pool.path()).unwrap(), [], "no list, nothing");

        let hot = vec![
            HotFile {
                name: "db".into(),
                ranges: vec![[0, 8192], [16384, 30000]],
            },
            HotFile {
                name: "blobs/7".into(),
                ranges: vec![[0, 4096]],
            },
            HotFile {
                name: "blobs/gone".into(),
                ranges: vec![[0, 4096]],
            },
        ];
        assert_eq!(save(&file, pool.path(), &hot).unwrap(), 8192 + 30000 + 8192);
        assert!(!file.with_extension("json.tmp").exists());
        let back = load(&file, pool.path()).unwrap();
        assert_eq!(back, hot);

        // Back as reads of the files the pool has now, cut at their lengths.
        let files = super::super::prewarm::pool_files(pool.path()).unwrap();
        let reads = reads(&back, pool.path(), &files);
        let got: Vec<(String, u64, u64)> = reads
            .iter()
            .map(|r| (name_below(pool.path(), &r.path).unwrap(), r.offset, r.len))
            .collect();
        assert_eq!(
            got,
            [
                ("db".to_string(), 0, 8192),
                ("db".to_string(), 16384, 40_000 - 16384),
                ("blobs/7".to_string(), 0, 100),
            ]
        );

        // Another pool's list is refused by name.
        let other = tempfile::tempdir().unwrap();
        let e = load(&file, other.path()).unwrap_err().to_string();
        assert!(e.contains("saved for the pool in"), "{e}");
    }

    #[test]
    fn a_bad_list_is_refused_naming_the_problem() {
        let pool = tempfile::tempdir().unwrap();
        let file = pool.path().join(HOT_PAGES_FILE);
        let canonical = pool.path().canonicalize().unwrap();
        let list = |version: u32, files: &str| {
            format!(
                r#"{{"version":{version},"pool":{},"saved_at_unix_ms":0,"files":{files}}}"#,
                serde_json::to_string(&canonical).unwrap()
            )
        };
        let cases = [
            ("garbage".to_string(), "expected"),
            (list(9, "[]"), "version 9"),
            (
                list(1, r#"[{"name":"../etc/passwd","ranges":[[0,1]]}]"#),
                "not a path below",
            ),
            (
                list(1, r#"[{"name":"/etc/passwd","ranges":[[0,1]]}]"#),
                "not a path below",
            ),
            (list(1, r#"[{"name":"","ranges":[]}]"#), "not a path below"),
            (list(1, r#"[{"name":"db","ranges":[[0,0]]}]"#), "empty"),
            (
                list(1, r#"[{"name":"db","ranges":[[18446744073709551615,2]]}]"#),
                "passes",
            ),
            (
                list(1, r#"[{"name":"db","ranges":[[100,50],[120,10]]}]"#),
                "overlaps",
            ),
            (
                list(1, r#"[{"name":"db","ranges":[[100,50],[0,10]]}]"#),
                "precedes",
            ),
            (
                list(1, r#"[{"name":"db","ranges":[[0,1]],"extra":1}]"#),
                "unknown field",
            ),
        ];
        for (text, says) in cases {
            std::fs::write(&file, &text).unwrap();
            let e = load(&file, pool.path()).unwrap_err();
            assert!(matches!(e, HotPagesError::Format { .. }), "{text}: {e}");
            assert!(e.to_string().contains(says), "{text}: {e}");
        }
        std::fs::write(&file, list(1, r#"[{"name":"db","ranges":[[0,1],[1,1]]}]"#)).unwrap();
        assert_eq!(
            load(&file, pool.path()).unwrap()[0].ranges.len(),
            2,
            "adjacent is fine"
        );

        let huge = std::fs::File::create(&file).unwrap();
        huge.set_len(MAX_HOT_PAGES_FILE_BYTES + 1).unwrap();
        assert!(matches!(
            load(&file, pool.path()),
            Err(HotPagesError::TooLarge { .. })
        ));
    }
}
