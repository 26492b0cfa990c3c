//! The winit application of the viewer: window, surface and device, the per-redraw cycle and
//! the keys. Everything testable without a window lives in the sibling modules; this one is
//! the glue, exercised end to end under Xvfb (`client/tests/viewer_xvfb.rs`).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use glam::DVec3;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, KeyEvent, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

use arbor_client_core::backend::{Backend, BackendError, CpuBackend};
use arbor_client_core::camera::CameraPath;
use arbor_client_core::image::Image;
use arbor_client_gpu::{GpuBackend, GpuContext};
use arbor_client_report::{CycleRecord, RunEvent, RunMeta, RunReport};
use arbor_client_session::{RenderMode, RunError, Session};

use super::blit::{Blit, FrameTexture, choose_surface_format, read_back};
use super::controls::{Button, Controls, Move};
use super::frame_scale::FrameScale;
use super::overlay::{Overlay, OverlayStats};
use super::{
    BackendChoice, Outcome, SCRIPTED_ZOOM_LINES, ViewerConfig, ViewerError, chart_path,
    next_lod_bias,
};

/// How often the overlay text is refreshed (its figures are averages over this interval).
const OVERLAY_INTERVAL: Duration = Duration::from_millis(250);

/// Opens the window, runs the viewer until it ends and writes the report (with `--report`).
/// Call it on the main thread (winit's event loop must live there) with a handle to a running
/// tokio runtime for the connection.
pub fn run(config: ViewerConfig, runtime: &tokio::runtime::Handle) -> Result<Outcome, ViewerError> {
    if config.width == 0 || config.height == 0 {
        return Err(ViewerError::Window(
            "the window needs at least 1×1 pixels".into(),
        ));
    }
    let event_loop = EventLoop::new()?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let stdin_closed = Arc::new(AtomicBool::new(false));
    if config.exit_after_converged && config.hold_until_stdin_eof {
        let flag = stdin_closed.clone();
        std::thread::spawn(move || {
            // Any content is ignored; only end of file (or a read error) matters.
            let _ = std::io::copy(&mut std::io::stdin().lock(), &mut std::io::sink());
            flag.store(true, Ordering::SeqCst);
        });
    }
    let mut app = App {
        config,
        runtime: runtime.clone(),
        started: Instant::now(),
        stdin_closed,
        state: None,
        error: None,
        outcome: None,
    };
    event_loop.run_app(&mut app)?;
    let App {
        state,
        error,
        outcome,
        config,
        ..
    } = app;
    if let Some(state) = state {
        let Running {
            session, report, ..
        } = *state;
        if let Some(path) = &config.report {
            write_report(&report, path)?;
        }
        session.close(runtime);
    }
    match error {
        Some(e) => Err(e),
        None => Ok(outcome.unwrap_or(Outcome::Closed { converged_at: None })),
    }
}

/// Writes the report CSV at `path` and its chart beside it.
fn write_report(report: &RunReport, path: &Path) -> Result<(), ViewerError> {
    report
        .write_csv(path)
        .map_err(|e| ViewerError::Output(format!("writing {}: {e}", path.display())))?;
    let chart = chart_path(path);
    let title = format!(
        "{} — viewer — {}×{}, {:.1} MiB budget",
        report.meta.scene, report.meta.width, report.meta.height, report.meta.budget_mib
    );
    arbor_client_report::chart::draw(report, &chart, &title)
        .map_err(|e| ViewerError::Output(format!("drawing {}: {e}", chart.display())))?;
    say(format_args!(
        "report: {} and {}",
        path.display(),
        chart.display()
    ));
    Ok(())
}

struct App {
    config: ViewerConfig,
    runtime: tokio::runtime::Handle,
    started: Instant,
    stdin_closed: Arc<AtomicBool>,
    state: Option<Box<Running>>,
    error: Option<ViewerError>,
    outcome: Option<Outcome>,
}

/// Where each cycle's frame comes from.
enum FrameSource {
    /// A CPU [`Image`] uploaded into the viewer's own texture.
    Upload(FrameTexture),
    /// The backend's own target ([`GpuBackend::target_view`]).
    InPlace,
}

/// Figures gathered between two overlay refreshes.
struct Interval {
    start: Instant,
    frames: u32,
    bytes: u64,
}

struct Running {
    // Dropped in order: the surface before the window it draws to.
    surface: wgpu::Surface<'static>,
    window: Arc<Window>,
    surface_config: wgpu::SurfaceConfiguration,
    /// The device the blit draws with, shared with the GPU renderer.
    gpu: Arc<GpuContext>,
    blit: Blit,
    source: FrameSource,
    session: Session,
    controls: Controls,
    overlay: Overlay,
    show_overlay: bool,
    report: RunReport,
    backend: String,
    last_frame: Instant,
    interval: Interval,
    converged_handled: bool,
    holding: bool,
    screenshots: u32,
    /// The fault injection has lost the device.
    device_lost: bool,
    /// Devices replaced so far.
    replacements: u32,
    /// The frame size while the camera moves.
    frame_scale: FrameScale,
    /// The clock `frame_scale` is fed with.
    clock_start: Instant,
    /// The previous frame's camera pose (position, forward, up), to see it move.
    last_pose: Option<[DVec3; 3]>,
    /// The latest frame's size when it was scaled down.
    scaled_frame: Option<(u32, u32)>,
    /// [`ViewerConfig::scripted_zoom_frames`].
    scripted_zoom_frames: u32,
    /// The first cycle whose full-size frame was converged (a scaled frame's convergence is a
    /// coarser picture's, so it does not count).
    converged_at: Option<u32>,
}

/// What draws to the window: its surface, the device, the surface's configuration and the blit.
struct WindowGpu {
    surface: wgpu::Surface<'static>,
    gpu: Arc<GpuContext>,
    surface_config: wgpu::SurfaceConfiguration,
    blit: Blit,
    /// The surface format is sRGB, so the blit decodes.
    decode_srgb: bool,
}

/// A device for `window` on the instance that makes its surface (a surface works only with the
/// instance that made it), the surface configured at `size` and a blit for an overlay panel of
/// `panel` pixels.
fn window_gpu(
    event_loop: &ActiveEventLoop,
    window: &Arc<Window>,
    size: (u32, u32),
    panel: (u32, u32),
) -> Result<WindowGpu, ViewerError> {
    let desc = wgpu::InstanceDescriptor::new_with_display_handle_from_env(Box::new(
        event_loop.owned_display_handle(),
    ));
    let backends = desc.backends;
    let instance = wgpu::Instance::new(desc);
    let surface = instance
        .create_surface(window.clone())
        .map_err(|e| ViewerError::Gpu(format!("creating the window surface: {e}")))?;
    let gpu = Arc::new(
        GpuContext::with_instance(instance, backends, Some(&surface))
            .map_err(|e| ViewerError::Gpu(e.to_string()))?,
    );
    let caps = surface.get_capabilities(&gpu.adapter);
    let (format, decode_srgb) = choose_surface_format(&caps.formats)
        .ok_or_else(|| ViewerError::Gpu("the surface offers no format".into()))?;
    let surface_config = wgpu::SurfaceConfiguration {
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        format,
        color_space: wgpu::SurfaceColorSpace::Auto,
        width: size.0.max(1),
        height: size.1.max(1),
        desired_maximum_frame_latency: 2,
        present_mode: wgpu::PresentMode::AutoVsync,
        alpha_mode: wgpu::CompositeAlphaMode::Auto,
        view_formats: vec![],
    };
    surface.configure(&gpu.device, &surface_config);
    let blit = Blit::new(&gpu.device, format, decode_srgb, panel);
    Ok(WindowGpu {
        surface,
        gpu,
        surface_config,
        blit,
        decode_srgb,
    })
}

/// The renderer for the configured [`BackendChoice`] on `gpu`, and where its frames are read.
fn make_backend(
    config: &ViewerConfig,
    gpu: &Arc<GpuContext>,
    size: (u32, u32),
) -> (Box<dyn Backend>, FrameSource) {
    // As `create_backend`: a software adapter is slower than the CPU twins on the same cores.
    let cpu = config.backend == BackendChoice::Cpu
        || (config.backend == BackendChoice::Auto && gpu.is_software());
    if cpu {
        (
            Box::new(CpuBackend),
            FrameSource::Upload(FrameTexture::new(&gpu.device, size.0, size.1)),
        )
    } else {
        let mut backend = GpuBackend::timed(gpu.clone());
        backend.set_feedback_mode(config.feedback);
        (Box::new(backend), FrameSource::InPlace)
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.state.is_some() || self.error.is_some() {
            return;
        }
        match self.start(event_loop) {
            Ok(state) => self.state = Some(Box::new(state)),
            Err(e) => self.fail(event_loop, e),
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        let Some(state) = self.state.as_deref_mut() else {
            return;
        };
        match event {
            WindowEvent::CloseRequested => self.close(event_loop),
            WindowEvent::Resized(size) => state.resize(size),
            WindowEvent::Focused(false) => state.controls.release_all(),
            WindowEvent::CursorMoved { position, .. } => {
                state.controls.cursor(position.x, position.y);
            }
            WindowEvent::CursorLeft { .. } => state.controls.cursor_left(),
            WindowEvent::MouseInput {
                state: s, button, ..
            } => {
                let b = match button {
                    MouseButton::Left => Button::Left,
                    MouseButton::Right => Button::Right,
                    _ => return,
                };
                state.controls.button(b, s == ElementState::Pressed);
            }
            WindowEvent::MouseWheel { delta, .. } => state.controls.wheel(match delta {
                MouseScrollDelta::LineDelta(_, y) => f64::from(y),
                MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
            }),
            WindowEvent::KeyboardInput { event, .. } => self.key(event_loop, &event),
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw(event_loop) {
                    self.fail(event_loop, e);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, _event_loop: &ActiveEventLoop) {
        if let Some(state) = &self.state {
            state.window.request_redraw();
        }
    }
}

impl App {
    fn fail(&mut self, event_loop: &ActiveEventLoop, e: ViewerError) {
        self.error.get_or_insert(e);
        event_loop.exit();
    }

    fn close(&mut self, event_loop: &ActiveEventLoop) {
        let converged_at = self.state.as_ref().and_then(|s| s.converged_at);
        self.outcome.get_or_insert(Outcome::Closed { converged_at });
        event_loop.exit();
    }

    fn start(&mut self, event_loop: &ActiveEventLoop) -> Result<Running, ViewerError> {
        let attributes = Window::default_attributes()
            .with_title("Arbor viewer")
            .with_inner_size(PhysicalSize::new(self.config.width, self.config.height));
        let window = Arc::new(
            event_loop
                .create_window(attributes)
                .map_err(|e| ViewerError::Window(e.to_string()))?,
        );
        let size = window.inner_size();
        let overlay = Overlay::new();
        let WindowGpu {
            surface,
            gpu,
            surface_config,
            blit,
            decode_srgb,
        } = window_gpu(
            event_loop,
            &window,
            (size.width, size.height),
            overlay.panel_size(),
        )?;

        let (backend, source) = make_backend(
            &self.config,
            &gpu,
            (surface_config.width, surface_config.height),
        );
        let session = Session::connect(self.config.session.clone(), &self.runtime, backend)?;
        let backend = session.core().backend_name();
        let frame = *session.core().frame();
        let scene = session.scene().clone();
        let core = &self.config.session.core;
        let url = &self.config.session.client.url;
        let report = RunReport {
            meta: RunMeta {
                scene: scene.name.clone(),
                server: format!("quic://{}:{}/{}", url.host, url.port, url.scene),
                width: surface_config.width,
                height: surface_config.height,
                feedback_ratio: core.analysis.ratio,
                budget_mib: core.budget_bytes as f64 / (1024.0 * 1024.0),
                camera_path: "viewer".into(),
                treelet_bytes: scene.treelet_nodes * arbor_proto::limits::NODE_BYTES,
            },
            records: Vec::new(),
            events: Vec::new(),
        };
        say(format_args!(
            "window 0x{:x} {}x{} surface {:?}{} backend {backend}",
            u64::from(window.id()),
            surface_config.width,
            surface_config.height,
            surface_config.format,
            if decode_srgb { " (decoding sRGB)" } else { "" },
        ));
        let now = Instant::now();
        Ok(Running {
            surface,
            window,
            surface_config,
            gpu,
            blit,
            source,
            session,
            controls: Controls::starting_at(&frame, &self.config.start, self.config.seed),
            overlay,
            show_overlay: self.config.overlay,
            report,
            backend,
            last_frame: now,
            interval: Interval {
                start: now,
                frames: 0,
                bytes: 0,
            },
            converged_handled: false,
            holding: false,
            screenshots: 0,
            device_lost: false,
            replacements: 0,
            frame_scale: FrameScale::new(self.config.frame_scale),
            clock_start: now,
            last_pose: None,
            scaled_frame: None,
            converged_at: None,
            scripted_zoom_frames: self.config.scripted_zoom_frames,
        })
    }

    /// After a frame: a lost device is replaced while replacements are left (and the fault
    /// injection of [`ViewerConfig::lose_device_after`] loses one).
    fn after_frame(
        &mut self,
        event_loop: &ActiveEventLoop,
        framed: Result<(), ViewerError>,
    ) -> Result<(), ViewerError> {
        let Some(state) = self.state.as_deref_mut() else {
            return framed;
        };
        let frames = state.report.records.len() as u32;
        if framed.is_ok() && self.config.lose_device_after == Some(frames) && !state.device_lost {
            state.device_lost = true;
            state.gpu.device.destroy();
        }
        let Err(BackendError::DeviceLost(reason)) = state.gpu.check() else {
            return framed;
        };
        if state.replacements >= self.config.device_replacements {
            return Err(RunError::Backend(BackendError::DeviceLost(reason)).into());
        }
        state.replacements += 1;
        let lost = Instant::now();
        let time_s = state.session.started().elapsed().as_secs_f64();
        let new = window_gpu(
            event_loop,
            &state.window,
            (state.surface_config.width, state.surface_config.height),
            state.overlay.panel_size(),
        )?;
        let (backend, source) = make_backend(
            &self.config,
            &new.gpu,
            (new.surface_config.width, new.surface_config.height),
        );
        state.session.replace_backend(backend)?;
        (
            state.surface,
            state.gpu,
            state.surface_config,
            state.blit,
            state.source,
        ) = (new.surface, new.gpu, new.surface_config, new.blit, source);
        state.backend = state.session.core().backend_name();
        state.refresh_overlay();
        let event =
            RunEvent::device_replaced(frames, time_s, &reason, &state.backend, lost.elapsed());
        note_event(&mut state.report, event);
        Ok(())
    }

    fn key(&mut self, event_loop: &ActiveEventLoop, event: &KeyEvent) {
        let PhysicalKey::Code(code) = event.physical_key else {
            return;
        };
        let pressed = event.state == ElementState::Pressed;
        let Some(state) = self.state.as_deref_mut() else {
            return;
        };
        let movement = match code {
            KeyCode::KeyW => Some(Move::Forward),
            KeyCode::KeyS => Some(Move::Back),
            KeyCode::KeyA => Some(Move::Left),
            KeyCode::KeyD => Some(Move::Right),
            KeyCode::KeyE => Some(Move::Up),
            KeyCode::KeyQ => Some(Move::Down),
            _ => None,
        };
        if let Some(m) = movement {
            state.controls.key(m, pressed);
            return;
        }
        if !pressed || event.repeat {
            return;
        }
        let result = match code {
            KeyCode::Escape => {
                self.close(event_loop);
                Ok(())
            }
            KeyCode::Tab => {
                state.controls.toggle_mode();
                Ok(())
            }
            KeyCode::KeyH | KeyCode::F1 => {
                state.show_overlay = !state.show_overlay;
                Ok(())
            }
            KeyCode::F12 | KeyCode::KeyP => {
                state.screenshots += 1;
                let path = PathBuf::from(format!(
                    "arbor-view-{}-{}.png",
                    std::process::id(),
                    state.screenshots
                ));
                state.screenshot(&path)
            }
            KeyCode::KeyC => {
                let frame = state.session.core().frame();
                let camera = state.controls.camera(1, 1);
                say(format_args!(
                    "camera: --camera-path {}",
                    CameraPath::look_of(&camera, frame)
                ));
                Ok(())
            }
            KeyCode::Minus | KeyCode::NumpadSubtract | KeyCode::Equal | KeyCode::NumpadAdd => {
                let coarser = matches!(code, KeyCode::Minus | KeyCode::NumpadSubtract);
                let base = state.session.core().lod_bias().base();
                state
                    .session
                    .set_lod_bias(next_lod_bias(base, coarser))
                    .map_err(|e| ViewerError::Session(RunError::from(e)))
            }
            KeyCode::KeyR => {
                let path = self
                    .config
                    .report
                    .clone()
                    .unwrap_or_else(|| PathBuf::from("arbor-view-report.csv"));
                write_report(&state.report, &path)
            }
            _ => Ok(()),
        };
        // A failed screenshot or report is reported, not fatal.
        if let Err(e) = result {
            eprintln!("error: {e}");
        }
    }

    fn redraw(&mut self, event_loop: &ActiveEventLoop) -> Result<(), ViewerError> {
        let Some(state) = self.state.as_deref_mut() else {
            return Ok(());
        };
        let framed = state.frame();
        self.after_frame(event_loop, framed)?;
        let Some(state) = self.state.as_deref_mut() else {
            return Ok(());
        };
        let converged_at = state.converged_at;
        if let (Some(cycle), false) = (converged_at, state.converged_handled) {
            state.converged_handled = true;
            if !state.controls.moved()
                && let Some(path) = &self.config.screenshot
            {
                state.screenshot(path)?;
            }
            say(format_args!("converged at cycle {cycle}"));
            if self.config.exit_after_converged {
                if self.config.hold_until_stdin_eof {
                    state.holding = true;
                } else {
                    self.outcome = Some(Outcome::Converged { cycle });
                    event_loop.exit();
                }
            }
        }
        if state.holding && self.stdin_closed.load(Ordering::SeqCst) {
            self.outcome = converged_at.map(|cycle| Outcome::Converged { cycle });
            event_loop.exit();
        }
        if let Some(limit) = self.config.timeout
            && converged_at.is_none()
            && self.started.elapsed() > limit
        {
            self.outcome = Some(Outcome::TimedOut {
                after: limit,
                cycles: state.report.records.len() as u32,
                state: not_converged(&state.report.records),
            });
            event_loop.exit();
        }
        Ok(())
    }
}

impl Running {
    fn resize(&mut self, size: PhysicalSize<u32>) {
        if size.width == 0 || size.height == 0 {
            return;
        }
        self.surface_config.width = size.width;
        self.surface_config.height = size.height;
        self.surface
            .configure(&self.gpu.device, &self.surface_config);
    }

    /// One cycle: camera, session step, frame upload, blit, present, overlay figures.
    fn frame(&mut self) -> Result<(), ViewerError> {
        let now = Instant::now();
        self.controls
            .advance((now - self.last_frame).as_secs_f64().min(0.25));
        self.last_frame = now;
        if (self.report.records.len() as u64) < u64::from(self.scripted_zoom_frames) {
            self.controls.wheel(SCRIPTED_ZOOM_LINES);
        }
        let (width, height) = (self.surface_config.width, self.surface_config.height);
        // A moving camera gets a smaller frame, stretched over the window by the blit.
        let clock = (now - self.clock_start).as_secs_f64();
        let full = self.controls.camera(width, height);
        let pose = [full.position, full.forward, full.up];
        if self.last_pose.is_some_and(|p| p != pose) {
            self.frame_scale.handle_motion(clock);
        }
        self.last_pose = Some(pose);
        let scale = self.frame_scale.poll_scale(clock);
        let size = self.frame_scale.poll_size(clock, width, height);
        let camera = if size == (width, height) {
            full
        } else {
            self.controls.camera(size.0, size.1)
        };
        let scaled = (size != (width, height)).then_some(size);
        match (self.scaled_frame, scaled) {
            (None, Some((w, h))) => say(format_args!("moving: frames at {w}x{h}")),
            (Some(_), None) => say(format_args!(
                "resting: frames at full size {width}x{height}"
            )),
            _ => {}
        }
        self.scaled_frame = scaled;
        let mode = match self.source {
            FrameSource::Upload(_) => RenderMode::Image,
            FrameSource::InPlace => RenderMode::InPlace,
        };
        let step_started = Instant::now();
        let step = self.session.step(&camera, mode, None)?;
        if let (FrameSource::Upload(texture), Some(image)) = (&mut self.source, &step.image) {
            if texture.size() != (image.width, image.height) {
                *texture = FrameTexture::new(&self.gpu.device, image.width, image.height);
            }
            texture.upload(&self.gpu.queue, image);
        }
        self.frame_scale
            .handle_frame(clock, scale, step_started.elapsed().as_secs_f64());
        if self.converged_at.is_none() && step.converged && self.scaled_frame.is_none() {
            self.converged_at = Some(step.record.cycle);
        }
        self.interval.frames += 1;
        self.interval.bytes += step.record.bytes_received;
        self.report.records.push(step.record);
        if let Some(event) = step.stall {
            note_event(&mut self.report, event);
        }
        if self.interval.start.elapsed() >= OVERLAY_INTERVAL || self.report.records.len() == 1 {
            self.refresh_overlay();
        }
        self.present()
    }

    fn frame_view(&self) -> Result<&wgpu::TextureView, ViewerError> {
        match &self.source {
            FrameSource::Upload(texture) => Ok(texture.view()),
            FrameSource::InPlace => self
                .session
                .core()
                .backend()
                .as_any()
                .downcast_ref::<GpuBackend>()
                .and_then(GpuBackend::target_view)
                .ok_or_else(|| ViewerError::Gpu("the renderer exposes no target".into())),
        }
    }

    fn present(&mut self) -> Result<(), ViewerError> {
        let surface_texture = match self.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {
                return Ok(());
            }
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                let size = self.window.inner_size();
                self.resize(size);
                return Ok(());
            }
            wgpu::CurrentSurfaceTexture::Validation => {
                return Err(ViewerError::Gpu(
                    "acquiring the surface texture failed validation".into(),
                ));
            }
        };
        let target = surface_texture
            .texture
            .create_view(&wgpu::TextureViewDescriptor::default());
        let mut encoder = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("frame"),
            });
        let frame = self.frame_view()?;
        self.blit.draw(
            &self.gpu.device,
            &self.gpu.queue,
            &mut encoder,
            &target,
            frame,
            self.show_overlay,
        );
        self.gpu.queue.submit([encoder.finish()]);
        self.window.pre_present_notify();
        self.gpu.queue.present(surface_texture);
        Ok(())
    }

    fn refresh_overlay(&mut self) {
        let elapsed = self.interval.start.elapsed().as_secs_f64().max(1e-9);
        let frames = f64::from(self.interval.frames.max(1));
        let stats = OverlayStats {
            backend: self.backend.clone(),
            mode: self.controls.mode().name(),
            frame_ms: elapsed * 1e3 / frames,
            fps: f64::from(self.interval.frames) / elapsed,
            scaled_frame: self.scaled_frame,
            record: self.report.records.last().cloned().unwrap_or_default(),
            bytes_per_s: self.interval.bytes as f64 / elapsed,
            treelets_received: self.session.client_stats().treelets_received,
            converged_at: self.converged_at,
        };
        self.blit
            .set_overlay(&self.gpu.queue, &self.overlay.draw(&stats.lines()));
        self.interval = Interval {
            start: Instant::now(),
            frames: 0,
            bytes: 0,
        };
    }

    /// Reads the frame texture back and writes it as a PNG.
    fn screenshot(&self, path: &Path) -> Result<(), ViewerError> {
        let view = self.frame_view()?;
        let image: Image = read_back(&self.gpu.device, &self.gpu.queue, view.texture())
            .map_err(|e| ViewerError::Gpu(format!("reading the frame back: {e}")))?;
        image
            .save_png(path)
            .map_err(|e| ViewerError::Output(e.to_string()))?;
        say(format_args!("screenshot: {}", path.display()));
        Ok(())
    }
}

/// Where a view that did not converge in time stands, from its cycle records: whether it still
/// asks for treelets and gets them (the server or the link behind), or has stopped asking with
/// pixels still unknown or wanting refinement (the client's feedback behind).
fn not_converged(records: &[CycleRecord]) -> String {
    let Some(last) = records.last() else {
        return "not converged: no cycle ran".into();
    };
    // The last second's worth of cycles, at least one.
    let recent_from = records
        .iter()
        .rposition(|r| r.time_s < last.time_s - 1.0)
        .map_or(0, |i| i + 1);
    let recent = &records[recent_from..];
    let sum = |f: fn(&CycleRecord) -> u64| -> (u64, u64) {
        (records.iter().map(f).sum(), recent.iter().map(f).sum())
    };
    let (received, received_recently) = sum(|r| u64::from(r.treelets_received));
    let (requests, requests_recently) = sum(|r| u64::from(r.requests_sent));
    let (dropped, _) = sum(|r| u64::from(r.dropped));
    let (twice, _) = sum(|r| u64::from(r.received_twice));
    let last_arrival = records
        .iter()
        .rfind(|r| r.treelets_received > 0)
        .map_or("none".into(), |r| {
            format!("cycle {} ({:.1} s)", r.cycle, r.time_s)
        });
    format!(
        "not converged at cycle {} ({:.1} s): {:.1} % of the pixels known, error mean {:.3} / max \
         {:.3} levels, lod bias {:.3}, {} of {} slots used; treelets received {received} \
         ({received_recently} in the last {} cycles, the last at {last_arrival}), {dropped} \
         dropped, {twice} received twice; treelets requested {requests} ({requests_recently} \
         in the last {} cycles)",
        last.cycle,
        last.time_s,
        last.known_share * 100.0,
        last.error.mean,
        last.error.max,
        last.lod_bias,
        last.slots_used,
        last.slots_total,
        recent.len(),
        recent.len(),
    )
}

/// An event of the run (a device replaced, a stall): on standard output and in the report.
fn note_event(report: &mut RunReport, event: RunEvent) {
    say(format_args!(
        "event at cycle {}: {}",
        event.cycle, event.what
    ));
    report.events.push(event);
}

/// Prints one status line on stdout. A reader that has gone away (`arbor-client view … | head
/// -1`) only ends the lines it would have read; the viewer goes on (`println!` panics on the
/// broken pipe).
fn say(line: std::fmt::Arguments<'_>) {
    say_to(&mut std::io::stdout().lock(), line);
}

fn say_to(out: &mut impl std::io::Write, line: std::fmt::Arguments<'_>) {
    // Nothing to do about a failed status line: the run's results are its files.
    let _ = out
        .write_fmt(line)
        .and_then(|()| out.write_all(b"\n"))
        .and_then(|()| out.flush());
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stdout whose reader has gone away.
    struct ClosedPipe;

    impl std::io::Write for ClosedPipe {
        fn write(&mut self, _: &[u8]) -> std::io::Result<usize> {
            Err(std::io::ErrorKind::BrokenPipe.into())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Err(std::io::ErrorKind::BrokenPipe.into())
        }
    }

    #[test]
    fn a_status_line_to_a_closed_pipe_is_dropped_quietly() {
        say_to(&mut ClosedPipe, format_args!("converged at cycle {}", 7));
        let mut written = Vec::new();
        say_to(&mut written, format_args!("converged at cycle {}", 7));
        assert_eq!(written, b"converged at cycle 7\n");
    }
}
