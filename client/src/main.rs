//! `arbor-client`: headless runs against a treelet server, with images, error-against-time
//! reports and charts; reference images of the fully resident scene; the window viewer.

#![forbid(unsafe_code)]

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use arbor_client_core::analysis::{AnalysisConfig, DEFAULT_FEEDBACK_RATIO};
use arbor_client_core::backend::{Backend, BackendError};
use arbor_client_core::camera::CameraPath;
use arbor_client_core::cycle::{
    CoreConfig, DEFAULT_ANALYSIS_BUDGET_MS, DEFAULT_LOAD_LIMIT, DEFAULT_LOOK_PAST,
    DEFAULT_MAX_REQUESTS, DEFAULT_PREFETCH_BELOW, Sampling,
};
use arbor_client_core::image::Image;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::presort::PriorityPolicy;
use arbor_client_core::render::Light;
use arbor_client_core::upload::DEFAULT_FILL_RATIO;
use arbor_client_gpu::{BackendChoice, FeedbackMode, create_backend_with};
use arbor_client_net::{ClientConfig, Trust, parse_server_url};
use arbor_client_session::headless::{HeadlessConfig, run_headless_on};
use arbor_client_session::reference::{ReferenceView, streamed_reference};
use arbor_client_session::session::SessionConfig;
use arbor_client_session::session::{FetchedScene, fetch_all, reference_image};
use arbor_client_viewer::{FrameScaleConfig, Outcome, ViewerConfig};
use arbor_proto::Channel;
use clap::{Args, Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "arbor-client",
    version,
    about = "Arbor client: stream a scene from a treelet server, render it headless, report \
             error against run time",
    after_help = "Examples:\n  \
        arbor-client reference --server quic://127.0.0.1:4433/lion --cert-fingerprint HEX \\\n      \
            --size 512x512 --out ref.png\n  \
        arbor-client render --server quic://127.0.0.1:4433/lion --cert-fingerprint HEX \\\n      \
            --cycles 400 --size 512x512 --budget-mib 4 --out lion.png --report run.csv \\\n      \
            --chart run-chart.png --reference ref.png\n  \
        arbor-client render --server quic://127.0.0.1:4433/lion --cert-fingerprint HEX \\\n      \
            --camera-path orbit:2 --cycles 300 --budget-mib 2 --out orbit.png --report orbit.csv"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Stream and render a camera path headless; write the last frame, the per-cycle report and
    /// its chart.
    Render(RenderArgs),
    /// Render what a camera sees with the whole scene resident: fetches only the treelets the
    /// view's fully refined cut needs (or, with --whole-scene, every treelet).
    Reference(ReferenceArgs),
    /// Open a window and stream, render and explore the scene interactively.
    #[command(after_help = VIEW_HELP)]
    View(ViewArgs),
}

const VIEW_HELP: &str = "Controls:\n  \
    orbit mode (start): left-drag turns about the scene centre, wheel zooms\n  \
    fly mode: W/S forward/back, A/D left/right, E/Q up/down, right-drag looks\n  \
    Tab switches mode, H toggles the overlay, F12 or P saves a screenshot, R writes the report,\n  \
    - and = make the picture coarser or finer by half an octree level (the LOD bias),\n  \
    C prints the camera as --camera-path look:… (for view, render and reference), Esc quits\n\n\
While the camera moves, frames are rendered smaller to stay within --moving-frame-ms (the\n\
overlay says at what size); they are full size again a quarter second after it stops.\n\n\
Examples:\n  \
    arbor-client view quic://127.0.0.1:4433/lion --cert-fingerprint HEX\n  \
    arbor-client view --server quic://127.0.0.1:4433/lion --cert-fingerprint HEX \\\n      \
        --size 1280x720 --budget-mib 16 --backend cpu --report view.csv\n  \
    arbor-client view --server quic://127.0.0.1:4433/lion --cert-fingerprint HEX \\\n      \
        --size 256x192 --screenshot shot.png --exit-after-converged --timeout-s 60\n  \
    arbor-client view --server quic://127.0.0.1:4433/lion --cert-fingerprint HEX \\\n      \
        --backend cpu --moving-frame-ms 33 --min-moving-scale 0.5";

#[derive(Args, Debug)]
struct Connection {
    /// `quic://HOST:PORT/SCENE`.
    #[arg(long, value_name = "quic://HOST:PORT/SCENE")]
    server: Option<String>,
    /// Another server of the same pool (repeatable): on a lost connection the client moves to
    /// the next one and keeps what it holds. Same scene; the same certificate (or --ca).
    #[arg(long, value_name = "quic://HOST:PORT/SCENE")]
    replica: Vec<String>,
    /// With replicas: milliseconds without a packet after which a connection counts as lost.
    #[arg(long, default_value_t = arbor_client_net::DEFAULT_FAILOVER_AFTER.as_millis() as u64)]
    failover_after_ms: u64,
    /// SHA-256 fingerprint of the server certificate (printed by `arbor-server serve`).
    #[arg(long, conflicts_with = "ca")]
    cert_fingerprint: Option<String>,
    /// PEM file with CA certificates to verify the server against instead.
    #[arg(long)]
    ca: Option<PathBuf>,
    /// Access token for scenes that need one.
    #[arg(long)]
    token: Option<String>,
    /// Channels to draw (those the scene lacks are left out): comma-separated of color,
    /// normal, density.
    #[arg(long, default_value = "color,normal,density")]
    channels: String,
    /// Seconds to wait for the server.
    #[arg(long, default_value_t = 20.0)]
    connect_timeout: f64,
}

#[derive(Args, Debug)]
struct View {
    /// static, orbit:DEG_PER_CYCLE, fly-in:CYCLES, jump:EVERY, or look:EX,EY,EZ:TX,TY,TZ (a
    /// fixed camera, points in scene edges from the centre; the viewer's C key prints one).
    #[arg(long, default_value = "static")]
    camera_path: String,
    /// Seed of the camera path's viewpoint.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Frame size WxH.
    #[arg(long, default_value = "512x512")]
    size: String,
    /// Scales the pixel footprint of the LOD test (>1 coarser).
    #[arg(long, default_value_t = 1.0)]
    lod_bias: f64,
    /// Where the analysis and render passes run: auto (the GPU when an adapter exists, software
    /// ones included; else the CPU reference, said on stderr), gpu, or cpu.
    #[arg(long, default_value = "auto")]
    backend: String,
    /// GPU only: whether a cycle waits for its analysis pass: auto (for frames up to 256² while
    /// the wait stays within 4 ms), wait (always: a moving view then knows itself), or
    /// pipelined (never: the feedback comes a cycle late).
    #[arg(long, default_value = "auto")]
    feedback: String,
}

#[derive(Args, Debug)]
struct RenderArgs {
    #[command(flatten)]
    connection: Connection,
    #[command(flatten)]
    view: View,
    /// Cycles to run (an upper bound with --until-converged).
    #[arg(long, default_value_t = 300)]
    cycles: u32,
    /// Slot buffer memory budget in MiB.
    #[arg(long, default_value_t = 64.0)]
    budget_mib: f64,
    /// Feedback grid is 1/n of the frame per axis: the grid sampling's share per cycle, and
    /// the least the adaptive sampling takes.
    #[arg(long, default_value_t = DEFAULT_FEEDBACK_RATIO)]
    feedback_ratio: u32,
    /// Which pixels the analysis pass samples: adaptive (pixels whose treelet arrived, then
    /// unknown ones, within --analysis-budget-ms) or grid (the thesis's 1/n grid every cycle).
    #[arg(long, default_value = "adaptive")]
    sampling: String,
    /// Wall time the analysis pass may take per cycle with adaptive sampling, ms.
    #[arg(long, default_value_t = DEFAULT_ANALYSIS_BUDGET_MS)]
    analysis_budget_ms: f64,
    /// Send plain request lists: no view and errors with them, so the server pushes nothing
    /// beyond what is listed (by default it also sends the descendants the view would refine).
    #[arg(long)]
    no_deep_push: bool,
    /// Frustum prefetch: while the list from the view's samples is shorter than this and the
    /// view is fully known, top free slots up with what lies in the frustum (lowest priority,
    /// never evicting); makes the next camera move cheap. 0 turns it off.
    #[arg(long, default_value_t = DEFAULT_PREFETCH_BELOW)]
    prefetch_below: usize,
    /// Look-past requests: once the view is fully known, trace the rays of pixels still wanting
    /// refinement past their coarse hit, up to this many coarse hits deep, and request what
    /// they meet behind (below every sampled item). Saves round trips where refined gaps reveal
    /// surfaces in other subtrees. 0 turns it off.
    #[arg(long, default_value_t = DEFAULT_LOOK_PAST)]
    look_past: u8,
    /// Keep the LOD bias fixed even when the view needs more slots than the budget holds
    /// (by default it is raised until the view fits, and the run converges to that target).
    #[arg(long)]
    fixed_bias: bool,
    /// Request priority: error-pixels (default), centre (error-pixels weighted towards the
    /// screen centre), max-error (the thesis's) or frustum (the peer's rule: refinable leaves in
    /// the view frustum by projected size, no feedback).
    #[arg(long, default_value = "error-pixels")]
    policy: String,
    /// Cap on the request list.
    #[arg(long, default_value_t = DEFAULT_MAX_REQUESTS)]
    max_requests: usize,
    /// Treelets inserted per cycle at most.
    #[arg(long, default_value_t = DEFAULT_LOAD_LIMIT)]
    load_limit: u32,
    /// Upload range fill ratio.
    #[arg(long, default_value_t = DEFAULT_FILL_RATIO)]
    fill_ratio: f32,
    /// A cycle lasts at least this many milliseconds (frame-rate cap).
    #[arg(long, default_value_t = 16.0)]
    cycle_ms: f64,
    /// Render only every k-th cycle (the last is always rendered).
    #[arg(long, default_value_t = 1)]
    render_every: u32,
    /// Lost GPU devices (a driver reset, the GPU removed) replaced by a new one before a loss
    /// ends the run; the run goes on with what it holds. With --backend auto a replacement may
    /// be the CPU twins.
    #[arg(long, default_value_t = 3)]
    device_replacements: u32,
    /// Stop once the view has converged (static camera).
    #[arg(long)]
    until_converged: bool,
    /// The last frame, PNG.
    #[arg(long)]
    out: PathBuf,
    /// The per-cycle report, CSV.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Error and traffic against time, PNG.
    #[arg(long)]
    chart: Option<PathBuf>,
    /// Reference image (from `arbor-client reference`) for image RMSE per cycle.
    #[arg(long)]
    reference: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct ViewArgs {
    /// `quic://HOST:PORT/SCENE` (or give it with --server).
    #[arg(value_name = "URL", conflicts_with = "server")]
    url: Option<String>,
    #[command(flatten)]
    connection: Connection,
    /// Seed of the start viewpoint (the `static` camera path's, so a headless render of the
    /// same camera is well defined).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Window size WxH (frames follow the window).
    #[arg(long, default_value = "1024x768")]
    size: String,
    /// Where the camera starts: static (seeded by --seed) or look:EX,EY,EZ:TX,TY,TZ, a
    /// bookmark the C key prints (points in scene edges from the centre).
    #[arg(long, default_value = "static")]
    camera_path: String,
    /// Scales the pixel footprint of the LOD test (>1 coarser).
    #[arg(long, default_value_t = 1.0)]
    lod_bias: f64,
    /// Slot buffer memory budget in MiB.
    #[arg(long, default_value_t = 64.0)]
    budget_mib: f64,
    /// Feedback buffer is 1/n of the frame per axis.
    #[arg(long, default_value_t = DEFAULT_FEEDBACK_RATIO)]
    feedback_ratio: u32,
    /// Treelets inserted per cycle at most.
    #[arg(long, default_value_t = DEFAULT_LOAD_LIMIT)]
    load_limit: u32,
    /// Renderer: gpu (wgpu, drawn in place), cpu (CPU frames uploaded to the window) or auto
    /// (gpu: the window needs an adapter anyway).
    #[arg(long, default_value = "auto")]
    backend: String,
    /// GPU only: whether a frame waits for its analysis pass: auto (for frames up to 256² while
    /// the wait stays within 4 ms), wait, or pipelined.
    #[arg(long, default_value = "auto")]
    feedback: String,
    /// Start with the statistics overlay hidden (H toggles it).
    #[arg(long)]
    no_overlay: bool,
    /// Written once the view has converged, if the camera was never moved (PNG).
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// The per-cycle report (CSV, written by R and at exit; the chart goes beside it).
    #[arg(long)]
    report: Option<PathBuf>,
    /// Exit with status 0 once the view has converged.
    #[arg(long)]
    exit_after_converged: bool,
    /// With --exit-after-converged: keep drawing after convergence until standard input is
    /// closed (lets a test capture the window first).
    #[arg(long, requires = "exit_after_converged")]
    hold_until_stdin_eof: bool,
    /// Exit with status 1 if the view has not converged after this many seconds.
    #[arg(long)]
    timeout_s: Option<f64>,
    /// Lost GPU devices (a driver reset, the GPU removed) replaced by a new one, window surface
    /// and renderer made again, before a loss ends the run; the run goes on with what it holds.
    #[arg(long, default_value_t = 3)]
    device_replacements: u32,
    /// Fault injection for tests: destroy the window's GPU device after this many frames.
    #[arg(long, hide = true)]
    lose_device_after_frames: Option<u32>,
    /// While the camera moves, frames are rendered smaller (each side scaled, stretched over
    /// the window) so one takes at most this many milliseconds; full size again once it rests.
    /// 0: always full size.
    #[arg(long, default_value_t = 20.0)]
    moving_frame_ms: f64,
    /// Smallest scale of each side of a moving frame, in (0, 1].
    #[arg(long, default_value_t = 0.25)]
    min_moving_scale: f64,
    /// Scripted motion for tests: zoom in a little in each of the first N frames.
    #[arg(long, hide = true, default_value_t = 0)]
    script_zoom_frames: u32,
}

#[derive(Args, Debug)]
struct ReferenceArgs {
    #[command(flatten)]
    connection: Connection,
    #[command(flatten)]
    view: View,
    /// Which cycle of the camera path to render.
    #[arg(long, default_value_t = 0)]
    cycle: u32,
    /// The image, PNG.
    #[arg(long)]
    out: PathBuf,
    /// Fetch every treelet of the scene instead of only the cut this view needs (same image;
    /// needs the whole scene in memory).
    #[arg(long)]
    whole_scene: bool,
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .with_ansi(colour_on_stderr())
        .init();
    if let Err(e) = run(Cli::parse()) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Colour only on a terminal (and not with `NO_COLOR`): logs written to files stay plain text.
fn colour_on_stderr() -> bool {
    use std::io::IsTerminal as _;
    std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}

fn run(cli: Cli) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    match cli.command {
        Command::Render(a) => render(a, runtime.handle()),
        Command::Reference(a) => reference(a, runtime.handle()),
        Command::View(a) => view(a, runtime.handle()),
    }
}

fn client_config(c: &Connection) -> Result<ClientConfig> {
    let server = c
        .server
        .as_deref()
        .context("give the server as quic://HOST:PORT/SCENE (--server)")?;
    let url = parse_server_url(server)?;
    let trust = match (&c.cert_fingerprint, &c.ca) {
        (Some(fp), None) => Trust::Fingerprint(fp.clone()),
        (None, Some(path)) => Trust::CaPem(
            std::fs::read(path).with_context(|| format!("reading CA file {}", path.display()))?,
        ),
        _ => bail!("give the server's --cert-fingerprint or a --ca file"),
    };
    let replicas = c
        .replica
        .iter()
        .map(|r| parse_server_url(r))
        .collect::<Result<Vec<_>, _>>()?;
    let mut config = ClientConfig::new(url, trust)
        .with_replicas(replicas)
        .with_failover_after(std::time::Duration::from_millis(c.failover_after_ms));
    if let Some(t) = &c.token {
        config = config.with_token(t.clone());
    }
    Ok(config)
}

fn channels(text: &str) -> Result<Vec<Channel>> {
    text.split(',')
        .filter(|s| !s.is_empty())
        .map(|s| {
            Channel::ALL
                .into_iter()
                .find(|c| c.name() == s.trim())
                .with_context(|| format!("unknown channel {s:?} (color, normal, density)"))
        })
        .collect()
}

fn size(text: &str) -> Result<(u32, u32)> {
    let (w, h) = text
        .split_once(['x', 'X'])
        .with_context(|| format!("size {text:?} is not WxH"))?;
    let w: u32 = w.parse().with_context(|| format!("width in {text:?}"))?;
    let h: u32 = h.parse().with_context(|| format!("height in {text:?}"))?;
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        bail!("size {w}x{h} must be within 1..=16384 per axis");
    }
    Ok((w, h))
}

fn timeout(seconds: f64) -> Result<Duration> {
    Duration::try_from_secs_f64(seconds)
        .ok()
        .filter(|d| !d.is_zero())
        .with_context(|| format!("timeout {seconds} s must be positive and finite"))
}

fn frame_scale(moving_frame_ms: f64, min_scale: f64) -> Result<FrameScaleConfig> {
    if !(moving_frame_ms.is_finite() && (0.0..=60_000.0).contains(&moving_frame_ms)) {
        bail!("moving frame time {moving_frame_ms} ms must be in [0, 60000] (0: always full size)");
    }
    let config = FrameScaleConfig {
        budget: (moving_frame_ms > 0.0).then(|| Duration::from_secs_f64(moving_frame_ms / 1e3)),
        min_scale,
    };
    config.validate()?;
    Ok(config)
}

fn budget_bytes(mib: f64) -> Result<u64> {
    if !(mib.is_finite() && mib > 0.0 && mib <= 1024.0 * 1024.0) {
        bail!("budget {mib} MiB must be in (0, 1 TiB]");
    }
    Ok((mib * 1024.0 * 1024.0) as u64)
}

fn view(mut a: ViewArgs, runtime: &tokio::runtime::Handle) -> Result<()> {
    if let Some(url) = a.url.take() {
        a.connection.server = Some(url);
    }
    let (width, height) = size(&a.size)?;
    let backend = BackendChoice::parse(&a.backend)
        .with_context(|| format!("backend {:?} (auto, gpu or cpu)", a.backend))?;
    let feedback = FeedbackMode::parse(&a.feedback)
        .with_context(|| format!("feedback {:?} (auto, wait or pipelined)", a.feedback))?;
    let start = match CameraPath::parse(&a.camera_path)? {
        p @ (CameraPath::Static | CameraPath::Look { .. }) => p,
        other => bail!("the viewer starts from static or look:…, not {other}: it moves by hand"),
    };
    let config = ViewerConfig {
        session: SessionConfig {
            client: client_config(&a.connection)?,
            core: CoreConfig {
                analysis: AnalysisConfig {
                    ratio: a.feedback_ratio,
                    lod_bias: a.lod_bias,
                },
                budget_bytes: budget_bytes(a.budget_mib)?,
                load_limit: a.load_limit,
                channels: channels(&a.connection.channels)?,
                ..CoreConfig::default()
            },
            connect_timeout: timeout(a.connection.connect_timeout)?,
            first_camera: Some(start.camera(0, &SceneFrame::UNIT, a.seed, width, height)),
        },
        seed: a.seed,
        start,
        width,
        height,
        backend,
        feedback,
        overlay: !a.no_overlay,
        screenshot: a.screenshot,
        report: a.report,
        exit_after_converged: a.exit_after_converged,
        hold_until_stdin_eof: a.hold_until_stdin_eof,
        timeout: a.timeout_s.map(timeout).transpose()?,
        device_replacements: a.device_replacements,
        lose_device_after: a.lose_device_after_frames,
        frame_scale: frame_scale(a.moving_frame_ms, a.min_moving_scale)?,
        scripted_zoom_frames: a.script_zoom_frames,
    };
    // Absurd parameters are refused before a window opens.
    config.session.core.validate()?;
    match arbor_client_viewer::run(config, runtime)? {
        Outcome::TimedOut {
            after,
            cycles,
            state,
        } => bail!(
            "the view did not converge within {:.1} s ({cycles} cycles); {state}",
            after.as_secs_f64()
        ),
        Outcome::Converged { .. } | Outcome::Closed { .. } => Ok(()),
    }
}

fn render(a: RenderArgs, runtime: &tokio::runtime::Handle) -> Result<()> {
    let (width, height) = size(&a.view.size)?;
    let camera_path = CameraPath::parse(&a.view.camera_path)?;
    let policy = PriorityPolicy::parse(&a.policy).with_context(|| {
        format!(
            "policy {:?} (error-pixels, centre, max-error or frustum)",
            a.policy
        )
    })?;
    let sampling = Sampling::parse(&a.sampling)
        .with_context(|| format!("sampling {:?} (adaptive or grid)", a.sampling))?;
    if !(a.budget_mib.is_finite() && a.budget_mib > 0.0 && a.budget_mib <= 1024.0 * 1024.0) {
        bail!("budget {} MiB must be in (0, 1 TiB]", a.budget_mib);
    }
    let min_cycle = Duration::try_from_secs_f64(a.cycle_ms / 1e3)
        .with_context(|| format!("cycle time {} ms", a.cycle_ms))?;
    let reference = a
        .reference
        .as_deref()
        .map(Image::load_png)
        .transpose()
        .context("loading the reference image")?;
    let config = HeadlessConfig {
        client: client_config(&a.connection)?,
        core: CoreConfig {
            analysis: AnalysisConfig {
                ratio: a.feedback_ratio,
                lod_bias: a.view.lod_bias,
            },
            policy,
            max_requests: a.max_requests,
            budget_bytes: (a.budget_mib * 1024.0 * 1024.0) as u64,
            load_limit: a.load_limit,
            fill_ratio: a.fill_ratio,
            channels: channels(&a.connection.channels)?,
            light: Light::default(),
            sampling,
            adjust_bias: !a.fixed_bias,
            deep_push: !a.no_deep_push,
            analysis_budget_ms: a.analysis_budget_ms,
            prefetch_below: a.prefetch_below,
            look_past: a.look_past,
        },
        camera_path,
        seed: a.view.seed,
        width,
        height,
        cycles: a.cycles,
        min_cycle,
        connect_timeout: timeout(a.connection.connect_timeout)?,
        reference,
        until_converged: a.until_converged,
        render_every: a.render_every,
        device_replacements: a.device_replacements,
    };
    let (choice, feedback) = backend_choice(&a.view.backend, &a.view.feedback)?;
    let mut first = Some(backend(choice, feedback)?);
    let run = run_headless_on(
        config,
        runtime,
        || match first.take() {
            Some(b) => Ok(b),
            None => backend(choice, feedback)
                .map_err(|e| BackendError::Device(format!("no backend to replace it: {e:#}"))),
        },
        |_| {},
    )?;
    run.image
        .save_png(&a.out)
        .with_context(|| format!("writing {}", a.out.display()))?;
    if let Some(path) = &a.report {
        run.report
            .write_csv(path)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &a.chart {
        let title = format!(
            "{} — {} — {}×{}, {:.1} MiB budget",
            run.scene.name, run.report.meta.camera_path, width, height, a.budget_mib
        );
        arbor_client_report::chart::draw(&run.report, path, &title)
            .with_context(|| format!("drawing {}", path.display()))?;
    }
    let mut lines = vec![
        format!("backend: {}", run.backend),
        run.report.summary().to_string(),
    ];
    lines.extend(
        run.report
            .events
            .iter()
            .map(|e| format!("event at cycle {} ({:.3} s): {}", e.cycle, e.time_s, e.what)),
    );
    lines.push(format!(
        "slots: peak {} of {} ({} B each, {:.2} MiB)",
        run.peak_slots,
        run.capacity,
        run.slot_bytes,
        (u64::from(run.capacity) * run.slot_bytes) as f64 / (1024.0 * 1024.0)
    ));
    lines.push(match run.converged_at {
        Some(c) => format!("converged at cycle {c}"),
        None => "not converged".to_owned(),
    });
    say(&lines)
}

fn reference(a: ReferenceArgs, runtime: &tokio::runtime::Handle) -> Result<()> {
    if !a.whole_scene {
        return streamed(a, runtime);
    }
    let (width, height) = size(&a.view.size)?;
    let camera_path = CameraPath::parse(&a.view.camera_path)?;
    let FetchedScene {
        scene,
        channels,
        treelets,
    } = fetch_all(
        &client_config(&a.connection)?,
        &channels(&a.connection.channels)?,
        timeout(a.connection.connect_timeout)?,
        runtime,
    )?;
    let frame = arbor_client_core::incore::SceneFrame::of(&scene);
    let camera = camera_path.camera(a.cycle, &frame, a.view.seed, width, height);
    let (choice, feedback) = backend_choice(&a.view.backend, &a.view.feedback)?;
    let mut backend = backend(choice, feedback)?;
    let image = reference_image(
        &scene,
        &channels,
        treelets,
        &camera,
        a.view.lod_bias,
        &Light::default(),
        backend.as_mut(),
    )?;
    image
        .save_png(&a.out)
        .with_context(|| format!("writing {}", a.out.display()))?;
    say(&[format!(
        "reference of {} ({} treelets) on {} at cycle {} of {}: {} covered pixels → {}",
        scene.name,
        scene.treelet_count,
        backend.name(),
        a.cycle,
        a.view.camera_path,
        image.coverage(),
        a.out.display()
    )])
}

/// `reference` fetching only the treelets the view's fully refined cut needs.
fn streamed(a: ReferenceArgs, runtime: &tokio::runtime::Handle) -> Result<()> {
    let (width, height) = size(&a.view.size)?;
    let camera_path = CameraPath::parse(&a.view.camera_path)?;
    let camera = |frame: &arbor_client_core::incore::SceneFrame| {
        camera_path.camera(a.cycle, frame, a.view.seed, width, height)
    };
    let light = Light::default();
    let view = ReferenceView {
        camera: &camera,
        lod_bias: a.view.lod_bias,
        light: &light,
    };
    let (choice, feedback) = backend_choice(&a.view.backend, &a.view.feedback)?;
    let mut backend = backend(choice, feedback)?;
    let r = streamed_reference(
        &client_config(&a.connection)?,
        &channels(&a.connection.channels)?,
        &view,
        timeout(a.connection.connect_timeout)?,
        runtime,
        backend.as_mut(),
    )?;
    r.image
        .save_png(&a.out)
        .with_context(|| format!("writing {}", a.out.display()))?;
    say(&[
        format!(
            "reference of {} on {} at cycle {} of {}: {} covered pixels → {}",
            r.scene.name,
            backend.name(),
            a.cycle,
            a.view.camera_path,
            r.image.coverage(),
            a.out.display()
        ),
        format!(
            "fetched {} of {} treelets in {} rounds ({:.2} s); cut held at most {:.1} MiB; peak RSS {:.1} MiB",
            r.treelets,
            r.scene.treelet_count,
            r.rounds,
            r.seconds,
            r.peak_cut_bytes as f64 / f64::from(1 << 20),
            peak_rss_mib()
        ),
    ])
}

/// Prints a command's closing lines on stdout once its files are written. A reader gone away
/// (`| head`) is no error: the work is done and the exit status says so.
fn say(lines: &[String]) -> Result<()> {
    use std::io::Write as _;
    let text: String = lines.iter().map(|l| format!("{l}\n")).collect();
    let mut stdout = std::io::stdout().lock();
    match stdout
        .write_all(text.as_bytes())
        .and_then(|()| stdout.flush())
    {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e).context("writing to stdout"),
        _ => Ok(()),
    }
}

/// The process's peak resident set (`VmHWM`), MiB; 0 where /proc does not say.
fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        })
        .map_or(0.0, |kib| kib / 1024.0)
}

/// What `--backend` and `--feedback` name.
fn backend_choice(text: &str, feedback: &str) -> Result<(BackendChoice, FeedbackMode)> {
    let choice = BackendChoice::parse(text)
        .with_context(|| format!("backend {text:?} (auto, gpu or cpu)"))?;
    let feedback = FeedbackMode::parse(feedback)
        .with_context(|| format!("feedback {feedback:?} (auto, wait or pipelined)"))?;
    Ok((choice, feedback))
}

/// Makes the backend `choice` names, with `feedback`, saying on stderr when `auto` takes the
/// CPU twins.
fn backend(choice: BackendChoice, feedback: FeedbackMode) -> Result<Box<dyn Backend>> {
    let chosen = create_backend_with(choice, feedback).context("opening the GPU")?;
    if let Some(reason) = &chosen.fallback {
        eprintln!("note: running on the CPU twins: {reason}");
    }
    Ok(chosen.backend)
}
