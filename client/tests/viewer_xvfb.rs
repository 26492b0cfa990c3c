//! The window viewer end to end: the real `arbor-client view` binary in a real X server (Xvfb),
//! streaming a real scan from the real server over loopback QUIC, compared with the headless
//! CPU render of the same camera.
//!
//! * **Launch.** Xvfb (`:N`, the first free display from 90, 1024×768×24) with a fresh 0700
//!   `XDG_RUNTIME_DIR`; a missing Xvfb or `xwd` fails the test with what to install (never a
//!   skip). The binary is the one Cargo built for this package's tests (`CARGO_BIN_EXE_*`, which
//!   exists only inside the package: hence this file lives here, not in `tests/`).
//! * **What is captured.** The viewer runs `--size 256x192 --no-overlay --exit-after-converged
//!   --hold-until-stdin-eof --screenshot … --report …` and prints its X window id and
//!   `converged at cycle N`. Then the test grabs the window's content from the X server with
//!   `xwd -id`, parses the XWD (big-endian header, 32-bit TrueColor pixels) and closes the
//!   viewer's standard input, which makes it exit 0.
//! * **Acceptance.** The window equals the reference — the CPU renderer on the fully resident
//!   scene with `CameraPath::Static`'s camera for the same seed — composited over the viewer's
//!   background where the reference has alpha 0, within [`TOLERANCE`]: a channel difference up
//!   to [`TOLERANCE`] counts as equal, at most [`MAX_DIFFERING_SHARE`] of the pixels may differ
//!   by more (the GPU renderer's f32 against the CPU's f64 at voxel edges). The screenshot
//!   (the frame texture read back) is held to the same. The CPU backend is exact (0). The run
//!   report must show many frames drawn while treelets were still arriving.
//! * **Backends.** The first run uses `--backend gpu` (the wgpu renderer, drawn in place and
//!   sampled by the blit), the second `--backend cpu` (CPU frames uploaded each cycle), so both
//!   frame paths reach the window.
//! * **A lost device.** The first run loses its device after [`LOSE_DEVICE_AFTER`] frames (the
//!   hidden `--lose-device-after-frames`, which destroys it): the viewer must say it replaced it,
//!   its report must carry the event, and everything above must still hold.
//! * **Overlay.** The second run, in the same X server, keeps the statistics overlay on: outside
//!   its panel the window is still the reference within the same tolerance; inside, the panel
//!   darkens the frame and carries text.
//! * **Moving frames.** A third run, on the GPU renderer (its target remade at each size),
//!   starts from a `--camera-path look:…` bookmark of the first runs' camera and zooms in during
//!   its first frames (the hidden `--script-zoom-frames`) with a 1 ms moving-frame budget: the
//!   viewer must say it drew the moving frames at a quarter of each side, then full size again
//!   once the camera rested, and converge to the reference of the camera where the zoom ended,
//!   within the same tolerance.
//! * **Timeout.** A last run with `--timeout-s 1` cannot converge in time and must exit 1 with
//!   a message saying so.

use std::ffi::OsString;
use std::io::{BufRead, BufReader, Read};
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use arbor_client_core::backend::CpuBackend;
use arbor_client_core::camera::CameraPath;
use arbor_client_core::image::Image;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::Light;
use arbor_client_report::{CycleRecord, RunReport};
use arbor_client_session::session::reference_image;
use arbor_client_viewer::blit::{BACKGROUND, OVERLAY_MARGIN};
use arbor_client_viewer::controls::Controls;
use arbor_client_viewer::overlay::Overlay;
use arbor_tests::streaming::serve;

const SIZE: (u32, u32) = (256, 192);
const SEED: u64 = 7;
/// Frames of the first run before its device is destroyed.
const LOSE_DEVICE_AFTER: u32 = 5;
/// A channel difference up to this counts as equal.
const TOLERANCE: u8 = 2;
/// Largest share of pixels allowed to differ by more than [`TOLERANCE`].
const MAX_DIFFERING_SHARE: f64 = 0.005;
/// Frames of the moving run that zoom in.
const ZOOM_FRAMES: u32 = 12;
/// How long the viewer may take to converge.
const CONVERGE_TIMEOUT: Duration = Duration::from_secs(240);

/// A child process stopped when dropped: SIGTERM, then SIGKILL after [`STOP_GRACE`]. Xvfb
/// killed outright leaves its display's lock file and socket behind (every run used to leave
/// one, and after a hundred runs on one machine no display of :90..:189 was free).
struct Reaped(Child);

/// How long a dropped child has to exit on SIGTERM.
const STOP_GRACE: Duration = Duration::from_secs(2);

impl Drop for Reaped {
    fn drop(&mut self) {
        arbor_tests::support::terminate(&mut self.0, STOP_GRACE);
    }
}

/// Whether display `:n` is taken: its lock file names a live process, or it has a socket but
/// no lock (not an X server of the usual kind). A lock left by a dead server is removed, with
/// its socket, so that the display can be used and its stale socket is not mistaken for the
/// new server's.
fn display_taken(n: u32) -> bool {
    let lock = PathBuf::from(format!("/tmp/.X{n}-lock"));
    let socket = PathBuf::from(format!("/tmp/.X11-unix/X{n}"));
    let pid = match std::fs::read_to_string(&lock) {
        Ok(text) => text.trim().parse::<u32>().ok(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return socket.exists(),
        // Unreadable: someone else's.
        Err(_) => return true,
    };
    match pid {
        Some(pid) if !Path::new(&format!("/proc/{pid}")).exists() => {
            let _ = std::fs::remove_file(&lock);
            let _ = std::fs::remove_file(&socket);
            lock.exists() || socket.exists()
        }
        _ => true,
    }
}

fn require_tool(name: &str, probe: &[&str], package: &str) {
    match Command::new(name)
        .args(probe)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
    {
        Ok(_) => {}
        Err(e) => panic!(
            "`{name}` cannot be run ({e}): the viewer test needs it — install the Debian package \
             `{package}` (scripts/test does)"
        ),
    }
}

/// Starts Xvfb on the first free display from :90; returns it and the display name.
fn start_xvfb() -> (Reaped, String) {
    require_tool("Xvfb", &["-help"], "xvfb");
    for n in 90..190 {
        let socket = PathBuf::from(format!("/tmp/.X11-unix/X{n}"));
        if display_taken(n) {
            continue;
        }
        let child = Command::new("Xvfb")
            .args([
                &format!(":{n}"),
                "-screen",
                "0",
                "1024x768x24",
                "-nolisten",
                "tcp",
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawning Xvfb");
        let mut xvfb = Reaped(child);
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            if socket.exists() {
                return (xvfb, format!(":{n}"));
            }
            if xvfb.0.try_wait().unwrap().is_some() {
                break; // Lost a race for this display: try the next.
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    panic!("could not start Xvfb on any display :90..:189");
}

/// An XWD dump of a 24/32-bit TrueColor window: `width × height` RGB pixels.
struct Xwd {
    width: u32,
    height: u32,
    rgb: Vec<[u8; 3]>,
}

/// Parses the XWD format (X11 `XWDFileHeader`: 25 big-endian `u32`s, the window name, the
/// colormap entries of 12 bytes each, then the pixels) for what Xvfb's 24-bit TrueColor
/// screens give: ZPixmap, 32 bits per pixel, 8-bit channel masks.
fn parse_xwd(data: &[u8]) -> Xwd {
    let field = |i: usize| u32::from_be_bytes(data[i * 4..i * 4 + 4].try_into().unwrap());
    assert!(data.len() >= 100, "XWD shorter than its header");
    let header_size = field(0) as usize;
    assert_eq!(field(1), 7, "XWD file version");
    assert_eq!(field(2), 2, "XWD pixmap format (ZPixmap)");
    let (width, height) = (field(4), field(5));
    let byte_order = field(7);
    assert_eq!(field(11), 32, "bits per pixel");
    let bytes_per_line = field(12) as usize;
    assert!(
        matches!(field(13), 4 | 5),
        "visual class (TrueColor or DirectColor)"
    );
    let masks = [field(14), field(15), field(16)];
    let ncolors = field(19) as usize;
    let start = header_size + ncolors * 12;
    assert!(
        data.len() >= start + bytes_per_line * height as usize,
        "XWD pixel data truncated"
    );
    let mut rgb = Vec::with_capacity((width * height) as usize);
    for y in 0..height as usize {
        for x in 0..width as usize {
            let o = start + y * bytes_per_line + x * 4;
            let b: [u8; 4] = data[o..o + 4].try_into().unwrap();
            let p = if byte_order == 0 {
                u32::from_le_bytes(b)
            } else {
                u32::from_be_bytes(b)
            };
            rgb.push(masks.map(|m| ((p & m) >> m.trailing_zeros()) as u8));
        }
    }
    Xwd { width, height, rgb }
}

/// How far a picture is from the reference.
#[derive(Debug)]
struct Difference {
    max: u8,
    mean: f64,
    /// Share of pixels with a channel more than [`TOLERANCE`] off.
    differing_share: f64,
}

/// Compares `pixels(x, y)` (RGB) with the reference composited over the viewer's background,
/// where `include(x, y)`.
fn compare(
    reference: &Image,
    include: impl Fn(u32, u32) -> bool,
    pixels: impl Fn(u32, u32) -> [u8; 3],
) -> Difference {
    let (mut max, mut sum, mut differing, mut n) = (0u8, 0u64, 0u64, 0u64);
    for y in 0..reference.height {
        for x in 0..reference.width {
            if !include(x, y) {
                continue;
            }
            n += 1;
            let r = reference.get(x, y).unwrap();
            let a = u32::from(r[3]);
            let want: [u8; 3] = std::array::from_fn(|k| {
                ((u32::from(r[k]) * a + u32::from(BACKGROUND[k]) * (255 - a) + 127) / 255) as u8
            });
            let got = pixels(x, y);
            let d = (0..3).map(|k| want[k].abs_diff(got[k])).max().unwrap();
            max = max.max(d);
            sum += u64::from(d);
            differing += u64::from(d > TOLERANCE);
        }
    }
    let n = n.max(1) as f64;
    Difference {
        max,
        mean: sum as f64 / n,
        differing_share: differing as f64 / n,
    }
}

fn assert_within(what: &str, d: &Difference) {
    eprintln!(
        "{what}: max channel difference {}, mean {:.4}, {:.3} % of pixels more than {TOLERANCE} \
         off (allowed {:.1} %)",
        d.max,
        d.mean,
        d.differing_share * 100.0,
        MAX_DIFFERING_SHARE * 100.0
    );
    assert!(
        d.differing_share <= MAX_DIFFERING_SHARE,
        "{what} differs from the headless reference: {d:?}"
    );
}

/// The whole captured window equals `reference` within the tolerance.
fn assert_window_is(what: &str, reference: &Image, window: &Xwd) {
    let d = compare(
        reference,
        |_, _| true,
        |x, y| window.rgb[(y * SIZE.0 + x) as usize],
    );
    assert_within(what, &d);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn window_shows_the_headless_render_of_the_same_camera_after_streaming() {
    require_tool("xwd", &["-help"], "x11-apps");
    let bin = PathBuf::from(env!("CARGO_BIN_EXE_arbor-client"));

    // The scene: lion with 1 KiB treelets, served by the real server in-process.
    let served = serve("points/lion_takanawa.copc.laz", "lion", 1024).await;
    let description = served.scene.clone();
    // The reference: the same camera with every treelet resident, on the CPU.
    let frame = SceneFrame::of(&description);
    let camera = CameraPath::Static.camera(0, &frame, SEED, SIZE.0, SIZE.1);
    let reference_of = |camera| {
        reference_image(
            &description,
            description.layout.channels(),
            served.treelets.clone(),
            camera,
            1.0,
            &Light::default(),
            &mut CpuBackend,
        )
        .unwrap()
    };
    let reference = reference_of(&camera);
    assert!(
        reference.coverage() > u64::from(SIZE.0 * SIZE.1 / 20),
        "the reference view shows too little of the scene ({} px)",
        reference.coverage()
    );

    let out = tempfile::tempdir().unwrap();
    let shot = out.path().join("shot.png");
    let report_path = out.path().join("view.csv");
    // `arbor-client view` on this server with `options`.
    let view_args = |options: &[&str]| -> Vec<OsString> {
        std::iter::once("view".to_owned())
            .chain(served.client_args("lion"))
            .chain(options.iter().map(|o| (*o).to_owned()))
            .map(OsString::from)
            .collect()
    };
    let (xvfb, display) = tokio::task::spawn_blocking(start_xvfb).await.unwrap();
    let lock = PathBuf::from(format!("/tmp/.X{}-lock", display.trim_start_matches(':')));
    let common = view_args(&[
        "--size",
        "256x192",
        "--seed",
        &SEED.to_string(),
        "--feedback-ratio",
        "4",
        // At most 128 treelets per frame, so the arrivals (about 8,000 treelets of 1 KiB) are
        // seen over many frames: with the default limit refinement converges in ~25 cycles.
        "--load-limit",
        "128",
        "--exit-after-converged",
        "--hold-until-stdin-eof",
        "--timeout-s",
        &CONVERGE_TIMEOUT.as_secs().to_string(),
    ]);
    let mut args = common.clone();
    args.extend([
        "--backend".into(),
        "gpu".into(),
        "--no-overlay".into(),
        "--screenshot".into(),
        shot.clone().into(),
        // The device is lost after the fifth frame: the viewer replaces it (surface, blit and
        // renderer made again, the session kept) and goes on to the same picture.
        "--lose-device-after-frames".into(),
        LOSE_DEVICE_AFTER.to_string().into(),
    ]);
    args.extend(["--report".into(), report_path.clone().into()]);
    let (window, viewer_stdout, elapsed) = view(&bin, &display, args).await;
    eprintln!("viewer output:\n{viewer_stdout}");
    assert!(
        viewer_stdout.contains(&format!(
            "event at cycle {LOSE_DEVICE_AFTER}: the GPU device was lost (destroyed); replaced by"
        )),
        "the viewer did not say it replaced the lost device"
    );

    // The window as the X server shows it.
    assert_eq!(
        (window.width, window.height),
        SIZE,
        "window size in the X server"
    );
    assert_window_is("window (xwd)", &reference, &window);

    // The screenshot: the frame texture read back.
    let screenshot = Image::load_png(&shot).unwrap();
    assert_eq!((screenshot.width, screenshot.height), SIZE);
    let coverage_diff = screenshot.coverage().abs_diff(reference.coverage());
    assert!(
        coverage_diff as f64 <= MAX_DIFFERING_SHARE * f64::from(SIZE.0 * SIZE.1),
        "covered pixels of the screenshot: {} against the reference's {}",
        screenshot.coverage(),
        reference.coverage()
    );
    let d = compare(
        &reference,
        |_, _| true,
        |x, y| {
            let p = screenshot.get(x, y).unwrap();
            let a = u32::from(p[3]);
            std::array::from_fn(|k| {
                ((u32::from(p[k]) * a + u32::from(BACKGROUND[k]) * (255 - a) + 127) / 255) as u8
            })
        },
    );
    assert_within("screenshot (frame texture)", &d);

    // Many frames while streaming: the report has a record per frame.
    let report = RunReport::read_csv(&report_path).unwrap();
    assert_eq!(report.events.len(), 1, "{:?}", report.events);
    assert_eq!(report.events[0].cycle, LOSE_DEVICE_AFTER);
    let records = &report.records;
    let inserting: Vec<u32> = records
        .iter()
        .filter(|r| r.treelets_inserted > 0)
        .map(|r| r.cycle)
        .collect();
    let (first, last) = (inserting[0], *inserting.last().unwrap());
    let span = records.last().unwrap().time_s - records[0].time_s;
    eprintln!(
        "{} frames in {span:.2} s ({:.1} fps, {elapsed:.1} s with connecting); treelets \
         inserted in {} cycles between cycle {first} and {last}",
        records.len(),
        (records.len() - 1) as f64 / span.max(1e-9),
        inserting.len()
    );
    let mean =
        |f: fn(&CycleRecord) -> f64| records.iter().map(f).sum::<f64>() / records.len() as f64;
    eprintln!(
        "mean per frame: analysis {:.2} ms, presort {:.2}, integrate {:.2}, upload {:.2}, render \
         {:.2}; frame interval {:.2} ms",
        mean(|r| r.analysis_ms),
        mean(|r| r.presort_ms),
        mean(|r| r.integrate_ms),
        mean(|r| r.upload_ms),
        mean(|r| r.render_ms),
        span * 1e3 / (records.len() - 1) as f64
    );
    assert!(records.len() >= 40, "only {} frames drawn", records.len());
    assert!(
        inserting.len() >= 3 && last - first >= 10,
        "treelets should arrive over many frames: {inserting:?}"
    );
    assert!(records.iter().all(|r| r.slots_used <= r.slots_total));
    assert!(records.last().unwrap().error.max == 0.0);
    assert!(arbor_client_viewer::chart_path(&report_path).exists());

    // Again with the overlay, on the CPU renderer (frames uploaded each cycle): the panel
    // covers the top-left corner with text, the rest of the window is still the reference.
    let moving_common = common.clone();
    let mut args = common;
    args.extend(["--backend".into(), "cpu".into()]);
    let (window, viewer_stdout, _) = view(&bin, &display, args).await;
    eprintln!("viewer output with the overlay:\n{viewer_stdout}");
    let (pw, ph) = Overlay::new().panel_size();
    let m = OVERLAY_MARGIN;
    let in_panel = move |x: u32, y: u32| x >= m && x < m + pw && y >= m && y < m + ph;
    let pixel = |x: u32, y: u32| window.rgb[(y * SIZE.0 + x) as usize];
    let d = compare(&reference, |x, y| !in_panel(x, y), pixel);
    assert_within("window with the overlay, outside the panel", &d);
    let panel = compare(&reference, in_panel, pixel);
    let text = (0..SIZE.1)
        .flat_map(|y| (0..SIZE.0).map(move |x| (x, y)))
        .filter(|&(x, y)| in_panel(x, y) && pixel(x, y).iter().all(|&c| c >= 200))
        .count();
    eprintln!(
        "overlay panel: {:.1} % of its pixels differ from the frame, {text} text pixels",
        panel.differing_share * 100.0
    );
    assert!(
        panel.differing_share > 0.9,
        "the panel was not drawn: {panel:?}"
    );
    assert!(text > 300, "no text in the panel ({text} bright pixels)");

    // A moving camera gets smaller frames; at rest the window is the full-size reference of
    // where the camera stopped.
    // It starts from a bookmark (what the C key prints) of the first runs' camera.
    let bookmark = CameraPath::look_of(&camera, &frame);
    let mut controls = Controls::starting_at(&frame, &bookmark, SEED);
    for _ in 0..ZOOM_FRAMES {
        controls.wheel(arbor_client_viewer::SCRIPTED_ZOOM_LINES);
    }
    let zoomed = controls.camera(SIZE.0, SIZE.1);
    assert!(
        zoomed.position.distance(camera.position) > 0.01 * frame.edge,
        "the scripted zoom moves the camera"
    );
    let zoomed_reference = reference_of(&zoomed);
    let mut args = moving_common;
    args.extend(
        [
            "--backend",
            "gpu",
            "--no-overlay",
            "--moving-frame-ms",
            "1",
            "--script-zoom-frames",
            &ZOOM_FRAMES.to_string(),
            "--camera-path",
            &bookmark.to_string(),
        ]
        .map(OsString::from),
    );
    let (window, viewer_stdout, _) = view(&bin, &display, args).await;
    eprintln!("viewer output while moving:\n{viewer_stdout}");
    let (small, full) = (
        format!("moving: frames at {}x{}", SIZE.0 / 4, SIZE.1 / 4),
        format!("resting: frames at full size {}x{}", SIZE.0, SIZE.1),
    );
    let (at_small, at_full) = (viewer_stdout.find(&small), viewer_stdout.find(&full));
    assert!(
        at_small.is_some() && at_full > at_small,
        "moving frames at a quarter of each side, then full size: {viewer_stdout}"
    );
    assert!(
        viewer_stdout.find("converged at cycle") > at_full,
        "converged only at full size: {viewer_stdout}"
    );
    assert_window_is("window after moving", &zoomed_reference, &window);

    // A view that cannot converge in time fails with a message and status 1: one treelet
    // inserted per cycle cannot bring the hundreds the view needs within a second.
    let args = view_args(&[
        "--size",
        "256x192",
        "--load-limit",
        "1",
        "--exit-after-converged",
        "--timeout-s",
        "1",
    ]);
    let (code, stderr) = tokio::task::spawn_blocking(move || {
        let runtime_dir = tempfile::tempdir().unwrap();
        let mut viewer = Reaped(
            viewer_command(&bin, &display, runtime_dir.path(), "error")
                .args(&args)
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .expect("launching arbor-client view"),
        );
        let mut stderr = String::new();
        viewer
            .0
            .stderr
            .take()
            .unwrap()
            .read_to_string(&mut stderr)
            .unwrap();
        (viewer.0.wait().unwrap().code(), stderr)
    })
    .await
    .unwrap();
    // Stopped as its shutdown expects, the X server leaves no lock behind: the next run (or
    // the next hundred) finds the display free.
    drop(xvfb);
    assert!(!lock.exists(), "Xvfb left {} behind", lock.display());
    eprintln!(
        "viewer with a 1 s timeout: exit {code:?}, {}",
        stderr.trim()
    );
    assert_eq!(code, Some(1), "{stderr}");
    assert!(stderr.contains("did not converge within 1.0 s"), "{stderr}");
    // And where it stood: what was known, received and asked for.
    for part in [
        "% of the pixels known",
        "treelets received",
        "treelets requested",
    ] {
        assert!(stderr.contains(part), "no {part:?} in: {stderr}");
    }
    served.server.shutdown().await;
}

/// `bin` set up to run in the X server on `display` only (no Wayland), with `runtime_dir` as its
/// `XDG_RUNTIME_DIR` (made 0700, as the XDG spec asks) and `RUST_LOG=log`.
fn viewer_command(bin: &Path, display: &str, runtime_dir: &Path, log: &str) -> Command {
    std::fs::set_permissions(runtime_dir, std::fs::Permissions::from_mode(0o700)).unwrap();
    let mut command = Command::new(bin);
    command
        .env("DISPLAY", display)
        .env_remove("WAYLAND_DISPLAY")
        .env("XDG_RUNTIME_DIR", runtime_dir)
        .env("RUST_LOG", log);
    command
}

/// [`run_viewer`] off the async workers.
async fn view(bin: &Path, display: &str, args: Vec<OsString>) -> (Xwd, String, f64) {
    let (bin, display) = (bin.to_path_buf(), display.to_owned());
    tokio::task::spawn_blocking(move || run_viewer(&bin, &display, &args))
        .await
        .unwrap()
}

/// Runs `bin` with `args` on `display` until it prints that it converged, grabs its window, then
/// closes its standard input and checks it exits 0; returns the window content, the viewer's
/// standard output and how long it ran.
fn run_viewer(bin: &Path, display: &str, args: &[OsString]) -> (Xwd, String, f64) {
    let runtime_dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let mut viewer = Reaped(
        viewer_command(bin, display, runtime_dir.path(), "warn")
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("launching arbor-client view"),
    );
    let stdin = viewer.0.stdin.take().unwrap();
    let stdout = viewer.0.stdout.take().unwrap();
    let mut stderr = viewer.0.stderr.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let stderr_text = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });
    let mut output = String::new();
    let mut window_id = None;
    let deadline = Instant::now() + CONVERGE_TIMEOUT + Duration::from_secs(60);
    loop {
        let wait = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(wait) {
            Ok(line) => {
                output.push_str(&line);
                output.push('\n');
                if let Some(rest) = line.strip_prefix("window 0x") {
                    let hex = rest.split_whitespace().next().unwrap();
                    window_id = Some(u64::from_str_radix(hex, 16).unwrap());
                }
                if line.starts_with("converged at cycle") {
                    break;
                }
            }
            Err(_) => {
                let _ = viewer.0.kill();
                panic!(
                    "the viewer did not report convergence (exit {:?}).\nstdout:\n{output}\n\
                     stderr:\n{}",
                    viewer.0.wait().ok(),
                    stderr_text.join().unwrap()
                );
            }
        }
    }
    let id = window_id.expect("the viewer printed no window id");
    // The converged frame has been presented; later frames are the same picture.
    std::thread::sleep(Duration::from_millis(300));
    let xwd = Command::new("xwd")
        .args(["-silent", "-display", display, "-id", &format!("0x{id:x}")])
        .output()
        .expect("running xwd");
    assert!(
        xwd.status.success(),
        "xwd failed: {}",
        String::from_utf8_lossy(&xwd.stderr)
    );
    drop(stdin);
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(s) = viewer.0.try_wait().unwrap() {
            break s;
        }
        assert!(
            Instant::now() < deadline,
            "the viewer did not exit after stdin closed"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    let elapsed = started.elapsed().as_secs_f64();
    output.extend(rx.try_iter().map(|l| l + "\n"));
    let stderr = stderr_text.join().unwrap();
    assert!(
        status.success(),
        "the viewer exited with {status}\nstdout:\n{output}\nstderr:\n{stderr}"
    );
    (parse_xwd(&xwd.stdout), output, elapsed)
}
