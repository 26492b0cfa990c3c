//! Run reports: per-cycle records of a client run, the CSV file they are kept in and the charts
//! drawn from them — error against run time, the measure of the whole system.
//!
//! This crate owns the *record* of a run, not its production: the run loop fills one
//! [`CycleRecord`] per client cycle (analysis → presort → request list → integrate arrivals →
//! upload → render) and collects them in a [`RunReport`] with the run's settings ([`RunMeta`]).
//! Everything that judges a run afterwards — [`RunReport::summary`], the chart in
//! [`crate::chart`], comparisons between runs — reads only this type or its CSV file, so the
//! format is defined here once and round-trips exactly ([`RunReport::write_csv`] /
//! [`RunReport::read_csv`]).
//!
//! # CSV format
//!
//! ```text
//! # arbor run report v3
//! # scene=…            (one `# key=value` line per RunMeta field, see META_KEYS)
//! cycle,time_s,analysis_ms,…,differing_share      (the header: CSV_COLUMNS)
//! 0,0.016,1.2,…,                                   (one row per cycle)
//! ```
//!
//! * v2 added `received_twice` after `push_dropped`; a v1 file has one column fewer than v2
//!   and is refused with [`ReportError::ColumnCount`].
//! * v3 added `latency_p50_ms` and `latency_max_ms` at the end; a v2 file (its rows two cells
//!   shorter, its header without them) is read with both empty.
//! * Column names carry their unit (`_s`, `_ms`, `_levels`, …); see [`CSV_COLUMNS`].
//! * Numbers are written with Rust's shortest round-trip formatting, so reading gives back the
//!   identical bits (`NaN`, `inf` and `-inf` included).
//! * An empty cell is `None` (only the optional columns `image_rmse`, `differing_share`,
//!   `latency_p50_ms` and `latency_max_ms`).
//! * Lines starting with `#` are comments; those of the form `# key=value` with a key from
//!   [`META_KEYS`] carry [`RunMeta`]. Every meta key must be present; unknown keys are ignored.
//!   Meta values escape `\` as `\\`, line feed as `\n` and carriage return as `\r`.
//! * `# event=CYCLE,TIME_S,WHAT` lines (any number, before the header) carry [`RunEvent`]s:
//!   what happened to the run between cycles, such as a lost GPU device replaced. `WHAT` is
//!   escaped like a meta value; a reader that does not know them ignores them as comments.
//! * Blank lines are ignored. There is no quoting: every data cell is a number.
//!
//! Malformed files give a [`ReportError`] that names the line (and column, where there is one),
//! never a panic.

#![forbid(unsafe_code)]

mod assets;
pub mod chart;
mod clip;
pub mod compare;

pub use arbor_client_core::summary::ErrorSummary;
pub use assets::FONT;

use std::fmt;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

/// The report's columns, once: name (with its unit), the [`CycleRecord`] field, and the cell
/// type. The CSV header ([`CSV_COLUMNS`]), the writer and the parser are all generated from this
/// one list, so they cannot disagree.
macro_rules! report_columns {
    ($($name:literal => $($field:ident).+ : $kind:ident),* $(,)?) => {
        /// The CSV header, in column order. Units are part of the names: `_s` seconds since the
        /// run started, `_ms` milliseconds of wall time in that phase, `bytes_` / `_bytes` bytes,
        /// `_levels` octree levels of screen-space error; counts are plain. `error_pixels` is
        /// the error-weighted pixel count (levels × pixels), `image_rmse` is in the units of the
        /// image comparison that produced it, `differing_share` is a fraction in 0..=1.
        pub const CSV_COLUMNS: &[&str] = &[$($name),*];

        /// One data row, without the line end.
        fn write_row(out: &mut String, r: &CycleRecord) {
            $(
                write_cell::$kind(out, r.$($field).+);
                out.push(',');
            )*
            out.pop();
        }

        /// One data row's cells, in column order; `width` is the row width the header set (a
        /// v2 report's rows lack the columns v3 added, which are then read as empty).
        fn parse_row(
            line: usize,
            cells: &[&str],
            width: usize,
        ) -> Result<CycleRecord, ReportError> {
            if cells.len() != width {
                return Err(ReportError::ColumnCount {
                    line,
                    found: cells.len(),
                    expected: width,
                });
            }
            let padded: Vec<&str>;
            let cells = if width < CSV_COLUMNS.len() {
                padded = cells.iter().copied().chain([""; V3_COLUMNS]).collect();
                &padded[..]
            } else {
                cells
            };
            let mut c = Cells {
                line,
                cells,
                next: 0,
            };
            let mut r = CycleRecord::default();
            $( r.$($field).+ = c.$kind()?; )*
            Ok(r)
        }
    };
}

report_columns! {
    "cycle" => cycle: u32,
    "time_s" => time_s: f64,
    "analysis_ms" => analysis_ms: f64,
    "presort_ms" => presort_ms: f64,
    "request_ms" => request_ms: f64,
    "integrate_ms" => integrate_ms: f64,
    "upload_ms" => upload_ms: f64,
    "render_ms" => render_ms: f64,
    "requests_sent" => requests_sent: u32,
    "treelets_received" => treelets_received: u32,
    "bytes_received" => bytes_received: u64,
    "treelets_inserted" => treelets_inserted: u32,
    "slots_used" => slots_used: u32,
    "slots_total" => slots_total: u32,
    "evictions" => evictions: u32,
    "dropped" => dropped: u32,
    "pushed" => pushed: u32,
    "push_dropped" => push_dropped: u32,
    "received_twice" => received_twice: u32,
    "upload_ranges" => upload_ranges: u32,
    "upload_bytes" => upload_bytes: u64,
    "samples" => samples: u32,
    "sampled" => sampled: u32,
    "known_share" => known_share: f64,
    "lod_bias" => lod_bias: f64,
    "error_mean_levels" => error.mean: f32,
    "error_p95_levels" => error.p95: f32,
    "error_max_levels" => error.max: f32,
    "error_pixels" => error.error_pixels: f64,
    "image_rmse" => image_rmse: opt_f64,
    "differing_share" => differing_share: opt_f64,
    "latency_p50_ms" => latency_p50_ms: opt_f64,
    "latency_max_ms" => latency_max_ms: opt_f64,
}

/// Cell writers by cell type: Rust's shortest round-trip formatting; `None` is an empty cell.
mod write_cell {
    use std::fmt::Write as _;

    pub(super) fn u32(out: &mut String, v: u32) {
        let _ = write!(out, "{v}");
    }
    pub(super) fn u64(out: &mut String, v: u64) {
        let _ = write!(out, "{v}");
    }
    pub(super) fn f32(out: &mut String, v: f32) {
        let _ = write!(out, "{v}");
    }
    pub(super) fn f64(out: &mut String, v: f64) {
        let _ = write!(out, "{v}");
    }
    pub(super) fn opt_f64(out: &mut String, v: Option<f64>) {
        if let Some(v) = v {
            let _ = write!(out, "{v}");
        }
    }
}

/// The `# key=value` meta keys, in the order they are written.
pub const META_KEYS: [&str; 8] = [
    "scene",
    "server",
    "width",
    "height",
    "feedback_ratio",
    "budget_mib",
    "camera_path",
    "treelet_bytes",
];

/// The comment key of a [`RunEvent`] line.
const EVENT_KEY: &str = "event";

/// The first line of every report file (a comment, so readers need not require it).
const MAGIC_LINE: &str = "# arbor run report v3";

/// Columns a v2 report lacks at the end of each row (`latency_p50_ms`, `latency_max_ms`).
const V3_COLUMNS: usize = 2;

/// What happened in one client cycle.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CycleRecord {
    /// Cycle number, from 0.
    pub cycle: u32,
    /// Seconds since the run started.
    pub time_s: f64,
    /// Wall time of the analysis (feedback) pass, ms.
    pub analysis_ms: f64,
    /// Wall time of presort, ms.
    pub presort_ms: f64,
    /// Wall time of building and sending the request list, ms.
    pub request_ms: f64,
    /// Wall time of integrating arrived treelets into the slot buffer, ms.
    pub integrate_ms: f64,
    /// Wall time of the upload, ms.
    pub upload_ms: f64,
    /// Wall time of rendering, ms.
    pub render_ms: f64,
    /// Items in the request list sent this cycle.
    pub requests_sent: u32,
    /// Treelets received this cycle: taken off the connection by the cycle (the first cycle
    /// also counts the root and any treelet that overtook it while connecting).
    pub treelets_received: u32,
    /// Wire bytes of those treelets.
    pub bytes_received: u64,
    /// Treelets inserted into the slot buffer this cycle.
    pub treelets_inserted: u32,
    /// Slots in use after this cycle.
    pub slots_used: u32,
    /// Slots in the buffer.
    pub slots_total: u32,
    /// Treelets evicted this cycle.
    pub evictions: u32,
    /// Treelets received but dropped this cycle (not inserted).
    pub dropped: u32,
    /// Of the inserted, treelets the server pushed (deep requests).
    pub pushed: u32,
    /// Pushed treelets dropped this cycle: parent not resident, or no free slot.
    pub push_dropped: u32,
    /// Treelets received this cycle that were already resident or already waiting: the link
    /// carried them for nothing (a list built before they arrived, a stream reset too late).
    pub received_twice: u32,
    /// Contiguous ranges uploaded this cycle.
    pub upload_ranges: u32,
    /// Bytes uploaded this cycle.
    pub upload_bytes: u64,
    /// Feedback samples that hit something.
    pub samples: u32,
    /// Pixels the analysis pass sampled this cycle.
    pub sampled: u32,
    /// Share of the view's pixels known (sampled since the view last changed), 0..=1.
    pub known_share: f64,
    /// The LOD bias in effect (raised above the configured one when the view needs more slots
    /// than the budget holds).
    pub lod_bias: f64,
    /// Screen-space error over those samples.
    pub error: ErrorSummary,
    /// RMSE of the rendered image against a reference image, when one was given.
    pub image_rmse: Option<f64>,
    /// Share of pixels that differ from the reference image (0..=1), when one was given.
    pub differing_share: Option<f64>,
    /// Median time from the first list naming a treelet to its arrival, ms, over the treelets
    /// this cycle received that a list had named (pushes are not; `None` when there were none).
    /// Over a link it is the round trip plus what queued in front: the server's backlog, the
    /// link's queue, lists that waited in the client's send buffer.
    pub latency_p50_ms: Option<f64>,
    /// The largest of those latencies, ms.
    pub latency_max_ms: Option<f64>,
}

/// The settings a run was made with.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunMeta {
    /// Scene name on the server.
    pub scene: String,
    /// Server address (URL).
    pub server: String,
    /// Render width, pixels.
    pub width: u32,
    /// Render height, pixels.
    pub height: u32,
    /// Feedback buffer downscale: one sample per `feedback_ratio`² pixels.
    pub feedback_ratio: u32,
    /// Slot-buffer budget, MiB.
    pub budget_mib: f64,
    /// Camera path (file name or description).
    pub camera_path: String,
    /// Bytes per treelet slot.
    pub treelet_bytes: u32,
}

/// A whole run: its settings and one record per cycle, in cycle order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunReport {
    /// The settings of the run.
    pub meta: RunMeta,
    /// One record per cycle.
    pub records: Vec<CycleRecord>,
    /// What happened to the run between cycles, in order.
    pub events: Vec<RunEvent>,
}

/// Something that happened to a run outside its cycles' records: a GPU device lost and
/// replaced, say. Its cycle's record is missing from the report (the cycle did not finish).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunEvent {
    /// The cycle it happened in.
    pub cycle: u32,
    /// Seconds since the run started.
    pub time_s: f64,
    /// What happened, for people.
    pub what: String,
}

impl RunEvent {
    /// The GPU device was lost at `cycle` (`time_s` into the run) for `reason`, and `backend`
    /// took its place within `took`.
    pub fn device_replaced(
        cycle: u32,
        time_s: f64,
        reason: &str,
        backend: &str,
        took: std::time::Duration,
    ) -> Self {
        Self {
            cycle,
            time_s,
            what: format!(
                "the GPU device was lost ({reason}); replaced by {backend} in {:.1} ms",
                took.as_secs_f64() * 1e3
            ),
        }
    }
}

/// Why a report could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// The file could not be created, written or read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: io::Error,
    },
    /// The file has no header row: it is empty or holds only comments and blank lines.
    /// `line` is the line just past the end of the file.
    #[error("line {line}: no header row (expected `{}`)", CSV_COLUMNS.join(","))]
    MissingHeader {
        /// 1-based line number.
        line: usize,
    },
    /// The first non-comment line is not the expected header (this is also what a file whose
    /// header was cut off gives: its first data row is taken for the header). `found` is empty
    /// when the row is too short, `expected` is empty when it is too long.
    #[error("line {line}, column {column}: header has `{found}` where `{expected}` is expected")]
    BadHeader {
        /// 1-based line number.
        line: usize,
        /// 1-based column number of the first mismatch.
        column: usize,
        /// The column name expected there.
        expected: &'static str,
        /// What the file has there.
        found: String,
    },
    /// A data row does not have one cell per column.
    #[error("line {line}: {found} columns, expected {expected}")]
    ColumnCount {
        /// 1-based line number.
        line: usize,
        /// Number of cells in the row.
        found: usize,
        /// Number of columns of the header (the current ones, or a v2 report's).
        expected: usize,
    },
    /// A cell is not a number of its column's type (or is empty in a required column).
    #[error("line {line}, column {column} ({name}): `{value}` is not {kind}")]
    BadValue {
        /// 1-based line number.
        line: usize,
        /// 1-based column number.
        column: usize,
        /// The column's name.
        name: &'static str,
        /// The cell as written.
        value: String,
        /// What the column needs, e.g. "an unsigned 32-bit integer".
        kind: &'static str,
    },
    /// A meta line (`# key=value`) has a value of the wrong type or a bad escape.
    #[error("line {line}: meta `{key}`: {reason}")]
    BadMeta {
        /// 1-based line number.
        line: usize,
        /// The meta key.
        key: &'static str,
        /// What is wrong with the value.
        reason: String,
    },
    /// A meta key is absent from the whole file.
    #[error("meta `{key}` missing (expected a `# {key}=…` line before the header)")]
    MissingMeta {
        /// The meta key.
        key: &'static str,
    },
}

impl RunReport {
    /// Writes the report as CSV (see the module docs for the format), replacing `path`.
    pub fn write_csv(&self, path: &Path) -> Result<(), ReportError> {
        fs::write(path, self.to_csv_string()).map_err(|source| ReportError::Io {
            path: path.to_path_buf(),
            source,
        })
    }

    /// The CSV text [`write_csv`](Self::write_csv) writes.
    pub fn to_csv_string(&self) -> String {
        use fmt::Write as _;
        let m = &self.meta;
        let mut s = String::with_capacity(256 + self.records.len() * 160);
        s.push_str(MAGIC_LINE);
        s.push('\n');
        let meta_values = [
            escape(&m.scene),
            escape(&m.server),
            m.width.to_string(),
            m.height.to_string(),
            m.feedback_ratio.to_string(),
            m.budget_mib.to_string(),
            escape(&m.camera_path),
            m.treelet_bytes.to_string(),
        ];
        for (key, value) in META_KEYS.iter().zip(meta_values) {
            let _ = writeln!(s, "# {key}={value}");
        }
        for e in &self.events {
            let _ = writeln!(
                s,
                "# {EVENT_KEY}={},{},{}",
                e.cycle,
                e.time_s,
                escape(&e.what)
            );
        }
        s.push_str(&CSV_COLUMNS.join(","));
        s.push('\n');
        for r in &self.records {
            write_row(&mut s, r);
            s.push('\n');
        }
        s
    }

    /// Reads a report written by [`write_csv`](Self::write_csv).
    pub fn read_csv(path: &Path) -> Result<RunReport, ReportError> {
        let text = fs::read_to_string(path).map_err(|source| ReportError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_csv_str(&text)
    }

    /// Parses the CSV text of a report (what [`read_csv`](Self::read_csv) does after reading).
    pub fn from_csv_str(text: &str) -> Result<RunReport, ReportError> {
        let mut meta: [Option<String>; META_KEYS.len()] = Default::default();
        let mut meta_lines = [0usize; META_KEYS.len()];
        let mut width = None;
        let mut records = Vec::new();
        let mut events = Vec::new();
        let mut last_line = 0;
        for (index, raw) in text.lines().enumerate() {
            let line = index + 1;
            last_line = line;
            let trimmed = raw.trim();
            if trimmed.is_empty() {
                continue;
            }
            if trimmed.starts_with('#') {
                // From the raw line, so that trailing spaces in a value survive.
                let comment = raw.trim_start()[1..].trim_start();
                if let Some((key, value)) = comment.split_once('=')
                    && key.trim() == EVENT_KEY
                {
                    events.push(parse_event(line, value)?);
                } else if let Some((key, value)) = comment.split_once('=')
                    && let Some(k) = META_KEYS.iter().position(|m| *m == key.trim())
                {
                    let value = unescape(value).map_err(|reason| ReportError::BadMeta {
                        line,
                        key: META_KEYS[k],
                        reason,
                    })?;
                    meta[k] = Some(value);
                    meta_lines[k] = line;
                }
                continue;
            }
            let cells: Vec<&str> = trimmed.split(',').map(str::trim).collect();
            let Some(width) = width else {
                width = Some(check_header(line, &cells)?);
                continue;
            };
            records.push(parse_row(line, &cells, width)?);
        }
        if width.is_none() {
            return Err(ReportError::MissingHeader {
                line: last_line + 1,
            });
        }
        Ok(RunReport {
            meta: build_meta(meta, meta_lines)?,
            records,
            events,
        })
    }

    /// Totals, convergence points and final values of the run.
    pub fn summary(&self) -> RunSummary {
        let sum =
            |f: fn(&CycleRecord) -> u64| self.records.iter().map(f).fold(0u64, u64::saturating_add);
        let first = |hit: fn(&CycleRecord) -> bool| {
            self.records.iter().find(|r| hit(r)).map(|r| Reached {
                cycle: r.cycle,
                time_s: r.time_s,
            })
        };
        let last = self.records.last();
        RunSummary {
            cycles: self.records.len(),
            seconds: last.map_or(0.0, |r| r.time_s),
            requests_sent: sum(|r| r.requests_sent.into()),
            treelets_received: sum(|r| r.treelets_received.into()),
            bytes_received: sum(|r| r.bytes_received),
            treelets_inserted: sum(|r| r.treelets_inserted.into()),
            evictions: sum(|r| r.evictions.into()),
            dropped: sum(|r| r.dropped.into()),
            upload_bytes: sum(|r| r.upload_bytes),
            error_zero: first(|r| r.known_share >= 1.0 && r.error.max == 0.0),
            image_exact: first(|r| r.image_rmse == Some(0.0)),
            final_error: last.map(|r| r.error).unwrap_or_default(),
            final_image_rmse: last.and_then(|r| r.image_rmse),
            final_differing_share: last.and_then(|r| r.differing_share),
            final_slots_used: last.map_or(0, |r| r.slots_used),
            final_slots_total: last.map_or(0, |r| r.slots_total),
            lod_bias_start: self.records.first().map_or(0.0, |r| r.lod_bias),
            lod_bias_final: last.map_or(0.0, |r| r.lod_bias),
            bias_adjusted: self.records.first().and_then(|r0| {
                self.records
                    .iter()
                    .find(|r| r.lod_bias != r0.lod_bias)
                    .map(|r| Reached {
                        cycle: r.cycle,
                        time_s: r.time_s,
                    })
            }),
            latency_p50_range_ms: self.records.iter().filter_map(|r| r.latency_p50_ms).fold(
                None,
                |range, v| match range {
                    None => Some((v, v)),
                    Some((lo, hi)) => Some((v.min(lo), v.max(hi))),
                },
            ),
            latency_max_ms: self
                .records
                .iter()
                .filter_map(|r| r.latency_max_ms)
                .reduce(f64::max),
        }
    }
}

/// The cycle at which something first happened.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reached {
    /// The record's cycle number.
    pub cycle: u32,
    /// The record's time since the run started, s.
    pub time_s: f64,
}

/// Totals, convergence points and final values of a run ([`RunReport::summary`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunSummary {
    /// Number of records.
    pub cycles: usize,
    /// `time_s` of the last record (0 with none).
    pub seconds: f64,
    /// Σ request-list items sent.
    pub requests_sent: u64,
    /// Σ treelets received.
    pub treelets_received: u64,
    /// Σ bytes received.
    pub bytes_received: u64,
    /// Σ treelets inserted.
    pub treelets_inserted: u64,
    /// Σ evictions.
    pub evictions: u64,
    /// Σ dropped treelets.
    pub dropped: u64,
    /// Σ bytes uploaded.
    pub upload_bytes: u64,
    /// First record that knows every pixel of the view and whose `error.max` is 0: nothing in
    /// view is refinable any more.
    pub error_zero: Option<Reached>,
    /// First record whose `image_rmse` is exactly 0 (identical to the reference image).
    pub image_exact: Option<Reached>,
    /// Error summary of the last record.
    pub final_error: ErrorSummary,
    /// Image RMSE of the last record.
    pub final_image_rmse: Option<f64>,
    /// Differing share of the last record.
    pub final_differing_share: Option<f64>,
    /// Slots used after the last record.
    pub final_slots_used: u32,
    /// Slots in the buffer at the last record.
    pub final_slots_total: u32,
    /// LOD bias of the first record.
    pub lod_bias_start: f64,
    /// LOD bias of the last record.
    pub lod_bias_final: f64,
    /// First record whose LOD bias differs from the first's: the target was adjusted to the
    /// memory budget.
    pub bias_adjusted: Option<Reached>,
    /// Smallest and largest of the cycles' median list-to-arrival latencies, ms (`None`: no
    /// cycle received a treelet a list had named, or a v2 report).
    pub latency_p50_range_ms: Option<(f64, f64)>,
    /// Largest list-to-arrival latency of the run, ms.
    pub latency_max_ms: Option<f64>,
}

impl fmt::Display for RunSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mb = self.bytes_received as f64 / 1e6;
        write!(f, "cycles:   {} over {:.3} s", self.cycles, self.seconds)?;
        if self.seconds > 0.0 {
            write!(f, " ({:.1} cycles/s)", self.cycles as f64 / self.seconds)?;
        }
        writeln!(f)?;
        write!(
            f,
            "received: {} treelets, {:.3} MB in {} requests",
            self.treelets_received, mb, self.requests_sent
        )?;
        if self.seconds > 0.0 {
            write!(f, " ({:.3} MB/s)", mb / self.seconds)?;
        }
        writeln!(f)?;
        if let (Some((lo, hi)), Some(max)) = (self.latency_p50_range_ms, self.latency_max_ms) {
            writeln!(
                f,
                "latency:  list to arrival, cycle medians {lo:.1}–{hi:.1} ms, largest {max:.1} ms"
            )?;
        }
        writeln!(
            f,
            "slots:    {} inserted, {} evicted, {} dropped; {}/{} used at the end; {:.3} MB uploaded",
            self.treelets_inserted,
            self.evictions,
            self.dropped,
            self.final_slots_used,
            self.final_slots_total,
            self.upload_bytes as f64 / 1e6
        )?;
        let e = &self.final_error;
        write!(
            f,
            "error:    final mean {:.3} / p95 {:.3} / max {:.3} levels, {:.0} error-pixels; ",
            e.mean, e.p95, e.max, e.error_pixels
        )?;
        match self.error_zero {
            Some(r) => writeln!(f, "max first 0 at cycle {} ({:.3} s)", r.cycle, r.time_s)?,
            None => writeln!(f, "max never 0 with the whole view known")?,
        }
        if let Some(r) = self.bias_adjusted {
            writeln!(
                f,
                "target:   adjusted to the memory budget from cycle {} ({:.3} s): LOD bias {} -> {:.3}",
                r.cycle, r.time_s, self.lod_bias_start, self.lod_bias_final
            )?;
        }
        write!(f, "image:    ")?;
        match (self.final_image_rmse, self.final_differing_share) {
            (None, None) if self.image_exact.is_none() => write!(f, "no reference"),
            (rmse, share) => {
                match rmse {
                    Some(v) => write!(f, "final RMSE {v:.4}")?,
                    None => write!(f, "final RMSE -")?,
                }
                match share {
                    Some(v) => write!(f, ", {:.3} % of pixels differ; ", v * 100.0)?,
                    None => write!(f, "; ")?,
                }
                match self.image_exact {
                    Some(r) => write!(f, "RMSE first 0 at cycle {} ({:.3} s)", r.cycle, r.time_s),
                    None => write!(f, "RMSE never 0"),
                }
            }
        }
    }
}

/// Checks the header row: the current columns, or a v2 report's (without the last
/// [`V3_COLUMNS`]). Returns the width every data row must have.
fn check_header(line: usize, cells: &[&str]) -> Result<usize, ReportError> {
    let v2 = &CSV_COLUMNS[..CSV_COLUMNS.len() - V3_COLUMNS];
    if cells == v2 {
        return Ok(v2.len());
    }
    for column in 0..cells.len().max(CSV_COLUMNS.len()) {
        let expected = CSV_COLUMNS.get(column).copied().unwrap_or("");
        let found = cells.get(column).copied().unwrap_or("");
        if expected != found {
            return Err(ReportError::BadHeader {
                line,
                column: column + 1,
                expected,
                found: found.to_string(),
            });
        }
    }
    Ok(CSV_COLUMNS.len())
}

/// Reads the cells of one data row in column order.
struct Cells<'a> {
    line: usize,
    cells: &'a [&'a str],
    next: usize,
}

impl Cells<'_> {
    fn take<T: std::str::FromStr>(&mut self, kind: &'static str) -> Result<T, ReportError> {
        let column = self.next;
        self.next += 1;
        let value = self.cells[column];
        value.parse().map_err(|_| ReportError::BadValue {
            line: self.line,
            column: column + 1,
            name: CSV_COLUMNS[column],
            value: value.to_string(),
            kind,
        })
    }
    fn u32(&mut self) -> Result<u32, ReportError> {
        self.take("an unsigned 32-bit integer")
    }
    fn u64(&mut self) -> Result<u64, ReportError> {
        self.take("an unsigned 64-bit integer")
    }
    fn f32(&mut self) -> Result<f32, ReportError> {
        self.take("a number")
    }
    fn f64(&mut self) -> Result<f64, ReportError> {
        self.take("a number")
    }
    fn opt_f64(&mut self) -> Result<Option<f64>, ReportError> {
        if self.cells[self.next].is_empty() {
            self.next += 1;
            return Ok(None);
        }
        self.take("a number or empty").map(Some)
    }
}

fn build_meta(
    values: [Option<String>; META_KEYS.len()],
    lines: [usize; META_KEYS.len()],
) -> Result<RunMeta, ReportError> {
    let [
        scene,
        server,
        width,
        height,
        feedback_ratio,
        budget_mib,
        camera_path,
        treelet_bytes,
    ] = values;
    let need =
        |v: Option<String>, k: usize| v.ok_or(ReportError::MissingMeta { key: META_KEYS[k] });
    fn num<T: std::str::FromStr>(v: &str, k: usize, line: usize) -> Result<T, ReportError> {
        v.trim().parse().map_err(|_| ReportError::BadMeta {
            line,
            key: META_KEYS[k],
            reason: format!("`{v}` is not a number of the right type"),
        })
    }
    Ok(RunMeta {
        scene: need(scene, 0)?,
        server: need(server, 1)?,
        width: num(&need(width, 2)?, 2, lines[2])?,
        height: num(&need(height, 3)?, 3, lines[3])?,
        feedback_ratio: num(&need(feedback_ratio, 4)?, 4, lines[4])?,
        budget_mib: num(&need(budget_mib, 5)?, 5, lines[5])?,
        camera_path: need(camera_path, 6)?,
        treelet_bytes: num(&need(treelet_bytes, 7)?, 7, lines[7])?,
    })
}

/// A `# event=CYCLE,TIME_S,WHAT` line's value.
fn parse_event(line: usize, value: &str) -> Result<RunEvent, ReportError> {
    let bad = |reason: String| ReportError::BadMeta {
        line,
        key: EVENT_KEY,
        reason,
    };
    let mut parts = value.splitn(3, ',');
    let (Some(cycle), Some(time_s), Some(what)) = (parts.next(), parts.next(), parts.next()) else {
        return Err(bad("expected `CYCLE,TIME_S,WHAT`".into()));
    };
    Ok(RunEvent {
        cycle: cycle
            .trim()
            .parse()
            .map_err(|_| bad(format!("`{cycle}` is not a cycle number")))?,
        time_s: time_s
            .trim()
            .parse()
            .map_err(|_| bad(format!("`{time_s}` is not a time in seconds")))?,
        what: unescape(what).map_err(bad)?,
    })
}

fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for ch in s.chars() {
        match ch {
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            c => out.push(c),
        }
    }
    out
}

fn unescape(s: &str) -> Result<String, String> {
    let mut out = String::with_capacity(s.len());
    let mut chars = s.chars();
    while let Some(ch) = chars.next() {
        if ch != '\\' {
            out.push(ch);
            continue;
        }
        match chars.next() {
            Some('\\') => out.push('\\'),
            Some('n') => out.push('\n'),
            Some('r') => out.push('\r'),
            Some(other) => return Err(format!("unknown escape `\\{other}`")),
            None => return Err("value ends in a lone `\\`".to_string()),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta() -> RunMeta {
        RunMeta {
            scene: "lille, street=1 \\ \"quoted\"\nsecond line ".to_string(),
            server: "quic://127.0.0.1:4433/lille".to_string(),
            width: 1920,
            height: 1080,
            feedback_ratio: 8,
            budget_mib: 512.5,
            camera_path: "paths/orbit #2.toml".to_string(),
            treelet_bytes: 65536,
        }
    }

    fn record(cycle: u32) -> CycleRecord {
        CycleRecord {
            cycle,
            time_s: f64::from(cycle) * 0.016_666,
            analysis_ms: 1.25,
            presort_ms: 0.1,
            request_ms: 0.03,
            integrate_ms: 2.0,
            upload_ms: 0.7,
            render_ms: 9.9,
            requests_sent: 40,
            treelets_received: 12,
            bytes_received: 786_432,
            treelets_inserted: 11,
            slots_used: cycle.wrapping_add(100),
            slots_total: 8192,
            evictions: 1,
            dropped: 1,
            pushed: 2,
            push_dropped: 0,
            received_twice: 4,
            upload_ranges: 3,
            upload_bytes: 720_896,
            samples: 32_400,
            sampled: 40_000,
            known_share: 1.0,
            lod_bias: 1.0,
            error: ErrorSummary {
                mean: 1.5,
                p95: 3.0,
                max: 4.0,
                error_pixels: 1.0e6,
            },
            image_rmse: Some(0.125),
            differing_share: None,
            latency_p50_ms: Some(52.5),
            latency_max_ms: Some(131.0),
        }
    }

    fn same_bits(a: &RunReport, b: &RunReport) -> bool {
        a.to_csv_string() == b.to_csv_string()
    }

    #[test]
    fn csv_round_trip_with_nones_and_extremes() {
        let mut extreme = record(u32::MAX);
        extreme.time_s = f64::MAX;
        extreme.analysis_ms = f64::MIN_POSITIVE;
        extreme.presort_ms = 5e-324; // smallest subnormal
        extreme.request_ms = -0.0;
        extreme.integrate_ms = f64::INFINITY;
        extreme.upload_ms = f64::NEG_INFINITY;
        extreme.render_ms = 0.1 + 0.2;
        extreme.bytes_received = u64::MAX;
        extreme.upload_bytes = u64::MAX;
        extreme.requests_sent = u32::MAX;
        extreme.error = ErrorSummary {
            mean: f32::MAX,
            p95: f32::MIN_POSITIVE,
            max: 1.0e-45, // smallest f32 subnormal
            error_pixels: 1.0e300,
        };
        extreme.image_rmse = None;
        extreme.differing_share = Some(1.0 / 3.0);
        let mut none = record(1);
        none.image_rmse = None;
        none.differing_share = None;
        let report = RunReport {
            meta: meta(),
            records: vec![record(0), none, extreme, CycleRecord::default()],
            events: Vec::new(),
        };
        let path = temp_path("round_trip.csv");
        report.write_csv(&path).unwrap();
        let back = RunReport::read_csv(&path).unwrap();
        let _ = fs::remove_file(&path);
        assert_eq!(back, report);
        // -0.0 == 0.0 for PartialEq; the text (and so the sign) must survive too.
        assert!(back.records[2].request_ms.is_sign_negative());
        assert!(same_bits(&back, &report));
    }

    #[test]
    fn csv_round_trips_nan() {
        let mut r = record(0);
        r.time_s = f64::NAN;
        r.error.mean = f32::NAN;
        r.image_rmse = Some(f64::NAN);
        let report = RunReport {
            meta: RunMeta::default(),
            records: vec![r],
            events: Vec::new(),
        };
        let back = RunReport::from_csv_str(&report.to_csv_string()).unwrap();
        assert!(back.records[0].time_s.is_nan());
        assert!(back.records[0].error.mean.is_nan());
        assert!(back.records[0].image_rmse.unwrap().is_nan());
        assert!(same_bits(&back, &report));
    }

    #[test]
    fn csv_header_has_units_and_empty_cells_for_none() {
        let mut r = record(7);
        r.image_rmse = None;
        r.latency_p50_ms = None;
        r.latency_max_ms = None;
        let text = RunReport {
            meta: meta(),
            records: vec![r],
            events: Vec::new(),
        }
        .to_csv_string();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], MAGIC_LINE);
        assert!(lines[1].starts_with("# scene=lille, street=1 \\\\ \"quoted\"\\nsecond line "));
        assert_eq!(lines[9], CSV_COLUMNS.join(","));
        assert!(lines[9].contains("time_s,analysis_ms") && lines[9].contains("image_rmse"));
        assert!(lines[10].starts_with("7,"));
        assert!(lines[10].ends_with(",,,,"), "{}", lines[10]);
        assert_eq!(lines.len(), 11);
    }

    #[test]
    fn empty_report_round_trips() {
        let report = RunReport {
            meta: meta(),
            records: vec![],
            events: Vec::new(),
        };
        let back = RunReport::from_csv_str(&report.to_csv_string()).unwrap();
        assert_eq!(back, report);
    }

    #[test]
    fn events_round_trip_and_bad_ones_name_their_line() {
        let report = RunReport {
            meta: meta(),
            records: vec![record(0), record(2)],
            events: vec![
                RunEvent {
                    cycle: 1,
                    time_s: 0.125,
                    what: "the GPU device was lost (destroyed), 3, 4\nreplaced".into(),
                },
                RunEvent {
                    cycle: 7,
                    time_s: f64::from(u32::MAX),
                    what: String::new(),
                },
            ],
        };
        let text = report.to_csv_string();
        assert!(text.contains("# event=1,0.125,the GPU device"), "{text}");
        assert_eq!(RunReport::from_csv_str(&text).unwrap(), report);
        // A file from before events, and one whose event lines are cut short.
        let plain = RunReport {
            events: Vec::new(),
            ..report.clone()
        };
        assert_eq!(
            RunReport::from_csv_str(&plain.to_csv_string()).unwrap(),
            plain
        );
        for (bad, reason) in [
            ("# event=1,0.125", "expected `CYCLE,TIME_S,WHAT`"),
            ("# event=x,0.125,lost", "`x` is not a cycle number"),
            ("# event=1,soon,lost", "`soon` is not a time in seconds"),
            ("# event=1,0.5,lost\\", "value ends in a lone `\\`"),
        ] {
            let text = good_text().replacen("cycle,", &format!("{bad}\ncycle,"), 1);
            let line = text.lines().position(|l| l == bad).unwrap() + 1;
            match RunReport::from_csv_str(&text) {
                Err(ReportError::BadMeta {
                    line: l,
                    key: "event",
                    reason: r,
                }) => {
                    assert_eq!((l, r.as_str()), (line, reason), "{bad}");
                }
                other => panic!("{bad}: {other:?}"),
            }
        }
    }

    #[test]
    fn crlf_and_blank_lines_are_accepted() {
        let report = RunReport {
            meta: meta(),
            records: vec![record(0), record(1)],
            events: Vec::new(),
        };
        let text = report.to_csv_string().replace('\n', "\r\n\r\n");
        assert_eq!(RunReport::from_csv_str(&text).unwrap(), report);
    }

    fn good_text() -> String {
        RunReport {
            meta: meta(),
            records: vec![record(0), record(1)],
            events: Vec::new(),
        }
        .to_csv_string()
    }

    /// Replaces line `n` (1-based) of the good text.
    fn with_line(n: usize, new: &str) -> String {
        let mut lines: Vec<String> = good_text().lines().map(str::to_string).collect();
        lines[n - 1] = new.to_string();
        lines.join("\n")
    }

    #[test]
    fn a_v2_report_is_read_with_the_latencies_empty() {
        let n = CSV_COLUMNS.len();
        let v2: Vec<String> = good_text()
            .lines()
            .map(|l| {
                if l == MAGIC_LINE {
                    "# arbor run report v2".to_string()
                } else if l.starts_with('#') {
                    l.to_string()
                } else {
                    let cells: Vec<&str> = l.split(',').collect();
                    assert_eq!(cells.len(), n);
                    cells[..n - V3_COLUMNS].join(",")
                }
            })
            .collect();
        let read = RunReport::from_csv_str(&v2.join("\n")).unwrap();
        let mut expected = vec![record(0), record(1)];
        for r in &mut expected {
            r.latency_p50_ms = None;
            r.latency_max_ms = None;
        }
        assert_eq!(read.records, expected);
        assert_eq!(read.meta, meta());
        // A v3 header with a row of v2's width is an error, not a silent padding.
        let current = good_text();
        let row = current.lines().nth(10).unwrap();
        let short: Vec<&str> = row.split(',').take(n - V3_COLUMNS).collect();
        let err = RunReport::from_csv_str(&with_line(11, &short.join(","))).unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::ColumnCount { line: 11, found, expected }
                    if found == n - V3_COLUMNS && expected == n
            ),
            "{err:?}"
        );
        // And a v2 header with a v3 row.
        let mut mixed = v2.clone();
        mixed[10] = row.to_string();
        let err = RunReport::from_csv_str(&mixed.join("\n")).unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::ColumnCount { line: 11, found, expected }
                    if found == n && expected == n - V3_COLUMNS
            ),
            "{err:?}"
        );
    }

    #[test]
    fn wrong_column_count_names_the_line() {
        let good = good_text();
        let row = good.lines().nth(10).unwrap();
        let err = RunReport::from_csv_str(&with_line(11, &format!("{row},5"))).unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::ColumnCount { line: 11, found, expected }
                    if found == CSV_COLUMNS.len() + 1 && expected == CSV_COLUMNS.len()
            ),
            "{err:?}"
        );
        let n = CSV_COLUMNS.len();
        assert_eq!(
            err.to_string(),
            format!("line 11: {} columns, expected {n}", n + 1)
        );
        let short = row.rsplit_once(',').unwrap().0;
        let err = RunReport::from_csv_str(&with_line(11, short)).unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::ColumnCount { line: 11, found, .. } if found == n - 1
            ),
            "{err:?}"
        );
    }

    #[test]
    fn non_number_names_line_and_column() {
        let good = good_text();
        let row = good.lines().nth(11).unwrap();
        let mut cells: Vec<&str> = row.split(',').collect();
        cells[10] = "lots";
        let err = RunReport::from_csv_str(&with_line(12, &cells.join(","))).unwrap_err();
        match &err {
            ReportError::BadValue {
                line: 12,
                column: 11,
                name: "bytes_received",
                value,
                ..
            } => {
                assert_eq!(value, "lots")
            }
            other => panic!("{other:?}"),
        }
        assert!(
            err.to_string()
                .starts_with("line 12, column 11 (bytes_received): `lots`")
        );
        // Negative counts, fractions in integer columns and empty required cells are errors too.
        for (col, bad) in [(0, "-1"), (8, "1.5"), (1, ""), (19, "x")] {
            let mut cells: Vec<&str> = row.split(',').collect();
            cells[col] = bad;
            let err = RunReport::from_csv_str(&with_line(12, &cells.join(","))).unwrap_err();
            assert!(
                matches!(err, ReportError::BadValue { line: 12, column, .. } if column == col + 1),
                "{err:?}"
            );
        }
    }

    #[test]
    fn missing_or_wrong_header_names_line_and_column() {
        // Header line (10) removed: the first data row is taken for the header.
        let text: String = good_text()
            .lines()
            .enumerate()
            .filter(|(i, _)| *i != 9)
            .map(|(_, l)| format!("{l}\n"))
            .collect();
        let err = RunReport::from_csv_str(&text).unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::BadHeader {
                    line: 10,
                    column: 1,
                    expected: "cycle",
                    ..
                }
            ),
            "{err:?}"
        );
        // A renamed column.
        let header = CSV_COLUMNS.join(",").replace("upload_ms", "upload_s");
        let err = RunReport::from_csv_str(&with_line(10, &header)).unwrap_err();
        assert!(
            matches!(err, ReportError::BadHeader { line: 10, column: 7, expected: "upload_ms", ref found } if found == "upload_s"),
            "{err:?}"
        );
        // A header with a column too many.
        let err =
            RunReport::from_csv_str(&with_line(10, &format!("{},extra", CSV_COLUMNS.join(","))))
                .unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::BadHeader {
                    line: 10,
                    column,
                    expected: "",
                    ..
                } if column == CSV_COLUMNS.len() + 1
            ),
            "{err:?}"
        );
        // Only comments, or nothing at all.
        let err = RunReport::from_csv_str("# scene=x\n\n").unwrap_err();
        assert!(
            matches!(err, ReportError::MissingHeader { line: 3 }),
            "{err:?}"
        );
        let err = RunReport::from_csv_str("").unwrap_err();
        assert!(
            matches!(err, ReportError::MissingHeader { line: 1 }),
            "{err:?}"
        );
    }

    #[test]
    fn bad_or_missing_meta_is_an_error() {
        let err = RunReport::from_csv_str(&with_line(4, "# width=wide")).unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::BadMeta {
                    line: 4,
                    key: "width",
                    ..
                }
            ),
            "{err:?}"
        );
        let err = RunReport::from_csv_str(&with_line(2, "# scene=a\\qb")).unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::BadMeta {
                    line: 2,
                    key: "scene",
                    ..
                }
            ),
            "{err:?}"
        );
        let err = RunReport::from_csv_str(&with_line(9, "# a comment")).unwrap_err();
        assert!(
            matches!(
                err,
                ReportError::MissingMeta {
                    key: "treelet_bytes"
                }
            ),
            "{err:?}"
        );
    }

    #[test]
    fn read_missing_file_is_io_error() {
        let err = RunReport::read_csv(Path::new("/nonexistent/arbor/run.csv")).unwrap_err();
        assert!(matches!(err, ReportError::Io { .. }), "{err:?}");
        assert!(err.to_string().starts_with("/nonexistent/arbor/run.csv: "));
    }

    #[test]
    fn summary_totals_and_convergence() {
        let mut records: Vec<CycleRecord> = (0..5).map(record).collect();
        records[3].error = ErrorSummary::default();
        records[4].error = ErrorSummary::default();
        records[4].image_rmse = Some(0.0);
        records[4].differing_share = Some(0.0);
        // Cycle 2 does not know the whole view yet: its error 0 does not count.
        records[2].error = ErrorSummary::default();
        records[2].known_share = 0.5;
        records[4].lod_bias = 2f64.sqrt();
        let s = RunReport {
            meta: meta(),
            records,
            events: Vec::new(),
        }
        .summary();
        assert_eq!(s.cycles, 5);
        assert_eq!(s.seconds, 4.0 * 0.016_666);
        assert_eq!(s.treelets_received, 60);
        assert_eq!(s.bytes_received, 5 * 786_432);
        assert_eq!(
            s.error_zero,
            Some(Reached {
                cycle: 3,
                time_s: 3.0 * 0.016_666
            })
        );
        assert_eq!(
            s.image_exact,
            Some(Reached {
                cycle: 4,
                time_s: 4.0 * 0.016_666
            })
        );
        assert_eq!((s.final_slots_used, s.final_slots_total), (104, 8192));
        let text = s.to_string();
        assert!(text.contains("max first 0 at cycle 3"), "{text}");
        assert!(text.contains("RMSE first 0 at cycle 4"), "{text}");
        assert_eq!(s.bias_adjusted.map(|r| r.cycle), Some(4));
        assert!(text.contains("LOD bias 1 -> 1.414"), "{text}");

        // Latencies: the range of the cycles' medians and the largest, over the cycles that
        // received listed treelets.
        let mut records: Vec<CycleRecord> = (0..3).map(record).collect();
        (records[0].latency_p50_ms, records[0].latency_max_ms) = (Some(30.0), Some(45.5));
        (records[1].latency_p50_ms, records[1].latency_max_ms) = (None, None);
        (records[2].latency_p50_ms, records[2].latency_max_ms) = (Some(12.25), Some(90.0));
        let s = RunReport {
            meta: meta(),
            records,
            events: Vec::new(),
        }
        .summary();
        assert_eq!(s.latency_p50_range_ms, Some((12.25, 30.0)));
        assert_eq!(s.latency_max_ms, Some(90.0));
        let text = s.to_string();
        assert!(
            text.contains("latency:  list to arrival, cycle medians 12.2–30.0 ms, largest 90.0 ms"),
            "{text}"
        );

        let empty = RunReport::default().summary();
        assert_eq!(empty, RunSummary::default());
        let text = empty.to_string();
        assert!(
            text.contains("max first 0") || text.contains("never 0"),
            "{text}"
        );
        assert!(text.contains("no reference"), "{text}");
        assert!(!text.contains("latency"), "{text}");

        let mut big = record(0);
        big.bytes_received = u64::MAX;
        let s = RunReport {
            meta: meta(),
            records: vec![big.clone(), big],
            events: Vec::new(),
        }
        .summary();
        assert_eq!(s.bytes_received, u64::MAX);
    }

    pub(crate) fn temp_path(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("arbor-report-{}-{name}", std::process::id()))
    }
}
