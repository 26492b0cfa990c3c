//! A corpus of broken inputs for the importers: each must be rejected with a clear error and
//! without a panic (see `tests/bad_input_import.rs`).
//!
//! Most cases are small files built inline; the LAS/LAZ truncation cases cut the real scans in
//! `../shared/data/points` at run time.

use std::path::PathBuf;

use arbor_server::import::{RawSpec, SampleType};

/// One broken input and what its error message must say.
#[derive(Debug, Clone)]
pub struct BadInput {
    /// Short unique name of the case.
    pub name: &'static str,
    /// File name to write the bytes under (its extension selects the importer).
    pub file_name: String,
    pub bytes: Vec<u8>,
    /// Substring the error message must contain, compared case-insensitively.
    pub expect: &'static str,
    /// Raw volume layout to pass in the import options, if any.
    pub raw: Option<RawSpec>,
}

/// The shared real-data directory (`../shared/data` from the project root).
pub fn data_dir() -> PathBuf {
    // `ARBOR_DATA` points test binaries built here at a copy of the scans on another machine
    // (`scripts/gpu-bundle`); by default, `../shared/data` beside the checkout they were built in.
    std::env::var_os("ARBOR_DATA").map_or_else(
        || PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data")),
        PathBuf::from,
    )
}

fn real(rel: &str) -> Vec<u8> {
    let path = data_dir().join(rel);
    std::fs::read(&path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()))
}

fn case(
    name: &'static str,
    file_name: &str,
    bytes: impl Into<Vec<u8>>,
    expect: &'static str,
) -> BadInput {
    BadInput {
        name,
        file_name: file_name.to_owned(),
        bytes: bytes.into(),
        expect,
        raw: None,
    }
}

/// A binary little-endian PLY: 4 vertices (float x y z), 2 faces (uchar count, int indices),
/// the second face using `last_index` as its last corner.
fn binary_ply(vertex_count_text: &str, last_index: i32) -> Vec<u8> {
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\ncomment corpus\nelement vertex {vertex_count_text}\n\
         property float x\nproperty float y\nproperty float z\nelement face 2\n\
         property list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    for v in [[0f32, 0., 0.], [1., 0., 0.], [1., 1., 0.], [0., 1., 0.]] {
        for c in v {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    for face in [[0i32, 1, 2], [0, 2, last_index]] {
        out.push(3);
        for i in face {
            out.extend_from_slice(&i.to_le_bytes());
        }
    }
    out
}

fn ply_header_len(bytes: &[u8]) -> usize {
    bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .map(|p| p + 11)
        .unwrap_or(0)
}

const ASCII_TRIANGLE: &str = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                              property float z\nelement face 1\nproperty list uchar int vertex_indices\n\
                              end_header\n";

fn nrrd(header: &str, data: &[u8]) -> Vec<u8> {
    let mut out = format!("NRRD0004\n# corpus\n{header}\n").into_bytes();
    out.extend_from_slice(data);
    out
}

/// CRC-32 (IEEE), bitwise; only for the few bytes of the corpus.
fn crc32(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A valid gzip member holding `data` in one stored (uncompressed) deflate block.
fn gzip(data: &[u8]) -> Vec<u8> {
    let len = u16::try_from(data.len()).expect("small corpus data");
    let mut out = vec![0x1f, 0x8b, 8, 0, 0, 0, 0, 0, 0, 0xff];
    out.push(1); // final block, stored
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(&(!len).to_le_bytes());
    out.extend_from_slice(data);
    out.extend_from_slice(&crc32(data).to_le_bytes());
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    out
}

const U8_2X3X4: &str = "type: uint8\ndimension: 3\nsizes: 2 3 4\nencoding: raw\n";

fn raw_spec() -> RawSpec {
    RawSpec {
        dims: [2, 3, 4],
        sample: SampleType::U8,
        spacing: [1.0, 1.0, 1.0],
        big_endian: false,
    }
}

/// A LAS 1.4 file with its extended-VLR count set to zero.
fn without_evlrs(bytes: &[u8]) -> Vec<u8> {
    let mut b = bytes.to_vec();
    if b.len() >= 247 {
        b[243..247].copy_from_slice(&0u32.to_le_bytes());
    }
    b
}

/// Every broken input of the corpus (reads the real LAS/LAZ scans to cut them).
pub fn bad_inputs() -> Vec<BadInput> {
    let good_ply = binary_ply("4", 3);
    let ply_header = ply_header_len(&good_ply);
    let autzen = real("points/autzen_trim.las");
    let lion = real("points/lion_takanawa.copc.laz");
    let lion_cut = &lion[..lion.len() * 6 / 10];
    // Lion cut mid-chunk, with its chunk table appended and pointed at, and no EVLRs: only the
    // LAZ decoder can notice that the point data stops early.
    let lion_mid_chunk = {
        let mut b = without_evlrs(lion_cut);
        let offset = u32::from_le_bytes([b[96], b[97], b[98], b[99]]) as usize;
        let table = i64::from_le_bytes(lion[offset..offset + 8].try_into().expect("8 bytes"));
        let evlr_start = u64::from_le_bytes(lion[235..243].try_into().expect("8 bytes"));
        b[offset..offset + 8].copy_from_slice(&(lion_cut.len() as i64).to_le_bytes());
        b.extend_from_slice(&lion[table as usize..evlr_start as usize]);
        b
    };
    let u8_data: Vec<u8> = (0..24).collect();

    let mut cases = vec![
        // Empty files of every format.
        case("empty_obj", "empty.obj", [], "empty"),
        case("empty_ply", "empty.ply", [], "empty"),
        case("empty_las", "empty.las", [], "empty"),
        case("empty_laz", "empty.copc.laz", [], "empty"),
        case("empty_nrrd", "empty.nrrd", [], "empty"),
        BadInput {
            raw: Some(raw_spec()),
            ..case("empty_raw", "empty.raw", [], "empty")
        },
        // PLY.
        case(
            "ply_truncated_vertex_data",
            "cut.ply",
            &good_ply[..ply_header + 30],
            "truncated element 'vertex' data",
        ),
        case(
            "ply_truncated_face_data",
            "cut.ply",
            &good_ply[..good_ply.len() - 5],
            "truncated element 'face' data",
        ),
        case(
            "ply_wrong_magic",
            "magic.ply",
            b"PLY\nformat ascii 1.0\nend_header\n".to_vec(),
            "bad magic",
        ),
        case(
            "ply_unsupported_property_type",
            "int128.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty int128 x\nproperty float y\nproperty float z\nend_header\n1 2 3\n".to_vec(),
            "property 'x' of element 'vertex' has unsupported type 'int128'",
        ),
        case(
            "ply_count_larger_than_file",
            "huge.ply",
            binary_ply("4000000000", 3),
            "count 4000000000 is larger than the file",
        ),
        case(
            "ply_face_index_out_of_range",
            "index.ply",
            binary_ply("4", 900),
            "face 1 has vertex index 900 but only 4 vertices",
        ),
        case(
            "ply_negative_face_index",
            "negindex.ply",
            binary_ply("4", -2),
            "face 1 has vertex index -2 but only 4 vertices",
        ),
        case(
            "ply_negative_count",
            "negative.ply",
            b"ply\nformat ascii 1.0\nelement vertex -3\nproperty float x\nproperty float y\nproperty float z\nend_header\n".to_vec(),
            "negative count -3",
        ),
        case(
            "ply_missing_x",
            "nox.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\nproperty float z\nend_header\n1 2\n".to_vec(),
            "element 'vertex' has no property 'x'",
        ),
        case(
            "ply_no_end_header",
            "noend.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n".to_vec(),
            "before 'end_header'",
        ),
        case(
            "ply_missing_format",
            "noformat.ply",
            b"ply\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n".to_vec(),
            "missing 'format' line",
        ),
        case(
            "ply_ascii_not_a_number",
            "text.ply",
            format!("{ASCII_TRIANGLE}0 0 0\n1 zero 0\n0 1 0\n3 0 1 2\n"),
            "element 'vertex' record 1, property 'y': 'zero' is not a valid number",
        ),
        case(
            "ply_nan_coordinate",
            "nan.ply",
            format!("{ASCII_TRIANGLE}0 0 0\n1 0 0\nnan 1 0\n3 0 1 2\n"),
            "vertex 2 has non-finite value NaN",
        ),
        case(
            "ply_ascii_too_few_records",
            "short.ply",
            format!("{ASCII_TRIANGLE}0 0 0\n1 0 0\n0 1 0\n"),
            "truncated element 'face' data",
        ),
        case(
            "ply_tristrip_index_out_of_range",
            "strip.ply",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement tristrips 1\nproperty list int int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n4 0 1 2 7\n".to_vec(),
            "tristrip 0 entry 3 has vertex index 7 but only 3 vertices",
        ),
        case(
            "ply_face_with_two_indices",
            "two.ply",
            format!("{ASCII_TRIANGLE}0 0 0\n1 0 0\n0 1 0\n2 0 1\n"),
            "face 0 has 2 vertex indices",
        ),
        // OBJ.
        case(
            "obj_index_out_of_range",
            "index.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
            "line 4: face 0 has vertex index 9 but only 3 vertices",
        ),
        case(
            "obj_negative_index_out_of_range",
            "negindex.obj",
            "v 0 0 0\nv 1 0 0\nf 1 2 -5\nv 0 1 0\n",
            "line 3: face 0 has vertex index -5 but only 2 vertices",
        ),
        case(
            "obj_index_zero",
            "zero.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
            "vertex index 0 is invalid",
        ),
        case(
            "obj_non_numeric_coordinate",
            "text.obj",
            "v 0 0 0\nv 1 0x 0\n",
            "line 2: vertex 1: '0x' is not a number",
        ),
        case(
            "obj_nan_coordinate",
            "nan.obj",
            "v 0 0 0\nv NaN 0 0\n",
            "line 2: vertex 1 has non-finite value NaN",
        ),
        case(
            "obj_infinite_coordinate",
            "inf.obj",
            "v 0 0 0\nv 0 0 -inf\n",
            "non-finite value -inf",
        ),
        case(
            "obj_two_vertex_face",
            "two.obj",
            "v 0 0 0\nv 1 0 0\nf 1 2\n",
            "line 3: face 0 has 2 vertices",
        ),
        case(
            "obj_too_few_coordinates",
            "short.obj",
            "v 0 0\n",
            "expected 3 coordinates after 'v'",
        ),
        case(
            "obj_no_faces_no_vertices",
            "nothing.obj",
            "# only a comment\no empty\ng group\n",
            "zero primitives",
        ),
        case(
            "obj_binary_garbage",
            "garbage.obj",
            vec![0xffu8; 2 << 20],
            "line longer than",
        ),
        // LAS / LAZ.
        case(
            "las_wrong_magic",
            "magic.las",
            [b"LASG".as_slice(), &autzen[4..400]].concat(),
            "bad magic",
        ),
        case(
            "las_truncated_header",
            "cut.las",
            &autzen[..300],
            "truncated LAS header and VLRs",
        ),
        case(
            "las_truncated_points",
            "cutpoints.las",
            &autzen[..autzen.len() - 1000],
            "expected 110000 points",
        ),
        case(
            "laz_truncated_60_percent",
            "cut.copc.laz",
            lion_cut,
            "truncated",
        ),
        case(
            "laz_truncated_chunk_table_missing",
            "cut2.laz",
            without_evlrs(lion_cut),
            "chunk table should be at byte",
        ),
        case(
            "laz_truncated_mid_chunk",
            "cut3.laz",
            lion_mid_chunk,
            "expected 341989 points",
        ),
        // NRRD.
        case(
            "nrrd_data_shorter_than_sizes",
            "short.nrrd",
            nrrd(U8_2X3X4, &u8_data[..20]),
            "needs exactly 24 bytes of data, got 20",
        ),
        case(
            "nrrd_data_longer_than_sizes",
            "long.nrrd",
            nrrd(U8_2X3X4, &[0u8; 30]),
            "needs exactly 24 bytes of data, got 30",
        ),
        case(
            "nrrd_bad_type",
            "type.nrrd",
            nrrd(
                "type: complex128\ndimension: 3\nsizes: 2 3 4\nencoding: raw\n",
                &u8_data,
            ),
            "unsupported type 'complex128'",
        ),
        case(
            "nrrd_gzip_corrupted",
            "corrupt.nrrd",
            nrrd(
                "type: uint8\ndimension: 3\nsizes: 2 3 4\nencoding: gzip\n",
                &{
                    // A gzip header followed by an invalid deflate block type (BTYPE = 11).
                    let mut g = gzip(&u8_data);
                    g[10] = 0x07;
                    g
                },
            ),
            "gzip",
        ),
        case(
            "nrrd_gzip_short",
            "gzshort.nrrd",
            nrrd(
                "type: uint8\ndimension: 3\nsizes: 2 3 5\nencoding: gz\n",
                &gzip(&u8_data),
            ),
            "needs exactly 30 bytes of data, got 24",
        ),
        case(
            "nrrd_dimension_2",
            "flat.nrrd",
            nrrd(
                "type: uint8\ndimension: 2\nsizes: 4 6\nencoding: raw\n",
                &u8_data,
            ),
            "dimension 2",
        ),
        case(
            "nrrd_wrong_magic",
            "magic.nrrd",
            [b"NRRX0004\n".as_slice(), U8_2X3X4.as_bytes(), b"\n", &u8_data].concat(),
            "bad magic",
        ),
        case(
            "nrrd_detached_data",
            "detached.nrrd",
            nrrd(
                "type: uint8\ndimension: 3\nsizes: 2 3 4\nencoding: raw\ndata file: engine.raw\n",
                &[],
            ),
            "detached nrrd data file 'engine.raw'",
        ),
        case(
            "nrrd_bzip2_encoding",
            "bz.nrrd",
            nrrd(
                "type: uint8\ndimension: 3\nsizes: 2 3 4\nencoding: bzip2\n",
                &u8_data,
            ),
            "encoding 'bzip2'",
        ),
        case(
            "nrrd_float_nan",
            "nan.nrrd",
            nrrd(
                "type: float\ndimension: 3\nsizes: 2 1 1\nendian: little\nencoding: raw\n",
                &[1f32.to_le_bytes(), f32::NAN.to_le_bytes()].concat(),
            ),
            "sample 1 has non-finite value NaN",
        ),
        case(
            "nrrd_missing_sizes",
            "nosizes.nrrd",
            nrrd("type: uint8\ndimension: 3\nencoding: raw\n", &u8_data),
            "missing required field 'sizes'",
        ),
        // Raw.
        case(
            "raw_without_spec",
            "volume.raw",
            u8_data.clone(),
            "raw volume needs --raw-dims/--raw-type",
        ),
        BadInput {
            raw: Some(raw_spec()),
            ..case(
                "raw_size_mismatch",
                "volume.raw",
                &u8_data[..20],
                "raw dims 2x3x4 of uint8 needs exactly 24 bytes of data, got 20",
            )
        },
        BadInput {
            raw: Some(RawSpec {
                sample: SampleType::F32,
                dims: [1, 1, 2],
                ..raw_spec()
            }),
            ..case(
                "raw_float_infinity",
                "volume.raw",
                [0f32.to_le_bytes(), f32::INFINITY.to_le_bytes()].concat(),
                "sample 1 has non-finite value inf",
            )
        },
        // Format detection.
        case(
            "unknown_extension",
            "scan.xyz",
            "1 2 3\n",
            "unknown file format (extension 'xyz')",
        ),
        case("no_extension", "scan", "1 2 3\n", "unknown file format"),
    ];
    // Names must be unique so that failures are easy to find.
    cases.sort_by_key(|c| c.name);
    cases
}
