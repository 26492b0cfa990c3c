//! A backend whose device was lost is replaced without starting over
//! ([`ClientCore::replace_backend`]): the new one is given every slot of the buffer at once,
//! nothing drawn by the old one is handed out again, the pixels of the pass that failed with
//! the old one are the new one's first to sample, and the run goes on from what it holds.
//! One that cannot hold the buffer is refused and the old one stays. Checked offline on lion
//! (1 KiB treelets) with a backend that runs the CPU twins and records what it is given; the GPU
//! backend on a real (destroyed) device is in `gpu_e2e.rs`.

use std::any::Any;
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};

use arbor_client_core::analysis::Feedback;
use arbor_client_core::backend::{Backend, BackendError, CpuBackend, PassInput};
use arbor_client_core::camera::CameraPath;
use arbor_client_core::cycle::{ClientCore, CoreConfig};
use arbor_client_core::image::Image;
use arbor_client_core::render::render;
use arbor_client_core::slots::{DecodedTreelet, SlotBuffer};
use arbor_client_core::upload::UploadPlan;
use arbor_proto::TreeletId;
use arbor_tests::support::small_lion_decoded;

/// The CPU twins, holding at most `max_slots` and recording the slots uploaded to them and the
/// renders asked of them.
#[derive(Debug)]
struct Recording {
    name: &'static str,
    max_slots: u32,
    uploaded: Arc<Mutex<Vec<u32>>>,
    renders: Arc<AtomicU32>,
    /// The pixels of every analysis pass asked of it, failed or not.
    analysed: Arc<Mutex<Vec<Vec<u32>>>>,
    /// The analysis pass (counted from 0) that fails as on a lost device.
    lose_device_at_pass: Option<usize>,
}

impl Recording {
    fn new(name: &'static str, max_slots: u32) -> Self {
        Self {
            name,
            max_slots,
            uploaded: Arc::default(),
            renders: Arc::default(),
            analysed: Arc::default(),
            lose_device_at_pass: None,
        }
    }
}

impl Backend for Recording {
    fn name(&self) -> String {
        self.name.into()
    }

    fn max_slots(&self, _treelet_nodes: u32, _channels: &[arbor_proto::Channel]) -> u32 {
        self.max_slots
    }

    fn analyse(
        &mut self,
        input: &PassInput<'_>,
        pixels: &[u32],
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        let pass = {
            let mut analysed = self.analysed.lock().unwrap();
            analysed.push(pixels.to_vec());
            analysed.len() - 1
        };
        if self.lose_device_at_pass == Some(pass) {
            return Err(BackendError::DeviceLost("destroyed by the test".into()));
        }
        CpuBackend.analyse(input, pixels, cycle, out)
    }

    fn upload(&mut self, _slots: &SlotBuffer, plan: &UploadPlan) -> Result<(), BackendError> {
        let mut uploaded = self.uploaded.lock().unwrap();
        for r in &plan.ranges {
            uploaded.extend(r.clone());
        }
        Ok(())
    }

    fn render(&mut self, input: &PassInput<'_>) -> Result<Image, BackendError> {
        self.renders.fetch_add(1, Ordering::Relaxed);
        CpuBackend.render(input)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// Slots of the tests' buffer.
const CAPACITY: u32 = 1024;

/// A core on lion (1 KiB treelets) with a buffer of [`CAPACITY`] slots, passes on `backend`;
/// the scene's decoded treelets.
fn lion_core(backend: Recording) -> (ClientCore, HashMap<TreeletId, DecodedTreelet>) {
    let (scene, treelets) = small_lion_decoded();
    let channels = scene.layout.channels().to_vec();
    let config = CoreConfig {
        budget_bytes: u64::from(CAPACITY) * SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
        channels,
        deep_push: false,
        ..CoreConfig::default()
    };
    let root = treelets[&TreeletId::ROOT].clone();
    let core = ClientCore::with_backend(scene, config, root, Box::new(backend)).unwrap();
    (core, treelets)
}

#[test]
fn a_replacement_gets_every_slot_and_the_run_goes_on_exactly() {
    let (mut core, treelets) = lion_core(Recording::new("first", u32::MAX));
    let capacity = core.slots().capacity();
    assert_eq!(capacity, CAPACITY);
    let camera = CameraPath::Static.camera(0, core.frame(), 3, 96, 96);
    let fresh = |core: &ClientCore| {
        render(
            &core.slots().view(),
            core.frame(),
            &camera,
            core.lod_bias().bias(),
            &core.config().light,
        )
    };
    let step = |core: &mut ClientCore| {
        let plan = core.plan(&camera).unwrap();
        for (id, _) in &plan.requests {
            core.handle_treelet(treelets[id].clone());
        }
        core.integrate();
        core.upload().unwrap();
        plan.converged
    };
    // Part of the way: a buffer with more than the root in it, and an image of it.
    for _ in 0..6 {
        step(&mut core);
    }
    let used = core.slots().used_slots();
    assert!(used > 50, "only {used} slots in use after six cycles");
    let before = core.render(&camera).unwrap();
    assert!(before == fresh(&core));

    // Too small for the buffer: refused, and the old backend goes on.
    let small = Recording::new("small", capacity - 1);
    let uploaded_small = small.uploaded.clone();
    match core.replace_backend(Box::new(small)) {
        Err(BackendError::OutOfMemory(reason)) => {
            assert!(reason.contains(&format!("{}", capacity - 1)), "{reason}");
            assert!(reason.contains(&format!("{capacity}")), "{reason}");
        }
        other => panic!("a backend of fewer slots than the buffer was taken: {other:?}"),
    }
    assert_eq!(core.backend_name(), "first");
    assert!(uploaded_small.lock().unwrap().is_empty());

    // The replacement: every slot at once, and it draws the next image itself.
    let second = Recording::new("second", capacity);
    let (uploaded, renders) = (second.uploaded.clone(), second.renders.clone());
    core.replace_backend(Box::new(second)).unwrap();
    assert_eq!(core.backend_name(), "second");
    assert_eq!(
        *uploaded.lock().unwrap(),
        (0..capacity).collect::<Vec<u32>>(),
        "the replacement was not given the whole buffer"
    );
    let again = core.render(&camera).unwrap();
    assert!(
        renders.load(Ordering::Relaxed) >= 1,
        "the old backend's image was handed out"
    );
    assert!(again == before, "the same buffer drew a different image");

    // The run goes on from what it holds to the exact picture.
    let converged = (0..400).any(|_| step(&mut core));
    assert!(converged, "the view did not converge after the replacement");
    assert!(core.slots().used_slots() >= used);
    assert!(core.render(&camera).unwrap() == fresh(&core));
}

/// A pass that fails with its device is answered by no pass of the replacement: its pixels are
/// the replacement's first to sample. Before, the plan waited for a later pass to show it was
/// lost, and here the replacement's first pass had no pixels at all: with nothing else left to
/// sample no later pass came, and only `LOST_PLAN_CYCLES` brought the pixels back.
#[test]
fn the_pixels_of_the_failed_pass_are_the_replacements_first() {
    let mut first = Recording::new("first", u32::MAX);
    first.lose_device_at_pass = Some(2);
    let lost_with = first.analysed.clone();
    let (mut core, _) = lion_core(first);
    let camera = CameraPath::Static.camera(0, core.frame(), 3, 256, 256);
    for _ in 0..2 {
        core.plan(&camera).unwrap();
        core.integrate();
        core.upload().unwrap();
    }
    match core.plan(&camera) {
        Err(BackendError::DeviceLost(_)) => {}
        other => panic!("the third pass did not fail: {other:?}"),
    }
    let failed = lost_with.lock().unwrap()[2].clone();
    assert!(!failed.is_empty(), "the failed pass sampled nothing");

    let second = Recording::new("second", u32::MAX);
    let analysed = second.analysed.clone();
    core.replace_backend(Box::new(second)).unwrap();
    core.plan(&camera).unwrap();
    let next: HashSet<u32> = analysed.lock().unwrap()[0].iter().copied().collect();
    let missing = failed.iter().filter(|p| !next.contains(p)).count();
    assert_eq!(
        missing,
        0,
        "{missing} of the failed pass's {} pixels not in the replacement's first pass ({} pixels)",
        failed.len(),
        next.len()
    );
}
