//! `arbor-client reference` without the whole scene: the streamed reference (only the treelets
//! the view's fully refined cut needs, fetched breadth first over loopback QUIC from the real
//! server) equals the whole-scene reference pixel for pixel on the real scans, for a distant
//! and a close camera, while fetching fewer treelets than the scene has.

use std::sync::Arc;
use std::time::Duration;

use arbor_client_core::backend::CpuBackend;
use arbor_client_core::camera::CameraPath;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::Light;
use arbor_client_session::reference::{ReferenceView, StreamedReference, streamed_reference};
use arbor_tests::streaming::{SIZE, Served, full, reference, serve};

fn streamed(served: &Arc<Served>, path: CameraPath, cycle: u32) -> StreamedReference {
    let client = served.client_config(served.server.quic_addr);
    let camera = move |frame: &SceneFrame| path.camera(cycle, frame, 7, SIZE.0, SIZE.1);
    let light = Light::default();
    let view = ReferenceView {
        camera: &camera,
        lod_bias: 1.0,
        light: &light,
    };
    streamed_reference(
        &client,
        served.scene.layout.channels(),
        &view,
        Duration::from_secs(30),
        &tokio::runtime::Handle::current(),
        &mut CpuBackend,
    )
    .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_streamed_reference_equals_the_whole_scene_reference() {
    // Points, a volume and a mesh; a distant and a close camera on lion.
    for (rel, name, treelet_bytes, close) in [
        ("points/lion_takanawa.copc.laz", "lion", 1024, true),
        ("points/autzen_trim.las", "autzen", 4096, false),
        ("volumes/engine_256x256x128_u8.nrrd", "engine", 1024, false),
        ("meshes/stanford-bunny.obj", "bunny", 1024, false),
    ] {
        let served = Arc::new(serve(rel, name, treelet_bytes).await);
        let full = full(&served);
        let views = [
            (CameraPath::Static, 0),
            (CameraPath::FlyIn { cycles: 10 }, 7),
        ];
        for &(path, cycle) in &views[..if close { 2 } else { 1 }] {
            let whole = reference(&served, &full, &path, cycle, &mut CpuBackend);
            let s = Arc::clone(&served);
            let r = tokio::task::spawn_blocking(move || streamed(&s, path, cycle))
                .await
                .unwrap();
            let what = format!("{name} {path:?}");
            assert!(whole.coverage() > 0, "{what}: the view shows nothing");
            assert_eq!(r.image, whole, "{what}: streamed reference differs");
            assert!(
                r.treelets < served.scene.treelet_count,
                "{what}: fetched {} of {} treelets",
                r.treelets,
                served.scene.treelet_count
            );
            assert!(r.rounds >= 1, "{what}");
            println!(
                "{what}: {} of {} treelets in {} rounds, cut at most {} bytes",
                r.treelets, served.scene.treelet_count, r.rounds, r.peak_cut_bytes
            );
        }
    }
}
