//! Stanford PLY: ascii, binary little endian and binary big endian.
//!
//! The `vertex` element gives positions (`x y z`, any numeric type), optional normals
//! (`nx ny nz`) and optional colours (`red green blue`). A `face` element (`vertex_indices` or
//! `vertex_index` list) is fan-triangulated; a `tristrips` element (`vertex_indices` list, `-1`
//! restarts the strip) is unrolled with the usual alternating winding, dropping degenerate
//! triangles. Without either element the file is a point cloud. Any other element is skipped.
//!
//! Element counts come from an untrusted header: nothing is allocated from them, and they are
//! checked against the bytes left in the file before an element is read.

//!
//! The header is read by [`header`], typed values by [`values`]; this file turns the body into
//! columns.

mod header;
mod values;

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use self::header::{Element, Encoding, Header, Kind, Scalar, bad_header, parse_header};
use self::values::{Ascii, Binary, ReadErr, Values};
use super::{ImportError, names, push, unit_to_u8, writer};
use crate::source::{ColumnWriter, MeshSource, PointSource, Source};

/// Where the vertex attributes sit in a vertex record (indices into `Element::props`).
struct VertexLayout {
    /// Property index → slot: 0..3 position, 3..6 normal, 6..9 colour.
    slot: Vec<Option<usize>>,
    has_normals: bool,
    color_type: Option<Scalar>,
}

impl VertexLayout {
    fn new(file: &str, e: &Element) -> Result<Self, ImportError> {
        let mut slot = vec![None; e.props.len()];
        for (k, name) in ["x", "y", "z"].iter().enumerate() {
            match e.scalar(name) {
                Some((i, _)) => slot[i] = Some(k),
                None => {
                    return Err(ImportError::MissingProperty {
                        file: file.to_owned(),
                        element: e.name.clone(),
                        property: (*name).to_owned(),
                    });
                }
            }
        }
        let normals: Vec<_> = ["nx", "ny", "nz"]
            .iter()
            .filter_map(|n| e.scalar(n))
            .collect();
        let has_normals = normals.len() == 3;
        if has_normals {
            for (k, (i, _)) in normals.iter().enumerate() {
                slot[*i] = Some(3 + k);
            }
        }
        let mut color_type = None;
        for names in [
            ["red", "green", "blue"],
            ["diffuse_red", "diffuse_green", "diffuse_blue"],
        ] {
            let c: Vec<_> = names.iter().filter_map(|n| e.scalar(n)).collect();
            if c.len() == 3 {
                for (k, (i, _)) in c.iter().enumerate() {
                    slot[*i] = Some(6 + k);
                }
                color_type = Some(c[0].1);
                break;
            }
        }
        Ok(Self {
            slot,
            has_normals,
            color_type,
        })
    }
}

fn color_channel(ty: Scalar, v: f64) -> u8 {
    match ty {
        Scalar::U8 | Scalar::I8 => v.clamp(0.0, 255.0) as u8,
        Scalar::U16 | Scalar::I16 => ((v.clamp(0.0, 65535.0) as u32) >> 8) as u8,
        Scalar::I32 | Scalar::U32 => v.clamp(0.0, 255.0) as u8,
        Scalar::F32 | Scalar::F64 => unit_to_u8(v),
    }
}

/// What the importer is collecting while it walks the body.
struct Sink<'a> {
    file: &'a str,
    vertex_count: u64,
    positions: ColumnWriter<[f64; 3]>,
    normals: Option<ColumnWriter<[f32; 3]>>,
    colors: Option<ColumnWriter<[u8; 3]>>,
    triangles: Option<ColumnWriter<[u32; 3]>>,
}

/// Context for turning [`ReadErr`] into [`ImportError`].
struct At<'a> {
    file: &'a str,
    element: &'a Element,
    record: u64,
    prop: &'a str,
}

impl At<'_> {
    fn err<V: Values>(&self, v: &V, e: ReadErr) -> ImportError {
        match e {
            ReadErr::Eof => ImportError::Truncated {
                file: self.file.to_owned(),
                what: format!(
                    "element '{}' data (the file ends inside record {}, property '{}', at {})",
                    self.element.name,
                    self.record,
                    self.prop,
                    v.position()
                ),
                expected: self.element.count,
                got: self.record,
                unit: "records",
            },
            ReadErr::Io(error) => ImportError::io(
                self.file,
                format!(
                    "reading element '{}' record {} at {}",
                    self.element.name,
                    self.record,
                    v.position()
                ),
                error,
            ),
            ReadErr::Syntax(detail) => ImportError::Syntax {
                file: self.file.to_owned(),
                line: v.line().unwrap_or(0),
                detail: format!(
                    "element '{}' record {}, property '{}': {detail}",
                    self.element.name, self.record, self.prop
                ),
            },
        }
    }

    fn value<V: Values>(&self, v: &mut V, ty: Scalar) -> Result<f64, ImportError> {
        v.value(ty).map_err(|e| self.err(v, e))
    }

    /// Reads a list length: a non-negative integer.
    fn list_len<V: Values>(&self, v: &mut V, ty: Scalar) -> Result<u64, ImportError> {
        let n = self.value(v, ty)?;
        if n < 0.0 {
            return Err(self.bad(v, format!("negative list length {n}")));
        }
        Ok(n as u64)
    }

    fn bad<V: Values>(&self, v: &V, detail: String) -> ImportError {
        match v.line() {
            Some(line) => ImportError::Syntax {
                file: self.file.to_owned(),
                line,
                detail: format!(
                    "element '{}' record {}, property '{}': {detail}",
                    self.element.name, self.record, self.prop
                ),
            },
            None => ImportError::Corrupt {
                file: self.file.to_owned(),
                detail: format!(
                    "element '{}' record {}, property '{}' at {}: {detail}",
                    self.element.name,
                    self.record,
                    self.prop,
                    v.position()
                ),
            },
        }
    }

    /// Reads and skips one property.
    fn skip<V: Values>(&self, v: &mut V, kind: Kind) -> Result<(), ImportError> {
        match kind {
            Kind::Scalar(s) => v.skip(s, 1).map_err(|e| self.err(v, e)),
            Kind::List { count, item } => {
                let n = self.list_len(v, count)?;
                v.skip(item, n).map_err(|e| self.err(v, e))
            }
        }
    }
}

impl<'a> Sink<'a> {
    /// Empty columns for what `plan` says the body holds.
    fn new(file: &'a str, scratch: &Path, plan: &BodyPlan) -> Result<Self, ImportError> {
        Ok(Sink {
            file,
            vertex_count: plan.vertex_count,
            positions: writer(file, scratch, names::POSITIONS)?,
            normals: if plan.layout.has_normals {
                Some(writer(file, scratch, names::NORMALS)?)
            } else {
                None
            },
            colors: if plan.layout.color_type.is_some() {
                Some(writer(file, scratch, names::COLORS)?)
            } else {
                None
            },
            triangles: if plan.is_mesh() {
                Some(writer(file, scratch, names::TRIANGLES)?)
            } else {
                None
            },
        })
    }

    /// The finished columns as a mesh (faces or strips gave triangles) or a point cloud.
    fn finish(self) -> Result<Source, ImportError> {
        let file = self.file;
        let col = |e| ImportError::column(file, e);
        let positions = self.positions.finish().map_err(col)?;
        let normals = match self.normals {
            Some(w) => Some(w.finish().map_err(col)?),
            None => None,
        };
        let colors = match self.colors {
            Some(w) => Some(w.finish().map_err(col)?),
            None => None,
        };
        let Some(triangles) = self.triangles else {
            if positions.is_empty() {
                return Err(ImportError::NoPrimitives {
                    file: file.to_owned(),
                    detail: "no vertices and no faces".to_owned(),
                });
            }
            return Ok(Source::Points(PointSource {
                positions,
                colors,
                normals,
            }));
        };
        if triangles.is_empty() {
            return Err(ImportError::NoPrimitives {
                file: file.to_owned(),
                detail: format!(
                    "the faces/strips give no triangles ({} vertices)",
                    self.vertex_count
                ),
            });
        }
        Ok(Source::Mesh(MeshSource {
            positions,
            normals,
            colors,
            triangles: triangles.finish().map_err(col)?,
        }))
    }
}

impl Sink<'_> {
    fn index<V: Values>(
        &self,
        at: &At<'_>,
        v: &mut V,
        ty: Scalar,
        primitive: impl Fn() -> String,
        allow_restart: bool,
    ) -> Result<Option<u32>, ImportError> {
        let raw = at.value(v, ty)?;
        if raw.fract() != 0.0 || !raw.is_finite() {
            return Err(at.bad(v, format!("vertex index {raw} is not an integer")));
        }
        if allow_restart && raw == -1.0 {
            return Ok(None);
        }
        if raw < 0.0 || raw >= self.vertex_count as f64 {
            return Err(ImportError::IndexOutOfRange {
                file: self.file.to_owned(),
                line: v.line(),
                primitive: primitive(),
                index: raw as i64,
                vertex_count: self.vertex_count,
            });
        }
        Ok(Some(raw as u32))
    }

    fn vertices<V: Values>(
        &mut self,
        v: &mut V,
        e: &Element,
        layout: &VertexLayout,
    ) -> Result<(), ImportError> {
        let file = self.file;
        for record in 0..e.count {
            let mut vals = [0f64; 9];
            for (p, slot) in e.props.iter().zip(&layout.slot) {
                let at = At {
                    file,
                    element: e,
                    record,
                    prop: &p.name,
                };
                match (p.kind, slot) {
                    (Kind::Scalar(s), Some(k)) => vals[*k] = at.value(v, s)?,
                    (kind, _) => at.skip(v, kind)?,
                }
            }
            if let Some(value) = vals[..3].iter().copied().find(|c| !c.is_finite()) {
                return Err(ImportError::NonFinite {
                    file: file.to_owned(),
                    line: v.line(),
                    record: format!("vertex {record}"),
                    value,
                });
            }
            push(file, &mut self.positions, [vals[0], vals[1], vals[2]])?;
            if let Some(w) = &mut self.normals {
                push(file, w, [vals[3] as f32, vals[4] as f32, vals[5] as f32])?;
            }
            if let (Some(w), Some(ty)) = (&mut self.colors, layout.color_type) {
                let c = [
                    color_channel(ty, vals[6]),
                    color_channel(ty, vals[7]),
                    color_channel(ty, vals[8]),
                ];
                push(file, w, c)?;
            }
        }
        Ok(())
    }

    /// Reads every record of `e`, skipping each property but the list at index `list`, and hands
    /// that list (place, length, item type) to `each`, which reads its items.
    fn each_list<V: Values>(
        &mut self,
        v: &mut V,
        e: &Element,
        list: usize,
        mut each: impl FnMut(&mut Self, &At<'_>, &mut V, u64, Scalar) -> Result<(), ImportError>,
    ) -> Result<(), ImportError> {
        let file = self.file;
        for record in 0..e.count {
            for (pi, p) in e.props.iter().enumerate() {
                let at = At {
                    file,
                    element: e,
                    record,
                    prop: &p.name,
                };
                let Kind::List { count, item } = p.kind else {
                    at.skip(v, p.kind)?;
                    continue;
                };
                if pi != list {
                    at.skip(v, p.kind)?;
                    continue;
                }
                let n = at.list_len(v, count)?;
                each(self, &at, v, n, item)?;
            }
        }
        Ok(())
    }

    fn faces<V: Values>(&mut self, v: &mut V, e: &Element, list: usize) -> Result<(), ImportError> {
        let file = self.file;
        self.each_list(v, e, list, |this, at, v, n, item| {
            let record = at.record;
            if n < 3 {
                return Err(at.bad(
                    v,
                    format!("face {record} has {n} vertex indices; a face needs at least 3"),
                ));
            }
            let name = || format!("face {record}");
            let first = this.index(at, v, item, name, false)?.unwrap_or(0);
            let mut prev = this.index(at, v, item, name, false)?.unwrap_or(0);
            for _ in 2..n {
                let cur = this.index(at, v, item, name, false)?.unwrap_or(0);
                if let Some(w) = &mut this.triangles {
                    push(file, w, [first, prev, cur])?;
                }
                prev = cur;
            }
            Ok(())
        })
    }

    fn strips<V: Values>(
        &mut self,
        v: &mut V,
        e: &Element,
        list: usize,
    ) -> Result<(), ImportError> {
        let file = self.file;
        let mut dropped = 0u64;
        self.each_list(v, e, list, |this, at, v, n, item| {
            let record = at.record;
            // Sliding window over the strip; `parity` is the index of the next triangle within
            // the current strip (odd triangles are flipped).
            let mut a: Option<u32> = None;
            let mut b: Option<u32> = None;
            let mut parity = 0u64;
            for entry in 0..n {
                let name = || format!("tristrip {record} entry {entry}");
                let Some(c) = this.index(at, v, item, name, true)? else {
                    a = None;
                    b = None;
                    parity = 0;
                    continue;
                };
                if let (Some(va), Some(vb)) = (a, b) {
                    let tri = if parity.is_multiple_of(2) {
                        [va, vb, c]
                    } else {
                        [vb, va, c]
                    };
                    parity += 1;
                    if va == vb || vb == c || va == c {
                        dropped += 1;
                    } else if let Some(w) = &mut this.triangles {
                        push(file, w, tri)?;
                    }
                }
                a = b;
                b = Some(c);
            }
            Ok(())
        })?;
        tracing::debug!(file, dropped, "dropped degenerate strip triangles");
        Ok(())
    }
}

/// Checks that `e`'s records can fit in the `available` bytes that follow (binary files), so
/// that a bogus count fails fast and clearly.
fn check_fits(
    file: &str,
    e: &Element,
    encoding: Encoding,
    pos: u64,
    file_len: u64,
) -> Result<(), ImportError> {
    let available = file_len.saturating_sub(pos);
    let (record, fixed) = match encoding {
        Encoding::Ascii => {
            // Every value takes at least one character and one separator.
            let values = e.props.len() as u64;
            (2 * values, false)
        }
        _ => e.min_binary_size(),
    };
    let needed = e.count.saturating_mul(record);
    let needed = if encoding == Encoding::Ascii {
        needed.saturating_sub(1)
    } else {
        needed
    };
    if needed <= available {
        return Ok(());
    }
    if encoding != Encoding::Ascii && needed <= file_len {
        // Plausible count, missing data: the file was cut short.
        return Err(ImportError::Truncated {
            file: file.to_owned(),
            what: format!("element '{}' data (starting at byte {pos})", e.name),
            expected: needed,
            got: available,
            unit: if fixed { "bytes" } else { "bytes (at least)" },
        });
    }
    Err(ImportError::CountTooLarge {
        file: file.to_owned(),
        what: format!("element '{}'", e.name),
        count: e.count,
        needed,
        available,
    })
}

pub(super) fn import(path: &Path, file: &str, scratch: &Path) -> Result<Source, ImportError> {
    let f = File::open(path).map_err(|e| ImportError::io(file, "opening the file", e))?;
    let file_len = f
        .metadata()
        .map_err(|e| ImportError::io(file, "reading file metadata", e))?
        .len();
    let mut r = BufReader::with_capacity(1 << 16, f);
    let header = parse_header(&mut r, file)?;
    tracing::debug!(file, ?header.encoding, elements = ?header.elements.iter().map(|e| (&e.name, e.count)).collect::<Vec<_>>(), "PLY header");
    let plan = BodyPlan::new(file, &header)?;
    let mut sink = Sink::new(file, scratch, &plan)?;
    let pos = header.data_start;
    match header.encoding {
        Encoding::Ascii => {
            let mut v = Ascii::new(r, header.lines + 1);
            body(&mut v, &header, &plan, &mut sink, file_len, |_| pos)?;
        }
        enc => {
            let mut v = Binary {
                r,
                pos,
                big: enc == Encoding::BigEndian,
            };
            body(&mut v, &header, &plan, &mut sink, file_len, |v| v.pos)?;
            if v.pos < file_len {
                tracing::debug!(
                    file,
                    extra = file_len - v.pos,
                    "ignoring bytes after the PLY body"
                );
            }
        }
    }
    sink.finish()
}

/// Checks the header of a PLY file meant as a tile of a point set: readable, and points only
/// (no faces or triangle strips). Reads no body.
pub(super) fn check_header(path: &Path, file: &str) -> Result<(), ImportError> {
    let f = File::open(path).map_err(|e| ImportError::io(file, "opening the file", e))?;
    let header = parse_header(&mut BufReader::new(f), file)?;
    if BodyPlan::new(file, &header)?.is_mesh() {
        return Err(ImportError::NotPointTile {
            file: file.to_owned(),
            kind: "a mesh (it has faces or triangle strips)".to_owned(),
        });
    }
    Ok(())
}

/// What the body holds, decided from the header: where the vertex attributes are, and the index
/// list of the `face` and `tristrips` elements. An element with no records (e.g. MeshLab's
/// `element face 0` in point clouds) does not make the file a mesh.
struct BodyPlan {
    layout: VertexLayout,
    vertex_count: u64,
    face_list: Option<usize>,
    strip_list: Option<usize>,
}

impl BodyPlan {
    fn new(file: &str, header: &Header) -> Result<Self, ImportError> {
        let Some(vertex) = header.elements.iter().find(|e| e.name == "vertex") else {
            return Err(bad_header(file, None, "no 'vertex' element"));
        };
        let layout = VertexLayout::new(file, vertex)?;
        let index_list = |names: &[&str]| -> Result<Option<usize>, ImportError> {
            match header
                .elements
                .iter()
                .find(|e| names.contains(&e.name.as_str()))
            {
                Some(e) if e.count > 0 => e
                    .list(&["vertex_indices", "vertex_index"])
                    .map(Some)
                    .ok_or_else(|| ImportError::MissingProperty {
                        file: file.to_owned(),
                        element: e.name.clone(),
                        property: "vertex_indices (list)".to_owned(),
                    }),
                _ => Ok(None),
            }
        };
        let plan = BodyPlan {
            layout,
            vertex_count: vertex.count,
            face_list: index_list(&["face"])?,
            strip_list: index_list(&["tristrips", "tristrip"])?,
        };
        if plan.is_mesh() && plan.vertex_count > u64::from(u32::MAX) + 1 {
            return Err(ImportError::Unsupported {
                file: file.to_owned(),
                feature: format!(
                    "{} vertices (at most 2^32 can be indexed)",
                    plan.vertex_count
                ),
            });
        }
        Ok(plan)
    }

    fn is_mesh(&self) -> bool {
        self.face_list.is_some() || self.strip_list.is_some()
    }
}

/// Reads every element of the body in order: vertices, faces and strips into `sink`, anything
/// else skipped.
fn body<V: Values>(
    v: &mut V,
    header: &Header,
    plan: &BodyPlan,
    sink: &mut Sink<'_>,
    file_len: u64,
    pos: impl Fn(&V) -> u64,
) -> Result<(), ImportError> {
    let file = sink.file;
    for e in &header.elements {
        check_fits(file, e, header.encoding, pos(v), file_len)?;
        match e.name.as_str() {
            "vertex" => sink.vertices(v, e, &plan.layout)?,
            "face" => sink.faces(v, e, plan.face_list.unwrap_or(usize::MAX))?,
            "tristrips" | "tristrip" => sink.strips(v, e, plan.strip_list.unwrap_or(usize::MAX))?,
            _ => {
                tracing::debug!(file, element = %e.name, count = e.count, "skipping PLY element");
                for record in 0..e.count {
                    for p in &e.props {
                        let at = At {
                            file,
                            element: e,
                            record,
                            prop: &p.name,
                        };
                        at.skip(v, p.kind)?;
                    }
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::import::{ImportOptions, import_file};

    fn run(bytes: &[u8]) -> (tempfile::TempDir, Result<Source, ImportError>) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.ply");
        std::fs::write(&path, bytes).unwrap();
        let r = import_file(&path, &ImportOptions::default(), dir.path());
        (dir, r)
    }

    fn mesh(bytes: &[u8]) -> (tempfile::TempDir, MeshSource) {
        match run(bytes) {
            (d, Ok(Source::Mesh(m))) => (d, m),
            (_, other) => panic!("expected mesh, got {other:?}"),
        }
    }

    fn err(bytes: &[u8]) -> String {
        match run(bytes).1 {
            Err(e) => e.to_string(),
            Ok(s) => panic!("expected error, got {}", s.describe()),
        }
    }

    /// A quad (two faces: a triangle and a quad) with ushort colour and a skipped element.
    fn binary(big: bool) -> Vec<u8> {
        let enc = if big {
            "binary_big_endian"
        } else {
            "binary_little_endian"
        };
        let mut out = format!(
            "ply\nformat {enc} 1.0\ncomment test\nelement vertex 4\nproperty float x\nproperty double y\n\
             property short z\nproperty float nx\nproperty float ny\nproperty float nz\n\
             property ushort red\nproperty ushort green\nproperty ushort blue\n\
             element material 2\nproperty uchar a\nproperty list uchar int b\n\
             element face 2\nproperty uchar flags\nproperty list uchar uint vertex_indices\nend_header\n"
        )
        .into_bytes();
        macro_rules! put {
            ($v:expr) => {
                if big {
                    out.extend_from_slice(&$v.to_be_bytes())
                } else {
                    out.extend_from_slice(&$v.to_le_bytes())
                }
            };
        }
        for (i, p) in [
            [0.0f64, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 2.0],
        ]
        .iter()
        .enumerate()
        {
            put!(p[0] as f32);
            put!(p[1]);
            put!(p[2] as i16);
            put!(0f32);
            put!(0f32);
            put!(1f32);
            put!(65535u16);
            put!((i as u16) * 256);
            put!(0u16);
        }
        // material: a, list of 2 ints
        for _ in 0..2 {
            out.push(7);
            out.push(2);
            put!(-5i32);
            put!(9i32);
        }
        out.push(0);
        out.push(3);
        for i in [0u32, 1, 2] {
            put!(i);
        }
        out.push(1);
        out.push(4);
        for i in [0u32, 1, 2, 3] {
            put!(i);
        }
        out
    }

    fn check_quad(m: &MeshSource) {
        assert_eq!(m.positions.len(), 4);
        assert_eq!(m.positions[3], [0.0, 1.0, 2.0]);
        assert_eq!(&m.triangles[..], &[[0, 1, 2], [0, 1, 2], [0, 2, 3]]);
        let n = m.normals.as_ref().expect("normals");
        assert_eq!(n[2], [0.0, 0.0, 1.0]);
        let c = m.colors.as_ref().expect("colours");
        assert_eq!(
            &c[..],
            &[[255, 0, 0], [255, 1, 0], [255, 2, 0], [255, 3, 0]]
        );
    }

    #[test]
    fn binary_little_endian() {
        let (_d, m) = mesh(&binary(false));
        check_quad(&m);
    }

    #[test]
    fn binary_big_endian() {
        let (_d, m) = mesh(&binary(true));
        check_quad(&m);
    }

    #[test]
    fn ascii_faces_and_uchar_colour() {
        let text = "ply\r\nformat ascii 1.0\r\ncomment hi\r\nelement vertex 4\r\nproperty float x\r\n\
                    property float y\r\nproperty float z\r\nproperty uchar red\r\nproperty uchar green\r\n\
                    property uchar blue\r\nelement face 2\r\nproperty list uchar int vertex_index\r\n\
                    end_header\r\n0 0 0 255 0 0\r\n1 0 0 0 255 0\r\n1 1 0 0 0 255\r\n0 1 0 1 2 3\r\n\
                    3 0 1 2\r\n4 0 1 2 3\r\n";
        let (_d, m) = mesh(text.as_bytes());
        assert_eq!(&m.triangles[..], &[[0, 1, 2], [0, 1, 2], [0, 2, 3]]);
        assert_eq!(m.colors.as_ref().unwrap()[3], [1, 2, 3]);
        assert!(m.normals.is_none());
    }

    #[test]
    fn ascii_float_colour_and_points() {
        let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\n\
                    property double z\nproperty float red\nproperty float green\nproperty float blue\n\
                    end_header\n0 0 0 1 0.5 0\n1 2 3 0 0 2\n";
        match run(text.as_bytes()).1 {
            Ok(Source::Points(p)) => {
                assert_eq!(p.positions[1], [1.0, 2.0, 3.0]);
                assert_eq!(&p.colors.unwrap()[..], &[[255, 128, 0], [0, 0, 255]]);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn empty_face_element_means_points() {
        let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n\
                    property float z\nelement face 0\nproperty list uchar int vertex_indices\n\
                    end_header\n0 0 0\n1 2 3\n";
        match run(text.as_bytes()).1 {
            Ok(Source::Points(p)) => assert_eq!(p.positions.len(), 2),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn tristrip_with_restart() {
        let text = "ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\n\
                    property float z\nelement tristrips 1\nproperty list int int vertex_indices\n\
                    end_header\n0 0 0\n1 0 0\n0 1 0\n1 1 0\n0 2 0\n1 2 0\n\
                    11 0 1 2 3 -1 2 3 4 4 5 3\n";
        let (_d, m) = mesh(text.as_bytes());
        // Strip 0 1 2 3: (0 1 2), (2 1 3). Restart. Strip 2 3 4 4 5 3: (2 3 4), (4 3 4) degenerate,
        // (4 4 5) degenerate, (4 5 3) at parity 3 → flipped (5 4 3).
        assert_eq!(
            &m.triangles[..],
            &[[0, 1, 2], [2, 1, 3], [2, 3, 4], [5, 4, 3]]
        );
    }

    #[test]
    fn ascii_strip_on_one_long_line() {
        // 30,000 entries (> 64 KiB) zig-zagging over two rows of vertices.
        let n = 15_000;
        let mut text = format!(
            "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\n\
             property float z\nelement tristrips 1\nproperty list int int vertex_indices\nend_header\n",
            2 * n
        );
        for i in 0..n {
            text += &format!("{i} 0 0\n{i} 1 0\n");
        }
        text += &format!("{}", 2 * n);
        for i in 0..n {
            text += &format!(" {} {}", 2 * i, 2 * i + 1);
        }
        text += "\n";
        assert!(text.lines().last().unwrap().len() > 1 << 16);
        let (_d, m) = mesh(text.as_bytes());
        assert_eq!(m.triangles.len(), 2 * n - 2);
        assert_eq!(m.triangles[1], [2, 1, 3]);
    }

    #[test]
    fn binary_tristrip() {
        let mut out = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\n\
                        property float y\nproperty float z\nelement tristrips 1\n\
                        property list int int vertex_indices\nend_header\n"
            .to_vec();
        for i in 0..4 {
            for c in [i as f32, (i % 2) as f32, 0.0] {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        for i in [4i32, 0, 1, 2, 3] {
            out.extend_from_slice(&i.to_le_bytes());
        }
        let (_d, m) = mesh(&out);
        assert_eq!(&m.triangles[..], &[[0, 1, 2], [2, 1, 3]]);
    }

    #[test]
    fn errors() {
        let good = binary(false);
        let header_len = good.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;

        let e = err(&good[..header_len + 20]);
        assert!(e.contains("truncated element 'vertex' data"), "{e}");
        let e = err(&good[..good.len() - 3]);
        assert!(e.contains("truncated element 'face' data"), "{e}");
        assert!(e.contains("expected 2 records, got 1"), "{e}");

        // Each malformed header or body, and the words its error must contain.
        let cases: [(&[u8], &str); 10] = [
            (
                b"plx\nformat ascii 1.0\nend_header\n",
                "bad magic",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty int128 x\nend_header\n",
                "property 'x' of element 'vertex' has unsupported type 'int128'",
            ),
            (
                b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0",
                "count 4000000000 is larger than the file",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex -3\nproperty float x\nend_header\n",
                "negative count -3",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\nproperty float z\nend_header\n0 0\n",
                "element 'vertex' has no property 'x'",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 900\n",
                "face 0 has vertex index 900 but only 3 vertices",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 nan 0\n",
                "vertex 1 has non-finite value NaN",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 abc 0\n",
                "record 1, property 'y': 'abc' is not a valid number",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
                "zero primitives",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n",
                "before 'end_header'",
            ),
        ];
        for (input, needle) in cases {
            let e = err(input);
            assert!(e.contains(needle), "{needle:?} not in {e}");
        }
    }

    fn real(name: &str) -> Source {
        let path = format!(
            "{}/../../shared/data/meshes/{name}",
            env!("CARGO_MANIFEST_DIR")
        );
        let dir = tempfile::tempdir().unwrap();
        import_file(Path::new(&path), &ImportOptions::default(), dir.path()).unwrap()
    }

    #[test]
    fn real_igea_strips() {
        let Source::Mesh(m) = real("igea.ply") else {
            panic!("igea is a mesh")
        };
        assert_eq!(m.positions.len(), 134_345);
        assert!(
            m.triangles.len() > 200_000,
            "{} triangles",
            m.triangles.len()
        );
        let n = m.positions.len() as u32;
        assert!(m.triangles.iter().flatten().all(|&i| i < n));
        assert!(
            m.triangles
                .iter()
                .all(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
        );
    }

    #[test]
    fn real_lucy() {
        let Source::Mesh(m) = real("lucy-100k.ply") else {
            panic!("lucy is a mesh")
        };
        assert_eq!(m.positions.len(), 49_987);
        assert_eq!(m.triangles.len(), 99_970);
        let n = m.positions.len() as u32;
        assert!(m.triangles.iter().flatten().all(|&i| i < n));
    }
}
