//! The client core renders a view again only when something it shows has changed: the camera,
//! the LOD bias in effect or the slot buffer's arrays ([`SlotBuffer::changes`]); when only the
//! arrays changed, a backend that can re-renders just the pixels whose rays may meet the
//! changed cells ([`SlotBuffer::take_changed_cells`]). Checked on
//! lion (1 KiB treelets) refined to convergence and then held: every image the core hands out,
//! memoised or not, equals a fresh CPU render of what is resident, and so does what the
//! backend's own target holds after an in-place render that was skipped.

use std::any::Any;
use std::collections::HashMap;
use std::sync::Arc;

use arbor_client_core::analysis::Feedback;
use arbor_client_core::backend::{Backend, BackendError, CpuBackend, PassInput};
use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::{ClientCore, CoreConfig};
use arbor_client_core::image::Image;
use arbor_client_core::render::render;
use arbor_client_core::slots::{DecodedTreelet, SlotBuffer};
use arbor_client_core::upload::UploadPlan;
use arbor_proto::TreeletId;
use arbor_tests::support::{decoded_treelets, small_lion};

/// The CPU twins, counting the renders they are asked for, with a target of their own that
/// [`Backend::render_in_place`] draws into (as the GPU backend's texture).
#[derive(Debug)]
struct Counting {
    renders: Arc<std::sync::atomic::AtomicU32>,
    in_place: Arc<std::sync::atomic::AtomicU32>,
    target: Arc<std::sync::Mutex<Option<Image>>>,
}

impl Backend for Counting {
    fn name(&self) -> String {
        "cpu, counting renders".into()
    }

    fn analyse(
        &mut self,
        input: &PassInput<'_>,
        pixels: &[u32],
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        CpuBackend.analyse(input, pixels, cycle, out)
    }

    fn upload(&mut self, _slots: &SlotBuffer, _plan: &UploadPlan) -> Result<(), BackendError> {
        Ok(())
    }

    fn render_in_place(&mut self, input: &PassInput<'_>) -> Result<bool, BackendError> {
        self.in_place
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        *self.target.lock().unwrap() = Some(CpuBackend.render(input)?);
        Ok(true)
    }

    fn render(&mut self, input: &PassInput<'_>) -> Result<Image, BackendError> {
        self.renders
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let image = CpuBackend.render(input)?;
        // The GPU backend's read-back draws into its target too.
        *self.target.lock().unwrap() = Some(image.clone());
        Ok(image)
    }

    fn render_rects(
        &mut self,
        input: &PassInput<'_>,
        image: &mut Image,
        rects: &[[u32; 4]],
    ) -> Result<bool, BackendError> {
        CpuBackend.render_rects(input, image, rects)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// What `core` shows from `camera`, rendered afresh.
fn fresh(core: &ClientCore, camera: &Camera) -> Image {
    render(
        &core.slots().view(),
        core.frame(),
        camera,
        core.lod_bias().bias(),
        &core.config().light,
    )
}

#[test]
fn an_unchanged_view_is_not_rendered_again_and_its_images_stay_exact() {
    let built = small_lion();
    let treelets: HashMap<TreeletId, DecodedTreelet> = decoded_treelets(&built.scene)
        .into_iter()
        .map(|t| (t.id(), t))
        .collect();
    let scene = Arc::new(built.scene.description.clone());
    let channels = scene.layout.channels().to_vec();
    let config = CoreConfig {
        budget_bytes: 4096 * SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
        channels,
        deep_push: false,
        ..CoreConfig::default()
    };
    let backend = Counting {
        renders: Default::default(),
        in_place: Default::default(),
        target: Default::default(),
    };
    let (renders, in_place, target) = (
        backend.renders.clone(),
        backend.in_place.clone(),
        backend.target.clone(),
    );
    let count =
        |c: &Arc<std::sync::atomic::AtomicU32>| c.load(std::sync::atomic::Ordering::Relaxed);
    let root = treelets[&TreeletId::ROOT].clone();
    let mut core = ClientCore::with_backend(scene, config, root, Box::new(backend)).unwrap();
    let camera = CameraPath::Static.camera(0, core.frame(), 3, 96, 96);
    let mut converged_at = None;
    let mut in_place_calls = 0;
    for cycle in 0..400u32 {
        let plan = core.plan(&camera).unwrap();
        for (id, _) in &plan.requests {
            core.handle_treelet(treelets[id].clone());
        }
        core.integrate();
        core.upload().unwrap();
        // Both ways of rendering, and now and then another view: the memo must not hand one
        // camera's image to another, nor leave the target holding it.
        let look = if cycle % 7 == 3 {
            CameraPath::Static.camera(0, core.frame(), 4, 96, 96)
        } else {
            camera
        };
        if cycle % 3 != 2 {
            assert!(core.render_in_place(&look).unwrap());
            in_place_calls += 1;
            assert!(
                target.lock().unwrap().as_ref() == Some(&fresh(&core, &look)),
                "cycle {cycle}: the target does not hold the view"
            );
        }
        if cycle % 3 != 1 {
            let image = core.render(&look).unwrap();
            assert!(image == fresh(&core, &look), "cycle {cycle}: image differs");
        }
        if plan.converged && converged_at.is_none() {
            converged_at = Some(cycle);
        }
        if converged_at.is_some_and(|c| cycle > c + 40) {
            break;
        }
    }
    let converged_at = converged_at.expect("the static view converges");
    assert!(
        count(&in_place) < in_place_calls,
        "{} of {in_place_calls} in-place renders reached the backend: none was skipped",
        count(&in_place)
    );
    // The read-back renders reach the backend under debug assertions too (each memoised image
    // is checked against a fresh one), so they are counted by the core.
    assert!(
        core.skipped_renders() > u64::from(in_place_calls - count(&in_place)),
        "{} renders skipped, {} of them in place",
        core.skipped_renders(),
        in_place_calls - count(&in_place)
    );
    assert!(
        core.partial_renders() > 0,
        "no image was rendered again only where the slots changed"
    );
    eprintln!(
        "converged at cycle {converged_at}: {} renders and {} of {in_place_calls} in place \
         reached the backend, {} skipped, {} partial",
        count(&renders),
        count(&in_place),
        core.skipped_renders(),
        core.partial_renders()
    );
}
