//! Tiled point sets as one scene: several LAS/LAZ files (and point PLY files), a directory of
//! them, or a glob, read into one [`Source`].
//!
//! Two passes. The **survey** reads every header first (no point is decoded): it checks each
//! file's header against its length, adds the declared point counts (64-bit) against the
//! primitive limit, and compares coordinate systems — tiles declaring different ones are refused,
//! naming both files, unless [`TileOptions::allow_mixed_crs`]. Only then do the points
//! **stream**, file after file in the given order, into one set of columns
//! ([`PointSetWriter`]); each LAS file is scaled and offset by its own header. Any error names
//! the tile and the place, and nothing has touched the pool yet (the pipeline parses before it
//! begins the pool's transaction), so a bad tile fails the whole import cleanly.

use std::path::{Path, PathBuf};

use super::las::{self, Crs};
use super::points_out::PointSetWriter;
use super::{Format, ImportError, detect_format, ply};
use crate::octree::MAX_PRIMITIVES;
use crate::source::Source;

/// How to read a tile set.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TileOptions {
    /// Import tiles whose coordinate systems differ (the caller vouches that they match).
    pub allow_mixed_crs: bool,
}

/// What the headers of a set say, before any point is read.
#[derive(Clone, Debug, PartialEq)]
pub struct SetSurvey {
    /// Files, in reading order.
    pub files: usize,
    /// Points the LAS headers declare (PLY tiles are counted when read).
    pub declared_points: u64,
    /// Bounds of the LAS headers, when any LAS file is in the set.
    pub bounds: Option<([f64; 3], [f64; 3])>,
}

fn is_pattern(s: &str) -> bool {
    s.contains(['*', '?'])
}

/// Whether `name` matches `pattern` (`*` any run of characters, `?` one character).
fn matches(pattern: &[char], name: &[char]) -> bool {
    match pattern.split_first() {
        None => name.is_empty(),
        Some(('*', rest)) => (0..=name.len()).any(|i| matches(rest, &name[i..])),
        Some(('?', rest)) => !name.is_empty() && matches(rest, &name[1..]),
        Some((c, rest)) => name.first() == Some(c) && matches(rest, &name[1..]),
    }
}

/// Whether the extension is one a tile set takes.
fn is_point_file(path: &Path) -> bool {
    matches!(detect_format(path), Ok(Format::Las | Format::Ply))
}

fn sorted_files(
    dir: &Path,
    keep: impl Fn(&Path) -> bool,
    what: &str,
) -> Result<Vec<PathBuf>, ImportError> {
    let io = |e| ImportError::io(what, "listing the directory", e);
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        if path.is_file() && keep(&path) {
            out.push(path);
        }
    }
    out.sort();
    Ok(out)
}

/// Expands the inputs of an import into files, in reading order: a file stays as it is; a
/// directory gives its LAS, LAZ and PLY files (not recursive), sorted by name; a path whose last
/// component holds `*` or `?` gives the matching files of its directory, sorted. A directory or
/// pattern that names no file is an error.
pub fn expand_inputs(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, ImportError> {
    let mut files = Vec::new();
    for input in inputs {
        let shown = input.display().to_string();
        let name = input
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let found = if is_pattern(&name) {
            let dir = match input.parent() {
                Some(p) if !p.as_os_str().is_empty() => p,
                _ => Path::new("."),
            };
            let pattern: Vec<char> = name.chars().collect();
            let found = sorted_files(
                dir,
                |p| {
                    let n: Vec<char> = p
                        .file_name()
                        .map(|n| n.to_string_lossy().chars().collect())
                        .unwrap_or_default();
                    matches(&pattern, &n)
                },
                &shown,
            )?;
            if found.is_empty() {
                return Err(ImportError::NoInputs {
                    pattern: shown,
                    how: "matches this pattern",
                });
            }
            found
        } else if input.is_dir() {
            let found = sorted_files(input, is_point_file, &shown)?;
            if found.is_empty() {
                return Err(ImportError::NoInputs {
                    pattern: shown,
                    how: "in this directory",
                });
            }
            found
        } else {
            vec![input.clone()]
        };
        files.extend(found);
    }
    if files.is_empty() {
        return Err(ImportError::NoInputs {
            pattern: "(no input)".into(),
            how: "was given",
        });
    }
    Ok(files)
}

/// The header pass: checks every file's header, adds the declared counts and compares the
/// coordinate systems. Decodes no point.
pub fn survey(files: &[PathBuf], opts: &TileOptions) -> Result<SetSurvey, ImportError> {
    let mut declared = 0u64;
    let mut bounds: Option<([f64; 3], [f64; 3])> = None;
    // The first file that declared a coordinate system (or none), to compare the rest with.
    let mut reference: Option<(String, Option<Crs>)> = None;
    for path in files {
        let file = path.display().to_string();
        match detect_format(path)? {
            Format::Las => {
                let s = las::survey(path, &file)?;
                declared = declared.saturating_add(s.points);
                if declared > MAX_PRIMITIVES {
                    return Err(ImportError::TooManyPrimitives {
                        file,
                        what: "points (declared by the headers so far)",
                        count: declared,
                        limit: MAX_PRIMITIVES,
                    });
                }
                let (lo, hi) = bounds.get_or_insert((s.min, s.max));
                for a in 0..3 {
                    lo[a] = lo[a].min(s.min[a]);
                    hi[a] = hi[a].max(s.max[a]);
                }
                match &reference {
                    None => reference = Some((file, s.crs)),
                    Some((first, crs)) if *crs != s.crs && !opts.allow_mixed_crs => {
                        let show = |c: &Option<Crs>| {
                            c.as_ref().map_or("none (no CRS records)".to_owned(), |c| {
                                c.description.clone()
                            })
                        };
                        return Err(ImportError::MixedCoordinateSystems {
                            first: first.clone(),
                            first_crs: show(crs),
                            second: file,
                            second_crs: show(&s.crs),
                        });
                    }
                    Some(_) => {}
                }
            }
            Format::Ply => ply::check_header(path, &file)?,
            other => {
                return Err(ImportError::NotPointTile {
                    file,
                    kind: format!("a {other} file"),
                });
            }
        }
    }
    Ok(SetSurvey {
        files: files.len(),
        declared_points: declared,
        bounds,
    })
}

/// Reads `files` (already expanded, see [`expand_inputs`]) as one point set into columns under
/// `scratch`: the survey first, then every file's points in order.
pub fn import_tiles(
    files: &[PathBuf],
    opts: &TileOptions,
    scratch: &Path,
) -> Result<Source, ImportError> {
    let surveyed = survey(files, opts)?;
    tracing::info!(
        files = surveyed.files,
        declared_points = surveyed.declared_points,
        bounds = ?surveyed.bounds,
        "tile set surveyed"
    );
    let label = match files {
        [one] => one.display().to_string(),
        [first, ..] => format!("{} (first of {} tiles)", first.display(), files.len()),
        [] => {
            return Err(ImportError::NoInputs {
                pattern: "(no input)".into(),
                how: "was given",
            });
        }
    };
    let mut out = PointSetWriter::new(&label, scratch)?;
    for (i, path) in files.iter().enumerate() {
        let file = path.display().to_string();
        match detect_format(path)? {
            Format::Las => las::read_into(path, &file, &mut out)?,
            _ => {
                let sub = scratch.join(format!("tile-{i}"));
                std::fs::create_dir_all(&sub)
                    .map_err(|e| ImportError::io(&file, "creating a tile scratch directory", e))?;
                match ply::import(path, &file, &sub)? {
                    Source::Points(p) => out.append_source(&file, &p)?,
                    other => {
                        return Err(ImportError::NotPointTile {
                            file,
                            kind: other.describe(),
                        });
                    }
                }
                let _ = std::fs::remove_dir_all(&sub);
            }
        }
        tracing::debug!(file, points_so_far = out.len(), "tile read");
    }
    out.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glob_matching() {
        let m = |p: &str, n: &str| {
            matches(
                &p.chars().collect::<Vec<_>>(),
                &n.chars().collect::<Vec<_>>(),
            )
        };
        assert!(m("*.laz", "tile_1.laz"));
        assert!(m("tile_?.la?", "tile_1.las"));
        assert!(!m("*.laz", "tile_1.las"));
        assert!(!m("tile_?.laz", "tile_12.laz"));
        assert!(m("*", ""));
        assert!(!m("?", ""));
    }

    #[test]
    fn expansion_of_directories_and_patterns() {
        let dir = tempfile::tempdir().unwrap();
        for n in ["b.laz", "a.las", "c.ply", "notes.txt"] {
            std::fs::write(dir.path().join(n), b"x").unwrap();
        }
        let names = |v: Vec<PathBuf>| -> Vec<String> {
            v.iter()
                .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
                .collect()
        };
        let all = expand_inputs(&[dir.path().to_owned()]).unwrap();
        assert_eq!(names(all), ["a.las", "b.laz", "c.ply"]);
        let some = expand_inputs(&[dir.path().join("*.la?")]).unwrap();
        assert_eq!(names(some), ["a.las", "b.laz"]);
        let e = expand_inputs(&[dir.path().join("*.nrrd")]).unwrap_err();
        assert!(
            e.to_string().contains("no LAS, LAZ or PLY file matches"),
            "{e}"
        );
        let empty = tempfile::tempdir().unwrap();
        let e = expand_inputs(&[empty.path().to_owned()]).unwrap_err();
        assert!(e.to_string().contains("in this directory"), "{e}");
    }
}
