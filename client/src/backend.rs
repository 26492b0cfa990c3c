//! Where the per-cycle GPU stages run: the analysis pass, the slot upload and the render pass
//! (DESIGN §5). [`ClientCore`](crate::run::ClientCore) drives a [`Backend`] and never knows
//! which one it has.
//!
//! [`CpuBackend`] runs the CPU twins (the reference every GPU stage is tested against); the
//! wgpu backend (`crate::gpu`) runs the WGSL passes. A backend may return the analysis of an
//! earlier cycle (the GPU one returns the previous cycle's read-back so the frame never waits
//! on it); the core only needs the freshest complete feedback.

use crate::analysis::{AnalysisConfig, Feedback, analyse};
use crate::camera::Camera;
use crate::image::Image;
use crate::incore::SceneFrame;
use crate::render::{Light, render};
use crate::slots::SlotBuffer;
use crate::upload::UploadPlan;

/// The GPU-side stages of a cycle.
pub trait Backend: std::fmt::Debug + Send {
    /// For people and reports: `cpu` or the adapter's name and backend.
    fn name(&self) -> String;

    /// The most slots of `treelet_nodes` records (plus `channels`) this backend can hold; the
    /// core shrinks its budget to it (a GPU binding may cover only so many bytes).
    fn max_slots(&self, _treelet_nodes: u32, _channels: &[arbor_proto::Channel]) -> u32 {
        u32::MAX
    }

    /// Runs the analysis pass of `cycle` and leaves in `out` the most recent complete feedback
    /// (this cycle's, or an earlier one's for a pipelined backend; empty before the first).
    fn analyse(
        &mut self,
        slots: &SlotBuffer,
        frame: &SceneFrame,
        camera: &Camera,
        config: &AnalysisConfig,
        cycle: u64,
        out: &mut Feedback,
    );

    /// Copies the slot ranges of `plan` from `slots` to wherever the passes read them.
    fn upload(&mut self, slots: &SlotBuffer, plan: &UploadPlan);

    /// Renders into the backend's own target without reading it back (the window viewer draws
    /// that target); `false` if the backend has no such target (the CPU one).
    fn render_in_place(
        &mut self,
        _slots: &SlotBuffer,
        _frame: &SceneFrame,
        _camera: &Camera,
        _lod_bias: f64,
        _light: &Light,
    ) -> bool {
        false
    }

    /// The target [`render_in_place`](Self::render_in_place) drew into, if any.
    fn target_view(&self) -> Option<&wgpu::TextureView> {
        None
    }

    /// Renders what is resident as seen from `camera`, read back.
    fn render(
        &mut self,
        slots: &SlotBuffer,
        frame: &SceneFrame,
        camera: &Camera,
        lod_bias: f64,
        light: &Light,
    ) -> Image;
}

/// The CPU twins: they read the slot buffer in place, so upload is a no-op.
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuBackend;

impl Backend for CpuBackend {
    fn name(&self) -> String {
        "cpu".into()
    }

    fn analyse(
        &mut self,
        slots: &SlotBuffer,
        frame: &SceneFrame,
        camera: &Camera,
        config: &AnalysisConfig,
        cycle: u64,
        out: &mut Feedback,
    ) {
        analyse(&slots.view(), frame, camera, config, cycle, out);
    }

    fn upload(&mut self, _slots: &SlotBuffer, _plan: &UploadPlan) {}

    fn render(
        &mut self,
        slots: &SlotBuffer,
        frame: &SceneFrame,
        camera: &Camera,
        lod_bias: f64,
        light: &Light,
    ) -> Image {
        render(&slots.view(), frame, camera, lod_bias, light)
    }
}

/// Which backend a run asks for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BackendChoice {
    /// The GPU when an adapter exists (software ones such as lavapipe included), else the CPU
    /// twins — saying so.
    #[default]
    Auto,
    /// The GPU or an error.
    Gpu,
    /// The CPU twins.
    Cpu,
}

impl BackendChoice {
    /// Parses `auto`, `gpu` or `cpu` (the CLI spelling).
    pub fn parse(text: &str) -> Option<Self> {
        match text {
            "auto" => Some(Self::Auto),
            "gpu" => Some(Self::Gpu),
            "cpu" => Some(Self::Cpu),
            _ => None,
        }
    }
}

/// A backend made for a run, and why it is not the GPU one when [`BackendChoice::Auto`] fell
/// back.
#[derive(Debug)]
pub struct ChosenBackend {
    pub backend: Box<dyn Backend>,
    /// `Some(reason)` when `Auto` found no usable adapter and runs on the CPU twins.
    pub fallback: Option<String>,
}

/// Makes the backend `choice` asks for.
pub fn create_backend(choice: BackendChoice) -> Result<ChosenBackend, crate::gpu::GpuError> {
    use std::sync::Arc;

    use crate::gpu::{GpuBackend, GpuContext};
    match choice {
        BackendChoice::Cpu => Ok(ChosenBackend {
            backend: Box::new(CpuBackend),
            fallback: None,
        }),
        BackendChoice::Gpu => Ok(ChosenBackend {
            backend: Box::new(GpuBackend::new(Arc::new(GpuContext::new(None)?))),
            fallback: None,
        }),
        BackendChoice::Auto => match GpuContext::new(None) {
            Ok(ctx) => Ok(ChosenBackend {
                backend: Box::new(GpuBackend::new(Arc::new(ctx))),
                fallback: None,
            }),
            Err(e) => Ok(ChosenBackend {
                backend: Box::new(CpuBackend),
                fallback: Some(e.to_string()),
            }),
        },
    }
}
