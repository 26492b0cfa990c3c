//! Dynamic frame resolution while the camera moves: the frame size that keeps a moving view
//! within its frame budget.
//!
//! A ray caster's frame costs about one ray per pixel, and on a slow backend (the CPU twins or
//! lavapipe on a few cores) a full window can take hundreds of milliseconds: a user moving the
//! camera would see a few frames a second. So while the camera moves, the viewer renders fewer
//! pixels — each side scaled by the same factor — and the blit stretches the frame over the
//! window; the coarser pixels also ask for coarser treelets (the LOD test uses the pixel angle),
//! so a passing view does not fill the link with detail nobody will see. Once the camera has
//! rested for [`SETTLE_SECONDS`] the frame is back at full size, so a resting view converges,
//! and is compared and captured, exactly as without scaling.
//!
//! Plain data with time passed in, like the session's scheduler:
//! [`FrameScale::handle_motion`] says the camera moved, [`FrameScale::handle_frame`] what a
//! frame cost, and [`FrameScale::poll_size`] gives the next frame's size. The cost model is that
//! a frame's time grows with its pixels: each moving frame's time divided by its pixel fraction
//! (the square of the scale) estimates a full frame's, smoothed over frames; the moving scale is
//! the largest whose estimate fits the budget, in steps of [`SCALE_STEP`] so the renderer's
//! targets are not remade every frame. It falls at once when frames are over the budget and
//! rises one step at a time when they are well under it. Resting frames teach nothing: an
//! unchanged view is often not redrawn at all.

use std::time::Duration;

/// How long the camera must be still before frames are back at full size, seconds. Longer
/// than the gap between a mouse drag's events, so a drag does not flip between sizes.
pub const SETTLE_SECONDS: f64 = 0.25;
/// The moving scale's granularity (of each side).
pub const SCALE_STEP: f64 = 1.0 / 16.0;
/// Weight of the newest frame in the smoothed full-frame time.
const SMOOTHING: f64 = 0.3;
/// The scale rises only when a frame at the next step up is predicted under this fraction of
/// the budget (hysteresis against flipping between two steps).
const RISE_BELOW: f64 = 0.8;

/// Why a frame-scale setting was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FrameScaleError {
    /// The smallest scale is not in (0, 1].
    #[error("smallest frame scale {0} must be in (0, 1]")]
    MinScale(f64),
}

/// What the governor aims for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameScaleConfig {
    /// Time a moving frame may take (the renderer's step and the frame's upload); `None`:
    /// always full size.
    pub budget: Option<Duration>,
    /// Smallest scale of each side while moving, in (0, 1].
    pub min_scale: f64,
}

impl Default for FrameScaleConfig {
    /// 20 ms a moving frame (50 Hz, the frame rate of the thesis Arbor follows), down to a
    /// quarter of each side.
    fn default() -> Self {
        Self {
            budget: Some(Duration::from_millis(20)),
            min_scale: 0.25,
        }
    }
}

impl FrameScaleConfig {
    /// Refuses a smallest scale outside (0, 1] (NaN included).
    pub fn validate(&self) -> Result<(), FrameScaleError> {
        if self.min_scale > 0.0 && self.min_scale <= 1.0 {
            Ok(())
        } else {
            Err(FrameScaleError::MinScale(self.min_scale))
        }
    }
}

/// The frame-size governor of one viewer window.
#[derive(Clone, Debug)]
pub struct FrameScale {
    config: FrameScaleConfig,
    /// The scale of moving frames, a multiple of [`SCALE_STEP`] in `[min_scale, 1]`.
    moving_scale: f64,
    /// Smoothed time of a full-size frame, seconds, from every frame so far.
    full_frame_seconds: Option<f64>,
    /// When the camera last moved, seconds on the caller's clock.
    last_motion: Option<f64>,
}

impl FrameScale {
    /// A governor at full size, knowing no frame yet.
    pub fn new(config: FrameScaleConfig) -> Self {
        Self {
            config,
            moving_scale: 1.0,
            full_frame_seconds: None,
            last_motion: None,
        }
    }

    /// Whether frames at `now` are moving frames: the camera moved less than
    /// [`SETTLE_SECONDS`] ago.
    pub fn moving(&self, now: f64) -> bool {
        self.last_motion
            .is_some_and(|t| now - t < SETTLE_SECONDS && now >= t)
    }

    /// The scale of each side for a frame at `now`: the moving scale while moving, else 1.
    pub fn poll_scale(&self, now: f64) -> f64 {
        if self.moving(now) {
            self.moving_scale
        } else {
            1.0
        }
    }

    /// The size of a frame at `now` for a window of `width × height`: each side scaled and
    /// rounded, at least one pixel.
    pub fn poll_size(&self, now: f64, width: u32, height: u32) -> (u32, u32) {
        let scale = self.poll_scale(now);
        if scale >= 1.0 {
            return (width, height);
        }
        let side = |s: u32| ((f64::from(s) * scale).round() as u32).clamp(1, s.max(1));
        (side(width), side(height))
    }

    /// The camera moved at `now` (seconds on the caller's clock): frames until
    /// [`SETTLE_SECONDS`] after it are moving frames. Call it before polling that frame's size.
    pub fn handle_motion(&mut self, now: f64) {
        if now.is_finite() {
            self.last_motion = Some(now);
        }
    }

    /// One finished frame, drawn at `now` at `scale`, whose step took `seconds`. Only moving
    /// frames teach the governor: a resting view's frames are often not drawn at all (the
    /// renderer skips an unchanged one), so their times say nothing of a moving frame's.
    /// Non-finite or non-positive figures are ignored.
    pub fn handle_frame(&mut self, now: f64, scale: f64, seconds: f64) {
        let Some(budget) = self.config.budget.map(|b| b.as_secs_f64()) else {
            return;
        };
        if !self.moving(now) {
            return;
        }
        if !(seconds.is_finite() && seconds > 0.0 && scale > 0.0 && scale <= 1.0) {
            return;
        }
        let full = seconds / (scale * scale);
        let smoothed = self
            .full_frame_seconds
            .map_or(full, |s| s + SMOOTHING * (full - s));
        self.full_frame_seconds = Some(smoothed);
        // The largest step whose predicted frame fits the budget.
        let fitting = snap_down((budget / smoothed).sqrt(), self.config.min_scale);
        if fitting < self.moving_scale {
            self.moving_scale = fitting;
        } else {
            let up = snap_down(self.moving_scale + SCALE_STEP, self.config.min_scale);
            if up > self.moving_scale && smoothed * up * up < RISE_BELOW * budget {
                self.moving_scale = up;
            }
        }
    }
}

/// `scale` rounded down to a multiple of [`SCALE_STEP`], within `[min_scale, 1]`.
fn snap_down(scale: f64, min_scale: f64) -> f64 {
    let snapped = (scale / SCALE_STEP + 1e-9).floor() * SCALE_STEP;
    if snapped.is_nan() {
        return min_scale;
    }
    snapped.clamp(min_scale, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    const FRAME: f64 = 1.0 / 60.0;

    fn governor(budget_ms: u64, min_scale: f64) -> FrameScale {
        FrameScale::new(FrameScaleConfig {
            budget: Some(Duration::from_millis(budget_ms)),
            min_scale,
        })
    }

    /// Runs `frames` frames from `start`, moving or not, each costing `full_seconds` at full
    /// size scaled by the pixels drawn; returns the time of the last one.
    fn run(g: &mut FrameScale, start: f64, frames: u32, moving: bool, full_seconds: f64) -> f64 {
        let mut now = start;
        for i in 0..frames {
            now = start + f64::from(i) * FRAME;
            if moving {
                g.handle_motion(now);
            }
            let scale = g.poll_scale(now);
            g.handle_frame(now, scale, full_seconds * scale * scale);
        }
        now
    }

    #[test]
    fn a_slow_moving_view_shrinks_until_its_frames_fit_the_budget() {
        let mut g = governor(20, 0.25);
        // 160 ms a full frame: the budget fits a pixel fraction of 1/8, a side of 0.354,
        // rounded down to 0.3125.
        let now = run(&mut g, 0.0, 30, true, 0.160);
        let scale = g.poll_scale(now);
        assert_eq!(scale, 5.0 * SCALE_STEP);
        assert!(0.160 * scale * scale <= 0.020);
        // The next step up would not fit.
        let up = scale + SCALE_STEP;
        assert!(0.160 * up * up > 0.020);
        assert_eq!(
            g.poll_size(now, 1024, 768),
            (320, 240),
            "each side scaled by the same factor"
        );
    }

    #[test]
    fn a_resting_view_is_full_size_and_keeps_what_moving_learned() {
        let mut g = governor(20, 0.25);
        let now = run(&mut g, 0.0, 30, true, 0.160);
        assert!(g.moving(now));
        // Still inside the settle time after the last motion: still scaled.
        assert!(g.poll_scale(now + SETTLE_SECONDS * 0.5) < 1.0);
        let rest = now + SETTLE_SECONDS;
        assert!(!g.moving(rest));
        assert_eq!(g.poll_scale(rest), 1.0);
        assert_eq!(g.poll_size(rest, 1024, 768), (1024, 768));
        // Frames at rest, however cheap (an unchanged view is not redrawn), teach nothing: the
        // moving scale is kept, and the next move starts at it at once.
        let now = run(&mut g, rest, 60, false, 0.001);
        g.handle_motion(now);
        assert_eq!(
            g.poll_scale(now),
            5.0 * SCALE_STEP,
            "the first moving frame is scaled already"
        );
    }

    #[test]
    fn never_below_the_smallest_scale_and_full_size_when_fast() {
        let mut g = governor(20, 0.5);
        let now = run(&mut g, 0.0, 40, true, 10.0);
        assert_eq!(g.poll_scale(now), 0.5, "clamped at the smallest scale");
        // The backend got fast (a lighter view): the scale climbs back, a step at a time,
        // to full size.
        let mut now = now;
        let mut last = g.poll_scale(now);
        for _ in 0..40 {
            now = run(&mut g, now + FRAME, 1, true, 0.004);
            let s = g.poll_scale(now);
            assert!(s - last <= SCALE_STEP + 1e-12, "rises one step at a time");
            last = s;
        }
        assert_eq!(last, 1.0);
    }

    #[test]
    fn noisy_frame_times_near_the_budget_do_not_flip_the_size() {
        let mut g = governor(20, 0.25);
        let mut now = run(&mut g, 0.0, 30, true, 0.080);
        let settled = g.poll_scale(now);
        let mut changes = 0;
        let mut last = settled;
        let mut rng = arbor_proto::rng::SplitMix64::new(7);
        for _ in 0..600 {
            // ±5 % around the same cost.
            let noise = 0.95 + 0.1 * rng.next_f64();
            now = run(&mut g, now + FRAME, 1, true, 0.080 * noise);
            let s = g.poll_scale(now);
            if s != last {
                changes += 1;
            }
            last = s;
        }
        assert!(changes <= 2, "{changes} size changes in 600 noisy frames");
    }

    #[test]
    fn without_a_budget_or_with_absurd_times_nothing_changes() {
        let mut g = FrameScale::new(FrameScaleConfig {
            budget: None,
            min_scale: 0.25,
        });
        run(&mut g, 0.0, 30, true, 10.0);
        assert_eq!(g.poll_scale(0.1), 1.0);

        let mut g = governor(20, 0.25);
        g.handle_motion(0.0);
        for bad in [f64::NAN, f64::INFINITY, -1.0, 0.0] {
            g.handle_frame(0.0, 1.0, bad);
            g.handle_frame(0.0, bad, 0.5);
        }
        assert_eq!(g.poll_scale(0.0), 1.0, "nothing learned from absurd inputs");
        let mut g = governor(20, 0.25);
        g.handle_motion(f64::NAN);
        g.handle_frame(0.0, 1.0, 10.0);
        assert_eq!(g.poll_size(0.0, 7, 3), (7, 3), "a NaN time is no motion");
        // A tiny window never gets a zero side.
        let mut g = governor(1, 0.25);
        run(&mut g, 0.0, 10, true, 1.0);
        assert_eq!(g.poll_size(9.0 * FRAME, 2, 1), (1, 1));
    }

    #[test]
    fn absurd_smallest_scales_are_refused() {
        for bad in [0.0, -0.5, 1.5, f64::NAN] {
            let config = FrameScaleConfig {
                budget: Some(Duration::from_millis(20)),
                min_scale: bad,
            };
            assert!(config.validate().is_err(), "{bad}");
        }
        assert!(FrameScaleConfig::default().validate().is_ok());
    }
}
