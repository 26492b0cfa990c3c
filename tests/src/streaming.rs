//! Streaming end to end, shared by the CPU and GPU tests: a real scan built into a real pool and
//! served by the real server, headless runs against it, and the reference of the fully resident
//! scene rendered by the same backend.

use std::collections::HashSet;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_core::analysis::AnalysisConfig;
use arbor_client_core::backend::render_resident;
use arbor_client_core::backend::{Backend, CpuBackend};
use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::CoreConfig;
use arbor_client_core::image::Image;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::Light;
use arbor_client_core::slots::{DecodedTreelet, SlotBuffer};
use arbor_client_core::traverse::{Lod, trace};
use arbor_client_net::{ClientConfig, ClientEvent, ServerUrl, TreeletClient, Trust};
use arbor_client_session::headless::{HeadlessConfig, HeadlessRun, run_headless_with};
use arbor_proto::{SceneDescription, TreeletId};
use arbor_server::daemon::{DaemonOptions, RunningServer, start_with};
use arbor_server::octree::BuildOptions;
use arbor_server::service::ServeConfig;
use arbor_server::service::config::{AdminTokenSource, SceneAccess};
use tempfile::TempDir;

use crate::support::{Built, build_file, decoded_treelets};

pub const TOKEN: &str = "client-e2e";
/// The admin token of the daemons [`serve_with`] starts.
pub const ADMIN_TOKEN: &str = "admin-client-e2e";
pub const SIZE: (u32, u32) = (96, 96);
/// Feedback ratio of these runs: 4 → every pixel sampled once per 16 cycles.
pub const RATIO: u32 = 4;

/// A scene served over loopback QUIC by the real server.
#[derive(Debug)]
pub struct Served {
    pub server: RunningServer,
    pub scene: SceneDescription,
    /// Every treelet, decoded from the pool with all the scene's channels.
    pub treelets: Vec<DecodedTreelet>,
    /// Per treelet, the bytes its message takes on the wire with all the scene's channels
    /// (compressed blocks as stored, plus the message header).
    pub wire_bytes: Vec<u64>,
    _pool_dir: TempDir,
    _data_dir: TempDir,
}

impl Served {
    /// The `arbor-client` arguments that reach scene `name` of this server: its URL, the
    /// certificate's fingerprint and the clients' token.
    pub fn client_args(&self, name: &str) -> [String; 6] {
        [
            "--server".into(),
            format!("quic://{}/{name}", self.server.quic_addr),
            "--cert-fingerprint".into(),
            self.server.fingerprint.clone(),
            "--token".into(),
            TOKEN.into(),
        ]
    }

    /// A client configuration for this server's scene through `addr` (the server's own address
    /// or a link emulator's in front of it): the certificate's fingerprint and the clients'
    /// token.
    pub fn client_config(&self, addr: SocketAddr) -> ClientConfig {
        let url = ServerUrl {
            host: addr.ip().to_string(),
            port: addr.port(),
            scene: self.scene.name.clone(),
        };
        ClientConfig::new(url, Trust::Fingerprint(self.server.fingerprint.clone()))
            .with_token(TOKEN)
    }
}

/// Builds a real scan (`treelet_bytes` treelets) into a fresh pool and serves it.
pub async fn serve(rel: &str, name: &str, treelet_bytes: u32) -> Served {
    serve_with(rel, name, treelet_bytes, DaemonOptions::default()).await
}

/// [`serve`] by a daemon started with `options`; with an import root, the admin API listens on
/// loopback (token [`ADMIN_TOKEN`]) and every scene is public.
pub async fn serve_with(
    rel: &str,
    name: &str,
    treelet_bytes: u32,
    options: DaemonOptions,
) -> Served {
    serve_altered(rel, name, treelet_bytes, options, |_| {}).await
}

/// [`serve_with`], with `alter` run on the built pool before the daemon opens it (a test that
/// damages what is stored). [`Served::treelets`] and [`Served::wire_bytes`] are the scene as
/// built, before `alter`.
pub async fn serve_altered(
    rel: &str,
    name: &str,
    treelet_bytes: u32,
    options: DaemonOptions,
    alter: impl FnOnce(&Built) + Send + 'static,
) -> Served {
    serve_inner(rel, name, treelet_bytes, options, alter, |_| {}).await
}

/// [`serve`] by a daemon whose configuration `tune` changed last (a benchmark comparing two
/// server settings in one run).
pub async fn serve_tuned(
    rel: &str,
    name: &str,
    treelet_bytes: u32,
    tune: impl FnOnce(&mut ServeConfig),
) -> Served {
    serve_inner(
        rel,
        name,
        treelet_bytes,
        DaemonOptions::default(),
        |_| {},
        tune,
    )
    .await
}

async fn serve_inner(
    rel: &str,
    name: &str,
    treelet_bytes: u32,
    options: DaemonOptions,
    alter: impl FnOnce(&Built) + Send + 'static,
    tune: impl FnOnce(&mut ServeConfig),
) -> Served {
    let rel = rel.to_owned();
    let name_owned = name.to_owned();
    let (built, treelets, wire_bytes) = tokio::task::spawn_blocking(move || {
        let built = build_file(
            &rel,
            &name_owned,
            &BuildOptions {
                treelet_bytes,
                ..BuildOptions::default()
            },
        );
        let treelets = decoded_treelets(&built.scene);
        let wire_bytes = wire_bytes(&built.scene);
        alter(&built);
        (built, treelets, wire_bytes)
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
    cfg.admin_token = AdminTokenSource::Inline(ADMIN_TOKEN.into());
    cfg.scenes
        .insert(name.into(), SceneAccess::Tokens(vec![TOKEN.into()]));
    if options.import_root.is_some() {
        cfg.admin_listen = Some("127.0.0.1:0".parse().unwrap());
    }
    // Benchmarks compare visible cuts on and off in one binary (`service::visibility`).
    let env = |key: &str| std::env::var(key).ok().and_then(|g| g.parse().ok());
    if let Some(grid) = env("ARBOR_VISIBILITY_GRID") {
        cfg.visibility_grid = grid;
    }
    if let Some(grid) = env("ARBOR_VISIBILITY_FINE_GRID") {
        cfg.visibility_fine_grid = grid;
    }
    if let Some(window) = std::env::var("ARBOR_INITIAL_WINDOW")
        .ok()
        .and_then(|w| w.parse().ok())
    {
        cfg.initial_window = window;
    }
    tune(&mut cfg);
    let server = start_with(cfg, options).await.unwrap();
    Served {
        server,
        scene: description,
        treelets,
        wire_bytes,
        _pool_dir: pool_dir,
        _data_dir: data_dir,
    }
}

/// Per treelet of `scene`, its message's bytes on the wire with every channel: the stored
/// compressed blocks and the largest message header.
pub fn wire_bytes(scene: &arbor_server::pool::StoredScene) -> Vec<u64> {
    let d = &scene.description;
    (0..d.treelet_count)
        .map(|id| {
            let id = arbor_proto::TreeletId(id);
            let nodes = scene.nodes(id).unwrap().map_or(0, |b| b.len());
            let channels: usize = d
                .layout
                .channels()
                .iter()
                .map(|&c| scene.channel(c, id).unwrap().map_or(0, |b| b.len()))
                .sum();
            (arbor_proto::limits::MAX_TREELET_MESSAGE_HEADER + nodes + channels) as u64
        })
        .collect()
}

/// A headless configuration for a run against `served` through `addr`.
pub fn headless(
    addr: SocketAddr,
    served: &Served,
    path: CameraPath,
    budget_bytes: u64,
) -> HeadlessConfig {
    HeadlessConfig {
        client: served.client_config(addr),
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
        device_replacements: 0,
    }
}

/// The fully resident buffer of the scene, with all its channels.
pub fn full(served: &Served) -> SlotBuffer {
    SlotBuffer::fully_resident(
        &served.scene,
        served.scene.layout.channels(),
        served.treelets.iter().cloned(),
    )
    .unwrap()
}

/// What `path` at `cycle` sees with everything resident, rendered by `backend`.
pub fn reference(
    served: &Served,
    full: &SlotBuffer,
    path: &CameraPath,
    cycle: u32,
    backend: &mut dyn Backend,
) -> Image {
    let frame = SceneFrame::of(&served.scene);
    let camera = path.camera(cycle, &frame, 7, SIZE.0, SIZE.1);
    render_resident(full, &frame, &camera, 1.0, &Light::default(), backend)
        .expect("rendering the reference")
}

/// What `camera` sees of the treelets in `slots` at LOD bias `bias`, on the CPU twins: with
/// every treelet resident, the reference a run at that bias must converge to.
pub fn cpu_render_at(slots: &SlotBuffer, frame: &SceneFrame, camera: &Camera, bias: f64) -> Image {
    render_resident(
        slots,
        frame,
        camera,
        bias,
        &Light::default(),
        &mut CpuBackend,
    )
    .expect("the CPU backend does not fail")
}

/// Treelets the view of `path` at `cycle` needs resident: those holding every pixel's hit in
/// the fully resident tree, and their ancestors.
pub fn needed_treelets(served: &Served, full: &SlotBuffer, path: &CameraPath, cycle: u32) -> u32 {
    needed_treelet_ids(&served.scene, full, path, cycle).len() as u32
}

/// The treelets [`needed_treelets`] counts, of `scene` with everything resident in `full`.
pub fn needed_treelet_ids(
    scene: &SceneDescription,
    full: &SlotBuffer,
    path: &CameraPath,
    cycle: u32,
) -> HashSet<TreeletId> {
    let frame = SceneFrame::of(scene);
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
                let mut s = Some(h.node / scene.treelet_nodes);
                while let Some(slot) = s {
                    if !slots.insert(slot) {
                        break;
                    }
                    s = full.parent_slot(slot);
                }
            }
        }
    }
    slots.iter().filter_map(|&s| full.treelet_in(s)).collect()
}

/// Bytes of slot buffer the whole scene would take.
pub fn scene_bytes(served: &Served) -> u64 {
    u64::from(served.scene.treelet_count)
        * SlotBuffer::slot_bytes(served.scene.treelet_nodes, served.scene.layout.channels())
}

/// Runs a static-camera session on the backend `make` creates (inside the run's thread) to
/// convergence, and checks it against the reference rendered by `reference_backend`.
pub async fn converge(
    served: &Arc<Served>,
    addr: SocketAddr,
    what: &str,
    reference_backend: &mut dyn Backend,
    make: impl FnOnce() -> Box<dyn Backend> + Send + 'static,
) -> HeadlessRun {
    converge_with(served, addr, what, reference_backend, make, |_| {}).await
}

/// [`converge`] with the run's configuration adjusted by `tweak` (policy, sampling, push).
pub async fn converge_with(
    served: &Arc<Served>,
    addr: SocketAddr,
    what: &str,
    reference_backend: &mut dyn Backend,
    make: impl FnOnce() -> Box<dyn Backend> + Send + 'static,
    tweak: impl FnOnce(&mut HeadlessConfig),
) -> HeadlessRun {
    let full = full(served);
    let reference = reference(served, &full, &CameraPath::Static, 0, reference_backend);
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
    tweak(&mut cfg);
    let handle = tokio::runtime::Handle::current();
    let t0 = Instant::now();
    let run = tokio::task::spawn_blocking(move || run_headless_with(cfg, &handle, make(), |_| {}))
        .await
        .unwrap()
        .unwrap_or_else(|e| panic!("{what}: run failed: {e}"));
    let records = &run.report.records;
    let last = records.last().unwrap();
    eprintln!(
        "{what}: {} treelets, view needs {needed}, budget {} slots; converged at {:?} after \
         {:.2} s ({} cycles), peak {} slots, {} treelets / {} B received, LOD bias {}, \
         {} dropped, {} pushed, {} pushes dropped",
        served.scene.treelet_count,
        run.capacity,
        run.converged_at,
        t0.elapsed().as_secs_f64(),
        records.len(),
        run.peak_slots,
        run.client.treelets_received,
        run.client.bytes_received,
        last.lod_bias,
        records.iter().map(|r| r.dropped).sum::<u32>(),
        records.iter().map(|r| r.pushed).sum::<u32>(),
        records.iter().map(|r| r.push_dropped).sum::<u32>(),
    );
    if run.converged_at.is_none() {
        // What a stall looks like: the last cycle that moved anything, and the last cycles.
        let moved = records
            .iter()
            .rposition(|r| r.requests_sent + r.treelets_received + r.evictions > 0);
        eprintln!("{what}: last cycle with requests, arrivals or evictions: {moved:?}");
        for r in records.iter().rev().take(3).rev() {
            eprintln!("{what}: {r:?}");
        }
    }
    let converged = run
        .converged_at
        .unwrap_or_else(|| panic!("{what}: did not converge in {} cycles", records.len()));
    assert_eq!(last.image_rmse, Some(0.0), "{what}: final image RMSE");
    assert_eq!(last.differing_share, Some(0.0), "{what}: differing pixels");
    assert_eq!(run.image, reference, "{what}: final image differs");
    // Error against time: positive at first, zero from the convergence round on.
    // (A pipelined backend's first feedback arrives a cycle late.)
    assert!(
        records.iter().take(3).any(|r| r.error.max > 0.0),
        "{what}: the root alone should be coarser than a pixel"
    );
    assert!(records[0].image_rmse.unwrap() > 0.0);
    // Convergence is every pixel of the view known, none coarser than a pixel.
    let at = &records[converged as usize];
    assert!(
        at.known_share == 1.0 && at.error.max == 0.0,
        "{what}: converged at cycle {converged} with {:.3} of the view known, error max {}",
        at.known_share,
        at.error.max
    );
    assert!(run.peak_slots <= run.capacity);
    assert_report_accounts(what, &run);
    run
}

/// A run's traffic columns count what its cycles took off the connection: a cycle's treelets
/// and bytes come from the same arrivals, every treelet inserted was received (the root too,
/// with the first cycle), and nothing is counted that the connection did not hand over.
pub fn assert_report_accounts(what: &str, run: &HeadlessRun) {
    let records = &run.report.records;
    for r in records {
        assert_eq!(
            r.treelets_received == 0,
            r.bytes_received == 0,
            "{what}: cycle {} counts {} treelets received but {} bytes",
            r.cycle,
            r.treelets_received,
            r.bytes_received
        );
    }
    let received: u64 = records.iter().map(|r| u64::from(r.treelets_received)).sum();
    let inserted: u64 = records.iter().map(|r| u64::from(r.treelets_inserted)).sum();
    let bytes: u64 = records.iter().map(|r| r.bytes_received).sum();
    assert!(
        received > inserted,
        "{what}: {received} treelets received, {inserted} inserted besides the root"
    );
    assert!(
        received <= run.client.treelets_received && bytes <= run.client.bytes_received,
        "{what}: the report counts {received} treelets / {bytes} B, the connection handed over \
         {} / {} B",
        run.client.treelets_received,
        run.client.bytes_received
    );
}

/// One request to a daemon's admin API (token [`ADMIN_TOKEN`]) on its own connection: the
/// status and the JSON body (`Null` when the body is not JSON).
pub async fn admin_request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    body: &str,
) -> (u16, serde_json::Value) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!(
        "{method} {path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {ADMIN_TOKEN}\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(req.as_bytes()).await.unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).await.unwrap();
    let raw = String::from_utf8(raw).unwrap();
    let (head, body) = raw.split_once("\r\n\r\n").unwrap();
    let status = head.split(' ').nth(1).unwrap().parse().unwrap();
    (
        status,
        serde_json::from_str(body).unwrap_or(serde_json::Value::Null),
    )
}

/// Fetches every treelet of the scene through `addr` and closes; panics on a disconnect or a
/// stall, and checks each treelet arrived once, with its blocks.
pub async fn fetch_scene(served: &Served, addr: SocketAddr) {
    let config = served
        .client_config(addr)
        .with_channels(served.scene.layout.channels().iter().copied());
    let mut client = TreeletClient::start(config).unwrap();
    let mut left: HashSet<TreeletId> = (0..served.treelets.len() as u32).map(TreeletId).collect();
    client
        .request(left.iter().map(|&id| (id, -(id.0 as f32))).collect())
        .unwrap();
    while !left.is_empty() {
        match tokio::time::timeout(Duration::from_secs(60), client.next_event()).await {
            Ok(Some(ClientEvent::Treelet(t))) => {
                assert!(left.remove(&t.id), "treelet {:?} arrived twice", t.id);
                assert!(
                    !t.nodes.is_empty() && t.wire_bytes > t.nodes.len(),
                    "treelet {:?} arrived with its blocks",
                    t.id
                );
            }
            Ok(Some(ClientEvent::Disconnected { reason, .. })) => panic!("disconnected: {reason}"),
            Ok(Some(_)) => {}
            Ok(None) | Err(_) => panic!("stalled with {} treelets left", left.len()),
        }
    }
    client.close().await;
}
