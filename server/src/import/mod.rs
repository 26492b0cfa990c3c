//! Scan importers: OBJ, PLY, LAS/LAZ, NRRD and headerless raw volumes.
//!
//! Every importer streams the input into [`ColumnWriter`]s in a caller-supplied scratch
//! directory and returns a [`Source`]. Nothing is sized from counts found in the file: element
//! and point counts are checked against the file length first, and data are read record by
//! record, so a bogus header gives a clear error instead of a huge allocation, and inputs larger
//! than RAM stay bounded.
//!
//! Errors ([`ImportError`]) always name the file and say exactly what is wrong: the line for text
//! formats, the element/property for PLY, the record index or byte offset for binary data.

use std::fmt;
use std::path::Path;
use std::str::FromStr;

use bytemuck::Pod;

use crate::source::{ColumnError, ColumnWriter, Source};

mod las;
mod nrrd;
mod obj;
mod ply;
pub mod points_out;
pub mod tiles;

/// Input file formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Format {
    /// Wavefront OBJ (text): vertices and polygon faces.
    Obj,
    /// Stanford PLY (ascii, binary little or big endian): meshes, triangle strips or points.
    Ply,
    /// ASPRS LAS 1.0–1.4, LAZ compressed or not (COPC files too).
    Las,
    /// NRRD volume with inline data (raw or gzip).
    Nrrd,
    /// Headerless raw volume, described by a [`RawSpec`].
    Raw,
}

impl Format {
    /// Lower-case name, as accepted by [`Format::from_str`].
    pub fn name(self) -> &'static str {
        match self {
            Format::Obj => "obj",
            Format::Ply => "ply",
            Format::Las => "las",
            Format::Nrrd => "nrrd",
            Format::Raw => "raw",
        }
    }
}

impl fmt::Display for Format {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Format {
    type Err = String;

    /// Accepts `obj`, `ply`, `las`, `laz`, `nrrd`, `raw` (case-insensitive).
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "obj" => Ok(Format::Obj),
            "ply" => Ok(Format::Ply),
            "las" | "laz" | "copc" => Ok(Format::Las),
            "nrrd" | "nhdr" => Ok(Format::Nrrd),
            "raw" => Ok(Format::Raw),
            _ => Err(format!(
                "unknown format '{s}' (expected obj, ply, las, laz, nrrd or raw)"
            )),
        }
    }
}

/// Sample type of a headerless raw volume.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SampleType {
    /// Unsigned 8-bit; value range 0..255.
    U8,
    /// Unsigned 16-bit; value range 0..65535.
    U16,
    /// 32-bit IEEE float; value range is the data's min..max.
    F32,
}

impl SampleType {
    /// Bytes per sample.
    pub fn size(self) -> u64 {
        match self {
            SampleType::U8 => 1,
            SampleType::U16 => 2,
            SampleType::F32 => 4,
        }
    }

    /// Canonical name (`uint8`, `uint16`, `float`).
    pub fn name(self) -> &'static str {
        match self {
            SampleType::U8 => "uint8",
            SampleType::U16 => "uint16",
            SampleType::F32 => "float",
        }
    }
}

impl fmt::Display for SampleType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for SampleType {
    type Err = String;

    /// Accepts `u8|uint8|uchar`, `u16|uint16|ushort`, `f32|float` (case-insensitive).
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "u8" | "uint8" | "uchar" => Ok(SampleType::U8),
            "u16" | "uint16" | "ushort" => Ok(SampleType::U16),
            "f32" | "float" => Ok(SampleType::F32),
            _ => Err(format!(
                "unknown sample type '{s}' (expected u8, uint8, uchar, u16, uint16, ushort, f32 or float)"
            )),
        }
    }
}

/// Layout of a headerless raw volume: `dims[0] * dims[1] * dims[2]` samples, x fastest.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RawSpec {
    pub dims: [u32; 3],
    pub sample: SampleType,
    /// Distance between samples along each axis.
    pub spacing: [f64; 3],
    /// Multi-byte samples are big endian (default little).
    pub big_endian: bool,
}

/// How to import a file.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ImportOptions {
    /// Force a format instead of detecting it from the file extension.
    pub format: Option<Format>,
    /// Layout of a headerless raw volume (required for [`Format::Raw`]).
    pub raw: Option<RawSpec>,
    /// How to read a tile set (several point files as one scene).
    pub tiles: tiles::TileOptions,
}

/// Formats `Some(line)` as `" line N"` for messages of the form `"file line N: ..."`.
fn at_line(line: &Option<u64>) -> String {
    match line {
        Some(l) => format!(" line {l}"),
        None => String::new(),
    }
}

/// Why an import failed. Every message starts with the file name.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The file could not be opened or read (other than ending early, see `Truncated`).
    #[error("{file}: {context}: {error}")]
    Io {
        file: String,
        /// What was being done, e.g. "opening the file", "reading vertex data".
        context: String,
        error: std::io::Error,
    },

    /// The format could not be detected from the extension.
    #[error(
        "{file}: unknown file format (extension '{extension}'); expected .obj, .ply, .las, .laz, .nrrd or .raw, or pass the format explicitly"
    )]
    UnknownFormat { file: String, extension: String },

    /// The file has no bytes at all.
    #[error("{file}: file is empty (0 bytes)")]
    Empty { file: String },

    /// The file does not start with the signature of the expected format.
    #[error("{file}: not a {format} file: bad magic '{found}' (expected '{expected}')")]
    BadMagic {
        file: String,
        format: &'static str,
        expected: String,
        found: String,
    },

    /// A header is malformed: missing or invalid field, bad syntax.
    #[error("{file}{}: bad header: {detail}", at_line(.line))]
    BadHeader {
        file: String,
        line: Option<u64>,
        detail: String,
    },

    /// A text body line is malformed (OBJ statements, ASCII PLY values).
    #[error("{file} line {line}: {detail}")]
    Syntax {
        file: String,
        line: u64,
        detail: String,
    },

    /// The data ends before everything the header promised was read.
    #[error("{file}: truncated {what}: expected {expected} {unit}, got {got}")]
    Truncated {
        file: String,
        /// What was being read, e.g. "element 'vertex' data (starting at byte 210)".
        what: String,
        expected: u64,
        got: u64,
        /// "bytes", "records", "points", ...
        unit: &'static str,
    },

    /// A count in the header cannot possibly fit in the file (bogus count, or a badly truncated file).
    #[error(
        "{file}: {what} count {count} is larger than the file: it needs at least {needed} bytes but only {available} bytes follow"
    )]
    CountTooLarge {
        file: String,
        what: String,
        count: u64,
        needed: u64,
        available: u64,
    },

    /// A face or strip refers to a vertex that does not exist.
    #[error("{file}{}: {primitive} has vertex index {index} but only {vertex_count} vertices", at_line(.line))]
    IndexOutOfRange {
        file: String,
        line: Option<u64>,
        /// e.g. "face 12", "tristrip 0 entry 345".
        primitive: String,
        index: i64,
        vertex_count: u64,
    },

    /// A property, field or sample type that the importer cannot read.
    #[error("{file}: {what} has unsupported type '{type_name}'")]
    UnsupportedType {
        file: String,
        /// e.g. "property 'x' of element 'vertex'", "NRRD field 'type'".
        what: String,
        type_name: String,
    },

    /// A valid but unsupported feature of the format (detached NRRD data, bzip2 encoding...).
    #[error("{file}: not supported: {feature}")]
    Unsupported { file: String, feature: String },

    /// A required PLY element property is missing.
    #[error("{file}: element '{element}' has no property '{property}'")]
    MissingProperty {
        file: String,
        element: String,
        property: String,
    },

    /// A coordinate or sample is NaN or infinite.
    #[error("{file}{}: {record} has non-finite value {value} (NaN and infinity are rejected)", at_line(.line))]
    NonFinite {
        file: String,
        line: Option<u64>,
        /// e.g. "vertex 12", "sample 4096".
        record: String,
        value: f64,
    },

    /// The file is well formed but holds nothing to build from.
    #[error("{file}: zero primitives: {detail}")]
    NoPrimitives { file: String, detail: String },

    /// Volume data length does not match the declared sizes.
    #[error("{file}: wrong data size: {layout} needs exactly {expected} bytes of data, got {got}")]
    WrongSize {
        file: String,
        /// e.g. "sizes 256 256 128 of uint8".
        layout: String,
        expected: u64,
        got: u64,
    },

    /// A headerless raw volume was imported without a [`RawSpec`].
    #[error("{file}: raw volume needs --raw-dims/--raw-type (no raw layout given)")]
    MissingRawSpec { file: String },

    /// Compressed data could not be decoded (corrupt gzip stream, LAZ decoder failure).
    #[error("{file}: corrupt data: {detail}")]
    Corrupt { file: String, detail: String },

    /// An error from the `las` crate while reading a LAS/LAZ file.
    #[error("{file}: {context}: {error}")]
    Las {
        file: String,
        /// e.g. "reading the LAS header", "decoding points 65536..131072".
        context: String,
        error: ::las::Error,
    },

    /// Writing a scratch column failed.
    #[error("{file}: {error}")]
    Column { file: String, error: ColumnError },

    /// Two tiles of one set declare different coordinate systems (`--allow-mixed-crs` reads
    /// them anyway, as if they shared one).
    #[error(
        "{second}: coordinate system {second_crs} differs from {first_crs} of {first}; tiles of one scene must share one (pass --allow-mixed-crs to import them anyway)"
    )]
    MixedCoordinateSystems {
        first: String,
        first_crs: String,
        second: String,
        second_crs: String,
    },

    /// A file of a tile set is not a point cloud (a mesh, a volume).
    #[error("{file}: a tile set takes point clouds only (LAS/LAZ, point PLY); this file is {kind}")]
    NotPointTile { file: String, kind: String },

    /// An input pattern, directory or list named no file to import.
    #[error("{pattern}: no LAS, LAZ or PLY file {how}")]
    NoInputs {
        pattern: String,
        /// e.g. "in this directory", "matches this pattern".
        how: &'static str,
    },

    /// More primitives than one scene can index (primitive ids are 32-bit).
    #[error(
        "{file}: {count} {what} exceed the limit of {limit} primitives per scene (primitive ids are 32-bit); split the set into several scenes"
    )]
    TooManyPrimitives {
        file: String,
        /// "points (from the headers)", "points", ...
        what: &'static str,
        count: u64,
        limit: u64,
    },
}

impl ImportError {
    pub(crate) fn io(file: &str, context: impl Into<String>, error: std::io::Error) -> Self {
        ImportError::Io {
            file: file.to_owned(),
            context: context.into(),
            error,
        }
    }

    pub(crate) fn column(file: &str, error: ColumnError) -> Self {
        ImportError::Column {
            file: file.to_owned(),
            error,
        }
    }
}

/// Detects the format from the file extension (case-insensitive): `.obj`, `.ply`, `.las`,
/// `.laz` (including `.copc.laz`), `.nrrd` (and `.nhdr`), `.raw`.
pub fn detect_format(path: &Path) -> Result<Format, ImportError> {
    let extension = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match extension.as_str() {
        "obj" => Ok(Format::Obj),
        "ply" => Ok(Format::Ply),
        "las" | "laz" => Ok(Format::Las),
        "nrrd" | "nhdr" => Ok(Format::Nrrd),
        "raw" => Ok(Format::Raw),
        _ => Err(ImportError::UnknownFormat {
            file: path.display().to_string(),
            extension,
        }),
    }
}

/// Imports `path` into columns under `scratch` (a directory that must exist and that the caller
/// owns; column files are named `src_*.col`).
pub fn import_file(
    path: &Path,
    opts: &ImportOptions,
    scratch: &Path,
) -> Result<Source, ImportError> {
    let file = path.display().to_string();
    let format = match opts.format {
        Some(f) => f,
        None => detect_format(path)?,
    };
    let meta =
        std::fs::metadata(path).map_err(|e| ImportError::io(&file, "opening the file", e))?;
    if meta.is_dir() {
        return Err(ImportError::io(
            &file,
            "opening the file",
            std::io::Error::other("is a directory"),
        ));
    }
    if meta.len() == 0 {
        return Err(ImportError::Empty { file });
    }
    tracing::debug!(file = %file, %format, bytes = meta.len(), "importing");
    let source = match format {
        Format::Obj => obj::import(path, &file, scratch)?,
        Format::Ply => ply::import(path, &file, scratch)?,
        Format::Las => las::import(path, &file, scratch)?,
        Format::Nrrd => nrrd::import_nrrd(path, &file, scratch)?,
        Format::Raw => match &opts.raw {
            Some(spec) => nrrd::import_raw(path, &file, spec, scratch)?,
            None => return Err(ImportError::MissingRawSpec { file }),
        },
    };
    tracing::info!(file = %file, "imported {}", source.describe());
    Ok(source)
}

/// Column file names (under the scratch directory, `.col` appended by [`ColumnWriter`]).
pub(crate) mod names {
    pub const POSITIONS: &str = "src_positions";
    pub const NORMALS: &str = "src_normals";
    pub const COLORS: &str = "src_colors";
    pub const TRIANGLES: &str = "src_triangles";
    pub const VALUES: &str = "src_values";
}

/// Creates a column writer, mapping the error to [`ImportError::Column`].
pub(crate) fn writer<T: Pod>(
    file: &str,
    scratch: &Path,
    name: &str,
) -> Result<ColumnWriter<T>, ImportError> {
    ColumnWriter::create(scratch, name).map_err(|e| ImportError::column(file, e))
}

/// Appends to a column writer, mapping the error to [`ImportError::Column`].
pub(crate) fn push<T: Pod>(
    file: &str,
    w: &mut ColumnWriter<T>,
    value: T,
) -> Result<(), ImportError> {
    w.push(value).map_err(|e| ImportError::column(file, e))
}

/// Maps a 0..1 float colour channel to 0..255 (clamped, rounded; NaN → 0).
pub(crate) fn unit_to_u8(v: f64) -> u8 {
    if v.is_nan() {
        0
    } else {
        (v.clamp(0.0, 1.0) * 255.0).round() as u8
    }
}

/// Human-readable, escaped rendering of a few leading bytes (for bad-magic messages).
pub(crate) fn show_bytes(bytes: &[u8]) -> String {
    bytes.escape_ascii().to_string()
}
