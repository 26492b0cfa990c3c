//! Refinement against run time, per policy, next to the physical limit (docs/design.md §10).
//!
//! `cargo bench -p arbor-tests --bench refine` (release). Real server over loopback QUIC and
//! through the UDP link emulator (25 ms each way, 100 Mbit/s); the real client session on the
//! CPU twins, 512×512, 64 MiB; lion and engine with 4 KiB treelets; a static camera (timed from
//! the moment the session starts connecting), and a jump to another viewpoint once the first
//! view has converged (timed from the jump). Per variant:
//!
//! * **error max 0**: the first cycle whose sampled pixels all see detail no coarser than a
//!   pixel;
//! * **converged**: the client's own claim, every pixel known and none coarser than a pixel;
//! * **RMSE 0**: the truth, found afterwards: the first cycle whose resident treelets render the
//!   fully resident reference exactly (a binary search over the cycles' resident sets, rendered
//!   by the CPU twin; the last cycle is checked too);
//! * bytes received, treelets dropped and treelets received twice (already resident or
//!   waiting) in the phase;
//! * the **physical limit** over the link: the wire bytes of the treelets the view needs (the
//!   final cut: what every pixel's ray meets until it stops where the fully resident scene stops
//!   it — the treelets holding the hits, their ancestors, and the ones a ray passes through,
//!   whose coarse hulls would otherwise stop it; after a jump, those not already resident; see
//!   [`needed`]) at 100 Mbit/s, plus one round trip for the request, plus one for the QUIC
//!   handshake on a fresh connection;
//! * the **transport floor** over the link, measured once per case and shared by its variants:
//!   a fresh connection through a fresh link emulator whose first list names exactly the
//!   treelets the view needs, parents first, timed from connecting until the last of them
//!   arrived (for the jump: on the same connection, after the first view's treelets arrived,
//!   from the second list). What any policy would reach knowing the view's needs in advance,
//!   with no client work: the limit plus what the transport adds (QUIC slow start from the
//!   server's initial window, queueing, acknowledgement timing).
//! * the **joint floors** of the jump over the link, printed once under the jump's first row:
//!   the same raw client fetching, from connecting, the first view's needs and then, in the
//!   same list, the jump's (an oracle of the jump), and the first view's needs and those of
//!   [`JUMP_DIRECTIONS`] jump cameras (what a policy that cannot know the next camera must
//!   hold to be ready for it), each against the first view's limit. A policy faster than the
//!   frustum policy on the jump (a cycle or two: the frustum policy's first view fetched its
//!   whole frustum) must hold the jump's needs when its first view converges, so these floors
//!   bound from below what its first view can reach.
//!
//! Prints tables; writes each run's CSV and one chart with every variant of the case "lion,
//! static, link" to `target/refine/`. No assertion on time.
//!
//! Then lion at 256² over loopback (every variant, best of three), the case of the loopback
//! target.
//!
//! Then the oversubscribed case: lion at 3 MiB and 256×256 for 600 cycles, the new client and
//! the thesis's (fixed grid, no bias control, no pushes): bytes received, bytes in the last 100
//! cycles, bytes of the treelets resident at the end, the LOD bias reached and whether the
//! picture equals the reference rendered at that bias.
//!
//! Then a lossy link (40 ms each way, 10 Mbit/s, 1 % loss each way, and again without loss):
//! lion at 512², static, the default client, the server with and without random-loss tolerance
//! (`arbor_server::service::random_loss`) and the client with its list window
//! ([`LIST_SEND_WINDOW`]) and with quinn's default, all four in turns (`ARBOR_REFINE_LOSSY_RUNS`
//! times, default 3; `ARBOR_REFINE_LOSSY=0` skips it): time to convergence, bytes down,
//! treelets received twice, list bytes up, packets the link lost or dropped.
//!
//! `ARBOR_REFINE_TIMELINE=1` records the server's per-treelet timeline
//! (`arbor_server::service::timeline`) in every case and prints under its row when the view's
//! last needed treelet was named, sent and acknowledged, and the bytes acknowledged up to then
//! by who named them (the client's list or a push) and whether the view needed them.
//! `ARBOR_REFINE_TIMELINE=2` adds a table every 50 ms: the needed treelets not yet named, named
//! and waiting, in flight and acknowledged, and the megabytes sent and acknowledged, needed and
//! not.
//!
//! `ARBOR_REFINE_REST_MS=N`: the first view rests N ms after converging (the client keeps
//! stepping, its prefetch may use the idle link) before the jump; the bytes received in the
//! rest are printed under the jump's row, whose limit counts what was resident after the rest
//! (no floor then). Default 0: the jump comes right at convergence.
//!
//! `ARBOR_REFINE_RUNS=N` runs every case of the main table N times (default 1) and prints the
//! run with the median RMSE-0 time, with the range of all N in the *RMSE0 range* column: over
//! the link the same code spreads by ±15 % on this 2-core machine, more than many changes move
//! it. `ARBOR_REFINE_FILTER=lion/static/link` (any part of `scene/path/link/variant`; several
//! separated by `|`) runs only the matching cases; `ARBOR_REFINE_SMALL=0` skips the 256² case
//! and `ARBOR_REFINE_OVERSUB=0` the oversubscribed one.
//!
//! Every session and floor measurement is a first contact: the server forgets what it
//! remembered of the client's path (`arbor_server::service::path_memory`) before each, so its
//! connection slow-starts from the initial window, as the physical limit's handshake assumes.
//! `ARBOR_REFINE_RETURNING=1` measures returning clients instead: the server keeps its memory,
//! and each case of the main table runs once more first, unmeasured, so every measured run and
//! its floor follow a session on the same path and resume its congestion window.
//!
//! `ARBOR_REFINE_UPLINK_MBIT=N` makes the link asymmetric: the client → server direction at N
//! Mbit/s (a home line's or a mobile uplink), the other still at 100 Mbit/s. Request lists are
//! what goes up.
//!
//! `ARBOR_REFINE_OUT=DIR` writes the CSVs and the chart there instead of `target/refine/`.
//!
//! `ARBOR_REFINE_BACKEND=gpu` runs the client sessions on the GPU instead of the CPU twins (one
//! device for the whole bench; no GPU is an error, not a fallback). On these 2-core machines the
//! twins' analysis pass is what the client spends most of a cycle on (engine's 512² view is
//! known in full only after about 0.45 s of cycles), so the GPU rows, from a machine that lends
//! one, show the same policies with that cost taken away.

use std::collections::HashSet;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use arbor_client_core::analysis::AnalysisConfig;
use arbor_client_core::backend::{Backend, CpuBackend};
use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::{CoreConfig, DEFAULT_LOOK_PAST, DEFAULT_PREFETCH_BELOW, Sampling};
use arbor_client_core::image::Image;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::presort::PriorityPolicy;
use arbor_client_core::slots::{DecodedTreelet, SlotBuffer, SlotConfig};
use arbor_client_core::traverse::Lod;
use arbor_client_gpu::{GpuBackend, GpuContext};
use arbor_client_net::transport::LIST_SEND_WINDOW;
use arbor_client_net::{ClientEvent, TreeletClient};
use arbor_client_report::{CycleRecord, RunMeta, RunReport};
use arbor_client_session::session::{RenderMode, Session, SessionConfig};
use arbor_proto::TreeletId;
use arbor_server::service::timeline::{Breakdown, Event as TimelineEvent, Progress, progress};
use arbor_server::service::visibility::CutCaster;
use arbor_tests::link::{LinkConfig, LinkEmulator};
use arbor_tests::streaming::{Served, cpu_render_at, full, serve, serve_tuned};

const SIZE: u32 = 512;
const BUDGET: u64 = 64 << 20;
const SEED: u64 = 7;
const DELAY: Duration = Duration::from_millis(25);
const RATE: u64 = 100_000_000 / 8;
/// A phase gives up after this long (it is then reported as not converged).
const PHASE_LIMIT: Duration = Duration::from_secs(60);

/// A client configuration under comparison.
#[derive(Clone, Copy)]
struct Variant {
    name: &'static str,
    policy: PriorityPolicy,
    sampling: Sampling,
    deep_push: bool,
    adjust_bias: bool,
    /// [`CoreConfig::prefetch_below`].
    prefetch_below: usize,
    /// [`CoreConfig::look_past`].
    look_past: u8,
}

const VARIANTS: [Variant; 7] = [
    Variant {
        name: "thesis: max-error, grid",
        policy: PriorityPolicy::MaxError,
        sampling: Sampling::Grid,
        deep_push: false,
        adjust_bias: false,
        look_past: 0,
        prefetch_below: 0,
    },
    Variant {
        name: "max-error",
        policy: PriorityPolicy::MaxError,
        sampling: Sampling::Adaptive,
        deep_push: true,
        adjust_bias: true,
        look_past: DEFAULT_LOOK_PAST,
        prefetch_below: DEFAULT_PREFETCH_BELOW,
    },
    Variant {
        name: "error-pixels (default)",
        policy: PriorityPolicy::ErrorTimesPixels,
        sampling: Sampling::Adaptive,
        deep_push: true,
        adjust_bias: true,
        look_past: DEFAULT_LOOK_PAST,
        prefetch_below: DEFAULT_PREFETCH_BELOW,
    },
    Variant {
        name: "centre",
        policy: PriorityPolicy::Centre,
        sampling: Sampling::Adaptive,
        deep_push: true,
        adjust_bias: true,
        look_past: DEFAULT_LOOK_PAST,
        prefetch_below: DEFAULT_PREFETCH_BELOW,
    },
    Variant {
        name: "frustum (peers)",
        policy: PriorityPolicy::Frustum,
        sampling: Sampling::Adaptive,
        deep_push: false,
        adjust_bias: true,
        look_past: 0,
        prefetch_below: 0,
    },
    Variant {
        name: "no-look-past default",
        policy: PriorityPolicy::ErrorTimesPixels,
        sampling: Sampling::Adaptive,
        deep_push: true,
        adjust_bias: true,
        look_past: 0,
        prefetch_below: DEFAULT_PREFETCH_BELOW,
    },
    Variant {
        name: "no-prefetch default",
        policy: PriorityPolicy::ErrorTimesPixels,
        sampling: Sampling::Adaptive,
        deep_push: true,
        adjust_bias: true,
        look_past: DEFAULT_LOOK_PAST,
        prefetch_below: 0,
    },
];

/// Where the run connects.
#[derive(Clone, Copy, PartialEq)]
enum Transport {
    Loopback,
    Link,
}

/// One phase of a run: a fixed camera until convergence (or the limit).
struct Phase {
    records: Vec<CycleRecord>,
    /// Resident treelets after each cycle.
    resident: Vec<Vec<TreeletId>>,
    /// `time_s` when the phase began.
    t0: f64,
}

/// What a phase came to.
struct Outcome {
    error0: Option<f64>,
    converged: Option<f64>,
    rmse0: Option<f64>,
    bytes: u64,
    dropped: u32,
    /// Treelets received that were already resident or waiting.
    twice: u32,
    limit: Option<f64>,
    /// With `ARBOR_REFINE_TIMELINE=1`: where the time to the last needed treelet went.
    timeline: Option<String>,
    /// With `ARBOR_REFINE_REST_MS`: bytes received while the first view rested before the jump.
    rest_bytes: Option<u64>,
    /// Over the link: bytes the client sent (request lists, acknowledgements, the handshake)
    /// over the whole session, both phases of a jump, and the most the uplink queued at once.
    upstream: Option<(u64, u64)>,
}

/// Whether the bench measures returning clients (`ARBOR_REFINE_RETURNING=1`, module docs).
fn returning() -> bool {
    std::env::var("ARBOR_REFINE_RETURNING").is_ok_and(|v| v == "1")
}

/// Makes the next connection a first contact unless returning clients are measured.
fn first_contact_unless_returning(served: &Served) {
    if !returning() {
        served.server.state.paths().clear();
    }
}

/// How long the first view rests after converging before the jump (`ARBOR_REFINE_REST_MS`,
/// default 0: the jump comes right at convergence).
fn rest_before_jump() -> Duration {
    Duration::from_millis(
        std::env::var("ARBOR_REFINE_REST_MS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(0),
    )
}

/// What the client sessions run their passes on (`ARBOR_REFINE_BACKEND`): the CPU twins
/// (`cpu`, the default: what CI machines have), or the GPU (`gpu`: one device for the whole
/// bench, each session with a backend of its own on it). The references and the RMSE-0 search
/// render on the CPU twins either way: the GPU's images equal theirs (`gpu_real`, `gpu_e2e`).
enum SessionBackend {
    Cpu,
    Gpu(Arc<GpuContext>),
}

impl SessionBackend {
    /// The backend `ARBOR_REFINE_BACKEND` names, opened once. A GPU that cannot be opened ends
    /// the bench with the reason: a figure labelled GPU must come from one.
    fn get() -> &'static SessionBackend {
        static CHOSEN: OnceLock<SessionBackend> = OnceLock::new();
        CHOSEN.get_or_init(|| match std::env::var("ARBOR_REFINE_BACKEND").as_deref() {
            Err(_) | Ok("cpu") => SessionBackend::Cpu,
            Ok("gpu") => SessionBackend::Gpu(Arc::new(GpuContext::new(None).unwrap_or_else(|e| {
                panic!("ARBOR_REFINE_BACKEND=gpu, but no GPU could be opened: {e}")
            }))),
            Ok(other) => panic!("ARBOR_REFINE_BACKEND={other:?}: expected cpu or gpu"),
        })
    }

    /// A backend for one session.
    fn make(&self) -> Box<dyn Backend> {
        match self {
            SessionBackend::Cpu => Box::new(CpuBackend),
            SessionBackend::Gpu(ctx) => Box::new(GpuBackend::timed(ctx.clone())),
        }
    }

    fn describe(&self) -> String {
        match self {
            SessionBackend::Cpu => "CPU twins".into(),
            SessionBackend::Gpu(ctx) => format!("GPU: {}", ctx.describe()),
        }
    }
}

fn main() {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    // `ARBOR_REFINE_OUT` for a binary carried to another machine, where this checkout's
    // target directory does not exist.
    let out = std::env::var_os("ARBOR_REFINE_OUT").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/refine"),
        PathBuf::from,
    );
    std::fs::create_dir_all(&out).unwrap();
    let scenes = [
        ("points/lion_takanawa.copc.laz", "lion"),
        ("volumes/engine_256x256x128_u8.nrrd", "engine"),
    ];
    println!(
        "# refine: {SIZE}×{SIZE}, {} MiB, 4 KiB treelets, client on the {} ({} cores)",
        BUDGET >> 20,
        SessionBackend::get().describe(),
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    println!(
        "{:<7} {:<6} {:<8} {:<24} {:>8} {:>8} {:>8} {:>13} {:>9} {:>7} {:>6} {:>8} {:>7} {:>8} {:>7}",
        "scene",
        "path",
        "link",
        "variant",
        "err0 s",
        "conv s",
        "RMSE0 s",
        "RMSE0 range",
        "MB",
        "dropped",
        "twice",
        "limit s",
        "×limit",
        "floor s",
        "×floor"
    );
    let filter = std::env::var("ARBOR_REFINE_FILTER").ok();
    let repeats: usize = std::env::var("ARBOR_REFINE_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1)
        .clamp(1, 100);
    let mut chart_runs: Vec<(String, RunReport)> = Vec::new();
    for (rel, name) in scenes {
        let served = Arc::new(runtime.block_on(serve(rel, name, 4096)));
        let full = full(&served);
        for jump in [false, true] {
            for transport in [Transport::Loopback, Transport::Link] {
                let mut floor: Option<Option<f64>> = None;
                let mut needs: Option<CaseNeeds> = None;
                let mut joint_printed = false;
                for v in VARIANTS {
                    let label = format!(
                        "{name}/{}/{}/{}",
                        if jump { "jump" } else { "static" },
                        if transport == Transport::Link {
                            "link"
                        } else {
                            "loopback"
                        },
                        v.name
                    );
                    if !filter
                        .as_ref()
                        .is_none_or(|f| f.split('|').any(|f| label.contains(f)))
                    {
                        continue;
                    }
                    if returning() {
                        run_case(&runtime, &served, &full, v, jump, transport, SIZE);
                    }
                    let mut runs: Vec<(Outcome, RunReport)> = (0..repeats)
                        .map(|_| run_case(&runtime, &served, &full, v, jump, transport, SIZE))
                        .collect();
                    // Median by the time to RMSE 0; a run that never got there sorts last.
                    let key = |o: &Outcome| o.rmse0.unwrap_or(f64::INFINITY);
                    runs.sort_by(|a, b| key(&a.0).total_cmp(&key(&b.0)));
                    let range = (repeats > 1).then(|| (key(&runs[0].0), key(&runs[repeats - 1].0)));
                    let (o, report) = runs.swap_remove(repeats / 2);
                    // A rest leaves more resident than the first view's needs, which the floor's
                    // jump assumes: no floor then.
                    let floor = *floor.get_or_insert_with(|| {
                        (transport == Transport::Link && !(jump && o.rest_bytes.is_some())).then(
                            || {
                                let n = needs.get_or_insert_with(|| case_needs(&served, jump));
                                transport_floor(&runtime, &served, n, repeats)
                            },
                        )
                    });
                    print_row(name, jump, transport, v, &o, range, floor);
                    // With a floor measured, the case's needs are known.
                    if let (
                        Some(_),
                        Some(CaseNeeds {
                            first,
                            jump: Some(oracle),
                        }),
                    ) = (floor, &needs)
                        && !joint_printed
                    {
                        joint_printed = true;
                        let j = joint_floor(&runtime, &served, first, oracle, repeats);
                        println!(
                            "    both views' needs in one list from connecting (an oracle of the \
                             jump): {:.3} s = {:.2}× the first view's limit {:.3} s; the first \
                             view's and {JUMP_DIRECTIONS} jump directions' needs ({:.2} MB, \
                             what a policy must hold to be ready for any jump): {:.3} s = {:.2}×",
                            j.oracle,
                            j.oracle / j.limit,
                            j.limit,
                            j.every_bytes as f64 / 1e6,
                            j.every,
                            j.every / j.limit
                        );
                    }
                    if let Some(t) = &o.timeline {
                        println!("    {t}");
                    }
                    if let (Some((sent, queued)), Some(_)) = (o.upstream, uplink_rate()) {
                        println!(
                            "    up: {:.3} MB sent over the session, at most {:.1} KB queued",
                            sent as f64 / 1e6,
                            queued as f64 / 1e3
                        );
                    }
                    if let Some(b) = o.rest_bytes {
                        println!(
                            "    the first view rested {} ms before the jump, receiving {:.3} MB",
                            rest_before_jump().as_millis(),
                            b as f64 / 1e6
                        );
                    }
                    let file = format!(
                        "{name}-{}-{}-{}.csv",
                        if jump { "jump" } else { "static" },
                        if transport == Transport::Link {
                            "link"
                        } else {
                            "loopback"
                        },
                        v.name.split(&[' ', ':'][..]).next().unwrap_or("run")
                    );
                    report.write_csv(&out.join(file)).unwrap();
                    if name == "lion" && !jump && transport == Transport::Link {
                        chart_runs.push((v.name.to_owned(), report));
                    }
                }
            }
        }
        runtime.block_on(async { drop(Arc::try_unwrap(served).ok()) });
    }
    if !chart_runs.is_empty() {
        let runs: Vec<(&str, &RunReport)> =
            chart_runs.iter().map(|(n, r)| (n.as_str(), r)).collect();
        let chart = out.join("lion-static-link.png");
        arbor_client_report::compare::draw_comparison(
            &runs,
            &chart,
            "lion 4 KiB, 512², static camera, 25 ms / 100 Mbit/s: error and bytes against time",
        )
        .unwrap();
        println!("chart: {}", chart.display());
    }
    if std::env::var("ARBOR_REFINE_SMALL").as_deref() != Ok("0") {
        small_loopback(&runtime);
    }
    if std::env::var("ARBOR_REFINE_OVERSUB").as_deref() != Ok("0") {
        oversubscribed(&runtime, &out);
    }
    if std::env::var("ARBOR_REFINE_LOSSY").as_deref() != Ok("0") {
        lossy_link(&runtime);
    }
}

/// quinn's default send window (8 × its 1.25 MB stream window): lists unbounded, as before
/// [`LIST_SEND_WINDOW`].
const QUINN_SEND_WINDOW: u64 = 10_000_000;

/// A home or mobile link with random loss, the product's default client (error-pixels) on lion
/// at 512², static camera: the server with and without random-loss tolerance
/// (`arbor_server::service::random_loss`), the client with its list window and with quinn's
/// default, all four in turns, `ARBOR_REFINE_LOSSY_RUNS` times (default 3), each turn with its
/// own loss sequence, shared by the four. Without loss as well, to show what the two cost where
/// nothing is lost. `ARBOR_REFINE_LOSSY=0` skips it.
fn lossy_link(runtime: &tokio::runtime::Runtime) {
    const DELAY: Duration = Duration::from_millis(40);
    const RATE: u64 = 10_000_000 / 8;
    let runs: usize = std::env::var("ARBOR_REFINE_LOSSY_RUNS")
        .ok()
        .and_then(|r| r.parse().ok())
        .unwrap_or(3)
        .max(1);
    let rel = "points/lion_takanawa.copc.laz";
    let tolerant = runtime.block_on(serve(rel, "lion", 4096));
    let plain = runtime.block_on(serve_tuned(rel, "lion", 4096, |c| {
        c.random_loss_tolerance = false;
    }));
    let variant = VARIANTS[2];
    let core = CoreConfig {
        policy: variant.policy,
        sampling: variant.sampling,
        deep_push: variant.deep_push,
        adjust_bias: variant.adjust_bias,
        prefetch_below: variant.prefetch_below,
        look_past: variant.look_past,
        budget_bytes: BUDGET,
        ..CoreConfig::default()
    };
    let setups: [(&str, &Served, u64); 4] = [
        ("Cubic, lists unbounded", &plain, QUINN_SEND_WINDOW),
        ("Cubic, lists paced", &plain, LIST_SEND_WINDOW),
        ("tolerant, lists unbounded", &tolerant, QUINN_SEND_WINDOW),
        ("tolerant, lists paced", &tolerant, LIST_SEND_WINDOW),
    ];
    for loss in [0.01, 0.0] {
        println!(
            "\n# lossy link: lion 4 KiB, {SIZE}², static, {} ms each way, {} Mbit/s, {} % loss \
             each way; {runs} runs in turns (median, range)",
            DELAY.as_millis(),
            RATE * 8 / 1_000_000,
            loss * 100.0
        );
        println!(
            "{:<27} {:>16} {:>15} {:>8} {:>9} {:>7} {:>6}",
            "server, client", "converged s", "range", "MB down", "twice", "MB up", "lost"
        );
        let mut rows: Vec<Vec<[f64; 5]>> = vec![Vec::new(); setups.len()];
        for turn in 0..runs {
            for (i, (_, served, window)) in setups.iter().enumerate() {
                let link = runtime
                    .block_on(LinkEmulator::start(
                        served.server.quic_addr,
                        LinkConfig::wan(DELAY, RATE)
                            .with_loss(loss)
                            .with_seed(turn as u64 + 1),
                    ))
                    .unwrap();
                let unit = CameraPath::Static.camera(0, &SceneFrame::UNIT, SEED, SIZE, SIZE);
                let mut session = connect_with(
                    runtime,
                    served,
                    link.local_addr(),
                    core.clone(),
                    unit,
                    *window,
                );
                let frame = *session.core().frame();
                let camera = CameraPath::Static.camera(0, &frame, SEED, SIZE, SIZE);
                let phase = run_phase(&mut session, &camera, true);
                session.close(runtime.handle());
                let last = phase.records.last().unwrap();
                let converged = last.known_share == 1.0 && last.error.max == 0.0;
                let stats = link.stats();
                rows[i].push([
                    if converged {
                        last.time_s
                    } else {
                        f64::INFINITY
                    },
                    phase.records.iter().map(|r| r.bytes_received).sum::<u64>() as f64 / 1e6,
                    f64::from(phase.records.iter().map(|r| r.received_twice).sum::<u32>()),
                    stats.upstream.bytes_forwarded as f64 / 1e6,
                    (stats.downstream.dropped_loss + stats.downstream.dropped_queue) as f64,
                ]);
                runtime.block_on(async { drop(link) });
            }
        }
        for ((name, _, _), runs) in setups.iter().zip(&mut rows) {
            runs.sort_by(|a, b| a[0].total_cmp(&b[0]));
            let m = runs[runs.len() / 2];
            let secs = |t: f64| {
                if t.is_finite() {
                    format!("{t:.2}")
                } else {
                    format!(">{}", PHASE_LIMIT.as_secs())
                }
            };
            println!(
                "{:<27} {:>16} {:>15} {:>8.2} {:>9} {:>7.2} {:>6}",
                name,
                secs(m[0]),
                format!("{}–{}", secs(runs[0][0]), secs(runs[runs.len() - 1][0])),
                m[1],
                m[2],
                m[3],
                m[4]
            );
        }
    }
}

/// Lion at 256², loopback, static camera, every policy on the CPU twins: time from the start of
/// the session to the client's own convergence claim and to RMSE 0, best of three.
fn small_loopback(runtime: &tokio::runtime::Runtime) {
    const SMALL: u32 = 256;
    const RUNS: usize = 3;
    let served = runtime.block_on(serve("points/lion_takanawa.copc.laz", "lion", 4096));
    let full = full(&served);
    println!("\n# loopback: lion 4 KiB, {SMALL}×{SMALL}, static, CPU twins, best of {RUNS}");
    println!(
        "{:<24} {:>8} {:>8} {:>9}",
        "variant", "conv s", "RMSE0 s", "MB"
    );
    for v in VARIANTS {
        let runs: Vec<Outcome> = (0..RUNS)
            .map(|_| {
                run_case(
                    runtime,
                    &served,
                    &full,
                    v,
                    false,
                    Transport::Loopback,
                    SMALL,
                )
                .0
            })
            .collect();
        let best = |f: fn(&Outcome) -> Option<f64>| {
            runs.iter()
                .filter_map(f)
                .min_by(f64::total_cmp)
                .map_or("-".to_owned(), |t| format!("{t:.3}"))
        };
        println!(
            "{:<24} {:>8} {:>8} {:>9.3}",
            v.name,
            best(|o| o.converged),
            best(|o| o.rmse0),
            runs.iter().map(|o| o.bytes).min().unwrap_or(0) as f64 / 1e6
        );
    }
    runtime.block_on(async { drop(served) });
}

fn print_row(
    scene: &str,
    jump: bool,
    transport: Transport,
    v: Variant,
    o: &Outcome,
    range: Option<(f64, f64)>,
    floor: Option<f64>,
) {
    let s = |t: Option<f64>| t.map_or("-".to_owned(), |t| format!("{t:.3}"));
    let range = range.map_or("-".to_owned(), |(lo, hi)| format!("{lo:.3}–{hi:.3}"));
    let ratio = |of: Option<f64>| match (o.rmse0, of) {
        (Some(t), Some(l)) => format!("{:.2}", t / l),
        _ => "-".to_owned(),
    };
    println!(
        "{:<7} {:<6} {:<8} {:<24} {:>8} {:>8} {:>8} {:>13} {:>9.3} {:>7} {:>6} {:>8} {:>7} {:>8} {:>7}",
        scene,
        if jump { "jump" } else { "static" },
        if transport == Transport::Link {
            "25ms/100M"
        } else {
            "loopback"
        },
        v.name,
        s(o.error0),
        s(o.converged),
        s(o.rmse0),
        range,
        o.bytes as f64 / 1e6,
        o.dropped,
        o.twice,
        s(o.limit),
        ratio(o.limit),
        s(floor),
        ratio(floor)
    );
}

/// What a case's views need: the first view's treelets, and for a jump those of the jump's
/// camera not among them.
struct CaseNeeds {
    first: HashSet<TreeletId>,
    jump: Option<HashSet<TreeletId>>,
}

fn case_needs(served: &Served, jump: bool) -> CaseNeeds {
    let first = camera_needs(served, 0, None);
    let jump = jump.then(|| camera_needs(served, 1, Some(&first)));
    CaseNeeds { first, jump }
}

/// What camera `k` of the bench's path needs (0: the static first view, `k` ≥ 1: the `k`-th
/// jump), less `known`.
fn camera_needs(served: &Served, k: u32, known: Option<&HashSet<TreeletId>>) -> HashSet<TreeletId> {
    let frame = SceneFrame::of(&served.scene);
    let path = if k == 0 {
        CameraPath::Static
    } else {
        CameraPath::Jump { every: 1 }
    };
    let camera = path.camera(k, &frame, SEED, SIZE, SIZE);
    let mut needs = needed(served, &frame, &camera, 1.0);
    if let Some(known) = known {
        needs.retain(|id| !known.contains(id));
    }
    needs
}

/// The median of `runs` measurements.
fn median_of(runs: usize, measure: impl FnMut(usize) -> f64) -> f64 {
    let mut times: Vec<f64> = (0..runs).map(measure).collect();
    times.sort_by(f64::total_cmp);
    times[runs / 2]
}

/// The transport floor of a case (module docs), the median of `runs` measurements: a raw
/// treelet client whose first list names exactly the first view's needed treelets, parents
/// first; for a jump, then the jump's needed treelets not yet received, timed from that list.
fn transport_floor(
    runtime: &tokio::runtime::Runtime,
    served: &Served,
    needs: &CaseNeeds,
    runs: usize,
) -> f64 {
    median_of(runs, |_| {
        runtime.block_on(floor_once(served, &[&needs.first], needs.jump.as_ref()))
    })
}

/// The physical limit of `bytes` over the link (module docs): their time at the link's rate,
/// one round trip for the request, and one more for the handshake of a fresh connection.
fn physical_limit(bytes: u64, handshake: bool) -> f64 {
    let rtt = 2.0 * DELAY.as_secs_f64();
    bytes as f64 / RATE as f64 + rtt + if handshake { rtt } else { 0.0 }
}

/// Jump directions whose needs [`joint_floor`] gathers for a policy that cannot know the next
/// camera (the bench's jump is the first of them).
const JUMP_DIRECTIONS: u32 = 64;

/// What [`joint_floor`] measured.
struct JointFloor {
    /// The first view's physical limit, seconds.
    limit: f64,
    /// Both views' needs in one list, seconds from connecting (median).
    oracle: f64,
    /// The first view's and every jump direction's needs in one list (median).
    every: f64,
    every_bytes: u64,
}

/// The jump case's joint floors (module docs), medians of `runs`: the first view's needs and
/// the jump's in one list from connecting, the first view's ranked first — what a policy
/// faster than the frustum policy on the jump (whose view must be resident when the first one
/// converges) could reach at best if it knew the jump — and the same with the needs of
/// [`JUMP_DIRECTIONS`] jump cameras, what a policy must hold when it cannot know the jump.
fn joint_floor(
    runtime: &tokio::runtime::Runtime,
    served: &Served,
    first: &HashSet<TreeletId>,
    oracle: &HashSet<TreeletId>,
    runs: usize,
) -> JointFloor {
    let mut every = oracle.clone();
    for k in 2..=JUMP_DIRECTIONS {
        every.extend(camera_needs(served, k, Some(first)));
    }
    let bytes = |set: &HashSet<TreeletId>| -> u64 {
        set.iter().map(|id| served.wire_bytes[id.0 as usize]).sum()
    };
    let joint = |then: &HashSet<TreeletId>| {
        median_of(runs, |_| {
            runtime.block_on(floor_once(served, &[first, then], None))
        })
    };
    JointFloor {
        limit: physical_limit(bytes(first), true),
        oracle: joint(oracle),
        every: joint(&every),
        every_bytes: bytes(first) + bytes(&every),
    }
}

/// A raw treelet client of `served` through `link`, every channel.
fn floor_client(served: &Served, link: &LinkEmulator) -> TreeletClient {
    let config = served
        .client_config(link.local_addr())
        .with_channels(served.scene.layout.channels().iter().copied());
    TreeletClient::start(config).unwrap()
}

/// A fresh link emulator in front of `served`'s server: [`DELAY`] each way, [`RATE`] down, and
/// up as well unless `ARBOR_REFINE_UPLINK_MBIT` sets the uplink's rate.
async fn start_link(served: &Served) -> LinkEmulator {
    let link = LinkEmulator::start(served.server.quic_addr, LinkConfig::wan(DELAY, RATE))
        .await
        .unwrap();
    if let Some(rate) = uplink_rate() {
        link.set_upstream_rate(Some(rate)).unwrap();
    }
    link
}

/// `ARBOR_REFINE_UPLINK_MBIT`, in bytes per second.
fn uplink_rate() -> Option<u64> {
    let mbit: f64 = std::env::var("ARBOR_REFINE_UPLINK_MBIT")
        .ok()?
        .parse()
        .ok()?;
    (mbit > 0.0).then(|| (mbit * 1e6 / 8.0) as u64)
}

/// One floor measurement from connecting: `first` in one list (each set ranked below the one
/// before, [`fetch_tiers`]) until all arrived, then, if given, `jump` in a second list, timed
/// from that list.
async fn floor_once(
    served: &Served,
    first: &[&HashSet<TreeletId>],
    jump: Option<&HashSet<TreeletId>>,
) -> f64 {
    first_contact_unless_returning(served);
    let link = start_link(served).await;
    // The list goes out with the connection (the client sends its latest list on connecting),
    // so the static floor counts the handshake as the limit does.
    let start = Instant::now();
    let mut client = floor_client(served, &link);
    fetch_tiers(&mut client, served, first).await;
    let took = match jump {
        None => start.elapsed(),
        Some(jump) => fetch_all(&mut client, served, jump).await,
    };
    client.close().await;
    link.shutdown().await;
    took.as_secs_f64()
}

/// Lists `wanted` (parents first: by level below the root, then id) and waits until every one
/// of them arrived; returns how long that took from the list.
async fn fetch_all(
    client: &mut TreeletClient,
    served: &Served,
    wanted: &HashSet<TreeletId>,
) -> Duration {
    fetch_tiers(client, served, &[wanted]).await
}

/// [`fetch_all`] of several sets in one list, each set ranked below the one before.
async fn fetch_tiers(
    client: &mut TreeletClient,
    served: &Served,
    tiers: &[&HashSet<TreeletId>],
) -> Duration {
    let level = |mut id: TreeletId| {
        let mut level = 0u32;
        while id != TreeletId::ROOT && !id.is_none() {
            id = served.treelets[id.0 as usize].treelet.header.parent_id;
            level += 1;
        }
        level
    };
    let list: Vec<(TreeletId, f32)> = tiers
        .iter()
        .enumerate()
        .flat_map(|(tier, wanted)| {
            wanted
                .iter()
                .map(move |&id| (id, -((tier as u32 * 1000 + level(id)) as f32)))
        })
        .collect();
    let t = Instant::now();
    client.request(list).unwrap();
    let mut left: HashSet<TreeletId> = tiers.iter().flat_map(|w| w.iter().copied()).collect();
    while !left.is_empty() {
        match tokio::time::timeout(Duration::from_secs(60), client.next_event()).await {
            Ok(Some(ClientEvent::Treelet(tr))) => {
                left.remove(&tr.id);
            }
            Ok(Some(ClientEvent::Disconnected { reason, .. })) => {
                panic!("transport floor: disconnected: {reason}")
            }
            Ok(Some(_)) => {}
            Ok(None) | Err(_) => panic!("transport floor: stalled with {} left", left.len()),
        }
    }
    t.elapsed()
}

/// A session of `v` against `served` (through a fresh link emulator for [`Transport::Link`]):
/// the first camera until convergence, and for `jump` a second one measured from the jump.
fn run_case(
    runtime: &tokio::runtime::Runtime,
    served: &Served,
    full: &SlotBuffer,
    v: Variant,
    jump: bool,
    transport: Transport,
    size: u32,
) -> (Outcome, RunReport) {
    let link = (transport == Transport::Link).then(|| runtime.block_on(start_link(served)));
    let addr = link
        .as_ref()
        .map_or(served.server.quic_addr, |l| l.local_addr());
    let core = CoreConfig {
        analysis: AnalysisConfig::default(),
        policy: v.policy,
        sampling: v.sampling,
        deep_push: v.deep_push,
        adjust_bias: v.adjust_bias,
        prefetch_below: v.prefetch_below,
        look_past: v.look_past,
        budget_bytes: BUDGET,
        ..CoreConfig::default()
    };
    let timeline = &served.server.state.timeline;
    let trace_level = std::env::var("ARBOR_REFINE_TIMELINE").unwrap_or_default();
    let trace = trace_level == "1" || trace_level == "2";
    if trace {
        timeline.start();
    }
    let unit_first = CameraPath::Static.camera(0, &SceneFrame::UNIT, SEED, size, size);
    let mut session = connect(runtime, served, addr, core, unit_first);
    let mut phase_start = session.started();
    let frame = *session.core().frame();
    let first = CameraPath::Static.camera(0, &frame, SEED, size, size);
    // The first phase counts from the moment the session started connecting (handshake, Hello,
    // root), as the physical limit does.
    let mut phase = run_phase(&mut session, &first, true);
    let mut camera = first;
    let mut handshake = true;
    let mut already = HashSet::new();
    let mut rest_bytes = None;
    if jump {
        let rest = rest_before_jump();
        if !rest.is_zero() {
            // The user looks at the converged view for a while: the client keeps stepping (its
            // prefetch may use the idle link) before the camera moves.
            let (start, mut bytes) = (Instant::now(), 0);
            while start.elapsed() < rest {
                bytes += session
                    .step(&first, RenderMode::Skip, None)
                    .unwrap()
                    .record
                    .bytes_received;
            }
            rest_bytes = Some(bytes);
        }
        already = resident(&session).into_iter().collect();
        camera = CameraPath::Jump { every: 1 }.camera(1, &frame, SEED, size, size);
        if trace {
            timeline.start();
        }
        phase_start = Instant::now();
        phase = run_phase(&mut session, &camera, false);
        handshake = false;
    }
    session.close(runtime.handle());
    let upstream = link.as_ref().map(|l| {
        let up = l.stats().upstream;
        (up.bytes_in, up.peak_queued_bytes)
    });
    if let Some(l) = link {
        runtime.block_on(l.shutdown());
    }
    // What the view needs beyond what the first view left resident: the limit's bytes over the
    // link, the timeline's needed treelets.
    let link = transport == Transport::Link;
    let still_needed: Option<HashSet<TreeletId>> = (link || trace).then(|| {
        let bias = phase.records.last().unwrap().lod_bias;
        needed(served, &frame, &camera, bias)
            .into_iter()
            .filter(|id| !already.contains(id))
            .collect()
    });
    let limit_needs = still_needed.as_ref().filter(|_| link);
    let mut outcome = judge(
        served,
        full,
        &frame,
        &camera,
        &phase,
        handshake,
        limit_needs,
    );
    outcome.rest_bytes = rest_bytes;
    outcome.upstream = upstream;
    if let Some(needed) = still_needed.as_ref().filter(|_| trace) {
        let recording = timeline.take();
        // One connection per case: the session of its events.
        let session = recording.events.iter().find_map(|e| match e {
            TimelineEvent::Listed { session, .. } => Some(*session),
            _ => None,
        });
        outcome.timeline = Some(session.map_or_else(
            || "nothing listed in this phase".to_owned(),
            |s| {
                let bytes = |id: TreeletId| served.wire_bytes[id.0 as usize];
                let mut text = Breakdown::of(&recording, s, phase_start, needed, bytes).summary();
                if trace_level == "2" {
                    let until = outcome.rmse0.unwrap_or(1.0);
                    text += &progress_table(&progress(
                        &recording,
                        s,
                        phase_start,
                        needed,
                        bytes,
                        PROGRESS_STEP,
                        until + PROGRESS_STEP,
                    ));
                }
                text
            },
        ));
    }
    let report = RunReport {
        meta: RunMeta {
            scene: served.scene.name.clone(),
            width: size,
            height: size,
            budget_mib: (BUDGET >> 20) as f64,
            camera_path: if jump { "jump" } else { "static" }.into(),
            ..RunMeta::default()
        },
        records: phase
            .records
            .iter()
            .cloned()
            .map(|mut r| {
                r.time_s -= phase.t0;
                r
            })
            .collect(),
        events: Vec::new(),
    };
    (outcome, report)
}

fn connect(
    runtime: &tokio::runtime::Runtime,
    served: &Served,
    addr: SocketAddr,
    core: CoreConfig,
    first_camera: Camera,
) -> Session {
    connect_with(runtime, served, addr, core, first_camera, LIST_SEND_WINDOW)
}

/// [`connect`] with a client whose request lists may have `list_send_window` bytes
/// unacknowledged.
fn connect_with(
    runtime: &tokio::runtime::Runtime,
    served: &Served,
    addr: SocketAddr,
    core: CoreConfig,
    first_camera: Camera,
    list_send_window: u64,
) -> Session {
    let client = served
        .client_config(addr)
        .with_list_send_window(list_send_window);
    first_contact_unless_returning(served);
    Session::connect(
        SessionConfig {
            client,
            core,
            connect_timeout: Duration::from_secs(30),
            first_camera: Some(first_camera),
        },
        runtime.handle(),
        SessionBackend::get().make(),
    )
    .unwrap()
}

/// Steps `camera` until every pixel is known and none is coarser than a pixel, or
/// [`PHASE_LIMIT`]. Times count from the session's start (`from_start`) or from now.
fn run_phase(session: &mut Session, camera: &Camera, from_start: bool) -> Phase {
    let t0 = if from_start {
        0.0
    } else {
        session.started().elapsed().as_secs_f64()
    };
    let wall = Instant::now();
    let mut phase = Phase {
        records: Vec::new(),
        resident: Vec::new(),
        t0,
    };
    while wall.elapsed() < PHASE_LIMIT {
        let step = session.step(camera, RenderMode::Skip, None).unwrap();
        phase.resident.push(resident(session));
        let done = step.record.known_share == 1.0 && step.record.error.max == 0.0;
        phase.records.push(step.record);
        if done {
            break;
        }
    }
    phase
}

/// The treelets `session` holds now.
fn resident(session: &Session) -> Vec<TreeletId> {
    let slots = session.core().slots();
    (0..slots.capacity())
        .filter_map(|s| slots.treelet_in(s))
        .collect()
}

/// The phase's figures; `limit_needs` (over the link) are the treelets the view needs that were
/// not resident when it began, whose bytes make the physical limit.
fn judge(
    served: &Served,
    full: &SlotBuffer,
    frame: &SceneFrame,
    camera: &Camera,
    phase: &Phase,
    handshake: bool,
    limit_needs: Option<&HashSet<TreeletId>>,
) -> Outcome {
    let r = &phase.records;
    let at = |i: usize| r[i].time_s - phase.t0;
    let error0 = r
        .iter()
        .position(|c| c.sampled > 0 && c.error.max == 0.0)
        .map(at);
    let last = r.last().unwrap();
    let converged = (last.known_share == 1.0 && last.error.max == 0.0).then(|| at(r.len() - 1));
    let bias = last.lod_bias;
    let reference = cpu_render_at(full, frame, camera, bias);
    let exact =
        |i: usize| render_subset(served, &phase.resident[i], frame, camera, bias) == reference;
    let rmse0 = if exact(r.len() - 1) {
        // Resident sets only grow in these phases (the budget holds the view): exactness is
        // monotone, so the first exact cycle is found by bisection.
        let (mut lo, mut hi) = (0, r.len() - 1);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if exact(mid) { hi = mid } else { lo = mid + 1 }
        }
        Some(at(lo))
    } else {
        eprintln!("warning: the last cycle does not render the reference exactly");
        None
    };
    let limit = limit_needs.map(|needed| {
        let bytes: u64 = needed
            .iter()
            .map(|id| served.wire_bytes[id.0 as usize])
            .sum();
        physical_limit(bytes, handshake)
    });
    Outcome {
        error0,
        converged,
        rmse0,
        bytes: r.iter().map(|c| c.bytes_received).sum(),
        dropped: r.iter().map(|c| c.dropped).sum(),
        twice: r.iter().map(|c| c.received_twice).sum(),
        limit,
        timeline: None,
        rest_bytes: None,
        upstream: None,
    }
}

/// The picture a client holding exactly `ids` draws.
fn render_subset(
    served: &Served,
    ids: &[TreeletId],
    frame: &SceneFrame,
    camera: &Camera,
    bias: f64,
) -> Image {
    let d = &served.scene;
    let channels = d.layout.channels().to_vec();
    let config = SlotConfig {
        budget_bytes: (ids.len() as u64 + 1) * SlotBuffer::slot_bytes(d.treelet_nodes, &channels),
        treelet_nodes: d.treelet_nodes,
        channels,
        visibility_max: 1,
        load_limit: u32::MAX,
    };
    let mut sorted = ids.to_vec();
    sorted.sort_unstable();
    let mut slots = SlotBuffer::new(config, served.treelets[0].clone()).unwrap();
    // Ids ascend down the tree: parents are inserted before their children.
    for id in sorted.into_iter().filter(|id| id.0 != 0) {
        slots.insert(served.treelets[id.0 as usize].clone());
    }
    cpu_render_at(&slots, frame, camera, bias)
}

/// The treelets a view needs resident to render exactly what the fully resident scene renders:
/// found by casting every pixel's ray through a tree that starts with the root and loads a
/// treelet whenever a ray stops at its refinable leaf while the leaf is coarser than a pixel
/// (the client's own request rule), until no ray does. Besides the treelets holding the hits
/// and their ancestors, that includes the ones a ray only passes through: a coarse voxel is a
/// hull of its subtree, and a ray that would pass through the subtree stops at the hull until
/// the subtree is loaded. Every one of them is needed (without it, some ray stops at its hull
/// and the pixel differs), and together they are enough (each ray then stops where the full
/// tree stops it: a ray that stopped stays stopped, since loading a treelet only refines hulls
/// behind the stop or elsewhere).
fn needed(served: &Served, frame: &SceneFrame, camera: &Camera, bias: f64) -> HashSet<TreeletId> {
    let nodes_only = |id: TreeletId| DecodedTreelet {
        treelet: served.treelets[id.0 as usize].treelet.clone(),
        attributes: Vec::new(),
    };
    // The server's visible cuts cast the same way; a buffer of the whole scene never runs out.
    let whole = u64::from(served.scene.treelet_count)
        * SlotBuffer::slot_bytes(served.scene.treelet_nodes, &[]);
    let caster = CutCaster::new(&served.scene, whole, nodes_only(TreeletId::ROOT)).unwrap();
    let lod = Lod {
        pixel_angle: camera.pixel_angle(),
        lod_bias: bias,
        max_depth: frame.max_depth,
    };
    let cast = caster.cast(camera, &lod, |id| Some(nodes_only(id)));
    assert!(cast.complete, "a whole-scene buffer holds every cast");
    cast.treelets
        .into_iter()
        .map(|(_, id)| id)
        .chain([TreeletId::ROOT])
        .collect()
}

/// Lion at 3 MiB, 256×256, 600 cycles: the new client against the thesis's.
fn oversubscribed(runtime: &tokio::runtime::Runtime, out: &std::path::Path) {
    const CYCLES: usize = 600;
    const SMALL: u32 = 256;
    let served = runtime.block_on(serve("points/lion_takanawa.copc.laz", "lion", 4096));
    let full = full(&served);
    println!("\n# oversubscribed: lion 4 KiB, 3 MiB, {SMALL}×{SMALL}, {CYCLES} cycles, loopback");
    println!(
        "{:<24} {:>6} {:>9} {:>11} {:>11} {:>7} {:>8} {:>6} {:>9} {:>6}",
        "variant",
        "slots",
        "MB recv",
        "MB last100",
        "MB resident",
        "ratio",
        "dropped",
        "bias",
        "conv cyc",
        "exact"
    );
    for v in [VARIANTS[0], VARIANTS[2]] {
        let core = CoreConfig {
            policy: v.policy,
            sampling: v.sampling,
            deep_push: v.deep_push,
            adjust_bias: v.adjust_bias,
            prefetch_below: v.prefetch_below,
            look_past: v.look_past,
            budget_bytes: 3 << 20,
            ..CoreConfig::default()
        };
        let unit_camera = CameraPath::Static.camera(0, &SceneFrame::UNIT, SEED, SMALL, SMALL);
        let mut session = connect(runtime, &served, served.server.quic_addr, core, unit_camera);
        let frame = *session.core().frame();
        let camera = CameraPath::Static.camera(0, &frame, SEED, SMALL, SMALL);
        let mut records = Vec::new();
        for _ in 0..CYCLES {
            records.push(
                session
                    .step(&camera, RenderMode::Skip, None)
                    .unwrap()
                    .record,
            );
        }
        let image = session.render(&camera).unwrap();
        let slots = session.core().slots();
        let resident: u64 = (0..slots.capacity())
            .filter_map(|s| slots.treelet_in(s))
            .map(|id| served.wire_bytes[id.0 as usize])
            .sum();
        let capacity = slots.capacity();
        let converged = session.converged_at();
        session.close(runtime.handle());
        let bias = records.last().unwrap().lod_bias;
        let reference = cpu_render_at(&full, &frame, &camera, bias);
        let received: u64 = records.iter().map(|r| r.bytes_received).sum();
        let tail: u64 = records[CYCLES - 100..]
            .iter()
            .map(|r| r.bytes_received)
            .sum();
        println!(
            "{:<24} {:>6} {:>9.3} {:>11.3} {:>11.3} {:>7.2} {:>8} {:>6.3} {:>9} {:>6}",
            v.name,
            capacity,
            received as f64 / 1e6,
            tail as f64 / 1e6,
            resident as f64 / 1e6,
            received as f64 / resident.max(1) as f64,
            records.iter().map(|r| r.dropped).sum::<u32>(),
            bias,
            converged.map_or("-".into(), |c| c.to_string()),
            image == reference
        );
        let report = RunReport {
            meta: RunMeta {
                scene: "lion".into(),
                width: SMALL,
                height: SMALL,
                budget_mib: 3.0,
                camera_path: "static".into(),
                ..RunMeta::default()
            },
            records,
            events: Vec::new(),
        };
        let name = v.name.split(&[' ', ':'][..]).next().unwrap_or("run");
        report
            .write_csv(&out.join(format!("oversubscribed-{name}.csv")))
            .unwrap();
    }
}

/// Rows of [`progress_table`], seconds apart.
const PROGRESS_STEP: f64 = 0.05;

/// The lines `ARBOR_REFINE_TIMELINE=2` prints under a row.
fn progress_table(rows: &[Progress]) -> String {
    let mb = |b: u64| b as f64 / 1e6;
    let mut out = String::from(
        "\n      t s | needed: unnamed named  sent acked | MB sent need / not | MB acked need / not",
    );
    for p in rows {
        out += &format!(
            "\n    {:>5.2} | {:>15} {:>5} {:>5} {:>5} | {:>13.2} / {:<4.2} | {:>14.2} / {:<4.2}",
            p.at,
            p.unnamed,
            p.named,
            p.sent,
            p.acked,
            mb(p.sent_bytes.0),
            mb(p.sent_bytes.1),
            mb(p.acked_bytes.0),
            mb(p.acked_bytes.1)
        );
    }
    out
}
