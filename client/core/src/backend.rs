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
use crate::render::{Light, render, render_rects};
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

/// Why a backend could not run a stage. A GPU backend reports these instead of panicking, and
/// once it has reported one every later call reports it again: a lost or faulted device is not
/// used again. The CPU backend never fails.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BackendError {
    /// The device is gone (a driver reset, the GPU removed, the device destroyed); what it held
    /// is lost with it.
    #[error("the GPU device was lost ({0})")]
    DeviceLost(String),
    /// The device ran out of memory for a buffer or a submission.
    #[error("the GPU ran out of memory: {0}")]
    OutOfMemory(String),
    /// The device refused a command or failed inside (a validation or internal error of the
    /// driver or of wgpu), or a read-back could not be mapped.
    #[error("the GPU failed: {0}")]
    Device(String),
}

/// The GPU-side stages of a cycle. Every stage may fail with a [`BackendError`] (a GPU device
/// can be lost at any time); the core passes it on and the session ends the run with it.
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
    fn analyse(
        &mut self,
        input: &PassInput<'_>,
        pixels: &[u32],
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError>;

    /// Copies the slot ranges of `plan` from `slots` to wherever the passes read them.
    fn upload(&mut self, slots: &SlotBuffer, plan: &UploadPlan) -> Result<(), BackendError>;

    /// Renders into the backend's own target without reading it back (the window viewer draws
    /// that target); `false` if the backend has no such target (the CPU one).
    fn render_in_place(&mut self, _input: &PassInput<'_>) -> Result<bool, BackendError> {
        Ok(false)
    }

    /// Renders what is resident as seen from `input.camera`, read back.
    fn render(&mut self, input: &PassInput<'_>) -> Result<Image, BackendError>;

    /// Whether [`Backend::render_rects`] draws less than the whole frame: only then does the
    /// core work out the rectangles.
    fn renders_rects(&self) -> bool {
        false
    }

    /// Renders again the pixels in `rects` (`[x0, y0, x1, y1]`, inclusive) of `image`, which
    /// holds [`Backend::render`]'s image of the same view from before the slot arrays changed,
    /// and only where the rectangles cover (see [`SlotBuffer::take_changed_cells`]). By
    /// default the whole frame, which is always right.
    fn render_rects(
        &mut self,
        input: &PassInput<'_>,
        image: &mut Image,
        _rects: &[[u32; 4]],
    ) -> Result<(), BackendError> {
        *image = self.render(input)?;
        Ok(())
    }

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

    fn analyse(
        &mut self,
        input: &PassInput<'_>,
        pixels: &[u32],
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        analyse_pixels(
            &input.slots.view(),
            input.frame,
            input.camera,
            input.analysis.lod_bias,
            pixels,
            cycle,
            out,
        );
        Ok(())
    }

    fn upload(&mut self, _slots: &SlotBuffer, _plan: &UploadPlan) -> Result<(), BackendError> {
        Ok(())
    }

    fn render(&mut self, input: &PassInput<'_>) -> Result<Image, BackendError> {
        Ok(render(
            &input.slots.view(),
            input.frame,
            input.camera,
            input.analysis.lod_bias,
            input.light,
        ))
    }

    fn renders_rects(&self) -> bool {
        true
    }

    fn render_rects(
        &mut self,
        input: &PassInput<'_>,
        image: &mut Image,
        rects: &[[u32; 4]],
    ) -> Result<(), BackendError> {
        render_rects(
            &input.slots.view(),
            input.frame,
            input.camera,
            input.analysis.lod_bias,
            input.light,
            image,
            rects,
        );
        Ok(())
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// Uploads every slot of `slots` to `backend`, in one range: what a backend that holds nothing
/// yet needs (a fully resident scene, or a replacement for a lost device).
pub fn upload_all(slots: &SlotBuffer, backend: &mut dyn Backend) -> Result<(), BackendError> {
    let config = slots.config();
    let all: Vec<u32> = (0..slots.capacity()).collect();
    let bytes = SlotBuffer::slot_data_bytes(config.treelet_nodes, &config.channels);
    backend.upload(slots, &UploadPlan::new(&all, 0.0, bytes))
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
) -> Result<Image, BackendError> {
    upload_all(slots, backend)?;
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
