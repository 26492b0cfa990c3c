//! Pushed treelets on the client side (docs/design.md §10), on a real scan's treelets: a push
//! is kept only in a free slot with its parent resident (or arriving in the same batch, or
//! within a few integrations); an orphan whose parent does not come, or a push that finds no
//! free slot, is dropped and counted, and never displaces what
//! the client holds. Arrivals not yet handed over are not listed again; second copies are
//! counted. In the tail of a view's refinement a short list is topped up with the frustum's
//! candidates (prefetch), only into the half of the buffer the view does not need; once the
//! whole view is known, what rays meet behind their coarse hits is listed below the sampled
//! items (look-past), which saves rounds of discovery.

use std::sync::Arc;

use arbor_client_core::cycle::{ClientCore, CoreConfig, ORPHAN_WAIT_INTEGRATIONS};
use arbor_client_core::slots::{DecodedTreelet, SlotBuffer};
use arbor_proto::TreeletId;
use arbor_tests::support::{decoded_treelets, small_lion};

/// The lion's treelets (small treelets, so the tree has several levels) and a core holding its
/// root, with room for `slots` slots in all.
fn lion_core(slots: u64) -> (Vec<DecodedTreelet>, ClientCore) {
    lion_core_with(slots, CoreConfig::default())
}

fn lion_core_with(slots: u64, config: CoreConfig) -> (Vec<DecodedTreelet>, ClientCore) {
    let built = small_lion();
    let treelets = decoded_treelets(&built.scene);
    let scene = Arc::new(built.scene.description.clone());
    let channels = scene.layout.channels().to_vec();
    let config = CoreConfig {
        budget_bytes: slots * SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
        channels,
        ..config
    };
    let core = ClientCore::new(scene, config, treelets[0].clone()).expect("core");
    (treelets, core)
}

fn parent(t: &DecodedTreelet) -> TreeletId {
    t.treelet.header.parent_id
}

#[test]
fn pushed_orphans_wait_for_their_parent_then_are_dropped_and_counted() {
    let (treelets, mut core) = lion_core(64);
    // A grandchild of the root: its parent is not resident. Nothing was listed yet, so every
    // arrival counts as pushed.
    let grandchild = treelets
        .iter()
        .find(|t| {
            let p = parent(t);
            p.0 != 0 && !p.is_none() && parent(&treelets[p.0 as usize]).0 == 0
        })
        .expect("the lion has three treelet levels")
        .clone();
    let middle = treelets[parent(&grandchild).0 as usize].clone();
    let used = core.slots().used_slots();

    // Alone, it waits in the backlog (taking no slot) for its parent...
    core.handle_treelet(grandchild.clone());
    for _ in 0..ORPHAN_WAIT_INTEGRATIONS {
        let i = core.integrate();
        assert_eq!(
            (i.push_dropped, i.pushed, i.inserted, i.dropped),
            (0, 0, 0, 0)
        );
        assert_eq!(core.backlog_len(), 1, "waiting");
        assert_eq!(core.slots().used_slots(), used, "an orphan takes no slot");
    }
    // ...and is dropped, and counted, when it does not come.
    let i = core.integrate();
    assert_eq!(
        (i.push_dropped, i.pushed, i.inserted, i.dropped),
        (1, 0, 0, 0)
    );
    assert_eq!(core.backlog_len(), 0);
    assert!(!core.slots().is_resident(grandchild.id()));

    // A parent arriving while the child waits: both kept.
    core.handle_treelet(grandchild.clone());
    let i = core.integrate();
    assert_eq!((i.push_dropped, i.inserted), (0, 0));
    core.handle_treelet(middle.clone());
    let i = core.integrate();
    assert_eq!(
        (i.push_dropped, i.pushed, i.inserted, i.dropped),
        (0, 2, 2, 0)
    );
    assert!(core.slots().is_resident(grandchild.id()) && core.slots().is_resident(middle.id()));
}

#[test]
fn pushes_take_only_free_slots_and_never_displace() {
    let (treelets, mut core) = lion_core(4);
    let children: Vec<_> = treelets
        .iter()
        .filter(|t| parent(t).0 == 0 && t.id().0 != 0)
        .cloned()
        .collect();
    let free = core.slots().free_slots() as usize;
    assert!(
        free >= 1 && children.len() > free,
        "{free} free, {} children",
        children.len()
    );
    let before: Vec<_> = (0..core.slots().capacity())
        .filter_map(|s| core.slots().treelet_in(s))
        .collect();

    for c in &children[..free + 2] {
        core.handle_treelet(c.clone());
    }
    let i = core.integrate();
    assert_eq!(i.pushed as usize, free);
    assert_eq!(
        i.push_dropped, 2,
        "the pushes beyond the free slots are dropped and counted"
    );
    assert_eq!((i.evicted, i.dropped), (0, 0), "a push never evicts");
    assert_eq!(core.slots().free_slots(), 0);
    assert!(
        before.iter().all(|&id| core.slots().is_resident(id)),
        "what was resident stays"
    );
}

/// What the connection has received but the caller has not decoded yet is not listed again
/// (the session takes arrivals off the connection before the presort and decodes them after
/// the list is sent); an arrival already resident or already waiting is counted as received
/// twice.
#[test]
fn arriving_treelets_are_not_listed_and_second_copies_are_counted() {
    use arbor_client_core::camera::CameraPath;

    let (treelets, mut core) = lion_core(4096);
    let camera = CameraPath::Static.camera(0, core.frame(), 3, 96, 96);
    let listed = |core: &mut ClientCore| -> Vec<TreeletId> {
        core.plan(&camera)
            .unwrap()
            .requests
            .iter()
            .map(|r| r.0)
            .collect()
    };
    let first = listed(&mut core);
    let wanted = *first.first().expect("the root's view wants its children");
    assert!(
        listed(&mut core).contains(&wanted),
        "still wanted a cycle later"
    );

    core.note_arriving([wanted]);
    assert!(
        !listed(&mut core).contains(&wanted),
        "arriving, so not listed"
    );
    // Never handed over (say it failed to decode): wanted again after the integration.
    let i = core.integrate();
    assert_eq!((i.inserted, i.received_twice), (0, 0));
    assert!(listed(&mut core).contains(&wanted));

    let t = treelets[wanted.0 as usize].clone();
    core.handle_treelet(t.clone());
    core.handle_treelet(t.clone());
    let i = core.integrate();
    assert_eq!((i.inserted, i.received_twice), (1, 1));
    core.handle_treelet(t);
    let i = core.integrate();
    assert_eq!((i.inserted, i.received_twice), (0, 1));
    assert!(!listed(&mut core).contains(&wanted), "resident");
}

/// Arrivals taken off the connection but not yet decoded are slots spoken for: the next list,
/// and the pushes its view allows, ask only for the room beyond them. (Without it, a burst of
/// pushes on loopback made the next list ask for the same slots again, and the oversubscribed
/// bench dropped 235 arrivals.)
#[test]
fn arrivals_not_yet_decoded_count_against_the_room_for_requests() {
    use arbor_client_core::camera::CameraPath;

    // A buffer of 12 slots (the root in one) and the bias held: the root's view wants more.
    let config = CoreConfig {
        adjust_bias: false,
        ..CoreConfig::default()
    };
    let (_, mut core) = lion_core_with(12, config);
    let camera = CameraPath::Static.camera(0, core.frame(), 3, 96, 96);
    let room = core.slots().room() as usize;
    let plan = core.plan(&camera).unwrap();
    assert_eq!(
        plan.requests.len(),
        room,
        "the view wants more than the buffer holds"
    );
    let coming: Vec<TreeletId> = plan.requests.iter().take(4).map(|r| r.0).collect();
    core.note_arriving(coming.iter().copied());
    let plan = core.plan(&camera).unwrap();
    assert_eq!(plan.requests.len(), room - coming.len());
    assert!(plan.requests.iter().all(|r| !coming.contains(&r.0)));
    let view = plan.view.expect("the default asks for pushes");
    assert!(
        view.free_slots as usize <= room - coming.len(),
        "{} free slots announced, {} left",
        view.free_slots,
        room - coming.len()
    );
}

/// Cycles of a core whose every request arrives before the next cycle (a perfect server): the
/// plans, until the view converged.
fn refine(
    core: &mut ClientCore,
    treelets: &[DecodedTreelet],
) -> Vec<arbor_client_core::cycle::Plan> {
    use arbor_client_core::camera::CameraPath;

    let camera = CameraPath::Static.camera(0, core.frame(), 3, 96, 96);
    let mut plans = Vec::new();
    for _ in 0..400 {
        let plan = core.plan(&camera).unwrap();
        for (id, _) in &plan.requests {
            core.handle_treelet(treelets[id.0 as usize].clone());
        }
        core.integrate();
        let converged = plan.converged;
        plans.push(plan);
        if converged {
            return plans;
        }
    }
    panic!("no convergence in 400 cycles");
}

/// The prefetched items of a plan, with their errors: listed after the sampled ones.
fn prefetched(plan: &arbor_client_core::cycle::Plan) -> Vec<(TreeletId, f32, f32)> {
    let sampled = plan.distinct_requests.min(plan.requests.len());
    plan.requests[sampled..]
        .iter()
        .zip(&plan.errors[sampled..])
        .map(|(&(id, priority), &error)| (id, priority, error))
        .collect()
}

#[test]
fn a_roomy_view_is_topped_up_from_the_frustum_below_every_sampled_item() {
    let (treelets, mut core) = lion_core(4096);
    let capacity = core.slots().capacity() as usize;
    let plans = refine(&mut core, &treelets);
    let with_prefetch: Vec<_> = plans.iter().filter(|p| !prefetched(p).is_empty()).collect();
    assert!(
        !with_prefetch.is_empty(),
        "a roomy buffer gets a prefetch in the tail ({} cycles)",
        plans.len()
    );
    let (mut whole_frustum, mut with_errors) = (0, 0);
    for plan in with_prefetch {
        let sampled = plan.distinct_requests;
        // The plan says where its prefetch starts (the deep list's `prefetch_from`): after the
        // sampled items and the look-past, and every prefetch item ranks below them.
        assert!(
            (sampled..plan.requests.len()).contains(&plan.prefetch_from),
            "prefetch from {} of {} ({sampled} sampled)",
            plan.prefetch_from,
            plan.requests.len()
        );
        let (found, guessed) = plan.requests.split_at(plan.prefetch_from);
        let lowest_found = found.iter().map(|r| r.1).fold(f32::INFINITY, f32::min);
        assert!(guessed.iter().all(|r| r.1 < lowest_found));
        let lowest_sampled = plan.requests[..sampled]
            .iter()
            .map(|r| r.1)
            .fold(f32::INFINITY, f32::min);
        assert!(
            plan.errors[..sampled].iter().all(|&e| e > 0.0),
            "the sampled items come first"
        );
        for (id, priority, error) in prefetched(plan) {
            assert!(
                priority > 0.0 && priority < lowest_sampled,
                "{id}: {priority}"
            );
            assert!((0.0..=64.0).contains(&error), "{id}: error {error}");
            // The rest of the frustum, without errors, only on a short list; what the view is
            // open to or lies around dirty pixels comes with its projected error.
            if error > 0.0 {
                with_errors += 1;
            } else {
                whole_frustum += 1;
                assert!(
                    sampled < CoreConfig::default().prefetch_below,
                    "only a short list is topped up with the whole frustum"
                );
            }
        }
        assert!(
            plan.requests.len() <= capacity / 2,
            "at most half the buffer"
        );
    }
    eprintln!("prefetched: {with_errors} with errors, {whole_frustum} of the rest of the frustum");
    assert!(
        with_errors > 0,
        "an open view (and dirty pixels) are prefetched with their projected errors"
    );
    assert!(
        core.slots().used_slots() as usize <= capacity / 2 + CoreConfig::default().prefetch_below
    );

    // Off: the same view lists only what its samples need.
    let (treelets, mut core) = lion_core_with(
        4096,
        CoreConfig {
            prefetch_below: 0,
            look_past: 0,
            ..CoreConfig::default()
        },
    );
    let plans = refine(&mut core, &treelets);
    assert!(plans.iter().all(|p| prefetched(p).is_empty()));
    assert!(plans.iter().all(|p| p.prefetch_from == p.requests.len()));
}

#[test]
fn a_tight_buffer_is_never_prefetched_into() {
    // First the view's own need, from a roomy run without prefetch.
    let (treelets, mut core) = lion_core_with(
        4096,
        CoreConfig {
            prefetch_below: 0,
            look_past: 0,
            ..CoreConfig::default()
        },
    );
    refine(&mut core, &treelets);
    let needed = u64::from(core.slots().used_slots());
    // A buffer the view fills more than half of.
    let (treelets, mut core) = lion_core(needed * 3 / 2);
    let plans = refine(&mut core, &treelets);
    assert!(
        plans.iter().all(|p| prefetched(p).is_empty()),
        "the view needs {needed} of {} slots",
        core.slots().capacity()
    );
}

#[test]
fn looking_past_coarse_hits_lists_what_lies_behind_below_every_sampled_item() {
    let only_look_past = |look_past| {
        lion_core_with(
            4096,
            CoreConfig {
                prefetch_below: 0,
                look_past,
                ..CoreConfig::default()
            },
        )
    };
    let (treelets, mut core) = only_look_past(CoreConfig::default().look_past);
    let capacity = core.slots().capacity() as usize;
    let plans = refine(&mut core, &treelets);
    let mut looked_past = 0;
    for plan in &plans {
        // Look-past items are found by rays, not guessed: no prefetch.
        assert_eq!(plan.prefetch_from, plan.requests.len());
        let sampled = plan.distinct_requests.min(plan.requests.len());
        let lowest_sampled = plan.requests[..sampled]
            .iter()
            .map(|r| r.1)
            .fold(f32::INFINITY, f32::min);
        let mut ids: Vec<TreeletId> = plan.requests.iter().map(|r| r.0).collect();
        ids.sort_unstable();
        ids.dedup();
        assert_eq!(ids.len(), plan.requests.len(), "an id listed twice");
        for (id, priority, error) in prefetched(plan) {
            looked_past += 1;
            // Below every sampled item, above where the prefetch starts.
            assert!(
                priority > 0.0 && priority <= 0.75 * lowest_sampled,
                "{id}: {priority} vs {lowest_sampled}"
            );
            assert!(error > 0.0 && error <= 64.0, "{id}: error {error}");
        }
        assert!(
            plan.requests.len() <= capacity / 2,
            "at most half the buffer"
        );
    }
    let rounds_with = plans.len();
    assert!(
        looked_past > 0,
        "lion's coarse hulls hide surfaces behind them"
    );

    // Off: only what the samples need, and more rounds to converge (each round here delivers
    // everything listed, so rounds count the round trips of discovery).
    let (treelets, mut core) = only_look_past(0);
    let plans = refine(&mut core, &treelets);
    assert!(plans.iter().all(|p| prefetched(p).is_empty()));
    eprintln!(
        "{looked_past} look-past items; rounds to converge {rounds_with} with, {} without",
        plans.len()
    );
    assert!(rounds_with < plans.len());
}
