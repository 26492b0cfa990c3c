//! The streaming convergence of `client_e2e.rs`, with the analysis and render passes on the GPU
//! backend (wgpu; lavapipe in CI): a static camera and a budget far below the scene converge to
//! the GPU's own render of the fully resident scene exactly (RMSE 0), over loopback QUIC.
//!
//! A device lost mid-run ends the run with the reason, or, where the run may replace it, the run
//! goes on on a new device from what it holds and still converges exactly.
//!
//! Fails loudly when there is no adapter: `scripts/test` installs lavapipe.

use std::sync::{Arc, Mutex};

use arbor_client_core::backend::{Backend, BackendError};
use arbor_client_core::camera::CameraPath;
use arbor_client_gpu::{GpuBackend, GpuContext};
use arbor_client_session::RunError;
use arbor_client_session::headless::{HeadlessRun, run_headless_on, run_headless_with};
use arbor_tests::streaming::{
    assert_report_accounts, converge, full, headless, reference, scene_bytes, serve,
};

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
    assert_ended_by_a_destroyed_device(result);
}

/// `result` is a run's end by the loss of a destroyed device.
fn assert_ended_by_a_destroyed_device(result: Result<HeadlessRun, RunError>) {
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

/// Makes GPU backends, each on a device of its own, keeping their contexts so that a test can
/// lose them.
fn device_maker(
    made: Arc<Mutex<Vec<Arc<GpuContext>>>>,
) -> impl FnMut() -> Result<Box<dyn Backend>, BackendError> {
    move || {
        let ctx = Arc::new(GpuContext::new(None).map_err(|e| {
            BackendError::Device(format!(
                "this test needs a wgpu adapter (scripts/test installs lavapipe): {e}"
            ))
        })?);
        made.lock().unwrap().push(ctx.clone());
        Ok(Box::new(GpuBackend::new(ctx)))
    }
}

/// With `device_replacements`, a device lost mid-run (destroyed here) is replaced by a new one:
/// the run goes on from the slots it holds, on the same connection, and converges to the
/// reference exactly; the report has no record of the cycle that failed and says when and why
/// the backend was replaced. A loss beyond the replacements allowed still ends the run.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_device_is_replaced_and_the_run_still_converges_exactly() {
    const LOST_AFTER: u32 = 3;
    let served = Arc::new(serve("points/lion_takanawa.copc.laz", "lion", 1024).await);
    let reference_ctx = Arc::new(GpuContext::new(None).unwrap_or_else(|e| {
        panic!("this test needs a wgpu adapter (scripts/test installs lavapipe): {e}")
    }));
    let expected = reference(
        &served,
        &full(&served),
        &CameraPath::Static,
        0,
        &mut GpuBackend::new(reference_ctx),
    );
    let mut config = headless(
        served.server.quic_addr,
        &served,
        CameraPath::Static,
        scene_bytes(&served),
    );
    config.reference = Some(expected.clone());
    config.until_converged = true;
    config.device_replacements = 1;

    let made: Arc<Mutex<Vec<Arc<GpuContext>>>> = Arc::default();
    let handle = tokio::runtime::Handle::current();
    let (run_made, run_config) = (made.clone(), config.clone());
    let run = tokio::task::spawn_blocking(move || {
        let lose = run_made.clone();
        run_headless_on(run_config, &handle, device_maker(run_made), |view| {
            if view.record.cycle == LOST_AFTER {
                lose.lock().unwrap()[0].device.destroy();
            }
        })
    })
    .await
    .expect("the run neither panics nor hangs")
    .unwrap_or_else(|e| panic!("the run ended although the device could be replaced: {e}"));
    assert_eq!(
        made.lock().unwrap().len(),
        2,
        "one device, then its replacement"
    );
    let events = &run.report.events;
    assert_eq!(events.len(), 1, "{events:?}");
    assert_eq!(events[0].cycle, LOST_AFTER + 1);
    assert!(
        events[0].what.contains("lost (destroyed)") && events[0].what.contains("replaced by"),
        "{}",
        events[0].what
    );
    let records = &run.report.records;
    assert!(records.iter().all(|r| r.cycle != LOST_AFTER + 1));
    assert!(records.iter().any(|r| r.cycle > LOST_AFTER + 1));
    assert_eq!(run.client.connects, 1, "the connection was not touched");
    let converged = run.converged_at.expect("converged after the replacement");
    assert!(converged > LOST_AFTER + 1);
    assert_eq!(records.last().unwrap().image_rmse, Some(0.0));
    assert!(
        run.image == expected,
        "the final image differs from the reference"
    );
    assert_report_accounts("lion after a lost device", &run);
    eprintln!(
        "lion: device lost after cycle {LOST_AFTER}, {}; converged at cycle {converged}",
        events[0].what
    );

    // Lost twice with one replacement allowed: the second loss ends the run.
    let made: Arc<Mutex<Vec<Arc<GpuContext>>>> = Arc::default();
    let handle = tokio::runtime::Handle::current();
    let run_made = made.clone();
    let result = tokio::task::spawn_blocking(move || {
        let lose = run_made.clone();
        run_headless_on(config, &handle, device_maker(run_made), |view| {
            let contexts = lose.lock().unwrap();
            if view.record.cycle == LOST_AFTER {
                contexts[0].device.destroy();
            }
            if view.record.cycle == LOST_AFTER + 3 {
                contexts[1].device.destroy();
            }
        })
    })
    .await
    .expect("the run neither panics nor hangs");
    assert_ended_by_a_destroyed_device(result);
    assert_eq!(made.lock().unwrap().len(), 2);
}
