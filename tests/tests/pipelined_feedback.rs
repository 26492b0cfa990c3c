//! A pipelined backend hands an analysis pass back a cycle late (the GPU backend reads feedback
//! back without waiting). Under a camera that moves every cycle, each pass then describes the
//! previous view: it must still steer the requests (as a hint), or a moving view would never ask
//! for anything — found by the main job's orbit on lavapipe (240 cycles, 0 requests). It must
//! not count as knowledge: a static camera still converges only on its own samples, exactly.

use std::any::Any;

use arbor_client_core::analysis::Feedback;
use arbor_client_core::backend::{Backend, BackendError, CpuBackend, PassInput};
use arbor_client_core::camera::CameraPath;
use arbor_client_core::cycle::{ClientCore, CoreConfig};
use arbor_client_core::image::Image;
use arbor_client_core::slots::SlotBuffer;
use arbor_client_core::upload::UploadPlan;
use arbor_proto::TreeletId;
use arbor_tests::support::small_lion_decoded;

/// The CPU twins, with every analysis pass handed back one call late.
#[derive(Debug, Default)]
struct LateCpu {
    pending: Option<Feedback>,
}

impl Backend for LateCpu {
    fn name(&self) -> String {
        "cpu, feedback a cycle late".into()
    }

    fn analyse(
        &mut self,
        input: &PassInput<'_>,
        pixels: &[u32],
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        let mut now = Feedback::default();
        CpuBackend.analyse(input, pixels, cycle, &mut now)?;
        *out = self.pending.replace(now).unwrap_or_default();
        Ok(())
    }

    fn upload(&mut self, _slots: &SlotBuffer, _plan: &UploadPlan) -> Result<(), BackendError> {
        Ok(())
    }

    fn render(&mut self, input: &PassInput<'_>) -> Result<Image, BackendError> {
        CpuBackend.render(input)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// What a run did.
#[derive(Debug, Default)]
struct Ran {
    /// Requests sent over the run and over its second half.
    requested: usize,
    requested_late: usize,
    /// Treelets inserted, slots evicted.
    inserted: u32,
    evicted: u32,
    /// The last plan's convergence.
    converged: bool,
}

/// Runs `cycles` cycles of lion (1 KiB treelets) on the late backend along `path` with room for
/// `slots` slots, answering every request at once.
fn run(path: CameraPath, cycles: u32, slots: u64) -> Ran {
    let (scene, treelets) = small_lion_decoded();
    let channels = scene.layout.channels().to_vec();
    let config = CoreConfig {
        budget_bytes: slots * SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
        channels,
        deep_push: false,
        ..CoreConfig::default()
    };
    let root = treelets[&TreeletId::ROOT].clone();
    let mut core =
        ClientCore::with_backend(scene, config, root, Box::new(LateCpu::default())).unwrap();
    let mut ran = Ran::default();
    for cycle in 0..cycles {
        let camera = path.camera(cycle, core.frame(), 3, 96, 96);
        let plan = core.plan(&camera).unwrap();
        ran.requested += plan.requests.len();
        if cycle >= cycles / 2 {
            ran.requested_late += plan.requests.len();
        }
        ran.converged = plan.converged;
        for (id, _) in &plan.requests {
            core.handle_treelet(treelets[id].clone());
        }
        let i = core.integrate();
        ran.inserted += i.inserted;
        ran.evicted += i.evicted;
        if ran.converged {
            break;
        }
    }
    ran
}

#[test]
fn a_moving_camera_refines_on_feedback_a_cycle_late() {
    let orbit = CameraPath::Orbit {
        degrees_per_cycle: 2.0,
    };
    let ran = run(orbit, 40, 4096);
    assert!(!ran.converged, "a moving view never converges");
    assert!(
        ran.requested > 100 && ran.inserted > 100,
        "the orbit asked for too little: {ran:?}"
    );
}

/// A buffer about the size of what the view needs: a moving view keeps making room for what
/// comes into view (the thesis's n² cycles of visibility held everything seen in a 128° arc and
/// stopped all requests once the buffer was full).
#[test]
fn a_moving_camera_keeps_refining_in_a_small_buffer() {
    let orbit = CameraPath::Orbit {
        degrees_per_cycle: 2.0,
    };
    let ran = run(orbit, 160, 400);
    assert!(
        ran.evicted > 50 && ran.requested_late > 50,
        "the orbit stopped refining: {ran:?}"
    );
}

#[test]
fn a_static_camera_converges_on_feedback_a_cycle_late() {
    let ran = run(CameraPath::Static, 400, 4096);
    assert!(ran.converged, "no convergence: {ran:?}");
    assert!(ran.inserted > 100, "{ran:?}");
}
