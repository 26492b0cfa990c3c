//! The wgpu path of the client (docs/design.md §5, §9): the analysis and render passes as WGSL compute
//! shaders over the incore buffer held in GPU storage buffers, and the slot upload.
//!
//! - [`context`] owns the wgpu instance, adapter, device and queue ([`GpuContext`]);
//! - [`layout`] owns every struct shared with WGSL, as `#[repr(C)]` Rust twins;
//! - [`backend`] owns the GPU buffers, pipelines and read-backs, and implements
//!   [`Backend`](arbor_client_core::backend::Backend) ([`GpuBackend`]);
//! - [`shaders`] embeds the WGSL of each pass, validated by naga at build time.
//!
//! The shaders are twins of the CPU modules (`trace.rs`, `analysis.rs`, `render.rs`): the tests
//! `client/tests/gpu_twin.rs` and `tests/tests/gpu_real.rs` hold them to the CPU answers.

#![forbid(unsafe_code)]

pub mod backend;
mod choice;
pub mod context;
pub mod layout;

pub use backend::{FeedbackMode, GpuBackend, PassTimes, UploadStats};
pub use choice::{BackendChoice, ChosenBackend, create_backend, create_backend_with};
pub use context::{GpuContext, GpuError};
pub use layout::FrameUniform;

/// The WGSL sources of the passes, each `shaders/traverse.wgsl` followed by the pass file,
/// validated with naga by this crate's `build.rs`.
pub mod shaders {
    /// The analysis pass; entry point [`ANALYSIS_ENTRY`].
    pub const ANALYSIS: &str = include_str!(concat!(env!("OUT_DIR"), "/analysis.wgsl"));
    /// The render pass; entry point [`RENDER_ENTRY`].
    pub const RENDER: &str = include_str!(concat!(env!("OUT_DIR"), "/render.wgsl"));
    /// Entry point (and pipeline label) of the analysis pass, named like its CPU module.
    pub const ANALYSIS_ENTRY: &str = "analysis";
    /// Entry point (and pipeline label) of the render pass, named like its CPU module.
    pub const RENDER_ENTRY: &str = "render";
}
