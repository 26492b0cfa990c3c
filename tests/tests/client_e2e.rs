//! The client streaming core end to end: real scans built into real sled pools, served by the
//! real server over loopback QUIC (and over the link emulator), streamed and rendered by the
//! real headless client (`arbor_client::run`).
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

use std::collections::HashSet;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client::analysis::AnalysisConfig;
use arbor_client::backend::CpuBackend;
use arbor_client::camera::CameraPath;
use arbor_client::headless::{HeadlessConfig, HeadlessRun, run_headless_with};
use arbor_client::image::Image;
use arbor_client::incore::SceneFrame;
use arbor_client::net::{ClientConfig, ServerUrl, Trust};
use arbor_client::render::{Light, render};
use arbor_client::run::CoreConfig;
use arbor_client::slots::{DecodedTreelet, SlotBuffer};
use arbor_client::trace::{Lod, trace};
use arbor_proto::SceneDescription;
use arbor_server::build::BuildOptions;
use arbor_server::service::config::{AdminTokenSource, SceneAccess};
use arbor_server::service::{RunningServer, ServeConfig, start};
use arbor_tests::link::{LinkConfig, LinkEmulator};
use arbor_tests::support::{Built, build_file, decoded_treelets};
use tempfile::TempDir;

const TOKEN: &str = "client-e2e";
const SIZE: (u32, u32) = (96, 96);
/// Feedback ratio of these runs: 4 → every pixel sampled once per 16 cycles.
const RATIO: u32 = 4;

struct Served {
    server: RunningServer,
    scene: SceneDescription,
    /// Every treelet, decoded from the pool with all the scene's channels.
    treelets: Vec<DecodedTreelet>,
    _pool_dir: TempDir,
    _data_dir: TempDir,
}

async fn serve(rel: &str, name: &str, treelet_bytes: u32) -> Served {
    let rel = rel.to_owned();
    let name_owned = name.to_owned();
    let (built, treelets) = tokio::task::spawn_blocking(move || {
        let built = build_file(
            &rel,
            &name_owned,
            &BuildOptions {
                treelet_bytes,
                ..BuildOptions::default()
            },
        );
        let treelets = decoded_treelets(&built.scene);
        (built, treelets)
    })
    .await
    .unwrap();
    let Built {
        pool,
        scene,
        pool_dir,
        source,
        scratch,
    } = built;
    let description = scene.description.clone();
    drop((pool, scene, source, scratch));
    let data_dir = tempfile::tempdir().unwrap();
    let mut cfg = ServeConfig::new(pool_dir.path());
    cfg.listen = "127.0.0.1:0".parse().unwrap();
    cfg.admin_listen = None;
    cfg.data_dir = Some(data_dir.path().to_owned());
    cfg.admin_token = AdminTokenSource::Inline("admin-client-e2e".into());
    cfg.scenes
        .insert(name.into(), SceneAccess::Tokens(vec![TOKEN.into()]));
    let server = start(cfg).await.unwrap();
    Served {
        server,
        scene: description,
        treelets,
        _pool_dir: pool_dir,
        _data_dir: data_dir,
    }
}

fn headless(
    addr: SocketAddr,
    served: &Served,
    path: CameraPath,
    budget_bytes: u64,
) -> HeadlessConfig {
    let url = ServerUrl {
        host: addr.ip().to_string(),
        port: addr.port(),
        scene: served.scene.name.clone(),
    };
    HeadlessConfig {
        client: ClientConfig::new(url, Trust::Fingerprint(served.server.fingerprint.clone()))
            .with_token(TOKEN),
        core: CoreConfig {
            analysis: AnalysisConfig {
                ratio: RATIO,
                lod_bias: 1.0,
            },
            budget_bytes,
            ..CoreConfig::default()
        },
        camera_path: path,
        seed: 7,
        width: SIZE.0,
        height: SIZE.1,
        cycles: 800,
        min_cycle: Duration::from_millis(4),
        connect_timeout: Duration::from_secs(30),
        reference: None,
        until_converged: false,
        render_every: 1,
    }
}

/// The fully resident buffer of the scene, with all its channels.
fn full(served: &Served) -> SlotBuffer {
    SlotBuffer::fully_resident(
        &served.scene,
        served.scene.layout.channels(),
        served.treelets.iter().cloned(),
    )
    .unwrap()
}

fn reference(served: &Served, full: &SlotBuffer, path: &CameraPath, cycle: u32) -> Image {
    let frame = SceneFrame::of(&served.scene);
    let camera = path.camera(cycle, &frame, 7, SIZE.0, SIZE.1);
    render(&full.view(), &frame, &camera, 1.0, &Light::default())
}

/// Treelets the view of `path` at `cycle` needs resident: those holding every pixel's hit in
/// the fully resident tree, and their ancestors.
fn needed_treelets(served: &Served, full: &SlotBuffer, path: &CameraPath, cycle: u32) -> u32 {
    let frame = SceneFrame::of(&served.scene);
    let camera = path.camera(cycle, &frame, 7, SIZE.0, SIZE.1);
    let lod = Lod {
        pixel_angle: camera.pixel_angle(),
        lod_bias: 1.0,
        max_depth: frame.max_depth,
    };
    let mut slots = HashSet::new();
    for y in 0..SIZE.1 {
        for x in 0..SIZE.0 {
            let ray = camera.ray(f64::from(x) + 0.5, f64::from(y) + 0.5);
            if let Some(h) = trace(&full.view(), &frame, &ray, &lod) {
                let mut s = Some(h.node / served.scene.treelet_nodes);
                while let Some(slot) = s {
                    if !slots.insert(slot) {
                        break;
                    }
                    s = full.parent_slot(slot);
                }
            }
        }
    }
    slots.len() as u32
}

fn scene_bytes(served: &Served) -> u64 {
    u64::from(served.scene.treelet_count)
        * SlotBuffer::slot_bytes(served.scene.treelet_nodes, served.scene.layout.channels())
}

/// Runs a static-camera session to convergence and checks it against the reference.
async fn converge(served: &Arc<Served>, addr: SocketAddr, what: &str) -> HeadlessRun {
    let full = full(served);
    let reference = reference(served, &full, &CameraPath::Static, 0);
    assert!(
        reference.coverage() > (SIZE.0 * SIZE.1 / 20) as u64,
        "{what}: the reference view shows too little of the scene ({} px)",
        reference.coverage()
    );
    // What this view needs and half as much again for treelets in flight and on their way
    // out, far below the whole scene.
    let needed = needed_treelets(served, &full, &CameraPath::Static, 0);
    let slot_bytes =
        SlotBuffer::slot_bytes(served.scene.treelet_nodes, served.scene.layout.channels());
    let budget = u64::from(needed + needed / 2) * slot_bytes;
    assert!(
        budget * 2 <= scene_bytes(served),
        "{what}: the view needs {needed} of {} treelets, not far below the scene",
        served.scene.treelet_count
    );
    let mut cfg = headless(addr, served, CameraPath::Static, budget);
    cfg.reference = Some(reference.clone());
    cfg.until_converged = true;
    let handle = tokio::runtime::Handle::current();
    let t0 = Instant::now();
    let run = tokio::task::spawn_blocking(move || {
        run_headless_with(cfg, &handle, Box::new(CpuBackend), |_| {})
    })
    .await
    .unwrap()
    .unwrap_or_else(|e| panic!("{what}: run failed: {e}"));
    let records = &run.report.records;
    let last = records.last().unwrap();
    eprintln!(
        "{what}: {} treelets, view needs {needed}, budget {} slots; converged at {:?} after \
         {:.2} s ({} cycles), peak {} slots, {} treelets / {} B received",
        served.scene.treelet_count,
        run.capacity,
        run.converged_at,
        t0.elapsed().as_secs_f64(),
        records.len(),
        run.peak_slots,
        run.client.treelets_received,
        run.client.bytes_received,
    );
    let converged = run
        .converged_at
        .unwrap_or_else(|| panic!("{what}: did not converge in {} cycles", records.len()));
    assert_eq!(last.image_rmse, Some(0.0), "{what}: final image RMSE");
    assert_eq!(last.differing_share, Some(0.0), "{what}: differing pixels");
    assert_eq!(run.image, reference, "{what}: final image differs");
    // Error against time: positive at first, zero from the convergence round on.
    assert!(
        records[0].error.max > 0.0,
        "{what}: the root alone should be coarser than a pixel"
    );
    assert!(records[0].image_rmse.unwrap() > 0.0);
    let round_start = (converged + 1 - RATIO * RATIO) as usize;
    assert!(
        records[round_start..].iter().all(|r| r.error.max == 0.0),
        "{what}: error not zero over the final round"
    );
    assert!(run.peak_slots <= run.capacity);
    run
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn static_camera_converges_exactly_over_loopback_with_a_fraction_of_the_scene() {
    for (rel, name) in [
        ("points/lion_takanawa.copc.laz", "lion"),
        ("volumes/engine_256x256x128_u8.nrrd", "engine"),
        ("meshes/igea.ply", "igea"),
    ] {
        let served = Arc::new(serve(rel, name, 1024).await);
        let addr = served.server.quic_addr;
        converge(&served, addr, name).await;
    }
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
    let run = converge(&served, link.local_addr(), "lion over 25 ms / 100 Mbit/s").await;
    let r = &run.report.records;
    let first_insert = r.iter().find(|c| c.treelets_inserted > 0).unwrap();
    assert!(
        first_insert.time_s >= 0.05,
        "nothing can arrive before one round trip (50 ms), got {:.3} s",
        first_insert.time_s
    );
    // The run's report and chart, kept for people to look at.
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("client-e2e");
    std::fs::create_dir_all(&out).unwrap();
    run.report.write_csv(&out.join("wan.csv")).unwrap();
    arbor_client::chart::draw(
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
            let reference = reference(&check, &full, &path, v.record.cycle);
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
}
