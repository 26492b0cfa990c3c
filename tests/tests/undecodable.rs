//! A treelet the client cannot decode — here a node block filed under another treelet's id, as
//! a faulty disk or tool would leave it in a pool — is held off the request lists for a hold
//! that doubles with each failure (`arbor_client_core::backoff`), instead of being asked for,
//! sent and dropped again every cycle for as long as the view lasts. The rest of the view
//! refines meanwhile, and a good copy (a repaired pool, a replica) is still taken when the hold
//! ends.
//!
//! * The core on its own, answering its lists from the decoded scene: the bad treelet is listed
//!   again only after each hold (listed every cycle before: 200 times in 200 cycles), and once
//!   a good copy comes the view converges. A new connection ends the holds.
//! * End to end over loopback QUIC, a real server serving a pool with the block misfiled: the
//!   client receives the bad treelet a few times in 800 cycles of a static view and of an
//!   orbit (105 times in the orbit before), never keeps it, and its static picture is exactly
//!   the reference rendered with everything resident but that treelet's subtree.

use std::collections::HashMap;
use std::sync::{Arc, OnceLock};

use arbor_client_core::backend::CpuBackend;
use arbor_client_core::backoff::DecodeBackoff;
use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::{ClientCore, CoreConfig};
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig};
use arbor_client_session::headless::run_headless_with;
use arbor_proto::TreeletId;
use arbor_server::daemon::DaemonOptions;
use arbor_tests::streaming::{
    SIZE, cpu_render_at, full, headless, needed_treelet_ids, scene_bytes, serve_altered,
};
use arbor_tests::support::{Built, decoded_treelets, rewrite_node_blocks, small_lion_decoded};

/// The cycle from which the core's bad treelet comes as a good copy.
const REPAIRED_AT: u32 = 200;

type Treelets = HashMap<TreeletId, DecodedTreelet>;

/// The lion's treelets (1 KiB) and a core holding its root, with room for all of them and no
/// pushes (every arrival answers a list), and the static camera.
fn lion_core() -> (Treelets, ClientCore, Camera) {
    let (scene, treelets) = small_lion_decoded();
    let channels = scene.layout.channels().to_vec();
    let config = CoreConfig {
        budget_bytes: u64::from(scene.treelet_count)
            * SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
        channels,
        deep_push: false,
        ..CoreConfig::default()
    };
    let core = ClientCore::new(scene, config, treelets[&TreeletId::ROOT].clone()).unwrap();
    let camera = CameraPath::Static.camera(0, core.frame(), 3, 96, 96);
    (treelets, core, camera)
}

#[test]
fn an_undecodable_treelet_is_listed_again_only_after_a_doubling_hold() {
    let (treelets, mut core, camera) = lion_core();

    let mut bad = None;
    let mut listed_at = Vec::new();
    let mut inserted_while_bad = 0;
    let mut converged_at = None;
    for cycle in 0..600u32 {
        let plan = core.plan(&camera).unwrap();
        // The bad one: the first child of the root the first list names.
        let bad = *bad.get_or_insert_with(|| {
            plan.requests
                .iter()
                .map(|&(id, _)| id)
                .find(|id| treelets[id].treelet.header.parent_id == TreeletId::ROOT)
                .expect("the first list names a child of the root")
        });
        for &(id, _) in &plan.requests {
            if id == bad {
                listed_at.push(cycle);
                if cycle < REPAIRED_AT {
                    core.handle_undecodable(id);
                    continue;
                }
            }
            core.handle_treelet(treelets[&id].clone());
        }
        let integration = core.integrate();
        if cycle < REPAIRED_AT {
            inserted_while_bad += integration.inserted;
            assert!(!core.slots().is_resident(bad));
        }
        if plan.converged {
            converged_at = Some(cycle);
            break;
        }
    }
    let bad = bad.unwrap();
    let before: Vec<u32> = listed_at
        .iter()
        .copied()
        .filter(|&c| c < REPAIRED_AT)
        .collect();
    eprintln!("{bad} listed at cycles {listed_at:?}; converged at {converged_at:?}");
    // Listed every cycle, it would be named about 200 times before the repair.
    assert!(
        (3..=6).contains(&before.len()),
        "listed {} times in {REPAIRED_AT} cycles: {before:?}",
        before.len()
    );
    for (k, pair) in before.windows(2).enumerate() {
        let hold = DecodeBackoff::hold_cycles(k as u32 + 1);
        assert!(
            u64::from(pair[1] - pair[0]) >= hold,
            "listed again after {} cycles, inside a hold of {hold}: {before:?}",
            pair[1] - pair[0]
        );
    }
    assert!(
        inserted_while_bad > 50,
        "the rest of the view refined meanwhile: {inserted_while_bad} inserted"
    );
    assert!(
        listed_at.iter().any(|&c| c >= REPAIRED_AT),
        "asked again after its hold: {listed_at:?}"
    );
    assert!(converged_at.is_some(), "the good copy completes the view");
    assert!(core.slots().is_resident(bad));
    assert_eq!(
        core.undecodable().failures(bad),
        0,
        "the decoded copy clears it"
    );
}

/// A new connection (maybe to another replica, whose copy may decode) ends every hold.
#[test]
fn a_new_connection_lists_the_undecodable_again_at_once() {
    let (_, mut core, camera) = lion_core();
    let first = core.plan(&camera).unwrap();
    assert!(first.requests.len() >= 2);
    let (bad, _) = first.requests[0];
    core.handle_undecodable(bad);
    core.integrate();
    let held = core.plan(&camera).unwrap();
    assert!(!held.requests.iter().any(|&(id, _)| id == bad), "held");
    assert!(core.undecodable().holds(bad, core.cycle()));
    core.forget_undecodable();
    let again = core.plan(&camera).unwrap();
    assert!(
        again.requests.iter().any(|&(id, _)| id == bad),
        "listed again"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_misfiled_block_is_received_a_few_times_and_the_rest_of_the_view_is_exact() {
    // The first child of the root the view needs, stored with another treelet's node block:
    // its frame header looks like any other, so the server sends it; the client finds the
    // wrong id when it decodes.
    let chosen = Arc::new(OnceLock::new());
    let misfile = {
        let chosen = chosen.clone();
        move |built: &Built| {
            let d = &built.scene.description;
            let all =
                SlotBuffer::fully_resident(d, d.layout.channels(), decoded_treelets(&built.scene))
                    .unwrap();
            let needed = needed_treelet_ids(d, &all, &CameraPath::Static, 0);
            let bad = (1..d.treelet_count)
                .map(TreeletId)
                .find(|&id| {
                    needed.contains(&id)
                        && all.slot_of(id).and_then(|s| all.parent_slot(s)) == Some(0)
                })
                .expect("the view needs a child of the root");
            let other = TreeletId(if bad.0 == 1 { 2 } else { 1 });
            let other = built.scene.nodes(other).unwrap().unwrap().to_vec();
            rewrite_node_blocks(built, |id, block| {
                if id == bad {
                    other.clone()
                } else {
                    block.to_vec()
                }
            });
            chosen.set(bad).unwrap();
        }
    };
    let served = Arc::new(
        serve_altered(
            "points/lion_takanawa.copc.laz",
            "lion",
            1024,
            DaemonOptions::default(),
            misfile,
        )
        .await,
    );
    let bad = *chosen.get().unwrap();
    let all = full(&served);

    let mut cfg = headless(
        served.server.quic_addr,
        &served,
        CameraPath::Static,
        scene_bytes(&served),
    );
    cfg.cycles = 800;
    let handle = tokio::runtime::Handle::current();
    let run = tokio::task::spawn_blocking(move || {
        run_headless_with(cfg, &handle, Box::new(CpuBackend), |view| {
            assert!(!view.slots.is_resident(bad), "the misfiled block was kept");
        })
    })
    .await
    .unwrap()
    .unwrap();
    let r = &run.report.records;
    let dropped: u32 = r.iter().map(|c| c.dropped).sum();
    let last_drop = r.iter().rev().find(|c| c.dropped > 0).map(|c| c.cycle);
    eprintln!(
        "misfiled: {dropped} arrivals dropped in {} cycles (the last at {last_drop:?}), {} B \
         received",
        r.len(),
        r.iter().map(|c| c.bytes_received).sum::<u64>()
    );
    // Every cycle would bring another copy without the holds (the server's redelivery guard
    // is a few round trips on loopback); with them, at most one per hold: 8, 16, 32, … cycles.
    assert!(
        (1..=10).contains(&dropped),
        "{dropped} undecodable arrivals in {} cycles",
        r.len()
    );
    assert_eq!(
        run.converged_at, None,
        "a view missing a treelet it needs does not claim convergence"
    );

    // A moving view sends a new list every cycle, and each would name the bad treelet while it
    // is in view (a static view's lists stop changing once the rest has converged, and the
    // client sends a list only when it changes).
    let mut cfg = headless(
        served.server.quic_addr,
        &served,
        CameraPath::Orbit {
            degrees_per_cycle: 0.5,
        },
        scene_bytes(&served),
    );
    cfg.cycles = 800;
    let handle = tokio::runtime::Handle::current();
    let orbit = tokio::task::spawn_blocking(move || {
        run_headless_with(cfg, &handle, Box::new(CpuBackend), |_| {})
    })
    .await
    .unwrap()
    .unwrap();
    let o = &orbit.report.records;
    let orbit_dropped: u32 = o.iter().map(|c| c.dropped).sum();
    let orbit_lists = o.iter().filter(|c| c.requests_sent > 0).count();
    eprintln!(
        "misfiled, orbiting: {orbit_dropped} arrivals dropped in {} cycles, {orbit_lists} with a list",
        o.len()
    );
    assert!(
        (1..=12).contains(&orbit_dropped),
        "{orbit_dropped} undecodable arrivals in {} cycles",
        o.len()
    );

    // Exact everywhere else: the reference with every treelet resident but the bad one and
    // what lies below it.
    let scene = &served.scene;
    let channels = scene.layout.channels();
    let config = SlotConfig {
        budget_bytes: scene_bytes(&served),
        treelet_nodes: scene.treelet_nodes,
        channels: channels.to_vec(),
        visibility_max: 1,
        load_limit: u32::MAX,
    };
    let mut without = SlotBuffer::new(config, served.treelets[0].clone()).unwrap();
    let mut missing = 0;
    for t in served.treelets.iter().skip(1).filter(|t| t.id() != bad) {
        match without.insert(t.clone()) {
            InsertOutcome::Inserted { .. } => {}
            InsertOutcome::ParentMissing => missing += 1,
            other => panic!("{}: {other:?}", t.id()),
        }
    }
    assert!(missing > 0, "{bad} has a subtree");
    let frame = SceneFrame::of(scene);
    let camera = CameraPath::Static.camera(0, &frame, 7, SIZE.0, SIZE.1);
    let expected = cpu_render_at(&without, &frame, &camera, 1.0);
    assert_ne!(
        expected,
        cpu_render_at(&all, &frame, &camera, 1.0),
        "the subtree shows in the view"
    );
    assert_eq!(run.image, expected);
}
