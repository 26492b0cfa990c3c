//! The client streaming core end to end: real scans built into real sled pools, served by the
//! real server over loopback QUIC (and over the link emulator), streamed and rendered by the
//! real headless client (`arbor_client_session::headless`) on the CPU twins; the helpers are in
//! `arbor_tests::streaming` (`gpu_e2e.rs` runs the same on the GPU backend).
//!
//! * **Static camera, budget far below the scene** (1.5× the treelets the view needs: 18–34 %
//!   of the scene for lion, engine and igea at 96², 1 KiB treelets): the image converges to the
//!   reference —
//!   the same camera with every treelet resident, rendered from the pool directly — exactly
//!   (RMSE 0, no differing pixel) within a bounded number of cycles, and the run's report shows
//!   the screen-space error falling to zero and staying there.
//! * **Orbiting camera, small budget**: memory stays within the budget every cycle, and no
//!   pixel that the reference of that cycle's camera covers is ever empty.
//! * **Over the link emulator** (25 ms each way, 100 Mbit/s): the same convergence.
//! * **A new LOD bias mid-run** (the viewer's quality keys, `Session::set_lod_bias`): the
//!   picture converges to the reference rendered at that bias, exactly, and back.

use std::sync::Arc;
use std::time::Duration;

use arbor_client_core::backend::CpuBackend;
use arbor_client_core::camera::CameraPath;
use arbor_client_core::cycle::Sampling;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::presort::PriorityPolicy;
use arbor_client_core::slots::SlotBuffer;
use arbor_client_session::headless::run_headless_with;
use arbor_client_session::session::{RenderMode, Session, SessionConfig};
use arbor_tests::link::{LinkConfig, LinkEmulator};
use arbor_tests::streaming::{
    SIZE, assert_report_accounts, converge, converge_with, cpu_render_at, full, headless,
    needed_treelets, reference, scene_bytes, serve,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn static_camera_converges_exactly_over_loopback_with_a_fraction_of_the_scene() {
    for (rel, name) in [
        ("points/lion_takanawa.copc.laz", "lion"),
        ("volumes/engine_256x256x128_u8.nrrd", "engine"),
        ("meshes/igea.ply", "igea"),
    ] {
        let served = Arc::new(serve(rel, name, 1024).await);
        let addr = served.server.quic_addr;
        converge(&served, addr, name, &mut CpuBackend, || {
            Box::new(CpuBackend)
        })
        .await;
    }
}

/// Every ranking policy, the thesis's fixed sampling grid and the run without deep pushes reach
/// the same exact picture: they change the order of arrival, never the result.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_policy_and_sampling_converges_exactly() {
    let served = Arc::new(serve("points/lion_takanawa.copc.laz", "lion", 1024).await);
    let addr = served.server.quic_addr;
    for policy in PriorityPolicy::ALL {
        let what = format!("lion, policy {policy:?}");
        let whole_scene = scene_bytes(&served);
        converge_with(
            &served,
            addr,
            &what,
            &mut CpuBackend,
            || Box::new(CpuBackend),
            |c| {
                c.core.policy = policy;
                // Without occlusion the frustum policy wants every treelet in the frustum,
                // hidden ones too: more than this budget holds (it would settle on a coarser
                // bias).
                if policy == PriorityPolicy::Frustum {
                    c.core.budget_bytes = whole_scene;
                }
            },
        )
        .await;
    }
    converge_with(
        &served,
        addr,
        "lion, fixed grid, no deep push",
        &mut CpuBackend,
        || Box::new(CpuBackend),
        |c| {
            c.core.sampling = Sampling::Grid;
            c.core.deep_push = false;
        },
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn static_camera_converges_exactly_over_the_emulated_wan() {
    let served = Arc::new(serve("points/lion_takanawa.copc.laz", "lion", 1024).await);
    let link = LinkEmulator::start(
        served.server.quic_addr,
        LinkConfig::wan(Duration::from_millis(25), 100_000_000 / 8),
    )
    .await
    .unwrap();
    let run = converge(
        &served,
        link.local_addr(),
        "lion over 25 ms / 100 Mbit/s",
        &mut CpuBackend,
        || Box::new(CpuBackend),
    )
    .await;
    let r = &run.report.records;
    let first_insert = r.iter().find(|c| c.treelets_inserted > 0).unwrap();
    assert!(
        first_insert.time_s >= 0.05,
        "nothing can arrive before one round trip (50 ms), got {:.3} s",
        first_insert.time_s
    );
    // A static view with room for everything: every treelet the server sends is new to the
    // client, except the few a list names just before they arrive from a stream the server
    // reset a moment earlier. (Resetting streams whose treelets a list still wanted sent a
    // tenth of lion's and a quarter of engine's treelets twice over this link.)
    let received: u32 = r.iter().map(|c| c.treelets_received).sum();
    let twice: u32 = r.iter().map(|c| c.received_twice).sum();
    eprintln!("{twice} of {received} treelets received twice");
    assert!(
        twice * 50 <= received,
        "{twice} of {received} treelets were received twice"
    );
    // List-to-arrival latencies: a treelet that was not already on its way when a list first
    // named it arrives a round trip (50 ms) later at the earliest; one pushed before it was
    // listed may come sooner, so the bound is on the run's median, not on every cycle's.
    let mut medians: Vec<f64> = r.iter().filter_map(|c| c.latency_p50_ms).collect();
    assert!(!medians.is_empty(), "no cycle received a listed treelet");
    for c in r {
        assert_eq!(c.latency_p50_ms.is_some(), c.latency_max_ms.is_some());
        if let (Some(p50), Some(max)) = (c.latency_p50_ms, c.latency_max_ms) {
            assert!(
                0.0 < p50 && p50 <= max,
                "cycle {}: {p50} / {max} ms",
                c.cycle
            );
            assert!(max <= c.time_s * 1e3, "cycle {}: {max} ms", c.cycle);
        }
    }
    medians.sort_by(f64::total_cmp);
    let median = medians[medians.len() / 2];
    eprintln!("cycle medians of list-to-arrival latency: {medians:?}");
    assert!(
        median >= 50.0,
        "median list-to-arrival latency {median:.1} ms, under the 50 ms round trip"
    );
    // The run's report and chart, kept for people to look at.
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("client-e2e");
    std::fs::create_dir_all(&out).unwrap();
    run.report.write_csv(&out.join("wan.csv")).unwrap();
    arbor_client_report::chart::draw(
        &run.report,
        &out.join("wan-chart.png"),
        "lion over 25 ms / 100 Mbit/s, static camera",
    )
    .unwrap();
    run.image.save_png(out.join("wan.png")).unwrap();
    eprintln!(
        "{}\nreport, chart and image in {}",
        run.report.summary(),
        out.display()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn orbiting_camera_stays_in_budget_and_never_shows_holes() {
    let served = Arc::new(serve("points/lion_takanawa.copc.laz", "lion", 1024).await);
    let full = full(&served);
    let path = CameraPath::Orbit {
        degrees_per_cycle: 3.0,
    };
    // Just above what the first view needs: the orbit must evict to go on.
    let needed = needed_treelets(&served, &full, &path, 0);
    let slot_bytes =
        SlotBuffer::slot_bytes(served.scene.treelet_nodes, served.scene.layout.channels());
    let budget = u64::from(needed + needed / 10) * slot_bytes;
    let mut cfg = headless(served.server.quic_addr, &served, path, budget);
    cfg.cycles = 150;
    let slot_bytes =
        SlotBuffer::slot_bytes(served.scene.treelet_nodes, served.scene.layout.channels());
    let handle = tokio::runtime::Handle::current();
    let check = served.clone();
    let (run, holes_checked) = tokio::task::spawn_blocking(move || {
        let mut checked = 0u32;
        let run = run_headless_with(cfg, &handle, Box::new(CpuBackend), |v| {
            let slots = v.slots;
            assert!(slots.used_slots() <= slots.capacity());
            assert!(u64::from(slots.capacity()) * slot_bytes <= budget);
            let image = v.image.expect("every cycle renders");
            let reference = reference(&check, &full, &path, v.record.cycle, &mut CpuBackend);
            let holes = image.uncovered_where_covered(&reference).unwrap();
            assert_eq!(
                holes, 0,
                "cycle {}: {holes} pixels empty that the reference covers",
                v.record.cycle
            );
            checked += 1;
        })
        .unwrap();
        (run, checked)
    })
    .await
    .unwrap();
    let evictions: u32 = run.report.records.iter().map(|r| r.evictions).sum();
    eprintln!(
        "orbit: {holes_checked} frames checked, capacity {} slots of {} treelets, peak {}, \
         {evictions} evictions",
        run.capacity, served.scene.treelet_count, run.peak_slots
    );
    assert_eq!(holes_checked, 150);
    assert!(evictions > 0, "the budget was meant to force evictions");
    assert_eq!(run.peak_slots, run.capacity, "the buffer should fill up");
    assert_report_accounts("lion, orbit", &run);
}

/// A budget a third of what the view needs: the client raises its LOD bias until the needed cut
/// fits, stops requesting, and converges exactly to the reference rendered at that bias.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversubscribed_view_settles_on_a_coarser_exact_picture_and_stops_requesting() {
    let served = Arc::new(serve("points/lion_takanawa.copc.laz", "lion", 1024).await);
    let full = full(&served);
    let needed = needed_treelets(&served, &full, &CameraPath::Static, 0);
    let slot_bytes =
        SlotBuffer::slot_bytes(served.scene.treelet_nodes, served.scene.layout.channels());
    let budget = u64::from(needed / 3) * slot_bytes;
    let mut cfg = headless(served.server.quic_addr, &served, CameraPath::Static, budget);
    cfg.cycles = 400;
    let handle = tokio::runtime::Handle::current();
    let run = tokio::task::spawn_blocking(move || {
        run_headless_with(cfg, &handle, Box::new(CpuBackend), |_| {})
    })
    .await
    .unwrap()
    .unwrap();
    let r = &run.report.records;
    let last = r.last().unwrap();
    let bias = last.lod_bias;
    let received: u64 = r.iter().map(|c| c.bytes_received).sum();
    let tail: u64 = r[r.len() - 100..].iter().map(|c| c.bytes_received).sum();
    let dropped: u32 = r.iter().map(|c| c.dropped).sum();
    eprintln!(
        "oversubscribed: view needs {needed}, capacity {} slots; bias {bias}, converged at \
         {:?}, {received} B received ({tail} B in the last 100 cycles), {dropped} dropped, \
         peak {} slots",
        run.capacity, run.converged_at, run.peak_slots
    );
    assert!(bias > 1.0, "the budget cannot hold the view at bias 1");
    assert!(
        r.iter().any(|c| c.lod_bias > 1.0) && r[0].lod_bias == 1.0,
        "the report shows the bias in effect per cycle"
    );
    assert_eq!(tail, 0, "traffic stops once the picture has settled");
    assert_eq!(
        r[r.len() - 100..]
            .iter()
            .map(|c| c.requests_sent)
            .sum::<u32>(),
        0
    );
    assert!(
        run.converged_at.is_some(),
        "converges against the adjusted target"
    );
    assert!(run.peak_slots <= run.capacity);
    assert_report_accounts("lion, oversubscribed", &run);
    // Exact: the biased reference, every treelet resident, same camera.
    let frame = arbor_client_core::incore::SceneFrame::of(&served.scene);
    let camera = CameraPath::Static.camera(0, &frame, 7, SIZE.0, SIZE.1);
    let biased = cpu_render_at(&full, &frame, &camera, bias);
    assert_eq!(
        run.image, biased,
        "the settled picture is the biased reference"
    );
    let unbiased = reference(&served, &full, &CameraPath::Static, 0, &mut CpuBackend);
    assert_ne!(run.image, unbiased, "and coarser than the unbiased one");
    let summary = run.report.summary().to_string();
    assert!(
        summary.contains("LOD bias"),
        "the summary says the target was adjusted: {summary}"
    );
}

/// The viewer's quality keys: a session told a coarser LOD bias converges to the reference
/// rendered at that bias, exactly, and back at 1 to the unbiased one; an absurd bias is refused
/// and changes nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_follows_a_new_lod_bias_to_its_exact_reference_and_back() {
    let served = Arc::new(serve("points/lion_takanawa.copc.laz", "lion", 1024).await);
    let full = full(&served);
    let cfg = headless(
        served.server.quic_addr,
        &served,
        CameraPath::Static,
        2 * scene_bytes(&served),
    );
    let frame = SceneFrame::of(&served.scene);
    let camera = CameraPath::Static.camera(0, &frame, cfg.seed, SIZE.0, SIZE.1);
    let handle = tokio::runtime::Handle::current();
    let served2 = served.clone();
    tokio::task::spawn_blocking(move || {
        let mut session = Session::connect(
            SessionConfig {
                client: cfg.client,
                core: cfg.core,
                connect_timeout: cfg.connect_timeout,
                first_camera: None,
            },
            &handle,
            Box::new(CpuBackend),
        )
        .unwrap();
        let converge_at = |session: &mut Session, bias: f64| {
            for _ in 0..2000 {
                let step = session.step(&camera, RenderMode::Image, None).unwrap();
                if step.converged {
                    assert_eq!(step.record.lod_bias, bias, "the bias in effect");
                    let reference = cpu_render_at(&full, &frame, &camera, bias);
                    assert_eq!(
                        step.image.unwrap(),
                        reference,
                        "converged at bias {bias}: the reference at that bias"
                    );
                    return step.record.cycle;
                }
                std::thread::sleep(Duration::from_millis(2));
            }
            panic!("no convergence at bias {bias} within 2,000 cycles");
        };
        let first = converge_at(&mut session, 1.0);
        session.set_lod_bias(4.0).unwrap();
        let coarse = converge_at(&mut session, 4.0);
        assert!(coarse > first);
        let err = session.set_lod_bias(f64::NAN).unwrap_err();
        assert!(err.to_string().contains("LOD bias"), "{err}");
        assert_eq!(session.core().lod_bias().base(), 4.0, "unchanged");
        session.set_lod_bias(1.0).unwrap();
        converge_at(&mut session, 1.0);
        let coarse = cpu_render_at(&full, &frame, &camera, 4.0);
        let fine = reference(&served2, &full, &CameraPath::Static, 0, &mut CpuBackend);
        assert_ne!(coarse, fine, "the two biases are two pictures");
    })
    .await
    .unwrap();
}
