//! Wavefront OBJ: `v` vertices (optionally with `w` or an RGB colour), `f` polygon faces.
//!
//! Faces are fan-triangulated. Positive indices may refer to vertices defined later in the file,
//! so they are checked once the whole file is read; negative (relative) indices are resolved
//! against the vertices read so far. Texture coordinates, normals (`vn` are per corner, not per
//! vertex), groups, materials and smoothing groups are ignored.

use std::collections::HashSet;
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use super::{ImportError, names, push, unit_to_u8, writer};
use crate::source::{ColumnWriter, MeshSource, PointSource, Source};

/// Longest accepted line; guards against binary files renamed to `.obj`.
const MAX_LINE: u64 = 1 << 20;

/// Colour given to vertices without one when other vertices of the file have a colour.
const DEFAULT_COLOR: [u8; 3] = [255, 255, 255];

fn syntax(file: &str, line: u64, detail: impl Into<String>) -> ImportError {
    ImportError::Syntax {
        file: file.to_owned(),
        line,
        detail: detail.into(),
    }
}

fn tokens(line: &[u8]) -> impl Iterator<Item = &[u8]> {
    line.split(|b| b.is_ascii_whitespace())
        .filter(|t| !t.is_empty())
}

fn show(tok: &[u8]) -> String {
    String::from_utf8_lossy(tok).into_owned()
}

/// The largest positive face index seen that was not yet defined when read.
struct ForwardRef {
    index: i64,
    line: u64,
    face: u64,
}

pub(super) fn import(path: &Path, file: &str, scratch: &Path) -> Result<Source, ImportError> {
    let f = File::open(path).map_err(|e| ImportError::io(file, "opening the file", e))?;
    let mut reader = BufReader::with_capacity(1 << 16, f);
    let mut obj = ObjReader::new(file, scratch)?;
    let mut buf = Vec::new();
    loop {
        buf.clear();
        let n = reader
            .by_ref()
            .take(MAX_LINE + 1)
            .read_until(b'\n', &mut buf)
            .map_err(|e| ImportError::io(file, format!("reading line {}", obj.line + 1), e))?;
        if n == 0 {
            break;
        }
        obj.line += 1;
        if n as u64 > MAX_LINE {
            return Err(syntax(
                file,
                obj.line,
                format!("line longer than {MAX_LINE} bytes (is this really an OBJ file?)"),
            ));
        }
        let content = match buf.iter().position(|&b| b == b'#') {
            Some(p) => &buf[..p],
            None => &buf[..],
        };
        obj.statement(content)?;
    }
    obj.finish()
}

/// The state of one OBJ file being read: the columns written so far and what the checks at the
/// end need.
struct ObjReader<'a> {
    file: &'a str,
    scratch: &'a Path,
    positions: ColumnWriter<[f64; 3]>,
    triangles: ColumnWriter<[u32; 3]>,
    /// Created at the first coloured vertex.
    colors: Option<ColumnWriter<[u8; 3]>>,
    /// Line number of the statement being read (1-based).
    line: u64,
    vertex_count: u64,
    face_count: u64,
    forward: Option<ForwardRef>,
    /// Scratch: the current face's vertex indices.
    corners: Vec<u32>,
    /// Unknown statements already logged (at most 32).
    unknown: HashSet<Vec<u8>>,
}

impl<'a> ObjReader<'a> {
    fn new(file: &'a str, scratch: &'a Path) -> Result<Self, ImportError> {
        Ok(Self {
            file,
            scratch,
            positions: writer::<[f64; 3]>(file, scratch, names::POSITIONS)?,
            triangles: writer::<[u32; 3]>(file, scratch, names::TRIANGLES)?,
            colors: None,
            line: 0,
            vertex_count: 0,
            face_count: 0,
            forward: None,
            corners: Vec::new(),
            unknown: HashSet::new(),
        })
    }

    fn syntax(&self, detail: impl Into<String>) -> ImportError {
        syntax(self.file, self.line, detail)
    }

    /// One statement (a line without its comment), by keyword.
    fn statement(&mut self, content: &[u8]) -> Result<(), ImportError> {
        let mut toks = tokens(content);
        let Some(keyword) = toks.next() else {
            return Ok(());
        };
        match keyword {
            b"v" => self.vertex(toks),
            b"f" => self.face(toks),
            b"vt" | b"vn" | b"vp" | b"g" | b"o" | b"s" | b"usemtl" | b"mtllib" | b"l" | b"p"
            | b"cstype" | b"deg" | b"curv" | b"surf" | b"parm" | b"end" | b"lod" => Ok(()),
            other => {
                if self.unknown.len() < 32 && self.unknown.insert(other.to_vec()) {
                    tracing::debug!(
                        file = self.file,
                        line = self.line,
                        "ignoring unknown OBJ statement '{}'",
                        show(other)
                    );
                }
                Ok(())
            }
        }
    }

    /// `v x y z [w | r g b]`.
    fn vertex<'t>(&mut self, toks: impl Iterator<Item = &'t [u8]>) -> Result<(), ImportError> {
        let vertex_count = self.vertex_count;
        let mut values = [0f64; 6];
        let mut count = 0usize;
        for tok in toks {
            if count == values.len() {
                return Err(self.syntax(format!(
                    "vertex {vertex_count}: too many numbers after 'v' (expected x y z, x y z w or x y z r g b)"
                )));
            }
            let value = std::str::from_utf8(tok)
                .ok()
                .and_then(|s| s.parse::<f64>().ok())
                .ok_or_else(|| {
                    self.syntax(format!(
                        "vertex {vertex_count}: '{}' is not a number (value {} after 'v')",
                        show(tok),
                        count + 1
                    ))
                })?;
            if !value.is_finite() {
                return Err(ImportError::NonFinite {
                    file: self.file.to_owned(),
                    line: Some(self.line),
                    record: format!("vertex {vertex_count}"),
                    value,
                });
            }
            values[count] = value;
            count += 1;
        }
        let color = match count {
            0..=2 => {
                return Err(self.syntax(format!(
                    "vertex {vertex_count}: expected 3 coordinates after 'v', got {count}"
                )));
            }
            3 | 4 => None,
            6 => Some([
                unit_to_u8(values[3]),
                unit_to_u8(values[4]),
                unit_to_u8(values[5]),
            ]),
            _ => {
                return Err(self.syntax(format!(
                    "vertex {vertex_count}: expected 3 (x y z), 4 (x y z w) or 6 (x y z r g b) numbers after 'v', got {count}"
                )));
            }
        };
        let file = self.file;
        push(file, &mut self.positions, [values[0], values[1], values[2]])?;
        match (&mut self.colors, color) {
            (Some(w), c) => push(file, w, c.unwrap_or(DEFAULT_COLOR))?,
            (None, Some(c)) => {
                // First coloured vertex: earlier vertices get the default colour.
                let mut w = writer::<[u8; 3]>(file, self.scratch, names::COLORS)?;
                for _ in 0..vertex_count {
                    push(file, &mut w, DEFAULT_COLOR)?;
                }
                push(file, &mut w, c)?;
                self.colors = Some(w);
            }
            (None, None) => {}
        }
        self.vertex_count += 1;
        Ok(())
    }

    /// `f i i i …` (each `i`, `i/t`, `i//n` or `i/t/n`), fan-triangulated.
    fn face<'t>(&mut self, toks: impl Iterator<Item = &'t [u8]>) -> Result<(), ImportError> {
        self.corners.clear();
        for tok in toks {
            let corner = self.corner(tok)?;
            self.corners.push(corner);
        }
        let face_count = self.face_count;
        if self.corners.len() < 3 {
            return Err(self.syntax(format!(
                "face {face_count} has {} vertices; a face needs at least 3",
                self.corners.len()
            )));
        }
        let c = &self.corners;
        for i in 1..c.len() - 1 {
            push(self.file, &mut self.triangles, [c[0], c[i], c[i + 1]])?;
        }
        self.face_count += 1;
        Ok(())
    }

    /// One face corner's vertex index, resolved to 0-based; a positive index past the vertices
    /// read so far is remembered and checked at the end.
    fn corner(&mut self, tok: &[u8]) -> Result<u32, ImportError> {
        let (face_count, vertex_count) = (self.face_count, self.vertex_count);
        let first = tok.split(|&b| b == b'/').next().unwrap_or_default();
        let index = std::str::from_utf8(first)
            .ok()
            .and_then(|s| s.parse::<i64>().ok())
            .ok_or_else(|| {
                self.syntax(format!(
                    "face {face_count}: '{}' is not a vertex index (expected i, i/t, i//n or i/t/n)",
                    show(tok)
                ))
            })?;
        let out_of_range = || ImportError::IndexOutOfRange {
            file: self.file.to_owned(),
            line: Some(self.line),
            primitive: format!("face {face_count}"),
            index,
            vertex_count,
        };
        let resolved = match index {
            0 => {
                return Err(self.syntax(format!(
                    "face {face_count}: vertex index 0 is invalid (OBJ indices start at 1)"
                )));
            }
            i if i < 0 => {
                // Relative to the vertices read so far: -1 is the last one.
                let r = vertex_count as i64 + i;
                if r < 0 {
                    return Err(out_of_range());
                }
                r
            }
            i => {
                if i as u64 > vertex_count && self.forward.as_ref().is_none_or(|f| i > f.index) {
                    self.forward = Some(ForwardRef {
                        index: i,
                        line: self.line,
                        face: face_count,
                    });
                }
                i - 1
            }
        };
        u32::try_from(resolved).map_err(|_| out_of_range())
    }

    /// The checks that need the whole file, then the source: a mesh, or points when the file
    /// has vertices and no faces.
    fn finish(self) -> Result<Source, ImportError> {
        let file = self.file;
        let vertex_count = self.vertex_count;
        if vertex_count > u64::from(u32::MAX) + 1 {
            return Err(ImportError::Unsupported {
                file: file.to_owned(),
                feature: format!("{vertex_count} vertices (at most 2^32 can be indexed)"),
            });
        }
        if let Some(f) = self.forward
            && f.index as u64 > vertex_count
        {
            return Err(ImportError::IndexOutOfRange {
                file: file.to_owned(),
                line: Some(f.line),
                primitive: format!("face {}", f.face),
                index: f.index,
                vertex_count,
            });
        }
        let colors = match self.colors {
            Some(w) => Some(w.finish().map_err(|e| ImportError::column(file, e))?),
            None => None,
        };
        let positions = self
            .positions
            .finish()
            .map_err(|e| ImportError::column(file, e))?;
        if self.face_count == 0 {
            if vertex_count == 0 {
                return Err(ImportError::NoPrimitives {
                    file: file.to_owned(),
                    detail: format!("no vertices and no faces in {} lines", self.line),
                });
            }
            tracing::info!(
                file,
                vertices = vertex_count,
                "OBJ has no faces: importing as points"
            );
            return Ok(Source::Points(PointSource {
                positions,
                colors,
                normals: None,
            }));
        }
        let triangles = self
            .triangles
            .finish()
            .map_err(|e| ImportError::column(file, e))?;
        Ok(Source::Mesh(MeshSource {
            positions,
            normals: None,
            colors,
            triangles,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::import::{ImportOptions, import_file};

    fn run(text: &str) -> (tempfile::TempDir, Result<Source, ImportError>) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.obj");
        std::fs::write(&path, text).unwrap();
        let r = import_file(&path, &ImportOptions::default(), dir.path());
        (dir, r)
    }

    fn mesh(text: &str) -> (tempfile::TempDir, MeshSource) {
        match run(text) {
            (d, Ok(Source::Mesh(m))) => (d, m),
            (_, other) => panic!("expected mesh, got {other:?}"),
        }
    }

    fn err(text: &str) -> String {
        match run(text).1 {
            Err(e) => e.to_string(),
            Ok(s) => panic!("expected error, got {}", s.describe()),
        }
    }

    #[test]
    fn triangles_and_index_forms() {
        let (_d, m) = mesh(
            "# comment\nmtllib x.mtl\no thing\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvn 0 0 1\n\
             s off\nusemtl m\nf 1 2 3\nf 2/1 4/1 3/1\nf 1//1 2//1 4//1\nf 1/1/1 3/1/1 4/1/1\n",
        );
        assert_eq!(m.positions.len(), 4);
        assert_eq!(
            &m.triangles[..],
            &[[0, 1, 2], [1, 3, 2], [0, 1, 3], [0, 2, 3]]
        );
        assert!(m.colors.is_none() && m.normals.is_none());
        assert_eq!(m.positions[3], [1.0, 1.0, 0.0]);
    }

    #[test]
    fn negative_indices_are_relative() {
        let (_d, m) = mesh("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 5 5 5\nf -1 -2 -3\n");
        assert_eq!(&m.triangles[..], &[[0, 1, 2], [3, 2, 1]]);
    }

    #[test]
    fn polygons_are_fans() {
        let (_d, m) = mesh("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv -1 0 0\nf 1 2 3 4 5\n");
        assert_eq!(&m.triangles[..], &[[0, 1, 2], [0, 2, 3], [0, 3, 4]]);
    }

    #[test]
    fn forward_references_and_crlf() {
        let (_d, m) = mesh("f 1 2 3\r\nv 0 0 0\r\nv 1 0 0\r\nv 0 1 0 1.0\r\n");
        assert_eq!(&m.triangles[..], &[[0, 1, 2]]);
        assert_eq!(m.positions.len(), 3);
    }

    #[test]
    fn vertex_colours() {
        let (_d, m) = mesh("v 0 0 0\nv 1 0 0 1 0 0.5\nv 0 1 0 0 1 0\nf 1 2 3\n");
        let c = m.colors.expect("colours");
        assert_eq!(&c[..], &[[255, 255, 255], [255, 0, 128], [0, 255, 0]]);
    }

    #[test]
    fn points_without_faces() {
        match run("v 0 0 0\nv 1 2 3\n").1 {
            Ok(Source::Points(p)) => assert_eq!(p.positions.len(), 2),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn errors() {
        let e = err("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n");
        assert!(
            e.contains("t.obj line 4: face 0 has vertex index 9 but only 3 vertices"),
            "{e}"
        );
        let e = err("v 0 0 0\nv 1 0 0\nf 1 2 -3\n");
        assert!(
            e.contains("line 3: face 0 has vertex index -3 but only 2 vertices"),
            "{e}"
        );
        let e = err("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n");
        assert!(e.contains("line 4") && e.contains("index 0"), "{e}");
        let e = err("v 0 0 0\nv 1 0 0\nf 1 2\n");
        assert!(e.contains("line 3: face 0 has 2 vertices"), "{e}");
        let e = err("v 0 0\n");
        assert!(
            e.contains("line 1: vertex 0: expected 3 coordinates after 'v'"),
            "{e}"
        );
        let e = err("v 0 0 0\nv 1 zero 0\n");
        assert!(
            e.contains("line 2: vertex 1: 'zero' is not a number"),
            "{e}"
        );
        let e = err("v 0 0 0\nv 1 nan 0\n");
        assert!(
            e.contains("line 2: vertex 1 has non-finite value NaN"),
            "{e}"
        );
        let e = err("v 0 0 0\nv 1 inf 0\n");
        assert!(e.contains("non-finite value inf"), "{e}");
        let e = err("v 0 0 0 1 2\n");
        assert!(e.contains("got 5"), "{e}");
        let e = err("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 x 2\n");
        assert!(e.contains("'x' is not a vertex index"), "{e}");
        let e = err("# nothing\n\ng group\n");
        assert!(e.contains("zero primitives"), "{e}");
    }

    #[test]
    fn real_bunny() {
        let path = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../shared/data/meshes/stanford-bunny.obj"
        ));
        let dir = tempfile::tempdir().unwrap();
        let src = import_file(path, &ImportOptions::default(), dir.path()).unwrap();
        let Source::Mesh(m) = src else {
            panic!("bunny is a mesh")
        };
        assert_eq!(m.triangles.len(), 69_451);
        assert_eq!(m.positions.len(), 35_947);
        let n = m.positions.len() as u32;
        assert!(m.triangles.iter().flatten().all(|&i| i < n));
    }
}
