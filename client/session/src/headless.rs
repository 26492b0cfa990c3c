//! Headless runs: a [`Session`] stepped along a camera path for a number of cycles, with the
//! per-cycle report (error against run time), the last frame and convergence.

use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_proto::SceneDescription;

use crate::RunError;
use crate::session::{RenderMode, Session, SessionConfig, compare};
use arbor_client_core::backend::{Backend, BackendError, CpuBackend};
use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::CoreConfig;
use arbor_client_core::image::Image;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::slots::SlotBuffer;
use arbor_client_net::{ClientConfig, ClientStats};
use arbor_client_report::{CycleRecord, RunEvent, RunMeta, RunReport};

/// A headless run: connection, camera path, cycle count and outputs.
#[derive(Clone, Debug)]
pub struct HeadlessConfig {
    pub client: ClientConfig,
    pub core: CoreConfig,
    pub camera_path: CameraPath,
    pub seed: u64,
    pub width: u32,
    pub height: u32,
    /// Upper bound on cycles.
    pub cycles: u32,
    /// A cycle takes at least this long (the rest is slept), like a frame-rate cap.
    pub min_cycle: Duration,
    /// How long to wait for `SceneInfo` and the root treelet.
    pub connect_timeout: Duration,
    /// Compared with every rendered frame (image RMSE and differing share in the report).
    pub reference: Option<Image>,
    /// Stop as soon as the view has converged (see [`HeadlessRun::converged_at`]).
    pub until_converged: bool,
    /// Render only every k-th cycle (1 = every cycle); the last cycle is always rendered.
    pub render_every: u32,
    /// Lost GPU devices the run replaces with a new backend before a loss ends it (0: the
    /// first loss ends the run). See [`run_headless_on`].
    pub device_replacements: u32,
}

/// What a headless run produced.
#[derive(Debug)]
pub struct HeadlessRun {
    pub report: RunReport,
    /// The last rendered frame.
    pub image: Image,
    /// The cycle (0-based) of the first exact convergence: every pixel of the view known, none
    /// seeing unloaded detail coarser than a pixel at the bias in effect, so the image is the
    /// fully resident scene's at that bias. `None` if that never happened.
    pub converged_at: Option<u32>,
    /// The most slots ever used, and the capacity.
    pub peak_slots: u32,
    pub capacity: u32,
    /// Bytes per slot (nodes, attributes, bookkeeping).
    pub slot_bytes: u64,
    pub client: ClientStats,
    pub scene: Arc<SceneDescription>,
    /// The backend that ran the passes.
    pub backend: String,
}

/// What an observer of [`run_headless_with`] sees after each cycle.
#[derive(Debug)]
pub struct CycleView<'a> {
    pub record: &'a CycleRecord,
    pub camera: &'a Camera,
    /// The frame, when this cycle rendered one.
    pub image: Option<&'a Image>,
    pub slots: &'a SlotBuffer,
}

/// Runs a headless session on the CPU twins. Synchronous: call it from a thread that is not a
/// tokio worker, with a handle to a running runtime (the connection lives there).
pub fn run_headless(
    config: HeadlessConfig,
    runtime: &tokio::runtime::Handle,
) -> Result<HeadlessRun, RunError> {
    run_headless_with(config, runtime, Box::new(CpuBackend), |_| {})
}

/// [`run_headless`] on `backend`, calling `observer` after every cycle (tests check each frame
/// with it). With no other backend to take its place, a lost device ends the run.
pub fn run_headless_with(
    config: HeadlessConfig,
    runtime: &tokio::runtime::Handle,
    backend: Box<dyn Backend>,
    observer: impl FnMut(&CycleView<'_>),
) -> Result<HeadlessRun, RunError> {
    let mut backend = Some(backend);
    run_headless_on(
        config,
        runtime,
        move || {
            backend.take().ok_or_else(|| {
                BackendError::DeviceLost("no other backend to replace the lost one".into())
            })
        },
        observer,
    )
}

/// [`run_headless`] on the backends `make_backend` makes: the first for the run and, each time
/// the device of the one in use is lost ([`BackendError::DeviceLost`]: a driver reset, the GPU
/// removed), another to go on with, up to [`HeadlessConfig::device_replacements`] times. The
/// resident slots are uploaded to the new one and the session goes on where it was; the cycle
/// that failed has no record, and the report's [`RunEvent`]s say when and why. A backend that
/// fails otherwise, or a replacement that cannot be made, ends the run with its error.
pub fn run_headless_on(
    config: HeadlessConfig,
    runtime: &tokio::runtime::Handle,
    mut make_backend: impl FnMut() -> Result<Box<dyn Backend>, BackendError>,
    mut observer: impl FnMut(&CycleView<'_>),
) -> Result<HeadlessRun, RunError> {
    config.core.validate()?;
    if config.width == 0 || config.height == 0 || config.render_every == 0 {
        return Err(RunError::Invalid(
            "frame size and render interval must be at least 1".into(),
        ));
    }
    if let Some(r) = &config.reference
        && (r.width != config.width || r.height != config.height)
    {
        return Err(RunError::Reference(format!(
            "{}×{} but the run renders {}×{}",
            r.width, r.height, config.width, config.height
        )));
    }
    let mut session = Session::connect(
        SessionConfig {
            client: config.client.clone(),
            core: config.core.clone(),
            connect_timeout: config.connect_timeout,
            first_camera: Some(config.camera_path.camera(
                0,
                &SceneFrame::UNIT,
                config.seed,
                config.width,
                config.height,
            )),
        },
        runtime,
        make_backend()?,
    )?;
    let result = cycles(&config, &mut session, &mut make_backend, &mut observer);
    let client = session.client_stats();
    let scene = session.scene().clone();
    let channels = session.channels().to_vec();
    let capacity = session.core().slots().capacity();
    let peak_slots = session.peak_slots();
    let converged_at = session.converged_at();
    let backend = session.core().backend_name();
    session.close(runtime);
    let (report, image) = result?;
    Ok(HeadlessRun {
        report,
        image,
        converged_at,
        peak_slots,
        capacity,
        slot_bytes: SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
        client,
        scene,
        backend,
    })
}

fn cycles(
    config: &HeadlessConfig,
    session: &mut Session,
    make_backend: &mut impl FnMut() -> Result<Box<dyn Backend>, BackendError>,
    observer: &mut impl FnMut(&CycleView<'_>),
) -> Result<(RunReport, Image), RunError> {
    let scene = session.scene().clone();
    let frame = *session.core().frame();
    let mut report = RunReport {
        meta: RunMeta {
            scene: scene.name.clone(),
            server: format!(
                "quic://{}:{}/{}",
                config.client.url.host, config.client.url.port, config.client.url.scene
            ),
            width: config.width,
            height: config.height,
            feedback_ratio: config.core.analysis.ratio,
            budget_mib: config.core.budget_bytes as f64 / (1024.0 * 1024.0),
            camera_path: config.camera_path.to_string(),
            treelet_bytes: scene.treelet_nodes * arbor_proto::limits::NODE_BYTES,
        },
        records: Vec::new(),
        events: Vec::new(),
    };
    let mut image = Image::new(config.width, config.height);
    let mut replacements = 0u32;
    for cycle in 0..config.cycles {
        let cycle_start = Instant::now();
        let camera =
            config
                .camera_path
                .camera(cycle, &frame, config.seed, config.width, config.height);
        let last = cycle + 1 == config.cycles;
        let render = last || cycle % config.render_every == 0;
        let stepped = session
            .step(
                &camera,
                if render {
                    RenderMode::Image
                } else {
                    RenderMode::Skip
                },
                config.reference.as_ref(),
            )
            .and_then(|mut step| {
                if (last || (step.converged_now && config.until_converged)) && step.image.is_none()
                {
                    // The run ends here: draw this cycle's frame after all.
                    let i = session.render(&camera)?;
                    if let Some(r) = &config.reference {
                        (step.record.image_rmse, step.record.differing_share) = compare(&i, r)?;
                    }
                    step.image = Some(i);
                }
                Ok(step)
            });
        let step = match stepped {
            Ok(step) => step,
            Err(RunError::Backend(BackendError::DeviceLost(reason)))
                if replacements < config.device_replacements =>
            {
                replacements += 1;
                let lost = Instant::now();
                let time_s = session.started().elapsed().as_secs_f64();
                tracing::warn!(cycle, %reason, "the GPU device was lost: replacing the backend");
                session.replace_backend(make_backend()?)?;
                report.events.push(RunEvent::device_replaced(
                    cycle,
                    time_s,
                    &reason,
                    &session.core().backend_name(),
                    lost.elapsed(),
                ));
                if last {
                    // The run ends here: its frame from the new backend.
                    image = session.render(&camera)?;
                }
                continue;
            }
            Err(e) => return Err(e),
        };
        let stop = last || (step.converged_now && config.until_converged);
        let rendered = step.image.is_some();
        if let Some(i) = step.image {
            image = i;
        }
        observer(&CycleView {
            record: &step.record,
            camera: &camera,
            image: rendered.then_some(&image),
            slots: session.core().slots(),
        });
        report.records.push(step.record);
        report.events.extend(step.stall);
        if stop {
            break;
        }
        if let Some(rest) = config.min_cycle.checked_sub(cycle_start.elapsed()) {
            std::thread::sleep(rest);
        }
    }
    Ok((report, image))
}
