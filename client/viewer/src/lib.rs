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
//!   CPU twins and 84–133 ms on lavapipe in the runs of `tests/tests/viewer_xvfb.rs`).
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

use arbor_client_gpu::{BackendChoice, FeedbackMode};
use arbor_client_session::{RunError, SessionConfig};

pub use frame_scale::FrameScaleConfig;

pub use window::run;

/// A viewer run.
#[derive(Clone, Debug)]
pub struct ViewerConfig {
    pub session: SessionConfig,
    /// Seed of the start camera ([`CameraPath::Static`](arbor_client_core::camera::CameraPath::Static)).
    pub seed: u64,
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
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Outcome {
    /// The user closed the window or pressed Escape.
    Closed { converged_at: Option<u32> },
    /// `exit_after_converged` and the view converged at this cycle.
    Converged { cycle: u32 },
    /// The timeout passed before convergence.
    TimedOut { after: Duration, cycles: u32 },
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
