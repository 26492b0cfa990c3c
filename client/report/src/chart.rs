//! Charts of a run: error and traffic against run time, as a PNG.
//!
//! This module owns the picture of a [`RunReport`]; it reads nothing but the report, so a chart
//! can be drawn during a run, after it, or from a CSV file read back with
//! [`RunReport::read_csv`]. One image, [`WIDTH`]×[`HEIGHT`] pixels, two or three panels
//! sharing the x axis (run time, s):
//!
//! * top: screen-space error mean, p95 and max (octree levels, left axis) and, when any record
//!   has one, image RMSE against the reference (right axis);
//! * bottom: received traffic in MB/s (10⁶ bytes per second: the cycle's `bytes_received`
//!   divided by the time since the previous record, or since the run started for the first; a
//!   record whose time did not advance uses the sum of its phase durations instead, and is left
//!   out when that is 0 too),
//!   and slots used and slots total (right axis);
//! * when any record has list-to-arrival latencies (report format v3), a third panel below:
//!   each cycle's median and largest latency in ms, the time from the list that named a
//!   treelet to its arrival — where a run waits on the link's queue rather than on its own
//!   cycles. Reports without them (v2 files, runs that received nothing listed) keep the two
//!   panels and their layout.
//!
//! Text is drawn by plotters' `ab_glyph` backend, which has no system font lookup: the DejaVu
//! Sans font in `client/assets/` is compiled in and registered on first use. The picture is
//! rendered into an in-memory RGB buffer and encoded with the `image` crate (plotters' own
//! `bitmap_encoder` would pull in an older `image`).
//!
//! Every series is clipped to its panel's plotting area (`clip.rs`), so a spike never crosses
//! into another panel; every series has its own colour.
//!
//! Degenerate reports never panic: values that are not finite are left out of the series,
//! empty or zero-width axis ranges are widened, and values and ranges are clipped to ±10¹². An empty
//! report still gives an `Ok` chart with empty axes and a "no cycles recorded" note; a
//! one-record report shows its values as single points.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

use crate::assets::FONT;
use crate::clip::{PlotArea, draw_clipped_line, legend_line};
use crate::{CycleRecord, RunReport};

/// Width of the chart, pixels.
pub const WIDTH: u32 = 1200;
/// Height of the chart, pixels.
pub const HEIGHT: u32 = 800;

/// Largest magnitude an axis range may reach; plotters' tick computation needs finite spans.
const RANGE_LIMIT: f64 = 1e12;

/// Width of the right axis area of every panel, kept even when a panel has no right axis so
/// that the panels' x axes line up.
const RIGHT_AXIS: u32 = 80;

/// Series drawn with markers too when a report has fewer records than this.
const MARKER_BELOW: usize = 30;

/// Why a chart could not be drawn.
#[derive(Debug, thiserror::Error)]
pub enum ChartError {
    /// The embedded font was rejected by plotters' font loader.
    #[error("the embedded chart font could not be registered")]
    Font,
    /// plotters failed while drawing into the in-memory buffer.
    #[error("drawing the chart: {0}")]
    Draw(String),
    /// The PNG could not be encoded or written.
    #[error("{}: {source}", path.display())]
    Write {
        /// The output file.
        path: PathBuf,
        /// The underlying error (encoding or I/O).
        #[source]
        source: ::image::ImageError,
    },
}

pub(crate) fn draw_err(e: impl std::fmt::Display) -> ChartError {
    ChartError::Draw(e.to_string())
}

/// Registers the embedded font under plotters' `sans-serif` family, once per process.
pub(crate) fn ensure_font() -> Result<(), ChartError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok =
        *REGISTERED.get_or_init(|| register_font("sans-serif", FontStyle::Normal, FONT).is_ok());
    if ok { Ok(()) } else { Err(ChartError::Font) }
}

/// Draws `report` as a [`WIDTH`]×[`HEIGHT`] PNG at `path` (replacing it) with `title` on top.
///
/// Returns `Ok` for every report, including an empty one (empty axes and a note); errors are
/// only the font, drawing or writing the file.
pub fn draw(report: &RunReport, path: &Path, title: &str) -> Result<(), ChartError> {
    save_png(&render_rgb(report, title)?, path)
}

/// Writes a packed RGB8 buffer of [`WIDTH`]×[`HEIGHT`] pixels as a PNG at `path`.
pub(crate) fn save_png(buf: &[u8], path: &Path) -> Result<(), ChartError> {
    ::image::save_buffer_with_format(
        path,
        buf,
        WIDTH,
        HEIGHT,
        ::image::ExtendedColorType::Rgb8,
        ::image::ImageFormat::Png,
    )
    .map_err(|source| ChartError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// Renders the chart into a packed RGB8 buffer of [`WIDTH`]×[`HEIGHT`] pixels.
pub fn render_rgb(report: &RunReport, title: &str) -> Result<Vec<u8>, ChartError> {
    render_with_plot_areas(report, title).map(|(buf, _)| buf)
}

/// [`render_rgb`], also returning the plotting areas of the panels, top to bottom.
pub(crate) fn render_with_plot_areas(
    report: &RunReport,
    title: &str,
) -> Result<(Vec<u8>, Vec<PlotArea>), ChartError> {
    ensure_font()?;
    let mut areas = Vec::new();
    let mut buf = vec![0u8; WIDTH as usize * HEIGHT as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let body = root.titled(title, ("sans-serif", 26)).map_err(draw_err)?;
        let data = Series::from_report(&report.records);
        let latency = !(data.latency_p50.is_empty() && data.latency_max.is_empty());
        let panels = body.split_evenly((if latency { 3 } else { 2 }, 1));
        areas.push(draw_error_panel(&panels[0], &data)?);
        areas.push(draw_traffic_panel(&panels[1], &data, !latency)?);
        if latency {
            areas.push(draw_latency_panel(&panels[2], &data)?);
        }
        if report.records.is_empty() {
            let style = ("sans-serif", 28)
                .into_font()
                .color(&RGBColor(120, 120, 120));
            root.draw(&Text::new(
                "no cycles recorded",
                (WIDTH as i32 / 2 - 110, 120),
                style,
            ))
            .map_err(draw_err)?;
        }
        root.present().map_err(draw_err)?;
    }
    Ok((buf, areas))
}

type Points = Vec<(f64, f64)>;

/// The report's columns as (time, value) points, non-finite values left out.
struct Series {
    x: Range<f64>,
    mean: Points,
    p95: Points,
    max: Points,
    rmse: Points,
    mb_per_s: Points,
    slots_used: Points,
    slots_total: Points,
    latency_p50: Points,
    latency_max: Points,
    markers: bool,
}

impl Series {
    fn from_report(records: &[CycleRecord]) -> Self {
        let pts = |f: &dyn Fn(&CycleRecord) -> Option<f64>| -> Points {
            records
                .iter()
                .filter_map(|r| Some((r.time_s, f(r)?)))
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .map(|(x, y)| (clip(x), clip(y)))
                .collect()
        };
        let mut mb_per_s = Vec::new();
        let mut prev_t: Option<f64> = None;
        for r in records {
            // The first record's interval starts with the run.
            let mut dt = r.time_s - prev_t.unwrap_or(0.0);
            if !(dt > 0.0) || !dt.is_finite() {
                dt = (r.analysis_ms
                    + r.presort_ms
                    + r.request_ms
                    + r.integrate_ms
                    + r.upload_ms
                    + r.render_ms)
                    / 1000.0;
            }
            let rate = r.bytes_received as f64 / 1e6 / dt;
            if dt > 0.0 && rate.is_finite() && r.time_s.is_finite() {
                mb_per_s.push((clip(r.time_s), clip(rate)));
            }
            if r.time_s.is_finite() {
                prev_t = Some(r.time_s);
            }
        }
        Series {
            x: axis_range(records.iter().map(|r| r.time_s), true),
            mean: pts(&|r| Some(f64::from(r.error.mean))),
            p95: pts(&|r| Some(f64::from(r.error.p95))),
            max: pts(&|r| Some(f64::from(r.error.max))),
            rmse: pts(&|r| r.image_rmse),
            mb_per_s,
            slots_used: pts(&|r| Some(f64::from(r.slots_used))),
            slots_total: pts(&|r| Some(f64::from(r.slots_total))),
            latency_p50: pts(&|r| r.latency_p50_ms),
            latency_max: pts(&|r| r.latency_max_ms),
            markers: records.len() < MARKER_BELOW,
        }
    }
}

/// Clips a finite value to ±[`RANGE_LIMIT`], so that every point lies inside its axis range
/// (plotters' pixel mapping overflows for points far outside it).
pub(crate) fn clip(v: f64) -> f64 {
    v.clamp(-RANGE_LIMIT, RANGE_LIMIT)
}

/// A plotting range over the finite `values` (and 0 when `include_zero`), padded 5 % above,
/// widened when empty or zero-width, clipped to ±[`RANGE_LIMIT`].
pub(crate) fn axis_range(values: impl Iterator<Item = f64>, include_zero: bool) -> Range<f64> {
    let (mut lo, mut hi) = if include_zero {
        (0.0, 0.0)
    } else {
        (f64::INFINITY, f64::NEG_INFINITY)
    };
    for v in values.filter(|v| v.is_finite()) {
        lo = lo.min(clip(v));
        hi = hi.max(clip(v));
    }
    if lo > hi {
        return 0.0..1.0;
    }
    let span = hi - lo;
    if span <= f64::EPSILON * hi.abs().max(lo.abs()).max(1e-300) {
        let pad = (hi.abs() * 0.1).max(1.0);
        return if include_zero && lo >= 0.0 {
            lo..hi + pad
        } else {
            lo - pad..hi + pad
        };
    }
    let top = hi + span * 0.05;
    let bottom = if include_zero && lo == 0.0 {
        0.0
    } else {
        lo - span * 0.05
    };
    bottom..top
}

const MEAN: RGBColor = RGBColor(31, 119, 180);
const P95: RGBColor = RGBColor(255, 127, 14);
const MAX: RGBColor = RGBColor(214, 39, 40);
const RMSE: RGBColor = RGBColor(148, 103, 189);
const RATE: RGBColor = RGBColor(44, 160, 44);
// Every series has its own colour, so a pixel tells which series (and panel) it belongs to.
const USED: RGBColor = RGBColor(23, 190, 207);
const TOTAL: RGBColor = RGBColor(140, 86, 75);
const LATENCY_P50: RGBColor = RGBColor(188, 189, 34);
const LATENCY_MAX: RGBColor = RGBColor(227, 119, 194);

/// One line of a panel.
struct Line<'a> {
    points: &'a Points,
    color: RGBColor,
    label: &'a str,
}

/// A panel: lines on a left and a right y axis over the shared x range.
struct Panel<'a> {
    caption: &'a str,
    /// Drawn under the bottom panel only.
    x_desc: Option<&'a str>,
    y_desc: &'a str,
    y2_desc: &'a str,
    /// Whether the right axis is drawn (its lines are drawn either way).
    right_axis: bool,
    left: Vec<Line<'a>>,
    right: Vec<Line<'a>>,
    legend: SeriesLabelPosition,
}

fn draw_error_panel(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    s: &Series,
) -> Result<PlotArea, ChartError> {
    let panel = Panel {
        caption: "Screen-space error",
        x_desc: None,
        y_desc: "error (octree levels)",
        y2_desc: "image RMSE vs reference",
        right_axis: !s.rmse.is_empty(),
        left: vec![
            Line {
                points: &s.mean,
                color: MEAN,
                label: "error mean (levels)",
            },
            Line {
                points: &s.p95,
                color: P95,
                label: "error p95 (levels)",
            },
            Line {
                points: &s.max,
                color: MAX,
                label: "error max (levels)",
            },
        ],
        right: vec![Line {
            points: &s.rmse,
            color: RMSE,
            label: "image RMSE (right axis)",
        }],
        legend: SeriesLabelPosition::UpperRight,
    };
    draw_panel(area, s, panel)
}

/// The traffic panel; `bottom`: it is the lowest panel and carries the x axis description.
fn draw_traffic_panel(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    s: &Series,
    bottom: bool,
) -> Result<PlotArea, ChartError> {
    let panel = Panel {
        caption: "Traffic and slots",
        x_desc: bottom.then_some(X_DESC),
        y_desc: "received (MB/s, 1 MB = 10⁶ B)",
        y2_desc: "slots",
        right_axis: true,
        left: vec![Line {
            points: &s.mb_per_s,
            color: RATE,
            label: "received (MB/s)",
        }],
        right: vec![
            Line {
                points: &s.slots_used,
                color: USED,
                label: "slots used (right axis)",
            },
            Line {
                points: &s.slots_total,
                color: TOTAL,
                label: "slots total (right axis)",
            },
        ],
        legend: SeriesLabelPosition::LowerRight,
    };
    draw_panel(area, s, panel)
}

fn draw_latency_panel(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    s: &Series,
) -> Result<PlotArea, ChartError> {
    let panel = Panel {
        caption: "List to arrival",
        x_desc: Some(X_DESC),
        y_desc: "latency (ms)",
        y2_desc: "",
        right_axis: false,
        left: vec![
            Line {
                points: &s.latency_p50,
                color: LATENCY_P50,
                label: "cycle median (ms)",
            },
            Line {
                points: &s.latency_max,
                color: LATENCY_MAX,
                label: "cycle largest (ms)",
            },
        ],
        right: Vec::new(),
        legend: SeriesLabelPosition::UpperRight,
    };
    draw_panel(area, s, panel)
}

/// The shared x axis's description, under the lowest panel.
const X_DESC: &str = "run time (s)";

/// Draws `panel` into `area`: axes from its lines' values, the lines (with markers for short
/// reports) and the legend. A right line with no points is left out of the legend. Returns the
/// plotting area's pixels.
fn draw_panel(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    s: &Series,
    panel: Panel<'_>,
) -> Result<PlotArea, ChartError> {
    let values = |lines: &[Line<'_>]| -> Vec<f64> {
        lines
            .iter()
            .flat_map(|l| l.points.iter().map(|p| p.1))
            .collect()
    };
    let y = axis_range(values(&panel.left).into_iter(), true);
    let y2 = axis_range(values(&panel.right).into_iter(), true);
    let mut chart = ChartBuilder::on(area)
        .margin(12)
        .x_label_area_size(if panel.x_desc.is_some() { 44 } else { 36 })
        .y_label_area_size(70)
        .right_y_label_area_size(RIGHT_AXIS)
        .caption(panel.caption, ("sans-serif", 20))
        .build_cartesian_2d(s.x.clone(), y)
        .map_err(draw_err)?
        .set_secondary_coord(s.x.clone(), y2);
    let mut mesh = chart.configure_mesh();
    if let Some(x_desc) = panel.x_desc {
        mesh.x_desc(x_desc);
    }
    mesh.y_desc(panel.y_desc)
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 16))
        .draw()
        .map_err(draw_err)?;
    if panel.right_axis {
        chart
            .configure_secondary_axes()
            .y_desc(panel.y2_desc)
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 16))
            .draw()
            .map_err(draw_err)?;
    }
    let plot = chart.plotting_area().get_pixel_range();
    // Lines are drawn clipped in pixels (clip.rs); the empty series only carry the legend.
    for line in &panel.left {
        let pixels: Vec<(i32, i32)> = line.points.iter().map(|p| chart.backend_coord(p)).collect();
        draw_clipped_line(area, &plot, &pixels, line.color, s.markers)?;
        chart
            .draw_series(std::iter::empty::<PathElement<(f64, f64)>>())
            .map_err(draw_err)?
            .label(line.label)
            .legend(legend_line(line.color));
    }
    for line in panel.right.iter().filter(|l| !l.points.is_empty()) {
        let secondary = chart.borrow_secondary();
        let pixels: Vec<(i32, i32)> = line
            .points
            .iter()
            .map(|p| secondary.backend_coord(p))
            .collect();
        draw_clipped_line(area, &plot, &pixels, line.color, s.markers)?;
        chart
            .draw_secondary_series(std::iter::empty::<PathElement<(f64, f64)>>())
            .map_err(draw_err)?
            .label(line.label)
            .legend(legend_line(line.color));
    }
    draw_legend(&mut chart, panel.legend)?;
    Ok(plot)
}

/// Draws the legend box of a panel's series at `position`.
pub(crate) fn draw_legend<'a, 'b: 'a, CT: plotters::coord::CoordTranslate>(
    chart: &mut ChartContext<'a, BitMapBackend<'b>, CT>,
    position: SeriesLabelPosition,
) -> Result<(), ChartError> {
    chart
        .configure_series_labels()
        .position(position)
        .label_font(("sans-serif", 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(draw_err)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{ErrorSummary, RunMeta};

    fn synthetic(n: u32) -> RunReport {
        let records = (0..n)
            .map(|i| {
                let t = f64::from(i) / 30.0;
                let e = (8.0 * (-t / 2.0).exp()) as f32;
                CycleRecord {
                    cycle: i,
                    time_s: t,
                    analysis_ms: 1.0,
                    render_ms: 12.0,
                    treelets_received: 5,
                    bytes_received: 200_000 + u64::from(i % 7) * 30_000,
                    slots_used: (i * 20).min(3000),
                    slots_total: 4096,
                    samples: 10_000,
                    pushed: 0,
                    push_dropped: 0,
                    sampled: 10_000,
                    known_share: 1.0,
                    lod_bias: 1.0,
                    error: ErrorSummary {
                        mean: e / 3.0,
                        p95: e * 0.8,
                        max: e,
                        error_pixels: f64::from(e) * 1e4,
                    },
                    image_rmse: Some(f64::from(e) * 2.5),
                    ..CycleRecord::default()
                }
            })
            .collect();
        RunReport {
            meta: RunMeta::default(),
            records,
            events: Vec::new(),
        }
    }

    fn temp_png(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("arbor-chart-{}-{name}.png", std::process::id()))
    }

    /// Decodes the PNG at `path`, checks its size, and returns how many distinct colours it has.
    fn check_png(path: &Path) -> usize {
        let img = ::image::open(path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (WIDTH, HEIGHT));
        let mut colours: Vec<[u8; 3]> = img.pixels().map(|p| p.0).collect();
        colours.sort_unstable();
        colours.dedup();
        colours.len()
    }

    #[test]
    fn chart_of_200_cycles_is_a_png_of_the_stated_size_with_content() {
        let path = temp_png("200");
        draw(&synthetic(200), &path, "synthetic run, 200 cycles").unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        let colours = check_png(&path);
        // Lines in several colours plus anti-aliased text: far from one flat colour.
        assert!(colours > 10, "only {colours} colours");
        let _ = std::fs::remove_file(&path);
    }

    #[test]
    fn text_is_drawn() {
        // The title region differs between two titles only if glyphs are really rendered.
        let report = synthetic(10);
        let a = render_rgb(&report, "AAAA").unwrap();
        let b = render_rgb(&report, "WWWW WWWW").unwrap();
        let title_rows = WIDTH as usize * 3 * 40;
        assert_ne!(a[..title_rows], b[..title_rows]);
    }

    #[test]
    fn one_record_and_empty_reports_draw() {
        for (name, report) in [("one", synthetic(1)), ("empty", RunReport::default())] {
            let path = temp_png(name);
            draw(&report, &path, name).unwrap();
            assert!(check_png(&path) > 2);
            let _ = std::fs::remove_file(&path);
        }
    }

    #[test]
    fn degenerate_values_draw() {
        let mut zero = synthetic(50);
        for r in &mut zero.records {
            r.error = ErrorSummary::default();
            r.bytes_received = 0;
            r.slots_used = 0;
            r.slots_total = 0;
            r.image_rmse = Some(0.0);
        }
        let mut nan = synthetic(50);
        for (i, r) in nan.records.iter_mut().enumerate() {
            if i % 3 == 0 {
                r.time_s = f64::NAN;
            }
            r.error.mean = f32::NAN;
            r.error.max = f32::INFINITY;
            r.image_rmse = if i % 2 == 0 { Some(f64::NAN) } else { None };
        }
        let mut huge = synthetic(5);
        huge.records[2].time_s = f64::MAX;
        huge.records[3].error.max = f32::MAX;
        huge.records[4].bytes_received = u64::MAX;
        // Time standing still: rates come from the phase durations.
        let mut still = synthetic(5);
        for r in &mut still.records {
            r.time_s = 1.0;
        }
        let mut no_time = synthetic(3);
        for r in &mut no_time.records {
            r.time_s = 0.0;
            r.analysis_ms = 0.0;
            r.render_ms = 0.0;
        }
        for (name, report) in [
            ("zero", zero),
            ("nan", nan),
            ("huge", huge),
            ("still", still),
            ("no_time", no_time),
        ] {
            render_rgb(&report, name).unwrap_or_else(|e| panic!("{name}: {e}"));
        }
    }

    /// A run with sharp spikes in every series: one-cycle jumps far above the rest, repeated
    /// timestamps (zero-length segments), and a burst of traffic in a single cycle.
    fn spiky(n: u32) -> RunReport {
        let mut report = synthetic(n);
        for (i, r) in report.records.iter_mut().enumerate() {
            if i % 17 == 5 {
                r.error.max = 60.0;
                r.error.p95 = 40.0;
                r.error.mean = 20.0;
                r.image_rmse = Some(90.0);
                r.bytes_received = 400_000_000;
                r.slots_used = 4096;
            }
            if i % 23 == 7 {
                r.error.max = 0.0;
                r.slots_used = 0;
            }
            if i % 11 == 3 && i > 0 {
                r.time_s = report_time(i - 1);
            }
            // Latencies with gaps (cycles that received nothing listed) and spikes.
            if i % 5 != 0 {
                r.latency_p50_ms = Some(20.0 + (i % 9) as f64);
                r.latency_max_ms = Some(if i % 13 == 4 { 5_000.0 } else { 60.0 });
            }
        }
        report
    }

    fn report_time(i: usize) -> f64 {
        i as f64 / 30.0
    }

    /// Every pixel of exactly a series colour lies inside the plotting area of its panel, with
    /// the latency panel and without it.
    #[test]
    fn series_are_clipped_to_their_panels() {
        let colours: [&[RGBColor]; 3] = [
            &[MEAN, P95, MAX, RMSE],
            &[RATE, USED, TOTAL],
            &[LATENCY_P50, LATENCY_MAX],
        ];
        for latency in [true, false] {
            for n in [12, 60, 400] {
                let mut report = spiky(n);
                if !latency {
                    for r in &mut report.records {
                        (r.latency_p50_ms, r.latency_max_ms) = (None, None);
                    }
                }
                let (buf, areas) = render_with_plot_areas(&report, "spikes").unwrap();
                assert_eq!(areas.len(), if latency { 3 } else { 2 });
                let mut drawn = [0usize; 3];
                for (i, px) in buf.chunks_exact(3).enumerate() {
                    let (x, y) = ((i % WIDTH as usize) as i32, (i / WIDTH as usize) as i32);
                    let colour = RGBColor(px[0], px[1], px[2]);
                    for (panel, area) in areas.iter().enumerate() {
                        if colours[panel].contains(&colour) {
                            drawn[panel] += 1;
                            assert!(
                                area.0.contains(&x) && area.1.contains(&y),
                                "{n}: {colour:?} at ({x}, {y}) outside panel {panel} {area:?}"
                            );
                        }
                    }
                }
                for (panel, &d) in drawn.iter().enumerate().take(areas.len()) {
                    assert!(d > 300, "{n}: only {d} series pixels in panel {panel}");
                }
            }
        }
    }

    /// The latency panel appears exactly when a record has a latency, below the other two, and
    /// a report without latencies keeps the two-panel layout.
    #[test]
    fn the_latency_panel_is_drawn_only_for_reports_with_latencies() {
        let mut report = synthetic(60);
        let (_, two) = render_with_plot_areas(&report, "without").unwrap();
        assert_eq!(two.len(), 2);
        report.records[30].latency_max_ms = Some(42.0);
        let (_, three) = render_with_plot_areas(&report, "with").unwrap();
        assert_eq!(three.len(), 3);
        assert!(three[0].1.end <= three[1].1.start && three[1].1.end <= three[2].1.start);
        assert!(
            three[1].1.len() < two[1].1.len(),
            "the panels share the height"
        );
    }

    #[test]
    fn axis_ranges_are_never_empty() {
        assert_eq!(axis_range(std::iter::empty(), true), 0.0..1.0);
        assert_eq!(axis_range(std::iter::empty(), false), 0.0..1.0);
        assert_eq!(axis_range([0.0, 0.0].into_iter(), true), 0.0..1.0);
        assert_eq!(axis_range([5.0].into_iter(), false), 4.0..6.0);
        assert_eq!(
            axis_range([f64::NAN, f64::INFINITY].into_iter(), true),
            0.0..1.0
        );
        assert_eq!(axis_range([0.0, 10.0].into_iter(), true), 0.0..10.5);
        let r = axis_range([f64::MAX, -f64::MAX].into_iter(), false);
        assert!(r.start.is_finite() && r.end.is_finite() && r.start < r.end);
    }

    #[test]
    fn rates_use_time_deltas_with_phase_fallback() {
        let mut report = synthetic(3);
        for r in &mut report.records {
            r.bytes_received = 1_000_000;
        }
        report.records[0].time_s = 0.0; // no time since the start: phases, 13 ms
        report.records[1].time_s = 0.5;
        report.records[2].time_s = 0.5; // time stood still: phases again
        let s = Series::from_report(&report.records);
        let rates: Vec<f64> = s.mb_per_s.iter().map(|p| p.1).collect();
        assert_eq!(rates, vec![1.0 / 0.013, 2.0, 1.0 / 0.013]);
        report.records[0].time_s = 0.25; // first record: time since the start
        let s = Series::from_report(&report.records);
        assert_eq!(s.mb_per_s[0].1, 4.0);
    }
}
