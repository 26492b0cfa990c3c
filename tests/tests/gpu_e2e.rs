//! The streaming convergence of `client_e2e.rs`, with the analysis and render passes on the GPU
//! backend (wgpu; lavapipe in CI): a static camera and a budget far below the scene converge to
//! the GPU's own render of the fully resident scene exactly (RMSE 0), over loopback QUIC.
//!
//! Fails loudly when there is no adapter: `scripts/test` installs lavapipe.

use std::sync::Arc;

use arbor_client_gpu::{GpuBackend, GpuContext};
use arbor_tests::streaming::{converge, serve};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn static_camera_converges_exactly_on_the_gpu_backend() {
    let ctx = Arc::new(GpuContext::new(None).unwrap_or_else(|e| {
        panic!("this test needs a wgpu adapter (scripts/test installs lavapipe): {e}")
    }));
    eprintln!("adapter: {}", ctx.describe());
    for (rel, name) in [
        ("points/lion_takanawa.copc.laz", "lion"),
        ("volumes/engine_256x256x128_u8.nrrd", "engine"),
    ] {
        let served = Arc::new(serve(rel, name, 1024).await);
        let mut reference_backend = GpuBackend::new(ctx.clone());
        let run_ctx = ctx.clone();
        let run = converge(
            &served,
            served.server.quic_addr,
            &format!("{name} on the GPU"),
            &mut reference_backend,
            move || Box::new(GpuBackend::new(run_ctx)),
        )
        .await;
        assert!(
            run.backend.contains(&ctx.info.name),
            "the run should have used the GPU backend, used {}",
            run.backend
        );
    }
}
