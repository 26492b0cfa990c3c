//! One chart comparing several runs of the same case (policies, variants): the screen-space
//! error and the bytes received against run time, one colour per run.
//!
//! The single-run chart ([`crate::chart`]) shows everything about one run; this one answers
//! "which run gets there first, and for how many bytes". Two panels share the x axis (run time,
//! s): the top one the error mean (octree levels) of each run, the bottom one each run's bytes
//! received so far (MB, 10⁶ bytes). Axis ranges cover every run's values and every line is
//! clipped to its panel's plotting area (`clip.rs`); values that are not finite are left out.

use std::path::Path;

use plotters::prelude::*;

use crate::RunReport;
use crate::chart::{
    ChartError, HEIGHT, WIDTH, axis_range, clip, draw_err, draw_legend, ensure_font, save_png,
};
use crate::clip::{PlotArea, draw_clipped_line, legend_line};

/// Colours of the runs, in order (repeated past ten runs).
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

type Points = Vec<(f64, f64)>;

/// `(time, value)` points of a run, non-finite ones left out.
fn series(report: &RunReport, value: impl Fn(&crate::CycleRecord, f64) -> f64) -> Points {
    let mut total = 0.0;
    report
        .records
        .iter()
        .map(|r| {
            total += r.bytes_received as f64;
            (r.time_s, value(r, total))
        })
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .map(|(x, y)| (clip(x), clip(y)))
        .collect()
}

/// Draws the runs, each `(label, report)`, as a [`WIDTH`]×[`HEIGHT`] PNG at `path`.
pub fn draw_comparison(
    runs: &[(&str, &RunReport)],
    path: &Path,
    title: &str,
) -> Result<(), ChartError> {
    let (buf, _) = render_comparison(runs, title)?;
    save_png(&buf, path)
}

/// The comparison as a packed RGB8 buffer, with the plotting areas of the two panels.
fn render_comparison(
    runs: &[(&str, &RunReport)],
    title: &str,
) -> Result<(Vec<u8>, [PlotArea; 2]), ChartError> {
    ensure_font()?;
    let error: Vec<Points> = runs
        .iter()
        .map(|(_, r)| series(r, |c, _| f64::from(c.error.mean)))
        .collect();
    let bytes: Vec<Points> = runs
        .iter()
        .map(|(_, r)| series(r, |_, total| total / 1e6))
        .collect();
    let x = axis_range(error.iter().flatten().map(|p| p.0), true);
    let mut buf = vec![0u8; WIDTH as usize * HEIGHT as usize * 3];
    let areas;
    {
        let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let body = root.titled(title, ("sans-serif", 26)).map_err(draw_err)?;
        let panels = body.split_evenly((2, 1));
        let labels: Vec<&str> = runs.iter().map(|(l, _)| *l).collect();
        let top = ("Screen-space error mean", "error mean (levels)", None);
        let bottom = ("Received so far", "MB received", Some("run time (s)"));
        areas = [
            draw_lines(&panels[0], &x, &error, &labels, top)?,
            draw_lines(&panels[1], &x, &bytes, &labels, bottom)?,
        ];
        root.present().map_err(draw_err)?;
    }
    Ok((buf, areas))
}

/// One panel: a line per run over the shared x range, `(caption, y label, x label)`, clipped to
/// the plotting area, whose pixels it returns.
fn draw_lines(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    x: &std::ops::Range<f64>,
    lines: &[Points],
    labels: &[&str],
    (caption, y_desc, x_desc): (&str, &str, Option<&str>),
) -> Result<PlotArea, ChartError> {
    let y = axis_range(lines.iter().flatten().map(|p| p.1), true);
    let mut chart = ChartBuilder::on(area)
        .margin(12)
        .x_label_area_size(44)
        .y_label_area_size(70)
        .caption(caption, ("sans-serif", 20))
        .build_cartesian_2d(x.clone(), y)
        .map_err(draw_err)?;
    let mut mesh = chart.configure_mesh();
    if let Some(x_desc) = x_desc {
        mesh.x_desc(x_desc);
    }
    mesh.y_desc(y_desc)
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 16))
        .draw()
        .map_err(draw_err)?;
    let plot = chart.plotting_area().get_pixel_range();
    for (i, (points, label)) in lines.iter().zip(labels).enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        let pixels: Vec<(i32, i32)> = points.iter().map(|p| chart.backend_coord(p)).collect();
        draw_clipped_line(area, &plot, &pixels, color, false)?;
        // The empty series only carries the legend entry.
        chart
            .draw_series(std::iter::empty::<PathElement<(f64, f64)>>())
            .map_err(draw_err)?
            .label(*label)
            .legend(legend_line(color));
    }
    draw_legend(&mut chart, SeriesLabelPosition::UpperRight)?;
    Ok(plot)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{CycleRecord, RunMeta};

    fn run(seconds: f64, levels: f32) -> RunReport {
        let records = (0..50)
            .map(|i| {
                let mut r = CycleRecord {
                    cycle: i,
                    time_s: seconds * f64::from(i) / 50.0,
                    bytes_received: 10_000,
                    ..CycleRecord::default()
                };
                r.error.mean = levels * (1.0 - i as f32 / 50.0);
                r
            })
            .collect();
        RunReport {
            meta: RunMeta::default(),
            records,
            events: Vec::new(),
        }
    }

    #[test]
    fn each_run_gets_its_own_colour_in_both_panels() {
        let a = run(1.0, 3.0);
        let b = run(2.0, 5.0);
        let path = std::env::temp_dir().join(format!("arbor-compare-{}.png", std::process::id()));
        draw_comparison(&[("a", &a), ("b", &b)], &path, "two runs").unwrap();
        let img = ::image::open(&path).unwrap().to_rgb8();
        std::fs::remove_file(&path).unwrap();
        assert_eq!(img.dimensions(), (WIDTH, HEIGHT));
        let count = |c: RGBColor| {
            let halves = [0..HEIGHT / 2, HEIGHT / 2..HEIGHT];
            halves.map(|rows| {
                rows.flat_map(|y| (0..WIDTH).map(move |x| (x, y)))
                    .filter(|&(x, y)| img.get_pixel(x, y).0 == [c.0, c.1, c.2])
                    .count()
            })
        };
        for c in &PALETTE[..2] {
            let [top, bottom] = count(*c);
            assert!(top > 200 && bottom > 200, "{c:?}: {top} / {bottom} pixels");
        }
        assert_eq!(count(PALETTE[2]), [0, 0], "a third colour for two runs");
    }

    #[test]
    fn spiky_runs_stay_inside_their_panels() {
        let mut spiky = run(1.0, 3.0);
        for (i, r) in spiky.records.iter_mut().enumerate() {
            if i % 7 == 3 {
                r.error.mean = 400.0;
                r.bytes_received = 900_000_000;
            }
            if i % 5 == 1 && i > 0 {
                r.time_s = 1.0 * (i - 1) as f64 / 50.0;
            }
        }
        let calm = run(2.0, 5.0);
        let (buf, [top, bottom]) =
            render_comparison(&[("spiky", &spiky), ("calm", &calm)], "spikes").unwrap();
        let mut drawn = 0;
        for (i, px) in buf.chunks_exact(3).enumerate() {
            let (x, y) = ((i % WIDTH as usize) as i32, (i / WIDTH as usize) as i32);
            let colour = RGBColor(px[0], px[1], px[2]);
            if PALETTE[..2].contains(&colour) {
                drawn += 1;
                let inside = |a: &PlotArea| a.0.contains(&x) && a.1.contains(&y);
                assert!(
                    inside(&top) || inside(&bottom),
                    "{colour:?} at ({x}, {y}) outside {top:?} and {bottom:?}"
                );
            }
        }
        assert!(drawn > 400, "only {drawn} series pixels");
    }
}
