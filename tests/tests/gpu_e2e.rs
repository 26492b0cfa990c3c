//! The streaming convergence of `client_e2e.rs`, with the analysis and render passes on the GPU
//! backend (wgpu; lavapipe in CI): a static camera and a budget far below the scene converge to
//! the GPU's own render of the fully resident scene exactly (RMSE 0), over loopback QUIC.
//!
//! A device lost mid-run ends the run with the reason.
//!
//! Fails loudly when there is no adapter: `scripts/test` installs lavapipe.

use std::sync::Arc;

use arbor_client_core::backend::BackendError;
use arbor_client_core::camera::CameraPath;
use arbor_client_gpu::{GpuBackend, GpuContext};
use arbor_client_session::RunError;
use arbor_client_session::headless::run_headless_with;
use arbor_tests::streaming::{converge, headless, scene_bytes, serve};

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

/// A GPU device lost in the middle of a streamed run (destroyed here, as a driver reset or a
/// removed GPU loses it) ends the run with an error that says so: no panic, no hang, and the
/// connection closed on the way out.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_device_lost_mid_run_ends_the_run_with_the_reason() {
    let ctx = Arc::new(GpuContext::new(None).unwrap_or_else(|e| {
        panic!("this test needs a wgpu adapter (scripts/test installs lavapipe): {e}")
    }));
    let served = Arc::new(serve("points/lion_takanawa.copc.laz", "lion", 1024).await);
    let config = headless(
        served.server.quic_addr,
        &served,
        CameraPath::Static,
        scene_bytes(&served),
    );
    const LOST_AFTER: u32 = 5;
    let handle = tokio::runtime::Handle::current();
    let run_ctx = ctx.clone();
    let (result, cycles) = tokio::task::spawn_blocking(move || {
        let mut cycles = 0;
        let result = run_headless_with(
            config,
            &handle,
            Box::new(GpuBackend::new(run_ctx.clone())),
            |view| {
                cycles += 1;
                if view.record.cycle == LOST_AFTER {
                    run_ctx.device.destroy();
                }
            },
        );
        (result, cycles)
    })
    .await
    .expect("the run neither panics nor hangs");
    assert_eq!(
        cycles,
        LOST_AFTER + 1,
        "the cycle after the loss is the run's last"
    );
    match result {
        Err(RunError::Backend(BackendError::DeviceLost(reason))) => {
            assert_eq!(reason, "destroyed");
        }
        Err(other) => panic!("expected the device's loss, got {other}"),
        Ok(run) => panic!(
            "the run went on for {} cycles after the device was lost",
            run.report.records.len()
        ),
    }
}
