//! Scalar volumes: NRRD with inline data (raw or gzip) and headerless raw files.
//!
//! Samples are converted to `f32` as they are read and streamed into a column, x fastest. The
//! data length must match `sizes × type size` exactly: short and long data are both errors.

use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use flate2::read::MultiGzDecoder;

use super::{ImportError, RawSpec, SampleType, names, push, show_bytes, writer};
use crate::source::{Source, VolumeSource};

/// Longest accepted header line and largest header.
const MAX_LINE: u64 = 1 << 16;
const MAX_HEADER: u64 = 1 << 20;

fn bad_header(file: &str, line: Option<u64>, detail: impl Into<String>) -> ImportError {
    ImportError::BadHeader {
        file: file.to_owned(),
        line,
        detail: detail.into(),
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Raw,
    Gzip,
}

/// The parts of a NRRD header the importer uses.
#[derive(Debug)]
struct Header {
    sample: SampleType,
    dims: [u32; 3],
    encoding: Encoding,
    big_endian: bool,
    spacing: [f64; 3],
    origin: [f64; 3],
}

fn parse_type(file: &str, name: &str) -> Result<SampleType, ImportError> {
    match name {
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => Ok(SampleType::U8),
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => {
            Ok(SampleType::U16)
        }
        "float" => Ok(SampleType::F32),
        other => Err(ImportError::UnsupportedType {
            file: file.to_owned(),
            what: "NRRD field 'type'".to_owned(),
            type_name: other.to_owned(),
        }),
    }
}

/// Parses `(a,b,c)` vectors and `none` entries: `"(1,0,0) (0,1,0) none"`.
fn parse_vectors(s: &str) -> Option<Vec<Option<Vec<f64>>>> {
    let mut out = Vec::new();
    let mut rest = s.trim();
    while !rest.is_empty() {
        if let Some(r) = rest.strip_prefix("none") {
            out.push(None);
            rest = r.trim_start();
        } else if let Some(r) = rest.strip_prefix('(') {
            let end = r.find(')')?;
            let v: Option<Vec<f64>> = r[..end]
                .split(',')
                .map(|c| c.trim().parse::<f64>().ok())
                .collect();
            out.push(Some(v?));
            rest = r[end + 1..].trim_start();
        } else {
            return None;
        }
    }
    Some(out)
}

/// Reads the header up to and including the blank line; returns it and the header length.
fn parse_header<R: BufRead>(r: &mut R, file: &str) -> Result<(Header, u64), ImportError> {
    let mut buf = Vec::new();
    let read = |r: &mut R, buf: &mut Vec<u8>| {
        buf.clear();
        r.by_ref()
            .take(MAX_LINE)
            .read_until(b'\n', buf)
            .map_err(|e| ImportError::io(file, "reading the NRRD header", e))
    };
    let mut pos = read(r, &mut buf)? as u64;
    check_magic(file, &buf)?;
    let mut fields = HeaderFields::default();
    let mut line_no = 1u64;
    loop {
        let n = read(r, &mut buf)?;
        line_no += 1;
        let line = Some(line_no);
        pos += n as u64;
        if n == 0 {
            // Header without the blank line: there is no inline data at all.
            break;
        }
        if (buf.last() != Some(&b'\n') && n as u64 == MAX_LINE) || pos > MAX_HEADER {
            return Err(bad_header(
                file,
                line,
                format!("header line too long or header larger than {MAX_HEADER} bytes"),
            ));
        }
        let text = String::from_utf8_lossy(&buf);
        let text = text.trim_end_matches(['\n', '\r']);
        if text.is_empty() {
            break;
        }
        if text.starts_with('#') {
            continue;
        }
        if let Some((key, _)) = text.split_once(":=")
            && !key.contains(": ")
        {
            continue; // key/value pair
        }
        let Some((field, value)) = text.split_once(": ") else {
            return Err(bad_header(
                file,
                line,
                format!("expected '<field>: <value>', got '{text}'"),
            ));
        };
        fields.field(file, line, field, value.trim())?;
    }
    Ok((fields.finish(file)?, pos))
}

fn check_magic(file: &str, first_line: &[u8]) -> Result<(), ImportError> {
    let magic = first_line.strip_suffix(b"\n").unwrap_or(first_line);
    let magic = magic.strip_suffix(b"\r").unwrap_or(magic);
    if magic.len() == 8 && magic.starts_with(b"NRRD000") && magic[7].is_ascii_digit() {
        return Ok(());
    }
    Err(ImportError::BadMagic {
        file: file.to_owned(),
        format: "NRRD",
        expected: "NRRD000N".to_owned(),
        found: show_bytes(&first_line[..first_line.len().min(16)]),
    })
}

/// The header fields read so far.
#[derive(Default)]
struct HeaderFields {
    sample: Option<SampleType>,
    dimension: Option<u32>,
    sizes: Option<[u32; 3]>,
    encoding: Option<Encoding>,
    /// `Some(true)` for big endian.
    endian: Option<bool>,
    spacings: Option<[f64; 3]>,
    /// Lengths of the space direction vectors.
    directions: Option<[f64; 3]>,
    origin: Option<[f64; 3]>,
}

impl HeaderFields {
    /// One `field: value` line, by field name.
    fn field(
        &mut self,
        file: &str,
        line: Option<u64>,
        field: &str,
        value: &str,
    ) -> Result<(), ImportError> {
        match field {
            "type" => self.sample = Some(parse_type(file, value)?),
            "dimension" => self.dimension = Some(parse_dimension(file, line, value)?),
            "sizes" => self.sizes = Some(parse_sizes(file, line, value)?),
            "encoding" => self.encoding = Some(parse_encoding(file, value)?),
            "endian" => self.endian = Some(parse_endian(file, line, value)?),
            "spacings" => self.spacings = Some(parse_spacings(file, line, value)?),
            "space directions" => self.directions = Some(parse_directions(file, line, value)?),
            "space origin" => self.origin = Some(parse_origin(file, line, value)?),
            "data file" | "datafile" => {
                return Err(ImportError::Unsupported {
                    file: file.to_owned(),
                    feature: format!(
                        "detached NRRD data file '{value}' (only inline data after the header is supported)"
                    ),
                });
            }
            "byte skip" | "byteskip" | "line skip" | "lineskip" => {
                if value != "0" {
                    return Err(ImportError::Unsupported {
                        file: file.to_owned(),
                        feature: format!("NRRD '{field}: {value}' (only 0 is supported)"),
                    });
                }
            }
            _ => tracing::debug!(file, field, value, "ignoring NRRD field"),
        }
        Ok(())
    }

    /// The header, once every required field was read.
    fn finish(self, file: &str) -> Result<Header, ImportError> {
        let missing = |f: &str| bad_header(file, None, format!("missing required field '{f}'"));
        let sample = self.sample.ok_or_else(|| missing("type"))?;
        self.dimension.ok_or_else(|| missing("dimension"))?;
        let dims = self.sizes.ok_or_else(|| missing("sizes"))?;
        let encoding = self.encoding.ok_or_else(|| missing("encoding"))?;
        let big_endian = match self.endian {
            Some(b) => b,
            None => {
                if sample.size() > 1 {
                    tracing::debug!(file, "NRRD has no 'endian' field; assuming little");
                }
                false
            }
        };
        Ok(Header {
            sample,
            dims,
            encoding,
            big_endian,
            spacing: self.directions.or(self.spacings).unwrap_or([1.0; 3]),
            origin: self.origin.unwrap_or([0.0; 3]),
        })
    }
}

fn header_floats(
    file: &str,
    line: Option<u64>,
    what: &str,
    value: &str,
) -> Result<Vec<f64>, ImportError> {
    value
        .split_ascii_whitespace()
        .map(|t| {
            t.parse::<f64>()
                .map_err(|_| bad_header(file, line, format!("{what}: '{t}' is not a number")))
        })
        .collect()
}

fn parse_dimension(file: &str, line: Option<u64>, value: &str) -> Result<u32, ImportError> {
    let d: u32 = value
        .parse()
        .map_err(|_| bad_header(file, line, format!("dimension '{value}' is not a number")))?;
    if d != 3 {
        return Err(ImportError::Unsupported {
            file: file.to_owned(),
            feature: format!("NRRD dimension {d} (only 3-D volumes can be imported)"),
        });
    }
    Ok(d)
}

fn parse_sizes(file: &str, line: Option<u64>, value: &str) -> Result<[u32; 3], ImportError> {
    let s: Vec<&str> = value.split_ascii_whitespace().collect();
    let parsed: Option<Vec<u32>> = s
        .iter()
        .map(|t| t.parse::<u32>().ok().filter(|&v| v > 0))
        .collect();
    match (parsed, s.len()) {
        (Some(v), 3) => Ok([v[0], v[1], v[2]]),
        _ => Err(bad_header(
            file,
            line,
            format!("sizes '{value}': expected 3 positive integers"),
        )),
    }
}

fn parse_encoding(file: &str, value: &str) -> Result<Encoding, ImportError> {
    match value {
        "raw" => Ok(Encoding::Raw),
        "gzip" | "gz" => Ok(Encoding::Gzip),
        other => Err(ImportError::Unsupported {
            file: file.to_owned(),
            feature: format!("NRRD encoding '{other}' (only raw and gzip are supported)"),
        }),
    }
}

/// `true` for big endian.
fn parse_endian(file: &str, line: Option<u64>, value: &str) -> Result<bool, ImportError> {
    match value {
        "little" => Ok(false),
        "big" => Ok(true),
        other => Err(bad_header(
            file,
            line,
            format!("endian '{other}' (expected little or big)"),
        )),
    }
}

fn parse_spacings(file: &str, line: Option<u64>, value: &str) -> Result<[f64; 3], ImportError> {
    let v = header_floats(file, line, "spacings", value)?;
    if v.len() != 3 {
        return Err(bad_header(
            file,
            line,
            format!("spacings '{value}': expected 3 values"),
        ));
    }
    // NaN means "unknown" in NRRD.
    let s = |x: f64| {
        if x.is_finite() && x != 0.0 {
            x.abs()
        } else {
            1.0
        }
    };
    Ok([s(v[0]), s(v[1]), s(v[2])])
}

/// The lengths of the three space direction vectors (the voxel spacing).
fn parse_directions(file: &str, line: Option<u64>, value: &str) -> Result<[f64; 3], ImportError> {
    let vecs = parse_vectors(value).ok_or_else(|| {
        bad_header(
            file,
            line,
            format!("space directions '{value}': expected (x,y,z) vectors"),
        )
    })?;
    let lengths: Option<Vec<f64>> = vecs
        .iter()
        .map(|v| {
            v.as_ref()
                .map(|v| v.iter().map(|c| c * c).sum::<f64>().sqrt())
                .filter(|l| l.is_finite() && *l > 0.0)
        })
        .collect();
    match lengths {
        Some(l) if l.len() == 3 => {
            let diagonal = vecs.iter().enumerate().all(|(i, v)| {
                v.as_ref()
                    .is_some_and(|v| v.iter().enumerate().all(|(j, c)| i == j || *c == 0.0))
            });
            if !diagonal {
                tracing::debug!(
                    file,
                    "NRRD axes are not axis aligned; using direction lengths as spacing"
                );
            }
            Ok([l[0], l[1], l[2]])
        }
        _ => Err(bad_header(
            file,
            line,
            format!("space directions '{value}': expected 3 non-zero vectors"),
        )),
    }
}

fn parse_origin(file: &str, line: Option<u64>, value: &str) -> Result<[f64; 3], ImportError> {
    parse_vectors(value)
        .and_then(|v| match &v[..] {
            [Some(o)] if o.len() == 3 && o.iter().all(|c| c.is_finite()) => {
                Some([o[0], o[1], o[2]])
            }
            _ => None,
        })
        .ok_or_else(|| {
            bad_header(
                file,
                line,
                format!("space origin '{value}': expected one (x,y,z) vector"),
            )
        })
}

fn layout_name(prefix: &str, dims: [u32; 3], sample: SampleType) -> String {
    format!(
        "{prefix} {}x{}x{} of {}",
        dims[0],
        dims[1],
        dims[2],
        sample.name()
    )
}

fn expected_bytes(file: &str, dims: [u32; 3], sample: SampleType) -> Result<u64, ImportError> {
    dims.iter()
        .try_fold(sample.size(), |acc, &d| acc.checked_mul(u64::from(d)))
        .ok_or_else(|| ImportError::Unsupported {
            file: file.to_owned(),
            feature: format!(
                "volume of {}x{}x{} samples (too large)",
                dims[0], dims[1], dims[2]
            ),
        })
}

/// Streams `expected` bytes of samples from `r` into the values column; checks that exactly
/// `expected` bytes are there.
#[allow(clippy::too_many_arguments)]
fn read_samples<R: Read>(
    mut r: R,
    file: &str,
    scratch: &Path,
    sample: SampleType,
    big_endian: bool,
    expected: u64,
    layout: &str,
    gzip: bool,
) -> Result<(crate::source::Column<f32>, [f32; 2]), ImportError> {
    let mut values = writer::<f32>(file, scratch, names::VALUES)?;
    let size = sample.size() as usize;
    let mut buf = vec![0u8; 1 << 16];
    let mut carry = [0u8; 4];
    let mut carried = 0usize;
    let mut total = 0u64;
    let mut index = 0u64;
    let mut lo = f32::INFINITY;
    let mut hi = f32::NEG_INFINITY;
    let read_err = |e: std::io::Error, total: u64| -> ImportError {
        if gzip
            && matches!(
                e.kind(),
                std::io::ErrorKind::InvalidInput
                    | std::io::ErrorKind::InvalidData
                    | std::io::ErrorKind::UnexpectedEof
            )
        {
            ImportError::Corrupt {
                file: file.to_owned(),
                detail: format!("gzip data: {e} (after {total} decompressed bytes)"),
            }
        } else {
            ImportError::io(file, format!("reading volume data after {total} bytes"), e)
        }
    };
    let decode = |b: &[u8]| -> f32 {
        match sample {
            SampleType::U8 => f32::from(b[0]),
            SampleType::U16 => {
                let v = [b[0], b[1]];
                f32::from(if big_endian {
                    u16::from_be_bytes(v)
                } else {
                    u16::from_le_bytes(v)
                })
            }
            SampleType::F32 => {
                let v = [b[0], b[1], b[2], b[3]];
                if big_endian {
                    f32::from_be_bytes(v)
                } else {
                    f32::from_le_bytes(v)
                }
            }
        }
    };
    while total < expected {
        let want = (expected - total).min(buf.len() as u64) as usize;
        let n = match r.read(&mut buf[..want]) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(read_err(e, total)),
        };
        total += n as u64;
        let mut chunk = &buf[..n];
        if carried > 0 {
            let take = (size - carried).min(chunk.len());
            carry[carried..carried + take].copy_from_slice(&chunk[..take]);
            carried += take;
            chunk = &chunk[take..];
            if carried < size {
                continue;
            }
            let v = decode(&carry[..size]);
            accept(file, &mut values, v, index, &mut lo, &mut hi)?;
            index += 1;
        }
        let mut samples = chunk.chunks_exact(size);
        for s in samples.by_ref() {
            let v = decode(s);
            accept(file, &mut values, v, index, &mut lo, &mut hi)?;
            index += 1;
        }
        let rest = samples.remainder();
        carry[..rest.len()].copy_from_slice(rest);
        carried = rest.len();
    }
    if total < expected {
        return Err(ImportError::WrongSize {
            file: file.to_owned(),
            layout: layout.to_owned(),
            expected,
            got: total,
        });
    }
    // Anything after the samples is an error too (wrong sizes or wrong type).
    let extra = std::io::copy(&mut r, &mut std::io::sink()).map_err(|e| read_err(e, total))?;
    if extra > 0 {
        return Err(ImportError::WrongSize {
            file: file.to_owned(),
            layout: layout.to_owned(),
            expected,
            got: total + extra,
        });
    }
    let range = match sample {
        SampleType::U8 => [0.0, 255.0],
        SampleType::U16 => [0.0, 65535.0],
        SampleType::F32 => [lo, hi],
    };
    let values = values.finish().map_err(|e| ImportError::column(file, e))?;
    Ok((values, range))
}

#[inline]
fn accept(
    file: &str,
    values: &mut crate::source::ColumnWriter<f32>,
    v: f32,
    index: u64,
    lo: &mut f32,
    hi: &mut f32,
) -> Result<(), ImportError> {
    if !v.is_finite() {
        return Err(ImportError::NonFinite {
            file: file.to_owned(),
            line: None,
            record: format!("sample {index}"),
            value: f64::from(v),
        });
    }
    *lo = lo.min(v);
    *hi = hi.max(v);
    push(file, values, v)
}

pub(super) fn import_nrrd(path: &Path, file: &str, scratch: &Path) -> Result<Source, ImportError> {
    let f = File::open(path).map_err(|e| ImportError::io(file, "opening the file", e))?;
    let mut r = BufReader::with_capacity(1 << 16, f);
    let (h, header_len) = parse_header(&mut r, file)?;
    tracing::debug!(file, ?h, header_len, "NRRD header");
    let expected = expected_bytes(file, h.dims, h.sample)?;
    let layout = layout_name("sizes", h.dims, h.sample);
    let (values, value_range) = match h.encoding {
        Encoding::Raw => read_samples(
            r,
            file,
            scratch,
            h.sample,
            h.big_endian,
            expected,
            &layout,
            false,
        )?,
        Encoding::Gzip => read_samples(
            MultiGzDecoder::new(r),
            file,
            scratch,
            h.sample,
            h.big_endian,
            expected,
            &format!("{layout} (decompressed)"),
            true,
        )?,
    };
    Ok(Source::Volume(VolumeSource {
        dims: h.dims,
        spacing: h.spacing,
        origin: h.origin,
        values,
        value_range,
    }))
}

pub(super) fn import_raw(
    path: &Path,
    file: &str,
    spec: &RawSpec,
    scratch: &Path,
) -> Result<Source, ImportError> {
    if spec.dims.contains(&0) {
        return Err(ImportError::Unsupported {
            file: file.to_owned(),
            feature: format!(
                "raw dims {}x{}x{} (every dimension must be at least 1)",
                spec.dims[0], spec.dims[1], spec.dims[2]
            ),
        });
    }
    if spec.spacing.iter().any(|s| !s.is_finite() || *s <= 0.0) {
        return Err(ImportError::Unsupported {
            file: file.to_owned(),
            feature: format!("raw spacing {:?} (must be positive)", spec.spacing),
        });
    }
    let f = File::open(path).map_err(|e| ImportError::io(file, "opening the file", e))?;
    let len = f
        .metadata()
        .map_err(|e| ImportError::io(file, "reading file metadata", e))?
        .len();
    let expected = expected_bytes(file, spec.dims, spec.sample)?;
    let layout = layout_name("raw dims", spec.dims, spec.sample);
    if len != expected {
        return Err(ImportError::WrongSize {
            file: file.to_owned(),
            layout,
            expected,
            got: len,
        });
    }
    let (values, value_range) = read_samples(
        BufReader::with_capacity(1 << 16, f),
        file,
        scratch,
        spec.sample,
        spec.big_endian,
        expected,
        &layout,
        false,
    )?;
    Ok(Source::Volume(VolumeSource {
        dims: spec.dims,
        spacing: spec.spacing,
        origin: [0.0; 3],
        values,
        value_range,
    }))
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::*;
    use crate::import::{Format, ImportOptions, import_file};

    fn gzip(data: &[u8]) -> Vec<u8> {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(data).unwrap();
        e.finish().unwrap()
    }

    fn nrrd(ty: &str, sizes: [u32; 3], extra: &str, encoding: &str, data: &[u8]) -> Vec<u8> {
        let mut out = format!(
            "NRRD0004\n# comment\ntype: {ty}\ndimension: 3\nsizes: {} {} {}\nencoding: {encoding}\n\
             kinds: domain domain domain\ncontent: test\nkey:=value\n{extra}{}\n",
            sizes[0],
            sizes[1],
            sizes[2],
            if extra.is_empty() { "" } else { "\n" }
        )
        .into_bytes();
        if encoding == "raw" {
            out.extend_from_slice(data);
        } else {
            out.extend_from_slice(&gzip(data));
        }
        out
    }

    fn run(
        name: &str,
        bytes: &[u8],
        opts: &ImportOptions,
    ) -> (tempfile::TempDir, Result<Source, ImportError>) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).unwrap();
        let r = import_file(&path, opts, dir.path());
        (dir, r)
    }

    fn volume(bytes: &[u8]) -> (tempfile::TempDir, VolumeSource) {
        match run("t.nrrd", bytes, &ImportOptions::default()) {
            (d, Ok(Source::Volume(v))) => (d, v),
            (_, other) => panic!("expected volume, got {other:?}"),
        }
    }

    fn err(name: &str, bytes: &[u8], opts: &ImportOptions) -> String {
        match run(name, bytes, opts).1 {
            Err(e) => e.to_string(),
            Ok(s) => panic!("expected error, got {}", s.describe()),
        }
    }

    #[test]
    fn u8_raw_and_gzip() {
        let data: Vec<u8> = (0..24).collect();
        for enc in ["raw", "gzip", "gz"] {
            let (_d, v) = volume(&nrrd(
                "uint8",
                [2, 3, 4],
                "spacings: 0.5 1 nan\nspace origin: (1,2,3)",
                enc,
                &data,
            ));
            assert_eq!(v.dims, [2, 3, 4]);
            assert_eq!(v.spacing, [0.5, 1.0, 1.0]);
            assert_eq!(v.origin, [1.0, 2.0, 3.0]);
            assert_eq!(v.value_range, [0.0, 255.0]);
            assert_eq!(v.values.len(), 24);
            assert_eq!(v.values[23], 23.0);
        }
    }

    #[test]
    fn u16_big_and_little_endian() {
        let vals: Vec<u16> = (0..8).map(|i| i * 1000 + 7).collect();
        for (endian, enc) in [("big", "raw"), ("little", "gzip"), ("big", "gzip")] {
            let data: Vec<u8> = vals
                .iter()
                .flat_map(|v| {
                    if endian == "big" {
                        v.to_be_bytes()
                    } else {
                        v.to_le_bytes()
                    }
                })
                .collect();
            let (_d, v) = volume(&nrrd(
                "unsigned short",
                [2, 2, 2],
                &format!("endian: {endian}\nspace directions: (0,2,0) (3,0,0) (0,0,4)"),
                enc,
                &data,
            ));
            assert_eq!(v.spacing, [2.0, 3.0, 4.0]);
            assert_eq!(v.value_range, [0.0, 65535.0]);
            assert_eq!(v.values[7], 7007.0);
        }
    }

    #[test]
    fn f32_range_and_nan() {
        let vals = [-1.5f32, 0.0, 2.0, 8.25, 3.0, 1.0, 0.5, -0.25];
        let data: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        for enc in ["raw", "gzip"] {
            let (_d, v) = volume(&nrrd("float", [2, 2, 2], "endian: little", enc, &data));
            assert_eq!(v.value_range, [-1.5, 8.25]);
            assert_eq!(&v.values[..], &vals);
        }
        let mut bad = vals;
        bad[5] = f32::NAN;
        let data: Vec<u8> = bad.iter().flat_map(|v| v.to_le_bytes()).collect();
        let e = err(
            "t.nrrd",
            &nrrd("float", [2, 2, 2], "endian: little", "raw", &data),
            &ImportOptions::default(),
        );
        assert!(e.contains("sample 5 has non-finite value NaN"), "{e}");
    }

    #[test]
    fn raw_headerless() {
        let vals: Vec<u16> = (0..12).map(|i| i * 300).collect();
        let data: Vec<u8> = vals.iter().flat_map(|v| v.to_be_bytes()).collect();
        let opts = ImportOptions {
            format: None,
            raw: Some(RawSpec {
                dims: [3, 2, 2],
                sample: SampleType::U16,
                spacing: [1.0, 1.0, 2.5],
                big_endian: true,
            }),
            ..ImportOptions::default()
        };
        match run("v.raw", &data, &opts).1 {
            Ok(Source::Volume(v)) => {
                assert_eq!(v.dims, [3, 2, 2]);
                assert_eq!(v.spacing, [1.0, 1.0, 2.5]);
                assert_eq!(v.values[11], 3300.0);
            }
            other => panic!("{other:?}"),
        }
        let e = err("v.raw", &data[..20], &opts);
        assert!(
            e.contains("raw dims 3x2x2 of uint16 needs exactly 24 bytes of data, got 20"),
            "{e}"
        );
        let e = err("v.raw", &data, &ImportOptions::default());
        assert!(e.contains("raw volume needs --raw-dims/--raw-type"), "{e}");
        let forced = ImportOptions {
            format: Some(Format::Raw),
            ..opts
        };
        assert!(matches!(
            run("v.bin", &data, &forced).1,
            Ok(Source::Volume(_))
        ));
    }

    #[test]
    fn errors() {
        let o = ImportOptions::default();
        let data = [0u8; 24];
        let e = err(
            "t.nrrd",
            &nrrd("uint8", [2, 3, 4], "", "raw", &data[..20]),
            &o,
        );
        assert!(
            e.contains("sizes 2x3x4 of uint8 needs exactly 24 bytes of data, got 20"),
            "{e}"
        );
        let e = err(
            "t.nrrd",
            &nrrd("uint8", [2, 3, 4], "", "raw", &[0u8; 30]),
            &o,
        );
        assert!(e.contains("needs exactly 24 bytes of data, got 30"), "{e}");
        let e = err(
            "t.nrrd",
            &nrrd("uint8", [2, 3, 4], "", "gzip", &[0u8; 30]),
            &o,
        );
        assert!(
            e.contains("(decompressed) needs exactly 24 bytes of data, got 30"),
            "{e}"
        );
        let e = err("t.nrrd", &nrrd("double", [2, 3, 4], "", "raw", &data), &o);
        assert!(
            e.contains("NRRD field 'type' has unsupported type 'double'"),
            "{e}"
        );
        let e = err(
            "t.nrrd",
            b"NRRD0004\ntype: uint8\ndimension: 2\nsizes: 2 2\nencoding: raw\n\n0000",
            &o,
        );
        assert!(e.contains("dimension 2"), "{e}");
        let mut gz = nrrd("uint8", [2, 3, 4], "", "gzip", &data);
        let n = gz.len();
        for b in &mut gz[n - 20..n - 8] {
            *b ^= 0x5a;
        }
        let e = err("t.nrrd", &gz, &o);
        assert!(e.contains("corrupt data: gzip"), "{e}");
        let e = err("t.nrrd", b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\ndata file: x.raw\n\n", &o);
        assert!(e.contains("detached NRRD data file 'x.raw'"), "{e}");
        let e = err("t.nrrd", b"NRRX0004\n", &o);
        assert!(e.contains("bad magic"), "{e}");
        let e = err(
            "t.nrrd",
            b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\n\n",
            &o,
        );
        assert!(e.contains("missing required field 'encoding'"), "{e}");
    }

    #[test]
    fn real_engine() {
        let path = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../shared/data/volumes/engine_256x256x128_u8.nrrd"
        ));
        let dir = tempfile::tempdir().unwrap();
        let src = import_file(path, &ImportOptions::default(), dir.path()).unwrap();
        let Source::Volume(v) = src else {
            panic!("engine is a volume")
        };
        assert_eq!(v.dims, [256, 256, 128]);
        assert_eq!(v.values.len(), 256 * 256 * 128);
        assert_eq!(v.spacing, [1.0, 1.0, 1.0]);
        assert_eq!(v.value_range, [0.0, 255.0]);
        let max = v.values.iter().copied().fold(0f32, f32::max);
        assert!(max > 100.0, "max sample {max}");
    }
}
