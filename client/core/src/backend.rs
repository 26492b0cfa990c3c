//! Where the per-cycle GPU stages run: the analysis pass, the slot upload and the render pass
//! (docs/design.md §5). [`ClientCore`](crate::cycle::ClientCore) drives a [`Backend`] and never knows
//! which one it has.
//!
//! [`CpuBackend`] runs the CPU twins (the reference every GPU stage is tested against); the
//! wgpu backend (`arbor-client-gpu`) runs the WGSL passes. A backend may return the analysis of an
//! earlier cycle (the GPU one returns the previous cycle's read-back so the frame never waits
//! on it); the core only needs the freshest complete feedback.

use std::any::Any;

use crate::analysis::{AnalysisConfig, Feedback, analyse_pixels};
use crate::camera::Camera;
use crate::image::Image;
use crate::incore::SceneFrame;
use crate::render::{Light, render};
use crate::slots::SlotBuffer;
use crate::upload::UploadPlan;

/// Everything a pass reads in one cycle: the incore octree, where it sits in the world, the
/// view, and the analysis and shading settings.
#[derive(Clone, Copy, Debug)]
pub struct PassInput<'a> {
    /// The incore octree (nodes and attributes).
    pub slots: &'a SlotBuffer,
    /// The scene's root cube and target depth.
    pub frame: &'a SceneFrame,
    /// The view.
    pub camera: &'a Camera,
    /// Feedback ratio and LOD bias (the render pass uses the LOD bias too).
    pub analysis: &'a AnalysisConfig,
    /// Shading of the render pass.
    pub light: &'a Light,
}

/// The GPU-side stages of a cycle.
pub trait Backend: std::fmt::Debug + Send {
    /// For people and reports: `cpu` or the adapter's name and backend.
    fn name(&self) -> String;

    /// The most slots of `treelet_nodes` records (plus `channels`) this backend can hold; the
    /// core shrinks its budget to it (a GPU binding may cover only so many bytes).
    fn max_slots(&self, _treelet_nodes: u32, _channels: &[arbor_proto::Channel]) -> u32 {
        u32::MAX
    }

    /// Runs the analysis pass of `cycle` over `pixels` (packed, see
    /// [`crate::analysis::pack_pixel`]) and leaves in `out` the most recent complete feedback:
    /// this cycle's, or an earlier one's for a pipelined backend (its `cycle` says which), or an
    /// empty one before the first.
    fn analyse(&mut self, input: &PassInput<'_>, pixels: &[u32], cycle: u64, out: &mut Feedback);

    /// Copies the slot ranges of `plan` from `slots` to wherever the passes read them.
    fn upload(&mut self, slots: &SlotBuffer, plan: &UploadPlan);

    /// Renders into the backend's own target without reading it back (the window viewer draws
    /// that target); `false` if the backend has no such target (the CPU one).
    fn render_in_place(&mut self, _input: &PassInput<'_>) -> bool {
        false
    }

    /// Renders what is resident as seen from `input.camera`, read back.
    fn render(&mut self, input: &PassInput<'_>) -> Image;

    /// Samples and seconds of the last analysis pass whose cost the backend measured itself
    /// (a GPU's timestamp queries); `None` when the caller's wall clock is the measure (the CPU
    /// twins run inside the call).
    fn analysis_cost(&self) -> Option<(usize, f64)> {
        None
    }

    /// The backend as [`Any`], so a shell that knows the concrete type (the viewer drawing a
    /// GPU backend's target) can reach it without the core knowing GPU types.
    fn as_any(&self) -> &dyn Any;
}

/// The CPU twins: they read the slot buffer in place, so upload is a no-op.
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuBackend;

impl Backend for CpuBackend {
    fn name(&self) -> String {
        "cpu".into()
    }

    fn analyse(&mut self, input: &PassInput<'_>, pixels: &[u32], cycle: u64, out: &mut Feedback) {
        analyse_pixels(
            &input.slots.view(),
            input.frame,
            input.camera,
            input.analysis.lod_bias,
            pixels,
            cycle,
            out,
        );
    }

    fn upload(&mut self, _slots: &SlotBuffer, _plan: &UploadPlan) {}

    fn render(&mut self, input: &PassInput<'_>) -> Image {
        render(
            &input.slots.view(),
            input.frame,
            input.camera,
            input.analysis.lod_bias,
            input.light,
        )
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// Uploads every slot of `slots` to `backend` and renders them: the image of a buffer that was
/// filled outside a run (a fully resident scene).
pub fn render_resident(
    slots: &SlotBuffer,
    frame: &SceneFrame,
    camera: &Camera,
    lod_bias: f64,
    light: &Light,
    backend: &mut dyn Backend,
) -> Image {
    let config = slots.config();
    let all: Vec<u32> = (0..slots.capacity()).collect();
    let bytes = SlotBuffer::slot_data_bytes(config.treelet_nodes, &config.channels);
    backend.upload(slots, &UploadPlan::new(&all, 0.0, bytes));
    let analysis = AnalysisConfig {
        lod_bias,
        ..AnalysisConfig::default()
    };
    backend.render(&PassInput {
        slots,
        frame,
        camera,
        analysis: &analysis,
        light,
    })
}
