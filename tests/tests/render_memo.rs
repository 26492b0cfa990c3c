//! The client core renders a view again only when something it shows has changed: the camera,
//! the LOD bias in effect or the slot buffer's arrays ([`SlotBuffer::changes`]); when only the
//! arrays changed, a backend that can re-renders just the pixels whose rays may meet the
//! changed cells ([`SlotBuffer::take_changed_cells`]). Checked on
//! lion (1 KiB treelets) refined to convergence and then held: every image the core hands out,
//! memoised or not, equals a fresh CPU render of what is resident, and so does what the
//! backend's own target holds after an in-place render that was skipped.

use std::any::Any;
use std::sync::Arc;

use arbor_client_core::analysis::Feedback;
use arbor_client_core::backend::{Backend, BackendError, CpuBackend, PassInput};
use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::{ClientCore, CoreConfig};
use arbor_client_core::image::Image;
use arbor_client_core::render::render;
use arbor_client_core::slots::SlotBuffer;
use arbor_client_core::upload::UploadPlan;
use arbor_proto::TreeletId;
use arbor_tests::support::small_lion_decoded;

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

    fn renders_rects(&self) -> bool {
        true
    }

    fn render_rects(
        &mut self,
        input: &PassInput<'_>,
        image: &mut Image,
        rects: &[[u32; 4]],
    ) -> Result<(), BackendError> {
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
    let (scene, treelets) = small_lion_decoded();
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

/// Partial renders in the stiff cases: the camera inside the scene (changed cells around and
/// behind the eye), close to it, and far away (the whole scene a few pixels wide), with a
/// budget of a third of the scene, so evictions restore leaves while the view refines. Every
/// image equals a fresh render of what is resident (and under debug assertions the core checks
/// each patched image itself).
#[test]
fn partial_renders_stay_exact_inside_near_and_far_with_evictions() {
    let (scene, treelets) = small_lion_decoded();
    let channels = scene.layout.channels().to_vec();
    let slots = u64::from(scene.treelet_count) / 3;
    let frame = arbor_client_core::incore::SceneFrame::of(&scene);
    let centre = glam::DVec3::from_array(frame.centre());
    let edge = frame.edge;
    let cameras = [
        (
            "inside",
            centre + glam::DVec3::new(0.05, -0.1, 0.02) * edge,
            centre,
        ),
        (
            "near",
            centre + glam::DVec3::new(0.3, -0.4, 0.1) * edge,
            centre,
        ),
        (
            "far",
            centre + glam::DVec3::new(30.0, -40.0, 10.0) * edge,
            centre,
        ),
    ];
    let mut partial = 0;
    for (what, eye, target) in cameras {
        let config = CoreConfig {
            budget_bytes: slots * SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
            channels: channels.clone(),
            deep_push: false,
            ..CoreConfig::default()
        };
        let root = treelets[&TreeletId::ROOT].clone();
        let mut core =
            ClientCore::with_backend(scene.clone(), config, root, Box::new(CpuBackend)).unwrap();
        let camera = Camera::look_at(
            eye,
            target + glam::DVec3::new(0.01, 0.0, 0.0) * edge,
            arbor_client_core::camera::WORLD_UP,
            arbor_client_core::camera::DEFAULT_FOV_Y,
            80,
            64,
        )
        .unwrap();
        let mut evicted = 0;
        for cycle in 0..120u32 {
            let plan = core.plan(&camera).unwrap();
            for (id, _) in &plan.requests {
                core.handle_treelet(treelets[id].clone());
            }
            evicted += core.integrate().evicted;
            core.upload().unwrap();
            let image = core.render(&camera).unwrap();
            assert!(
                image == fresh(&core, &camera),
                "{what}, cycle {cycle}: the image differs from a fresh render"
            );
            if plan.converged {
                break;
            }
        }
        eprintln!(
            "{what}: {} partial renders, {} skipped, {evicted} evicted",
            core.partial_renders(),
            core.skipped_renders()
        );
        partial += core.partial_renders();
    }
    assert!(partial > 0, "no partial render in any of the cases");
}
