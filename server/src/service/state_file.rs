//! The small JSON files the service keeps in its data directory from one run to the next (the
//! path memory, the pool's hot pages): written whole or not at all, read back within a bound.

use std::io::Write as _;
use std::path::Path;

use serde::Serialize;
use serde::de::DeserializeOwned;

/// What reading a state file found.
#[derive(Debug)]
pub enum ReadState<T> {
    /// No file: a first run.
    Missing,
    /// Larger than the bound, bytes: not read.
    TooLarge(u64),
    /// Not JSON of the type; serde's reason.
    Malformed(String),
    Read(T),
}

/// Writes `value` as JSON to `path`: to a temporary file beside it, synced, then renamed, so a
/// crash leaves the old file or the new one, never half of one.
pub fn write_json(path: &Path, value: &impl Serialize) -> std::io::Result<()> {
    let text = serde_json::to_vec(value).map_err(std::io::Error::other)?;
    let tmp = path.with_extension("json.tmp");
    let mut f = std::fs::File::create(&tmp)?;
    f.write_all(&text)?;
    f.sync_all()?;
    drop(f);
    std::fs::rename(&tmp, path)
}

/// Reads the JSON file `path` of at most `limit` bytes.
pub fn read_json<T: DeserializeOwned>(path: &Path, limit: u64) -> std::io::Result<ReadState<T>> {
    let bytes = match std::fs::metadata(path) {
        Ok(m) => m.len(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(ReadState::Missing),
        Err(e) => return Err(e),
    };
    if bytes > limit {
        return Ok(ReadState::TooLarge(bytes));
    }
    let text = std::fs::read(path)?;
    Ok(match serde_json::from_slice(&text) {
        Ok(v) => ReadState::Read(v),
        Err(e) => ReadState::Malformed(e.to_string()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_state_file_comes_back_whole_or_says_what_it_is() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state.json");
        assert!(matches!(
            read_json::<Vec<u32>>(&path, 100).unwrap(),
            ReadState::Missing
        ));
        write_json(&path, &vec![1u32, 2, 3]).unwrap();
        assert!(!path.with_extension("json.tmp").exists());
        assert!(matches!(
            read_json::<Vec<u32>>(&path, 100).unwrap(),
            ReadState::Read(v) if v == [1, 2, 3]
        ));
        assert!(matches!(
            read_json::<Vec<u32>>(&path, 3).unwrap(),
            ReadState::TooLarge(7)
        ));
        assert!(matches!(
            read_json::<String>(&path, 100).unwrap(),
            ReadState::Malformed(e) if e.contains("expected")
        ));
        // Written again over the old one.
        write_json(&path, &vec![4u32]).unwrap();
        assert!(matches!(
            read_json::<Vec<u32>>(&path, 100).unwrap(),
            ReadState::Read(v) if v == [4]
        ));
    }
}
