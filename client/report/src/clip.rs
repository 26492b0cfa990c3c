//! Series lines and markers clipped to a panel's plotting area.
//!
//! plotters draws a series wherever its points map and does not clip to the plotting area; its
//! thick-line polygons also overshoot at sharp turns and at repeated points (a spike used to
//! cross into the panel below). So lines are drawn here segment by segment in pixels, each cut
//! (Liang–Barsky) to the plotting area inset by half the stroke, and markers as squares cut to
//! the area: no pixel of a series lies outside its panel.

use std::ops::Range;

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::chart::{ChartError, draw_err};

/// Pixels of a panel's plotting area, the rectangle inside its axes: `(x range, y range)`.
pub(crate) type PlotArea = (Range<i32>, Range<i32>);

/// Line width of every series, pixels.
pub(crate) const STROKE: u32 = 2;

/// Half the side of a marker square, pixels.
const MARKER: i32 = 3;

/// Draws `pixels` (backend coordinates, in order) on `area` as a [`STROKE`]-wide line in
/// `colour`, with a marker at each point when `markers`, clipped to `plot`.
pub(crate) fn draw_clipped_line(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    plot: &PlotArea,
    pixels: &[(i32, i32)],
    colour: RGBColor,
    markers: bool,
) -> Result<(), ChartError> {
    let (bx, by) = area.get_base_pixel();
    let local = |(x, y): (f64, f64)| (x.round() as i32 - bx, y.round() as i32 - by);
    // A 2-px line covers one pixel on each side of its centre: keep the centre one pixel in.
    let inset = STROKE as i32 / 2 + 1;
    let bounds = [
        f64::from(plot.0.start + inset),
        f64::from(plot.0.end - 1 - inset),
        f64::from(plot.1.start + inset),
        f64::from(plot.1.end - 1 - inset),
    ];
    for pair in pixels.windows(2) {
        let a = (f64::from(pair[0].0), f64::from(pair[0].1));
        let b = (f64::from(pair[1].0), f64::from(pair[1].1));
        let Some((a, b)) = clip_segment(a, b, bounds) else {
            continue;
        };
        let (a, b) = (local(a), local(b));
        if a == b {
            continue;
        }
        area.draw(&PathElement::new(vec![a, b], colour.stroke_width(STROKE)))
            .map_err(draw_err)?;
    }
    if markers {
        for &(x, y) in pixels {
            let x0 = (x - MARKER).max(plot.0.start);
            let x1 = (x + MARKER).min(plot.0.end - 1);
            let y0 = (y - MARKER).max(plot.1.start);
            let y1 = (y + MARKER).min(plot.1.end - 1);
            if x0 <= x1 && y0 <= y1 {
                let rect =
                    Rectangle::new([(x0 - bx, y0 - by), (x1 - bx, y1 - by)], colour.filled());
                area.draw(&rect).map_err(draw_err)?;
            }
        }
    }
    Ok(())
}

/// The part of segment `a`–`b` inside `[x_min, x_max, y_min, y_max]` (Liang–Barsky), `None`
/// when nothing of it is inside or the bounds are empty.
pub(crate) fn clip_segment(
    a: (f64, f64),
    b: (f64, f64),
    [x_min, x_max, y_min, y_max]: [f64; 4],
) -> Option<((f64, f64), (f64, f64))> {
    if !(x_min <= x_max && y_min <= y_max) {
        return None;
    }
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a.0 - x_min),
        (dx, x_max - a.0),
        (-dy, a.1 - y_min),
        (dy, y_max - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let t = q / p;
            if p < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    (t0 <= t1).then_some((
        (a.0 + t0 * dx, a.1 + t0 * dy),
        (a.0 + t1 * dx, a.1 + t1 * dy),
    ))
}

/// A legend entry for a line drawn with [`draw_clipped_line`]: a short stroke in `colour`.
pub(crate) fn legend_line(colour: RGBColor) -> impl Fn((i32, i32)) -> PathElement<(i32, i32)> {
    move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], colour.stroke_width(STROKE))
}

#[cfg(test)]
mod tests {
    use super::clip_segment;

    const BOX: [f64; 4] = [0.0, 10.0, 0.0, 10.0];

    #[test]
    fn segments_are_cut_to_the_box() {
        assert_eq!(
            clip_segment((2.0, 2.0), (8.0, 8.0), BOX),
            Some(((2.0, 2.0), (8.0, 8.0)))
        );
        assert_eq!(
            clip_segment((5.0, -10.0), (5.0, 20.0), BOX),
            Some(((5.0, 0.0), (5.0, 10.0)))
        );
        assert_eq!(
            clip_segment((-5.0, 5.0), (15.0, 5.0), BOX),
            Some(((0.0, 5.0), (10.0, 5.0)))
        );
        assert_eq!(clip_segment((11.0, 0.0), (20.0, 5.0), BOX), None);
        assert_eq!(
            clip_segment((0.0, 0.0), (1.0, 1.0), [1.0, 0.0, 0.0, 1.0]),
            None
        );
        // A point inside stays a point; one outside is gone.
        assert_eq!(
            clip_segment((3.0, 3.0), (3.0, 3.0), BOX),
            Some(((3.0, 3.0), (3.0, 3.0)))
        );
        assert_eq!(clip_segment((-3.0, 3.0), (-3.0, 3.0), BOX), None);
    }
}
