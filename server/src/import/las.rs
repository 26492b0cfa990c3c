//! LAS and LAZ point clouds (LAS 1.0–1.4, COPC files too) through the `las` crate.
//!
//! Positions are the crate's scaled-and-offset `f64` coordinates. Colour is collected as the
//! file's 16-bit RGB in a first pass while tracking the largest channel value; many writers store
//! 8-bit values in the 16-bit fields, so if no channel exceeds 255 the values are used as they
//! are, otherwise they are true 16-bit and shifted down by 8.
//!
//! Before handing the file to the crate, the header's offsets and counts are checked against the
//! file length, so truncated files give a precise error instead of an I/O error deep inside the
//! decoder (and a bogus EVLR length never becomes a huge allocation).

use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;

use ::las::raw;

use super::points_out::PointSetWriter;
use super::{ImportError, show_bytes};
use crate::source::Source;

/// Most points decoded per batch (several LAZ chunks, which the parallel decoder spreads over
/// the cores: with 2¹⁸ points, five chunks of 50,000 left a core idle for the last one).
const BATCH: u64 = 1 << 20;
/// Most bytes of decoded records held per batch (records can be up to 64 KiB long).
const BATCH_BYTES: u64 = 32 << 20;
/// Size of an EVLR header (reserved, user id, record id, length, description).
const EVLR_HEADER: u64 = 60;

fn las_err(file: &str, context: impl Into<String>, error: ::las::Error) -> ImportError {
    ImportError::Las {
        file: file.to_owned(),
        context: context.into(),
        error,
    }
}

fn is_eof(e: &::las::Error) -> bool {
    match e {
        ::las::Error::Io(io) => io.kind() == std::io::ErrorKind::UnexpectedEof,
        // The `laz` crate's error type is not re-exported by `las`; its Debug form names the
        // wrapped I/O error kind.
        ::las::Error::LasZipError(inner) => {
            let debug = format!("{inner:?}");
            debug.starts_with("IoError(") && debug.contains("UnexpectedEof")
        }
        _ => false,
    }
}

/// Reads `N` bytes at `offset`, or `None` past the end of the file.
fn read_at<const N: usize>(f: &mut File, offset: u64) -> std::io::Result<Option<[u8; N]>> {
    let mut b = [0u8; N];
    f.seek(SeekFrom::Start(offset))?;
    match f.read_exact(&mut b) {
        Ok(()) => Ok(Some(b)),
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => Ok(None),
        Err(e) => Err(e),
    }
}

/// Checks the header against the file length; returns the raw header.
fn precheck(file: &str, f: &mut File, file_len: u64) -> Result<raw::Header, ImportError> {
    let io = |e| ImportError::io(file, "reading the LAS header", e);
    let magic = read_at::<4>(f, 0).map_err(io)?;
    if magic != Some(*b"LASF") {
        let mut head = [0u8; 4];
        f.seek(SeekFrom::Start(0)).map_err(io)?;
        let n = f.read(&mut head).map_err(io)?;
        return Err(ImportError::BadMagic {
            file: file.to_owned(),
            format: "LAS",
            expected: "LASF".to_owned(),
            found: show_bytes(&head[..n]),
        });
    }
    f.seek(SeekFrom::Start(0)).map_err(io)?;
    let header = match raw::Header::read_from(BufReader::new(&mut *f)) {
        Ok(h) => h,
        Err(e) if is_eof(&e) => {
            // Header size field at byte 94, when present.
            let expected = match read_at::<2>(f, 94).map_err(io)? {
                Some(b) => u64::from(u16::from_le_bytes(b)),
                None => 227,
            };
            return Err(ImportError::Truncated {
                file: file.to_owned(),
                what: "LAS header".to_owned(),
                expected,
                got: file_len,
                unit: "bytes",
            });
        }
        Err(e) => return Err(las_err(file, "reading the LAS header", e)),
    };
    let offset = u64::from(header.offset_to_point_data);
    if offset > file_len {
        return Err(ImportError::Truncated {
            file: file.to_owned(),
            what: format!("LAS header and VLRs (point data should start at byte {offset})"),
            expected: offset,
            got: file_len,
            unit: "bytes",
        });
    }
    if let Some(evlr) = header.evlr
        && evlr.number_of_evlrs > 0
    {
        let start = evlr.start_of_first_evlr;
        let len = match read_at::<8>(f, start.saturating_add(20)).map_err(io)? {
            Some(b) if start.saturating_add(EVLR_HEADER) <= file_len => u64::from_le_bytes(b),
            _ => {
                return Err(ImportError::Truncated {
                    file: file.to_owned(),
                    what: format!("LAS extended VLRs (the first starts at byte {start})"),
                    expected: start.saturating_add(EVLR_HEADER),
                    got: file_len,
                    unit: "bytes",
                });
            }
        };
        let end = start.saturating_add(EVLR_HEADER).saturating_add(len);
        if end > file_len {
            return Err(ImportError::Truncated {
                file: file.to_owned(),
                what: format!("LAS extended VLR at byte {start} ({len} bytes of data)"),
                expected: end,
                got: file_len,
                unit: "bytes",
            });
        }
    }
    if header.point_data_record_format & 0x80 != 0 {
        check_chunk_table(file, f, file_len, offset)?;
    }
    Ok(header)
}

/// Checks the LAZ chunk table the way the `laz` crate will find it: the offset is the first 8
/// bytes of the point data, or, when the writer could not fill it in, the last 8 bytes of the
/// file. A table past the end of the file means the file was cut short; a table claiming more
/// chunks than the file has bytes is corrupt (and would make the decoder allocate it).
fn check_chunk_table(
    file: &str,
    f: &mut File,
    file_len: u64,
    offset: u64,
) -> Result<(), ImportError> {
    let io = |e| ImportError::io(file, "reading the LAZ chunk table offset", e);
    let Some(b) = read_at::<8>(f, offset).map_err(io)? else {
        return Err(ImportError::Truncated {
            file: file.to_owned(),
            what: format!("LAZ data (no chunk table offset at byte {offset})"),
            expected: offset + 8,
            got: file_len,
            unit: "bytes",
        });
    };
    let mut table = i64::from_le_bytes(b);
    if table <= offset as i64 && file_len >= 8 {
        if let Some(b) = read_at::<8>(f, file_len - 8).map_err(io)? {
            table = i64::from_le_bytes(b);
        }
        if table <= offset as i64 {
            // No chunk table at all; the decoder manages without one (or says so).
            return Ok(());
        }
    }
    let table = table as u64;
    match read_at::<8>(f, table).map_err(io)? {
        None => Err(ImportError::Truncated {
            file: file.to_owned(),
            what: format!("LAZ data (the chunk table should be at byte {table})"),
            expected: table.saturating_add(8),
            got: file_len,
            unit: "bytes",
        }),
        Some(b) => {
            let chunks = u64::from(u32::from_le_bytes([b[4], b[5], b[6], b[7]]));
            if chunks > file_len {
                return Err(ImportError::Corrupt {
                    file: file.to_owned(),
                    detail: format!(
                        "the LAZ chunk table at byte {table} claims {chunks} chunks in a {file_len}-byte file"
                    ),
                });
            }
            Ok(())
        }
    }
}

pub(super) fn import(path: &Path, file: &str, scratch: &Path) -> Result<Source, ImportError> {
    let mut out = PointSetWriter::new(file, scratch)?;
    read_into(path, file, &mut out)?;
    out.finish()
}

/// Appends every point of the LAS/LAZ file at `path` to `out` (positions scaled and offset by
/// this file's own header; colour when the file has it).
pub(super) fn read_into(
    path: &Path,
    file: &str,
    out: &mut PointSetWriter<'_>,
) -> Result<(), ImportError> {
    let (mut reader, header) = open(path, file)?;
    let format = *header.point_format();
    let n = header.number_of_points();
    out.begin_file(file, format.has_color, false)?;
    let batch = (BATCH_BYTES / u64::from(format.len()).max(1)).clamp(1, BATCH);
    let kind = if format.is_compressed { "LAZ" } else { "LAS" };
    // Decoding (this thread, the LAZ chunks spread over rayon) and appending to the scratch
    // columns (a scoped thread) overlap: appended one after the other, the columns left a core
    // idle for a third of the read. At most three batches exist at once.
    let appending = &mut *out;
    std::thread::scope(|scope| {
        let (full_tx, full_rx) = std::sync::mpsc::sync_channel::<(::las::PointData, u64)>(1);
        let (empty_tx, empty_rx) = std::sync::mpsc::channel::<::las::PointData>();
        let appender = scope.spawn(move || {
            for (pd, first) in full_rx {
                push_batch(appending, file, &pd, first)?;
                let _ = empty_tx.send(pd);
            }
            Ok::<(), ImportError>(())
        });
        let mut decoded = Ok(());
        let mut done = 0u64;
        while done < n {
            let mut pd = empty_rx
                .try_recv()
                .unwrap_or_else(|_| ::las::PointDataBuilder::new().for_header(&header).build());
            let want = batch.min(n - done);
            match read_batch(&mut reader, &mut pd, file, kind, done, want, n) {
                Ok(got) => {
                    // A closed channel: the appender failed; its error is the one to report.
                    if full_tx.send((pd, done)).is_err() {
                        break;
                    }
                    done += got;
                }
                Err(e) => {
                    decoded = Err(e);
                    break;
                }
            }
        }
        drop(full_tx);
        let appended = appender
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        appended.and(decoded)
    })?;
    out.end_las_file();
    Ok(())
}

/// What a LAS/LAZ header says before any point is decoded.
#[derive(Clone, Debug)]
pub(super) struct LasSurvey {
    /// Points declared (the 64-bit count of LAS 1.4, or the legacy 32-bit one).
    pub points: u64,
    /// Bounds declared in the header.
    pub min: [f64; 3],
    pub max: [f64; 3],
    /// The coordinate system records, if any.
    pub crs: Option<Crs>,
}

/// A file's coordinate system: its CRS records, compared byte for byte.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(super) struct Crs {
    /// (record id, data) of every `LASF_Projection` record, sorted.
    records: Vec<(u16, Vec<u8>)>,
    /// A short human description (the WKT's name, or the GeoTIFF key count).
    pub description: String,
}

/// Reads and checks the header and VLRs of a LAS/LAZ file without decoding points.
pub(super) fn survey(path: &Path, file: &str) -> Result<LasSurvey, ImportError> {
    let (reader, header) = open(path, file)?;
    drop(reader);
    let b = header.bounds();
    Ok(LasSurvey {
        points: header.number_of_points(),
        min: [b.min.x, b.min.y, b.min.z],
        max: [b.max.x, b.max.y, b.max.z],
        crs: crs_of(&header),
    })
}

fn crs_of(header: &::las::Header) -> Option<Crs> {
    let mut records: Vec<(u16, Vec<u8>)> = header
        .all_vlrs()
        .filter(|v| v.is_crs())
        .map(|v| (v.record_id, v.data.clone()))
        .collect();
    if records.is_empty() {
        return None;
    }
    records.sort();
    let wkt = records
        .iter()
        .find(|(id, _)| *id == 2112)
        .map(|(_, d)| String::from_utf8_lossy(d).trim_end_matches('\0').to_owned());
    let description = match wkt {
        // `PROJCS["NAD83 / Oregon GIC Lambert (ft)",...` → its first quoted name.
        Some(w) => format!(
            "WKT {:?}",
            w.split('"')
                .nth(1)
                .unwrap_or(&w)
                .chars()
                .take(80)
                .collect::<String>()
        ),
        None => {
            let keys = records
                .iter()
                .find(|(id, _)| *id == 34735)
                .map_or(0, |(_, d)| d.len() / 8);
            format!(
                "GeoTIFF keys ({} keys, {} bytes of records)",
                keys.saturating_sub(1),
                records.iter().map(|r| r.1.len()).sum::<usize>()
            )
        }
    };
    Some(Crs {
        records,
        description,
    })
}

/// Opens the file after the header checks that need no decoder ([`precheck`]): the reader and
/// its header, which declares at least one point whose records fit the file.
fn open(path: &Path, file: &str) -> Result<(::las::Reader, ::las::Header), ImportError> {
    let mut f = File::open(path).map_err(|e| ImportError::io(file, "opening the file", e))?;
    let file_len = f
        .metadata()
        .map_err(|e| ImportError::io(file, "reading file metadata", e))?
        .len();
    let raw_header = precheck(file, &mut f, file_len)?;
    f.seek(SeekFrom::Start(0))
        .map_err(|e| ImportError::io(file, "seeking to the start", e))?;
    let reader = ::las::Reader::new(BufReader::with_capacity(1 << 16, f)).map_err(|e| {
        let context = if is_eof(&e) {
            "reading the LAS VLRs or the LAZ chunk table (the file ends too early: truncated?)"
        } else {
            "reading the LAS header"
        };
        las_err(file, context, e)
    })?;
    let header = reader.header().clone();
    let format = *header.point_format();
    let n = header.number_of_points();
    tracing::debug!(
        file,
        version = %header.version(),
        format = %format,
        compressed = format.is_compressed,
        points = n,
        "LAS header"
    );
    if n == 0 {
        return Err(ImportError::NoPrimitives {
            file: file.to_owned(),
            detail: "the LAS header declares 0 points".to_owned(),
        });
    }
    let offset = u64::from(raw_header.offset_to_point_data);
    let record_len = u64::from(raw_header.point_data_record_length).max(1);
    if !format.is_compressed {
        let available = file_len.saturating_sub(offset);
        if n.saturating_mul(record_len) > available {
            return Err(ImportError::Truncated {
                file: file.to_owned(),
                what: format!("LAS point data ({record_len}-byte records from byte {offset})"),
                expected: n,
                got: available / record_len,
                unit: "points",
            });
        }
    }
    Ok((reader, header))
}

/// Decodes points `done..done + want` of `n` into `pd`; a panic of the decoder on hostile data
/// is caught and reported as corrupt data.
fn read_batch(
    reader: &mut ::las::Reader,
    pd: &mut ::las::PointData,
    file: &str,
    kind: &str,
    done: u64,
    want: u64,
    n: u64,
) -> Result<u64, ImportError> {
    let got = catch_unwind(AssertUnwindSafe(|| reader.fill_points(want, pd)));
    let truncated = || ImportError::Truncated {
        file: file.to_owned(),
        what: format!(
            "{kind} point data (the data ends within points {done}..{})",
            done + want
        ),
        expected: n,
        got: done,
        unit: "points",
    };
    match got {
        Ok(Ok(0)) => Err(ImportError::Truncated {
            file: file.to_owned(),
            what: format!("{kind} point data"),
            expected: n,
            got: done,
            unit: "points",
        }),
        Ok(Ok(k)) => Ok(k),
        Ok(Err(e)) if is_eof(&e) => Err(truncated()),
        Ok(Err(e)) => Err(las_err(
            file,
            format!("decoding points {done}..{}", done + want),
            e,
        )),
        Err(_) => Err(ImportError::Corrupt {
            file: file.to_owned(),
            detail: format!(
                "the {kind} decoder failed on points {done}..{} (corrupt or truncated compressed data)",
                done + want
            ),
        }),
    }
}

/// Appends a decoded batch whose first point is point `first` of the file; coordinates must
/// be finite.
fn push_batch(
    out: &mut PointSetWriter<'_>,
    file: &str,
    pd: &::las::PointData,
    first: u64,
) -> Result<(), ImportError> {
    for (i, ((x, y), z)) in pd.x().zip(pd.y()).zip(pd.z()).enumerate() {
        if let Some(value) = [x, y, z].into_iter().find(|c| !c.is_finite()) {
            return Err(ImportError::NonFinite {
                file: file.to_owned(),
                line: None,
                record: format!(
                    "point {} (check the header scale and offset)",
                    first + i as u64
                ),
                value,
            });
        }
        out.push_position(file, [x, y, z])?;
    }
    if out.keeps_colour()
        && let Some(rgb) = pd.rgb()
    {
        for (r, g, b) in rgb {
            out.push_las_colour(file, [r, g, b])?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::import::points_out::is_8bit;
    use crate::import::{ImportOptions, import_file};
    use crate::source::PointSource;

    fn data(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data/points")
            .join(name)
    }

    fn points(path: &Path) -> (tempfile::TempDir, PointSource) {
        let dir = tempfile::tempdir().unwrap();
        match import_file(path, &ImportOptions::default(), dir.path()) {
            Ok(Source::Points(p)) => (dir, p),
            other => panic!("expected points, got {other:?}"),
        }
    }

    fn max_channel(path: &Path) -> u16 {
        let mut r = ::las::Reader::from_path(path).unwrap();
        let pd = r.read_all().unwrap();
        pd.rgb()
            .unwrap()
            .map(|(r, g, b)| r.max(g).max(b))
            .max()
            .unwrap()
    }

    #[test]
    fn real_autzen_8bit_in_16bit_fields() {
        let path = data("autzen_trim.las");
        assert!(is_8bit(max_channel(&path)));
        let (_d, p) = points(&path);
        assert_eq!(p.positions.len(), 110_000);
        let c = p.colors.expect("autzen has colour");
        assert_eq!(c.len(), 110_000);
        // 8-bit values used as they are: the colour column spans a wide range, not just 0..1.
        assert!(c.iter().flatten().any(|&v| v > 100));
        // Large projected coordinates survive as f64.
        assert!(p.positions[0][0].abs() > 100_000.0, "{:?}", p.positions[0]);
        let mut r = ::las::Reader::from_path(&path).unwrap();
        let first = r.read_points(1).unwrap();
        let x0 = first.x().next().unwrap();
        assert_eq!(p.positions[0][0], x0);
    }

    #[test]
    fn real_lion_true_16bit() {
        let path = data("lion_takanawa.copc.laz");
        let max = max_channel(&path);
        assert!(!is_8bit(max), "max channel {max}");
        let (_d, p) = points(&path);
        assert_eq!(p.positions.len(), 341_989);
        let c = p.colors.expect("lion has colour");
        assert_eq!(c.len(), 341_989);
        assert!(c.iter().flatten().any(|&v| v > 128));
    }

    /// A LAS 1.4 file with its EVLR count set to zero.
    fn without_evlrs(bytes: &[u8]) -> Vec<u8> {
        let mut b = bytes.to_vec();
        b[243..247].copy_from_slice(&0u32.to_le_bytes());
        b
    }

    #[test]
    fn errors() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = std::fs::read(data("autzen_trim.las")).unwrap();
        let run = |name: &str, b: &[u8]| {
            let p = dir.path().join(name);
            std::fs::write(&p, b).unwrap();
            match import_file(&p, &ImportOptions::default(), dir.path()) {
                Err(e) => e.to_string(),
                Ok(s) => panic!("expected error, got {}", s.describe()),
            }
        };
        let e = run("a.las", &bytes[..300]);
        assert!(e.contains("truncated LAS header and VLRs"), "{e}");
        let e = run("b.las", &bytes[..100]);
        assert!(e.contains("truncated LAS header"), "{e}");
        let e = run("c.las", &bytes[..bytes.len() - 1000]);
        assert!(
            e.contains("truncated LAS point data") && e.contains("expected 110000 points"),
            "{e}"
        );
        let mut bad = bytes.clone();
        bad[..4].copy_from_slice(b"LASX");
        let e = run("d.las", &bad[..1000]);
        assert!(e.contains("bad magic"), "{e}");

        let lion = std::fs::read(data("lion_takanawa.copc.laz")).unwrap();
        let cut = &lion[..lion.len() * 6 / 10];
        let e = run("e.laz", cut);
        assert!(e.contains("truncated LAS extended VLRs"), "{e}");
        let e = run("f.laz", &without_evlrs(cut));
        assert!(
            e.contains("truncated LAZ data (the chunk table should be at byte"),
            "{e}"
        );
        // Cut mid-chunk but with a readable chunk table: the decoder itself runs out of data.
        let mut streamed = without_evlrs(cut);
        streamed[941..949].copy_from_slice(&(cut.len() as i64).to_le_bytes());
        streamed.extend_from_slice(&lion[2_735_575..2_735_635]);
        let e = run("g.laz", &streamed);
        assert!(
            e.contains("truncated LAZ point data") && e.contains("expected 341989 points"),
            "{e}"
        );
    }
}
