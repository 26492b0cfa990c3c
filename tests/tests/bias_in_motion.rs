//! A view that needs more slots than the budget holds, seen by a camera that moves every cycle
//! through a pass too slow to sample the whole frame in one cycle — the case of a slow backend
//! (the CPU, lavapipe) flying through a large scan with a small budget.
//!
//! The LOD bias used to be raised only once every pixel of one view was known, which such a
//! camera never allows: the buffer filled, every slot was still seen, nothing could be asked
//! for, and the picture stayed wrong for as long as the camera moved (the 10⁸-point city at
//! 16 MiB orbiting on the CPU backend: no raise in 600 cycles, 3,400 error-pixels a cycle on
//! average; docs/measurements.md, stop 61). A part of the view that already wants more than the
//! room is now enough to raise it (`LodBiasControl::raise_if_oversubscribed`).
//!
//! And with a pass that does know each whole view, a moving camera used to unlock after every
//! cycle the lower a failed lower had locked, so the bias went down and up every few cycles,
//! evicting for the finer level and fetching it each time; a failed lower now waits ever longer
//! before the next (`bias::LOWER_RETRY_CYCLES`).
//!
//! And a link slower than the camera: room for a view's needs used to be made from what no pixel
//! reaches for the whole request list at once, though the link delivered it over many cycles,
//! so up to three quarters of the slots stood empty for seconds while what they had held came
//! back into view; room is now made for a few cycles of arrivals at a time
//! (`cycle::OUTSIDE_EVICTION_HORIZON`).
//!
//! The core alone, answering each list at once from the decoded scene: lion, 1 KiB treelets, a
//! budget a third of what a static view of it needs, an orbit of 1° a cycle, a quarter of the
//! frame sampled per cycle (or all of it); then the camera stops, and the picture settles
//! exactly on the reference rendered at the bias it ends with, which is where a core that saw
//! only that view settles.

use std::collections::HashMap;

use arbor_client_core::bias::LOWER_RETRY_CYCLES;
use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::{ClientCore, CoreConfig, Plan};
use arbor_client_core::cycle::{MIN_OUTSIDE_EVICTION, OUTSIDE_EVICTION_HORIZON};
use arbor_client_core::slots::{DecodedTreelet, SlotBuffer};
use arbor_proto::{SceneDescription, TreeletId};
use arbor_tests::streaming::cpu_render_at;
use arbor_tests::support::{lion_1k_decoded, small_lion_decoded};

const SIZE: u32 = 96;
/// Pixels the analysis pass may sample per cycle: a quarter of the frame.
const SAMPLES_PER_CYCLE: usize = (SIZE * SIZE / 4) as usize;
const SEED: u64 = 3;

type Treelets = HashMap<TreeletId, DecodedTreelet>;

fn core(scene: &SceneDescription, treelets: &Treelets, slots: u32) -> ClientCore {
    let channels = scene.layout.channels().to_vec();
    let config = CoreConfig {
        budget_bytes: u64::from(slots) * SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
        channels,
        deep_push: false,
        ..CoreConfig::default()
    };
    ClientCore::new(
        std::sync::Arc::new(scene.clone()),
        config,
        treelets[&TreeletId::ROOT].clone(),
    )
    .unwrap()
}

/// One cycle: analyse at most `samples` pixels, presort, answer the list at once, integrate.
fn cycle(core: &mut ClientCore, treelets: &Treelets, camera: &Camera, samples: usize) -> Plan {
    cycle_over_link(core, treelets, camera, samples, usize::MAX)
}

/// [`cycle`] over a link that delivers only the first `arrivals` of each list.
fn cycle_over_link(
    core: &mut ClientCore,
    treelets: &Treelets,
    camera: &Camera,
    samples: usize,
    arrivals: usize,
) -> Plan {
    core.analyse(camera, samples).unwrap();
    let plan = core.presort();
    for &(id, _) in plan.requests.iter().take(arrivals) {
        core.handle_treelet(treelets[&id].clone());
    }
    core.integrate();
    plan
}

/// Slots a static view of lion at `size`² needs at bias 1: what a core with room for everything
/// holds once it has converged.
fn needed_slots(scene: &SceneDescription, treelets: &Treelets, size: u32) -> u32 {
    let mut core = core(scene, treelets, scene.treelet_count);
    let camera = CameraPath::Static.camera(0, core.frame(), SEED, size, size);
    for _ in 0..500 {
        if cycle(&mut core, treelets, &camera, usize::MAX).converged {
            return core.slots().used_slots();
        }
    }
    panic!("the static view did not converge in 500 cycles");
}

#[test]
fn an_oversubscribed_moving_view_raises_its_bias_without_ever_knowing_a_whole_view() {
    let (scene, treelets) = small_lion_decoded();
    let needed = needed_slots(&scene, &treelets, SIZE);
    let mut core = core(&scene, &treelets, needed / 3);
    let path = CameraPath::Orbit {
        degrees_per_cycle: 1.0,
    };
    let mut plans = Vec::new();
    for c in 0..360u32 {
        let camera = path.camera(c, core.frame(), SEED, SIZE, SIZE);
        plans.push(cycle(&mut core, &treelets, &camera, SAMPLES_PER_CYCLE));
    }
    let first_raise = plans.iter().position(|p| p.bias_changed);
    let bias = plans.last().unwrap().lod_bias;
    let half = &plans[180..];
    let wrong_cycles = half.iter().filter(|p| p.error.error_pixels > 0.0).count();
    let mean_error_pixels =
        half.iter().map(|p| p.error.error_pixels).sum::<f64>() / half.len() as f64;
    let requested: usize = half.iter().map(|p| p.requests.len()).sum();
    eprintln!(
        "needed {needed} slots, capacity {}; first raise at {first_raise:?}, bias {bias}; second \
         half: {wrong_cycles} of {} cycles with error, {mean_error_pixels:.1} error-pixels a \
         cycle, {requested} treelets requested",
        core.slots().capacity(),
        half.len()
    );
    assert!(
        plans.iter().all(|p| p.known_share < 1.0),
        "the pass never knows a whole view (else this tests nothing)"
    );
    assert!(
        first_raise.is_some_and(|c| c < 30),
        "raised early in the orbit: {first_raise:?}"
    );
    assert!(bias > 1.0, "the bias in effect at the end: {bias}");
    assert!(
        mean_error_pixels < 0.02 * f64::from(SIZE * SIZE),
        "the moving picture keeps up: {mean_error_pixels:.1} error-pixels a cycle"
    );
    assert!(
        requested > 0,
        "the orbit keeps refining what comes into view"
    );

    let camera = path.camera(359, core.frame(), SEED, SIZE, SIZE);
    settles_where_a_fresh_core_would(&scene, &treelets, &mut core, &camera, needed / 3);
}

/// Stops the camera at `camera`, samples the whole frame each cycle until `core` converges, and
/// checks the picture is exactly the reference at the bias it settled on, and that bias at most
/// a quarter level above the one a core of `slots` that saw only this view settles on. Returns
/// the settled bias.
fn settles_where_a_fresh_core_would(
    scene: &SceneDescription,
    treelets: &Treelets,
    core: &mut ClientCore,
    camera: &Camera,
    slots: u32,
) -> f64 {
    let settled = (0..400)
        .map(|_| cycle(core, treelets, camera, usize::MAX))
        .find(|p| p.converged)
        .expect("the stopped view converges within 400 cycles")
        .lod_bias;
    let full =
        SlotBuffer::fully_resident(scene, scene.layout.channels(), treelets.values().cloned())
            .unwrap();
    assert_eq!(
        core.render(camera).unwrap(),
        cpu_render_at(&full, core.frame(), camera, settled),
        "the settled picture is the reference at bias {settled}"
    );
    let mut fresh = self::core(scene, treelets, slots);
    let from_scratch = (0..400)
        .map(|_| cycle(&mut fresh, treelets, camera, usize::MAX))
        .find(|p| p.converged)
        .expect("a core that saw only this view converges")
        .lod_bias;
    eprintln!(
        "stopped: converged at bias {settled}; a core that saw only this view: {from_scratch}"
    );
    assert!(
        settled <= from_scratch * 2f64.powf(0.25) + 1e-9,
        "the orbit left the bias at {settled}, more than a quarter level above the \
         {from_scratch} a core that saw only this view settles on"
    );
    settled
}

/// With the whole frame sampled every cycle, a moving view is known whole each cycle, and a
/// lower that fits one view used to be tried again right after every failed one: the next
/// views wanted what it did not, the bias rose again, and each try evicted for the finer level
/// and fetched it (lion at a third of its need orbiting 1° a cycle: 26 lowers in 360 cycles).
/// Now a failed lower waits `LOWER_RETRY_CYCLES` before the next, doubling with each failure in
/// a row; once the camera stops, the bias settles where a core that saw only that view does.
#[test]
fn a_moving_view_retries_failed_lowers_ever_more_rarely() {
    let (scene, treelets) = small_lion_decoded();
    let needed = needed_slots(&scene, &treelets, SIZE);
    let slots = needed / 3;
    let mut core = core(&scene, &treelets, slots);
    let path = CameraPath::Orbit {
        degrees_per_cycle: 1.0,
    };
    let mut biases = Vec::new();
    for c in 0..360u32 {
        let camera = path.camera(c, core.frame(), SEED, SIZE, SIZE);
        biases.push(cycle(&mut core, &treelets, &camera, usize::MAX).lod_bias);
    }
    let lowers: Vec<usize> = (1..biases.len())
        .filter(|&c| biases[c] < biases[c - 1])
        .collect();
    eprintln!("orbit at {slots} slots of {needed} needed: lowers at cycles {lowers:?}");
    assert!(
        lowers.len() <= 6,
        "{} lowers in 360 cycles of orbit: {lowers:?}",
        lowers.len()
    );
    for pair in lowers.windows(2) {
        assert!(
            pair[1] - pair[0] >= LOWER_RETRY_CYCLES as usize,
            "lowers at cycles {} and {}: {lowers:?}",
            pair[0],
            pair[1]
        );
    }
    let camera = path.camera(359, core.frame(), SEED, SIZE, SIZE);
    settles_where_a_fresh_core_would(&scene, &treelets, &mut core, &camera, slots);
}

/// Treelets the link of [`room_is_made_as_the_link_delivers`] delivers per cycle.
const LINK_ARRIVALS_PER_CYCLE: usize = 24;

/// The whole lion at 256², a budget of what its static view needs, that view converged, then an
/// orbit of 1° a cycle for half a turn with the whole frame sampled every cycle, and a link that delivers
/// [`LINK_ARRIVALS_PER_CYCLE`] of each list: the views' needs lack room for far more than a few
/// cycles of arrivals, yet no more slots stand empty after an integration than the horizon
/// frees at that rate (one victim's descendants may go beyond the count asked for). With room
/// made for the whole list, up to 1,880 did. Then the camera stops, and the picture converges
/// exactly.
#[test]
fn room_is_made_as_the_link_delivers() {
    const LINK_SIZE: u32 = 256;
    let (scene, treelets) = lion_1k_decoded();
    let needed = needed_slots(&scene, &treelets, LINK_SIZE);
    let mut core = core(&scene, &treelets, needed);
    let orbit = CameraPath::Orbit {
        degrees_per_cycle: 1.0,
    };
    let start = orbit.camera(0, core.frame(), SEED, LINK_SIZE, LINK_SIZE);
    assert!(
        (0..400).any(|_| cycle(&mut core, &treelets, &start, usize::MAX).converged),
        "the first view converges, filling the buffer"
    );
    let frees = OUTSIDE_EVICTION_HORIZON
        .saturating_mul(LINK_ARRIVALS_PER_CYCLE as u32)
        .max(MIN_OUTSIDE_EVICTION);
    let (mut most_empty, mut shortfall, mut converged) = (0, 0, None);
    for c in 0..2000 {
        let camera = orbit.camera(c.min(180), core.frame(), SEED, LINK_SIZE, LINK_SIZE);
        // The analysis frees no slot: what the presort found free.
        let free = core.slots().free_slots();
        let plan = cycle_over_link(
            &mut core,
            &treelets,
            &camera,
            usize::MAX,
            LINK_ARRIVALS_PER_CYCLE,
        );
        shortfall = shortfall.max((plan.distinct_requests as u32).saturating_sub(free));
        most_empty = most_empty.max(core.slots().free_slots());
        if plan.converged && c >= 180 {
            converged = Some(plan.lod_bias);
            break;
        }
    }
    eprintln!(
        "{needed} slots; the views lacked room for up to {shortfall}; at most {most_empty} \
         empty after an integration (the horizon frees {frees}); converged at {converged:?}"
    );
    assert!(
        shortfall > 4 * frees,
        "the views must lack far more room than the horizon frees (else this tests nothing)"
    );
    assert!(
        most_empty <= 2 * frees,
        "{most_empty} slots stood empty, more than room for a few cycles of arrivals ({frees})"
    );
    let bias = converged.expect("the stopped view converges");
    let camera = orbit.camera(180, core.frame(), SEED, LINK_SIZE, LINK_SIZE);
    let full =
        SlotBuffer::fully_resident(&scene, scene.layout.channels(), treelets.values().cloned())
            .unwrap();
    assert_eq!(
        core.render(&camera).unwrap(),
        cpu_render_at(&full, core.frame(), &camera, bias),
        "the stopped view's picture is the reference at bias {bias}"
    );
}
