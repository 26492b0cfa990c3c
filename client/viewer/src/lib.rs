//! The window viewer (`arbor-client view`): one [`Session`](arbor_client_session::Session) stepped once
//! per redraw of a winit window, its frame drawn to a wgpu surface with the statistics overlay.
//!
//! The viewer owns the clock of an interactive run, the way [`arbor_client_session::headless`] owns it for a
//! scripted one: every redraw it moves the camera from the input ([`controls`]), steps the
//! session (which never waits on the network, so frames keep coming while treelets stream),
//! draws the frame and the overlay ([`overlay`]) with the blit pass ([`blit`]) and presents. It
//! keeps a [`RunReport`](arbor_client_report::RunReport) of every cycle, like a headless run.
//!
//! Where the frame comes from ([`BackendChoice`]):
//! * **cpu** — the CPU twins render an [`Image`](arbor_client_core::image::Image) each cycle and the
//!   viewer uploads it into its own `rgba8unorm` texture. Needs a wgpu device only for the
//!   blit, and is the fallback wherever the GPU renderer cannot run.
//! * **gpu** — the wgpu renderer ([`GpuBackend`](arbor_client_gpu::GpuBackend)) draws in place into
//!   its own target texture, which the blit samples directly (no read-back). It shares the
//!   window's [`GpuContext`](arbor_client_gpu::GpuContext), opened on the instance that made the
//!   surface.
//! * **auto** — as for headless runs: gpu on a hardware adapter, cpu when the window's adapter
//!   is a software one such as Mesa's lavapipe (it runs the passes on the machine's cores, more
//!   slowly than the twins: on the 2-core build machine a 256×192 frame took 41–99 ms with the
//!   CPU twins and 84–133 ms on lavapipe in the runs of `client/tests/viewer_xvfb.rs`).
//!
//! `C` prints the camera as a `--camera-path look:…` bookmark, which `view` (its start) and
//! the headless commands take.
//!
//! `-` and `=` make the picture coarser or finer by half an octree level ([`next_lod_bias`],
//! through [`Session::set_lod_bias`](arbor_client_session::Session::set_lod_bias)).
//!
//! While the camera moves, frames are drawn smaller so each stays within a frame budget
//! ([`frame_scale`]), and full size again once it rests; only a full-size frame counts as
//! converged.
//!
//! A lost device (a driver reset, the GPU removed) is replaced up to `--device-replacements`
//! times: a new device for the window, its surface, blit and renderer made again, the session
//! given the new renderer ([`Session::replace_backend`](arbor_client_session::Session::replace_backend))
//! and the run going on from what it holds; the report's events and standard output say so.
//!
//! For automated runs: `--screenshot` is written when the view converges with the camera never
//! moved, `converged at cycle N` is printed then, `--exit-after-converged` ends the run there
//! (after standard input closes, with `--hold-until-stdin-eof`, so a test can capture the
//! window first) and `--timeout-s` fails a run that does not converge in time.

#![forbid(unsafe_code)]

pub mod blit;
pub mod controls;
pub mod frame_scale;
pub mod overlay;
mod window;

use std::path::PathBuf;
use std::time::Duration;

use arbor_client_core::camera::CameraPath;
use arbor_client_gpu::{BackendChoice, FeedbackMode};
use arbor_client_session::{RunError, SessionConfig};

pub use frame_scale::FrameScaleConfig;

pub use window::run;

/// A viewer run.
#[derive(Clone, Debug)]
pub struct ViewerConfig {
    pub session: SessionConfig,
    /// Seed of the start camera ([`CameraPath::Static`]).
    pub seed: u64,
    /// Where the camera starts: `Static` (seeded) or a `Look` bookmark.
    pub start: CameraPath,
    /// Window inner size, pixels; frames follow the window's size.
    pub width: u32,
    pub height: u32,
    pub backend: BackendChoice,
    /// Whether a GPU frame waits for its analysis pass ([`FeedbackMode`]).
    pub feedback: FeedbackMode,
    /// Draw the statistics overlay (`H` toggles).
    pub overlay: bool,
    /// Written once the view converges with the camera never moved.
    pub screenshot: Option<PathBuf>,
    /// The run report (CSV) written by `R` and at exit; the chart goes beside it.
    pub report: Option<PathBuf>,
    /// Exit (successfully) once the view has converged.
    pub exit_after_converged: bool,
    /// With `exit_after_converged`: keep drawing after convergence until standard input
    /// reaches end of file.
    pub hold_until_stdin_eof: bool,
    /// Fail if the view has not converged this long after the start.
    pub timeout: Option<Duration>,
    /// Lost GPU devices replaced by a new one (window surface, blit and renderer rebuilt, the
    /// session kept) before a loss ends the run.
    pub device_replacements: u32,
    /// Fault injection for tests: destroy the window's device after this many frames, once.
    pub lose_device_after: Option<u32>,
    /// Frames rendered smaller while the camera moves ([`frame_scale`]).
    pub frame_scale: FrameScaleConfig,
    /// Scripted motion for tests: the wheel turns by [`SCRIPTED_ZOOM_LINES`] in each of the
    /// first this many frames, as a user zooming in would.
    pub scripted_zoom_frames: u32,
}

/// Wheel notches per frame of [`ViewerConfig::scripted_zoom_frames`].
pub const SCRIPTED_ZOOM_LINES: f64 = 0.05;

/// How a viewer run ended.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    /// The user closed the window or pressed Escape.
    Closed { converged_at: Option<u32> },
    /// `exit_after_converged` and the view converged at this cycle.
    Converged { cycle: u32 },
    /// The timeout passed before convergence.
    TimedOut {
        after: Duration,
        cycles: u32,
        /// Where the view stood, for people: what is known, what arrives, what is asked for.
        state: String,
    },
}

/// Why the viewer stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    #[error("window system: {0}")]
    Window(String),
    #[error("GPU: {0}")]
    Gpu(String),
    #[error(transparent)]
    Session(#[from] RunError),
    #[error("{0}")]
    Output(String),
}

impl From<winit::error::EventLoopError> for ViewerError {
    fn from(e: winit::error::EventLoopError) -> Self {
        Self::Window(e.to_string())
    }
}

/// Smallest LOD bias the quality keys reach: detail down to a quarter pixel.
pub const MIN_KEY_LOD_BIAS: f64 = 0.25;
/// Largest LOD bias the quality keys reach: voxels up to 64 pixels.
pub const MAX_KEY_LOD_BIAS: f64 = 64.0;

/// The LOD bias after a quality key (`-` coarser, `=` finer): half an octree level (a factor
/// √2) from the nearest half level to `current`, within [`MIN_KEY_LOD_BIAS`] and
/// [`MAX_KEY_LOD_BIAS`]. Snapping to half levels keeps a run of presses from drifting, so `-`
/// then `=` returns to the bias it started from.
pub fn next_lod_bias(current: f64, coarser: bool) -> f64 {
    let half_levels = |b: f64| (2.0 * b.log2()).round();
    let (lo, hi) = (half_levels(MIN_KEY_LOD_BIAS), half_levels(MAX_KEY_LOD_BIAS));
    let k = if current.is_finite() && current > 0.0 {
        half_levels(current).clamp(lo, hi)
    } else {
        0.0
    };
    let next = if coarser { k + 1.0 } else { k - 1.0 };
    2f64.powf(next.clamp(lo, hi) / 2.0)
}

/// The chart path that goes with a report path: `run.csv` → `run-chart.png`.
pub fn chart_path(report: &std::path::Path) -> PathBuf {
    let stem = report
        .file_stem()
        .map_or_else(|| "report".into(), |s| s.to_string_lossy().into_owned());
    report.with_file_name(format!("{stem}-chart.png"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quality_keys_move_by_half_levels_within_bounds() {
        let b = next_lod_bias(1.0, true);
        assert!((b - 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(next_lod_bias(b, false), 1.0, "- then = is where it started");
        assert_eq!(next_lod_bias(next_lod_bias(1.0, true), true), 2.0);
        // A bias from the command line between half levels snaps to the nearest first.
        assert_eq!(next_lod_bias(1.1, true), 2f64.sqrt());
        let mut b = 1.0;
        for _ in 0..40 {
            b = next_lod_bias(b, true);
        }
        assert_eq!(b, MAX_KEY_LOD_BIAS);
        for _ in 0..40 {
            b = next_lod_bias(b, false);
        }
        assert_eq!(b, MIN_KEY_LOD_BIAS);
        // Beyond the bounds (from the command line) the keys come back within them; absurd
        // values start from 1.
        assert_eq!(next_lod_bias(1000.0, true), MAX_KEY_LOD_BIAS);
        assert_eq!(next_lod_bias(1000.0, false), 2f64.powf(11.0 / 2.0));
        assert_eq!(next_lod_bias(f64::NAN, true), 2f64.sqrt());
    }

    #[test]
    fn chart_goes_beside_the_report() {
        assert_eq!(
            chart_path(std::path::Path::new("/tmp/x/run.csv")),
            PathBuf::from("/tmp/x/run-chart.png")
        );
        assert_eq!(
            chart_path(std::path::Path::new("run")),
            PathBuf::from("run-chart.png")
        );
    }
}
