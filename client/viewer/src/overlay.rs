//! The viewer's statistics overlay: lines of text about the last cycles, rasterised on the CPU
//! with `ab_glyph` into a small RGBA panel that the blit pass composites over the frame.
//!
//! Plain data, no window or GPU: [`OverlayStats::lines`] says what is shown and
//! [`Overlay::draw`] turns lines into an [`OverlayImage`], so both are unit-tested here. The
//! panel has a fixed size ([`Overlay::panel_size`]) so the GPU texture holding it never has to
//! be recreated; text that does not fit is clipped.
//!
//! Pixels are straight-alpha RGBA8 holding sRGB-encoded colour, like the frames the renderers
//! produce: the blit shader treats both the same way.

use ab_glyph::{Font, FontRef, PxScale, ScaleFont, point};

use arbor_client_report::CycleRecord;
use arbor_client_report::FONT;

/// Lines the panel has room for.
pub const LINES: u32 = 9;
/// Panel width, pixels.
pub const PANEL_WIDTH: u32 = 340;
/// Text size, pixels per em.
pub const TEXT_PX: f32 = 13.0;
/// Margin around the text inside the panel, pixels.
const PAD: u32 = 4;
/// The panel's background: near-black, partly transparent.
pub const PANEL_BACKGROUND: [u8; 4] = [8, 10, 14, 176];
/// Text colour (sRGB).
pub const TEXT_COLOUR: [u8; 3] = [235, 238, 242];

/// A straight-alpha RGBA8 raster: `width · height · 4` bytes, rows top to bottom, no padding.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct OverlayImage {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
}

impl OverlayImage {
    /// The pixel at `(x, y)`, `None` outside.
    pub fn get(&self, x: u32, y: u32) -> Option<[u8; 4]> {
        (x < self.width && y < self.height).then(|| {
            let o = (y as usize * self.width as usize + x as usize) * 4;
            [
                self.rgba[o],
                self.rgba[o + 1],
                self.rgba[o + 2],
                self.rgba[o + 3],
            ]
        })
    }
}

/// Rasterises text lines with the embedded DejaVu Sans.
#[derive(Clone, Debug)]
pub struct Overlay {
    font: FontRef<'static>,
    scale: PxScale,
}

impl Default for Overlay {
    fn default() -> Self {
        Self::new()
    }
}

impl Overlay {
    /// # Panics
    /// If the embedded font does not parse (it is compiled in, so never at run time).
    pub fn new() -> Self {
        Self {
            font: FontRef::try_from_slice(FONT).expect("the embedded font parses"),
            scale: PxScale::from(TEXT_PX),
        }
    }

    /// Distance between baselines, whole pixels.
    pub fn line_height(&self) -> u32 {
        let s = self.font.as_scaled(self.scale);
        (s.height() + s.line_gap()).ceil() as u32
    }

    /// The panel size every [`draw`](Self::draw) returns.
    pub fn panel_size(&self) -> (u32, u32) {
        (PANEL_WIDTH, 2 * PAD + LINES * self.line_height())
    }

    /// The panel with `lines` drawn top to bottom; lines beyond [`LINES`] and text beyond the
    /// right edge are clipped.
    pub fn draw(&self, lines: &[String]) -> OverlayImage {
        let (width, height) = self.panel_size();
        let mut rgba = Vec::with_capacity(width as usize * height as usize * 4);
        for _ in 0..width * height {
            rgba.extend_from_slice(&PANEL_BACKGROUND);
        }
        let mut image = OverlayImage {
            width,
            height,
            rgba,
        };
        let scaled = self.font.as_scaled(self.scale);
        let line_height = self.line_height() as f32;
        for (i, line) in lines.iter().take(LINES as usize).enumerate() {
            let baseline = PAD as f32 + i as f32 * line_height + scaled.ascent();
            let mut caret = point(PAD as f32, baseline);
            let mut previous = None;
            for c in line.chars() {
                let id = scaled.glyph_id(c);
                if let Some(p) = previous {
                    caret.x += scaled.kern(p, id);
                }
                previous = Some(id);
                let glyph = id.with_scale_and_position(self.scale, caret);
                caret.x += scaled.h_advance(id);
                let Some(outline) = self.font.outline_glyph(glyph) else {
                    continue;
                };
                let bounds = outline.px_bounds();
                outline.draw(|gx, gy, coverage| {
                    let x = bounds.min.x as i64 + i64::from(gx);
                    let y = bounds.min.y as i64 + i64::from(gy);
                    blend_text(&mut image, x, y, coverage);
                });
            }
        }
        image
    }
}

/// Blends [`TEXT_COLOUR`] with `coverage` over the pixel at `(x, y)` (straight alpha, in the
/// encoded space like the rest of the panel); outside the panel nothing happens.
fn blend_text(image: &mut OverlayImage, x: i64, y: i64, coverage: f32) {
    if x < 0 || y < 0 || x >= i64::from(image.width) || y >= i64::from(image.height) {
        return;
    }
    let c = coverage.clamp(0.0, 1.0);
    let o = (y as usize * image.width as usize + x as usize) * 4;
    let px = &mut image.rgba[o..o + 4];
    for (k, &t) in TEXT_COLOUR.iter().enumerate() {
        px[k] = (f32::from(px[k]) * (1.0 - c) + f32::from(t) * c).round() as u8;
    }
    px[3] = (f32::from(px[3]) * (1.0 - c) + 255.0 * c).round() as u8;
}

/// What the overlay reports.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OverlayStats {
    /// Backend name (`cpu` or the adapter).
    pub backend: String,
    /// Camera control mode.
    pub mode: &'static str,
    /// Mean frame time over the last interval, ms.
    pub frame_ms: f64,
    /// Frames per second over the last interval.
    pub fps: f64,
    /// The latest frame's size, pixels, when it was scaled down from the window's while the
    /// camera moved ([`crate::frame_scale`]); `None` at full size.
    pub scaled_frame: Option<(u32, u32)>,
    /// The latest cycle.
    pub record: CycleRecord,
    /// Received bytes per second over the last interval.
    pub bytes_per_s: f64,
    /// Treelets received in all.
    pub treelets_received: u64,
    /// The cycle the view converged at, if it has.
    pub converged_at: Option<u32>,
}

impl OverlayStats {
    /// The overlay's text, at most [`LINES`] lines.
    pub fn lines(&self) -> Vec<String> {
        let r = &self.record;
        vec![
            format!("{} | {} (Tab)", self.backend, self.mode),
            match self.scaled_frame {
                Some((w, h)) => format!(
                    "frame {:.1} ms  {:.1} fps  moving at {w}×{h}",
                    self.frame_ms, self.fps
                ),
                None => format!("frame {:.1} ms  {:.1} fps", self.frame_ms, self.fps),
            },
            format!(
                "analysis {:.2}  presort {:.2}  integrate {:.2} ms",
                r.analysis_ms, r.presort_ms, r.integrate_ms
            ),
            format!("upload {:.2}  render {:.2} ms", r.upload_ms, r.render_ms),
            format!(
                "slots {}/{}  requests {}  LOD bias {:.2} (-/=)",
                r.slots_used, r.slots_total, r.requests_sent, r.lod_bias
            ),
            format!(
                "{:.2} MB/s  {} treelets received",
                self.bytes_per_s / 1e6,
                self.treelets_received
            ),
            format!(
                "error max {:.2}  mean {:.3} levels",
                r.error.max, r.error.mean
            ),
            match self.converged_at {
                Some(c) => format!("cycle {}  converged at {c}", r.cycle),
                None => format!("cycle {}  streaming", r.cycle),
            },
            "F12/P shot  R report  H overlay  Esc quit".into(),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arbor_client_core::summary::ErrorSummary;

    #[test]
    fn layout_is_width_height_rgba_with_the_background_everywhere_without_text() {
        let o = Overlay::new();
        let img = o.draw(&[]);
        let (w, h) = o.panel_size();
        assert_eq!((img.width, img.height), (w, h));
        assert_eq!(img.rgba.len(), w as usize * h as usize * 4);
        assert!(
            h >= LINES * 13,
            "room for {LINES} lines of {TEXT_PX} px: {h}"
        );
        assert!(
            img.rgba
                .chunks_exact(4)
                .all(|p| p == PANEL_BACKGROUND.as_slice())
        );
        assert_eq!(img.get(w - 1, h - 1), Some(PANEL_BACKGROUND));
        assert_eq!(img.get(w, 0), None);
        assert_eq!(img.get(0, h), None);
    }

    #[test]
    fn text_changes_pixels_where_it_is_drawn_and_only_there() {
        let o = Overlay::new();
        let blank = o.draw(&[]);
        let one = o.draw(&["frame 16.7 ms".into()]);
        let lh = o.line_height();
        let changed: Vec<(u32, u32)> = (0..one.height)
            .flat_map(|y| (0..one.width).map(move |x| (x, y)))
            .filter(|&(x, y)| one.get(x, y) != blank.get(x, y))
            .collect();
        assert!(changed.len() > 50, "{} pixels changed", changed.len());
        // All in the first line's band, starting at the left margin.
        assert!(
            changed
                .iter()
                .all(|&(x, y)| y < PAD + lh + 2 && x >= PAD - 1)
        );
        // Text is brighter and more opaque than the panel.
        let brightest = changed
            .iter()
            .map(|&(x, y)| one.get(x, y).unwrap())
            .max_by_key(|p| p[0])
            .unwrap();
        assert!(brightest[0] > 200 && brightest[3] > 240, "{brightest:?}");

        // The second line lands one line height lower; different text, different pixels.
        let two = o.draw(&["".into(), "frame 16.7 ms".into()]);
        for &(x, y) in &changed {
            assert_eq!(two.get(x, y + lh), one.get(x, y));
        }
        assert_ne!(o.draw(&["frame 33.3 ms".into()]), one);
    }

    #[test]
    fn long_and_surplus_lines_are_clipped_not_a_panic() {
        let o = Overlay::new();
        let lines: Vec<String> = (0..LINES + 5)
            .map(|i| "W".repeat(200 + i as usize))
            .collect();
        let img = o.draw(&lines);
        assert_eq!(img.rgba.len(), img.width as usize * img.height as usize * 4);
        // The right-most column got text.
        assert!((0..img.height).any(|y| img.get(img.width - 1, y) != Some(PANEL_BACKGROUND)));
    }

    #[test]
    fn stats_lines_name_every_figure() {
        let stats = OverlayStats {
            backend: "cpu".into(),
            mode: "orbit",
            frame_ms: 16.3,
            fps: 61.5,
            scaled_frame: None,
            record: CycleRecord {
                cycle: 42,
                analysis_ms: 1.5,
                presort_ms: 0.25,
                integrate_ms: 2.0,
                upload_ms: 0.5,
                render_ms: 9.75,
                slots_used: 120,
                slots_total: 512,
                requests_sent: 17,
                lod_bias: 1.41,
                error: ErrorSummary {
                    mean: 0.125,
                    max: 3.0,
                    ..ErrorSummary::default()
                },
                ..CycleRecord::default()
            },
            bytes_per_s: 2.5e6,
            treelets_received: 99,
            converged_at: None,
        };
        let lines = stats.lines();
        assert!(lines.len() <= LINES as usize);
        let text = lines.join("\n");
        for want in [
            "cpu",
            "orbit",
            "16.3 ms",
            "61.5 fps",
            "analysis 1.50",
            "presort 0.25",
            "integrate 2.00",
            "upload 0.50",
            "render 9.75",
            "slots 120/512",
            "requests 17",
            "LOD bias 1.41",
            "2.50 MB/s",
            "99 treelets",
            "max 3.00",
            "mean 0.125",
            "cycle 42",
            "streaming",
        ] {
            assert!(text.contains(want), "{want:?} missing from\n{text}");
        }
        let done = OverlayStats {
            converged_at: Some(40),
            ..stats
        };
        assert!(done.lines().join("\n").contains("converged at 40"));
        assert!(!done.lines().join("\n").contains("moving at"));
        let moving = OverlayStats {
            scaled_frame: Some((320, 240)),
            ..done
        };
        let lines = moving.lines();
        assert!(lines.len() <= LINES as usize);
        assert!(lines[1].contains("16.3 ms") && lines[1].contains("moving at 320×240"));
    }
}
