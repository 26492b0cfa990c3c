//! Serving the imported scene with the real `arbor-server serve` (its own process) and
//! streaming one 1024×768 view into a 64 MiB slot buffer with the real headless client in this
//! process, until the view converges exactly; three times from a server with visible cuts on
//! (the default) and three times from one with them off (`visibility_grid = 0`), the first of
//! each from a fresh server. Figures per view: time to converge, cycles, treelets and bytes
//! received, and the server's CPU time for it (user + system of its process, `/proc/PID/stat`);
//! then the client's peak RSS (this process's `VmHWM`, against its RSS before the runs).
//!
//! With `ARBOR_SCALE_RESTART=N`, then N rounds of a restart, the server confined to a memory
//! cgroup smaller than the pool: a server serves one view and is stopped (SIGTERM), the page
//! cache is dropped, and the first view from its successor (the same data directory, so the
//! hot-page list the first left) is timed, in turns with the list removed before the restart.
//!
//! Unless `ARBOR_SCALE_CHECK=0`, then views streamed while the same server checks the scene
//! (`arbor-server verify --server`, the daemon's live check), between a view before and one
//! after: the check's time, and the server's RSS before, after and at its peak. Unless
//! `ARBOR_SCALE_COPY=0`, the same while a fresh server copies its pool into its data directory
//! (`arbor-server copy --server`, the daemon's live copy). `ARBOR_SCALE_JOB_RATE=RATE` gives
//! those servers `--background-read-rate RATE` (`20MB`); `ARBOR_SCALE_JOB_MEMORY_MIB=N` starts
//! them in a memory cgroup of N MiB (root, cgroup v1), the page cache dropped first;
//! `ARBOR_SCALE_JOB_SECONDS=N` stops the job after N s (the CLI interrupted, which cancels it);
//! `ARBOR_SCALE_JOB_COLD_VIEWS=1` drops the page cache before each timed view (root);
//! `ARBOR_SCALE_JOB_CONFIG=TOML` gives them these config lines (`message_cache_bytes = 0`,
//! `pool_cache_bytes = 1048576`: the server's own caches out of the way, so each view reads the
//! pool). `ARBOR_SCALE_READ_BPS` holds their disk to bytes a second.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use arbor_client_core::analysis::AnalysisConfig;
use arbor_client_core::camera::CameraPath;
use arbor_client_core::cycle::CoreConfig;
use arbor_client_net::{ClientConfig, ServerUrl, Trust};
use arbor_client_session::headless::{HeadlessConfig, run_headless};

/// Views streamed from each server.
const VIEWS: usize = 3;
/// The client's slot budget.
const BUDGET: u64 = 64 << 20;

fn status_mib(field: &str) -> f64 {
    process_status_mib("self", field)
}

/// A field of `/proc/{process}/status` in MiB (0 when missing).
fn process_status_mib(process: &str, field: &str) -> f64 {
    std::fs::read_to_string(format!("/proc/{process}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix(field))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        })
        .map_or(0.0, |kib| kib / 1024.0)
}

/// Where cgroup v1 keeps its block I/O controller.
const BLKIO_CGROUPS: &str = "/sys/fs/cgroup/blkio";

/// The whole disk holding `path`, as `MAJOR:MINOR` (the parent of a partition: the block I/O
/// limits apply to disks).
fn disk_of(path: &Path) -> String {
    use std::os::unix::fs::MetadataExt;
    let dev = std::fs::metadata(path).unwrap().dev();
    let major = ((dev >> 32) & !0xfff) | ((dev >> 8) & 0xfff);
    let minor = ((dev >> 12) & !0xff) | (dev & 0xff);
    let sys = Path::new("/sys/dev/block").join(format!("{major}:{minor}"));
    let disk = if sys.join("partition").exists() {
        sys.join("../dev")
    } else {
        sys.join("dev")
    };
    std::fs::read_to_string(&disk)
        .unwrap_or_else(|e| panic!("ARBOR_SCALE_READ_*: reading {}: {e}", disk.display()))
        .trim()
        .to_owned()
}

/// `ARBOR_SCALE_READ_IOPS=N` and/or `ARBOR_SCALE_READ_BPS=B`: a fresh block I/O cgroup that
/// holds reads of the pool's disk to N a second (cloud block storage past its burst) and/or B
/// bytes a second (a throughput baseline), for the next server to start in, and the page cache
/// dropped, so the pool (and sled's open) is read from that disk. Needs root and cgroup v1's
/// blkio controller; says so loudly when either is missing. Returns the cgroup (removed with
/// the server).
fn throttled_reads(pool: &Path) -> Option<std::path::PathBuf> {
    static NEXT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let limit = |knob: &str| {
        std::env::var(knob).ok().map(|v| {
            v.parse::<u64>()
                .unwrap_or_else(|_| panic!("{knob} is a whole number a second, not {v:?}"))
        })
    };
    let limits: Vec<(&str, &str, u64)> = [
        ("ARBOR_SCALE_READ_IOPS", "blkio.throttle.read_iops_device"),
        ("ARBOR_SCALE_READ_BPS", "blkio.throttle.read_bps_device"),
    ]
    .into_iter()
    .filter_map(|(knob, file)| limit(knob).map(|l| (knob, file, l)))
    .collect();
    let &(knob, file, first) = limits.first()?;
    let disk = disk_of(pool);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let cgroup = fresh_cgroup(
        knob,
        BLKIO_CGROUPS,
        &n.to_string(),
        file,
        format!("{disk} {first}"),
    );
    for &(knob, file, value) in &limits[1..] {
        let path = cgroup.join(file);
        let value = format!("{disk} {value}");
        std::fs::write(&path, &value)
            .unwrap_or_else(|e| panic!("{knob}: writing {value} to {}: {e}", path.display()));
    }
    drop_page_cache(knob);
    Some(cgroup)
}

/// A fresh cgroup (v1) under the controller at `root`, named for this process and `tag`, with
/// `value` written to its `limit` file; `knob` (the setting that asked for it) names it in the
/// loud failure when root or the controller is missing.
fn fresh_cgroup(
    knob: &str,
    root: &str,
    tag: &str,
    limit: &str,
    value: String,
) -> std::path::PathBuf {
    let cgroup = Path::new(root).join(format!("arbor-scale-{}-{tag}", std::process::id()));
    std::fs::create_dir(&cgroup).unwrap_or_else(|e| {
        panic!(
            "{knob} needs root and cgroup v1's controller at {root}: creating {}: {e}",
            cgroup.display()
        )
    });
    let file = cgroup.join(limit);
    std::fs::write(&file, &value)
        .unwrap_or_else(|e| panic!("{knob}: writing {value} to {}: {e}", file.display()));
    cgroup
}

/// Syncs and drops the page cache (root), so what follows is read from the disk; `why` names
/// the setting that asked for it in the failure.
fn drop_page_cache(why: &str) {
    let synced = Command::new("sync").status().is_ok_and(|s| s.success());
    assert!(synced, "sync failed");
    std::fs::write("/proc/sys/vm/drop_caches", "3")
        .unwrap_or_else(|e| panic!("{why}: dropping the page cache (root): {e}"));
}

/// A running `arbor-server serve` on loopback.
struct Server {
    child: Child,
    /// From its start to its first line saying where it serves (the pool opened).
    serving_after: Duration,
    /// The block I/O cgroup it runs in (`ARBOR_SCALE_READ_IOPS`/`_BPS`), removed once it ended.
    throttled: Option<std::path::PathBuf>,
    url: ServerUrl,
    fingerprint: String,
    /// Its admin API (`http://127.0.0.1:PORT`, loopback) and the file holding its token.
    admin: String,
    admin_token_file: String,
    /// Kept open: a server (before stop 49) whose stdout closed before its last serving line
    /// stopped serving.
    _stdout: std::io::Lines<BufReader<std::process::ChildStdout>>,
    /// Its data directory when it made its own (not a restart's).
    _state: Option<tempfile::TempDir>,
    /// The memory cgroup it runs in, removed once it ended.
    confined: Option<std::path::PathBuf>,
}

impl Server {
    /// Starts serving `pool`, with `config` (TOML) when given; scenes are public either way.
    fn start(server_bin: &str, pool: &Path, scene: &str, config: Option<&str>) -> Server {
        Server::start_with(server_bin, pool, scene, config, &[])
    }

    /// [`Server::start`] with more arguments for `serve`.
    fn start_with(
        server_bin: &str,
        pool: &Path,
        scene: &str,
        config: Option<&str>,
        args: &[String],
    ) -> Server {
        let state = tempfile::tempdir().unwrap();
        let mut server =
            Server::start_in(server_bin, pool, scene, config, state.path(), None, args);
        server._state = Some(state);
        server
    }

    /// A server with scenes public, on the data directory `state`, in the memory cgroup (v1)
    /// `cgroup` from its first instruction.
    fn start_confined(
        server_bin: &str,
        pool: &Path,
        scene: &str,
        config: Option<&str>,
        (state, cgroup): (&Path, &Path),
        args: &[String],
    ) -> Server {
        Server::start_in(server_bin, pool, scene, config, state, Some(cgroup), args)
    }

    /// [`Server::start_with`] with the data directory `state`, in the memory cgroup (v1)
    /// `confined` from its first instruction when given (a shell enters it, then runs the
    /// server).
    fn start_in(
        server_bin: &str,
        pool: &Path,
        scene: &str,
        config: Option<&str>,
        state: &Path,
        confined: Option<&Path>,
        args: &[String],
    ) -> Server {
        let throttled = throttled_reads(pool);
        // The server enters its cgroups before its first instruction (a shell enters them,
        // then runs it): sled's open is read under the same limits as its treelets.
        let cgroups: Vec<&Path> = [throttled.as_deref(), confined]
            .into_iter()
            .flatten()
            .collect();
        let mut cmd = if cgroups.is_empty() {
            Command::new(server_bin)
        } else {
            let mut sh = Command::new("sh");
            sh.args([
                "-c",
                "IFS=:; for g in $0; do echo $$ > \"$g/cgroup.procs\" || exit 1; done; exec \"$@\"",
            ])
            .arg(
                cgroups
                    .iter()
                    .map(|g| g.display().to_string())
                    .collect::<Vec<_>>()
                    .join(":"),
            )
            .arg(server_bin);
            sh
        };
        let spawned = std::time::Instant::now();
        cmd.args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--admin",
            "127.0.0.1:0",
            "--db",
        ])
        .arg(pool)
        .arg("--data-dir")
        .arg(state);
        let copies = state.join("copies");
        std::fs::create_dir_all(&copies).expect("making the copy root");
        cmd.arg("--copy-root").arg(copies).args(args);
        if let Some(config) = config {
            let file = state.join("serve.toml");
            std::fs::write(&file, format!("default_access = \"public\"\n{config}\n")).unwrap();
            cmd.arg("--config").arg(file);
        }
        let stderr = match std::env::var_os("ARBOR_SCALE_SERVER_LOG") {
            Some(path) => Stdio::from(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(&path)
                    .expect("ARBOR_SCALE_SERVER_LOG: opening the file"),
            ),
            None => Stdio::null(),
        };
        let mut child = cmd
            .stdout(Stdio::piped())
            .stderr(stderr)
            .spawn()
            .expect("starting arbor-server serve");
        let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let (mut addr, mut fingerprint, mut admin, mut admin_token_file) = (None, None, None, None);
        let mut serving_after = Duration::ZERO;
        while addr.is_none() || fingerprint.is_none() || admin_token_file.is_none() {
            let line = lines.next().expect("serve output").unwrap();
            if let Some(a) = line.strip_prefix("quic ") {
                addr = Some(a.parse::<std::net::SocketAddr>().unwrap());
                serving_after = spawned.elapsed();
            }
            if let Some(f) = line.strip_prefix("fingerprint ") {
                fingerprint = Some(f.to_owned());
            }
            if let Some(a) = line.strip_prefix("admin ") {
                admin = Some(format!("http://{a}"));
            }
            if let Some(f) = line.strip_prefix("admin-token-file ") {
                admin_token_file = Some(f.to_owned());
            }
        }
        let addr = addr.unwrap();
        Server {
            child,
            serving_after,
            throttled,
            url: ServerUrl {
                host: addr.ip().to_string(),
                port: addr.port(),
                scene: scene.to_owned(),
            },
            fingerprint: fingerprint.unwrap(),
            admin: admin.expect("the server printed its admin address"),
            admin_token_file: admin_token_file.unwrap(),
            _stdout: lines,
            _state: None,
            confined: confined.map(Path::to_owned),
        }
    }

    /// Stops the server as its operator would (SIGTERM), waiting until it exited: it saves its
    /// state (the hot-page list) on the way out.
    fn stop(mut self) {
        let sent = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .is_ok_and(|s| s.success());
        assert!(sent, "kill -TERM {} failed", self.child.id());
        let status = self.child.wait().expect("waiting for the server");
        assert!(status.success(), "the server ended with {status}");
    }

    /// Its admin API's `/metrics` text (`curl`, with its token).
    fn metrics(&self) -> String {
        let token = std::fs::read_to_string(&self.admin_token_file).expect("the admin token");
        let out = Command::new("curl")
            .args(["-sf", "-H"])
            .arg(format!("Authorization: Bearer {}", token.trim()))
            .arg(format!("{}/metrics", self.admin))
            .output()
            .expect("curl for the server's /metrics");
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// The server process's user + system CPU time so far, seconds (clock ticks of 1/100 s).
    fn cpu_seconds(&self) -> f64 {
        let f = super::monitor::stat_fields(&self.child.id().to_string());
        // Fields 14 and 15 (utime, stime).
        (f.get(11).copied().unwrap_or(0) + f.get(12).copied().unwrap_or(0)) as f64 / 100.0
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        for cgroup in [&self.throttled, &self.confined].into_iter().flatten() {
            let _ = std::fs::remove_dir(cgroup);
        }
    }
}

/// Streams the view from `server` until it converges; prints one line of figures and returns
/// the seconds to exact convergence (`None`: not within the client's cycles).
fn stream_view(server: &Server, what: &str, runtime: &tokio::runtime::Runtime) -> Option<f64> {
    let config = HeadlessConfig {
        client: ClientConfig::new(
            server.url.clone(),
            Trust::Fingerprint(server.fingerprint.clone()),
        ),
        core: CoreConfig {
            analysis: AnalysisConfig::default(),
            budget_bytes: BUDGET,
            ..CoreConfig::default()
        },
        camera_path: CameraPath::Static,
        seed: 7,
        width: 1024,
        height: 768,
        cycles: 3000,
        // Never reached by a cycle that renders (25–40 ms here); a client waiting for the disk
        // would otherwise spin through its 3,000 cycles in 3 s.
        min_cycle: Duration::from_millis(5),
        connect_timeout: Duration::from_secs(30),
        reference: None,
        until_converged: true,
        render_every: 50,
        device_replacements: 0,
    };
    let cpu = server.cpu_seconds();
    let run = run_headless(config, runtime.handle()).expect("headless run");
    let cpu = server.cpu_seconds() - cpu;
    let s = run.report.summary();
    let converged = run
        .converged_at
        .and_then(|c| run.report.records.get(c as usize))
        .map(|r| r.time_s);
    println!(
        "  {what}: {} in {} cycles ({:.1} s); {} treelets, {:.1} MiB received; slots peak {} of {}; server CPU {cpu:.2} s",
        match converged {
            Some(t) => format!("converged exactly at {t:.2} s"),
            None => "NOT converged".into(),
        },
        s.cycles,
        s.seconds,
        s.treelets_received,
        s.bytes_received as f64 / f64::from(1 << 20),
        run.peak_slots,
        run.capacity
    );
    converged
}

pub fn serve_and_stream(server_bin: &str, pool: &Path, scene: &str) {
    let rss_before = status_mib("VmRSS:");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let first_view_after = Duration::from_millis(
        std::env::var("ARBOR_SCALE_FIRST_VIEW_AFTER_MS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(0),
    );
    println!();
    println!(
        "stream 1024x768, budget {} MiB, loopback; {VIEWS} views per server, the first from a fresh one {} ms after it started:",
        BUDGET >> 20,
        first_view_after.as_millis()
    );
    // `ARBOR_SCALE_PLAIN_VIEWS=0`: only the jobs' and restarts' views below.
    let plain = std::env::var("ARBOR_SCALE_PLAIN_VIEWS").as_deref() != Ok("0");
    for (servers, config) in [
        ("visible cuts on (the default)", None),
        (
            "visible cuts off (visibility_grid = 0)",
            Some("visibility_grid = 0"),
        ),
    ]
    .into_iter()
    .filter(|_| plain)
    {
        let server = Server::start(server_bin, pool, scene, config);
        println!(
            " {servers}: serving {:.2} s after its start",
            server.serving_after.as_secs_f64()
        );
        if !first_view_after.is_zero() {
            std::thread::sleep(first_view_after);
        }
        for view in 0..VIEWS {
            let what = if view == 0 { "first view" } else { "again" };
            stream_view(&server, what, &runtime);
        }
    }
    if std::env::var("ARBOR_SCALE_CHECK").as_deref() != Ok("0") {
        job_while_streaming(server_bin, pool, scene, &runtime, AdminJob::Check);
    }
    if std::env::var("ARBOR_SCALE_COPY").as_deref() != Ok("0") {
        job_while_streaming(server_bin, pool, scene, &runtime, AdminJob::Copy);
    }
    let rounds = std::env::var("ARBOR_SCALE_RESTART").ok().map_or(0, |v| {
        v.parse::<u32>()
            .expect("ARBOR_SCALE_RESTART is a number of rounds")
    });
    if rounds > 0 {
        restart_and_stream(server_bin, pool, scene, rounds, &runtime);
    }
    println!(
        "client RSS: peak {:.1} MiB (before the runs {:.1} MiB; slot buffer {:.1} MiB)",
        status_mib("VmHWM:"),
        rss_before,
        BUDGET as f64 / f64::from(1 << 20)
    );
}

/// Background work a server does while it serves, asked for through its admin API.
#[derive(Clone, Copy)]
enum AdminJob {
    /// `verify --server`: the live check of the scene.
    Check,
    /// `copy --server`: the live copy of the pool into the server's copy root.
    Copy,
}

impl AdminJob {
    fn name(self) -> &'static str {
        match self {
            AdminJob::Check => "check",
            AdminJob::Copy => "copy",
        }
    }

    /// The CLI's arguments that ask `server` for it.
    fn args(self, server: &Server, scene: &str) -> Vec<String> {
        let mut args: Vec<String> = match self {
            AdminJob::Check => vec!["verify".into(), "--scene".into(), scene.into()],
            AdminJob::Copy => vec!["copy".into(), "--to".into(), format!("{scene}-copy")],
        };
        args.extend([
            "--quiet".into(),
            "--server".into(),
            server.admin.clone(),
            "--token-file".into(),
            server.admin_token_file.clone(),
        ]);
        args
    }
}

/// A view before, during and after the server's live check of the scene or live copy of its
/// pool (asked for by the CLI, as its operator would), from a fresh server: the job's time and
/// the server's memory around it.
fn job_while_streaming(
    server_bin: &str,
    pool: &Path,
    scene: &str,
    runtime: &tokio::runtime::Runtime,
    job: AdminJob,
) {
    let name = job.name();
    let rate = std::env::var("ARBOR_SCALE_JOB_RATE")
        .ok()
        .filter(|r| !r.is_empty());
    let args: Vec<String> = rate
        .iter()
        .flat_map(|r| ["--background-read-rate".to_owned(), r.clone()])
        .collect();
    let confined_mib = std::env::var("ARBOR_SCALE_JOB_MEMORY_MIB")
        .ok()
        .map(|v| v.parse::<u64>().expect("ARBOR_SCALE_JOB_MEMORY_MIB is MiB"));
    let bound = std::env::var("ARBOR_SCALE_JOB_SECONDS")
        .ok()
        .map(|v| Duration::from_secs(v.parse().expect("ARBOR_SCALE_JOB_SECONDS is seconds")));
    // Server settings for the job's server (`message_cache_bytes = 0` with a small
    // `pool_cache_bytes`: every view reads the pool, a client looking where no one looked).
    let config = std::env::var("ARBOR_SCALE_JOB_CONFIG")
        .ok()
        .filter(|c| !c.is_empty());
    let server = match confined_mib {
        None => Server::start_with(server_bin, pool, scene, config.as_deref(), &args),
        Some(mib) => {
            let state = tempfile::tempdir().unwrap();
            let cgroup = memory_cgroup(mib, &format!("job-{name}"));
            drop_page_cache("ARBOR_SCALE_JOB_MEMORY_MIB");
            let mut server = Server::start_confined(
                server_bin,
                pool,
                scene,
                config.as_deref(),
                (state.path(), &cgroup),
                &args,
            );
            server._state = Some(state);
            server
        }
    };
    let pid = server.child.id().to_string();
    println!(
        " a live {name} ({} --server) on a fresh server with visible cuts on{}, background reads \
         at most {}{}:",
        job.args(&server, scene)[0],
        confined_mib.map_or(String::new(), |m| format!(" in a {m} MiB memory cgroup")),
        rate.as_deref().unwrap_or("off"),
        bound.map_or(String::new(), |b| format!(
            ", the {name} stopped after {} s",
            b.as_secs()
        ))
    );
    stream_view(&server, "first view", runtime);
    let cold = std::env::var("ARBOR_SCALE_JOB_COLD_VIEWS").as_deref() == Ok("1");
    // Each timed view from the disk (the page cache dropped first): a client looking where no
    // one looked, whose reads meet the job's.
    let view = |what: &str| {
        if cold {
            drop_page_cache("ARBOR_SCALE_JOB_COLD_VIEWS");
        }
        stream_view(&server, what, runtime)
    };
    let before = view(&format!("before the {name}"));
    let rss_before = process_status_mib(&pid, "VmRSS:");
    let started = std::time::Instant::now();
    let mut running = Command::new(server_bin)
        .args(job.args(&server, scene))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("starting the {name}: {e}"));
    // Let the job get going, then stream views while it runs (at least one).
    std::thread::sleep(Duration::from_millis(500));
    let mut during = Vec::new();
    let mut stopped = false;
    loop {
        during.push(view(&format!("during the {name}")).unwrap_or(f64::INFINITY));
        if running.try_wait().expect("the job's status").is_some() {
            break;
        }
        if bound.is_some_and(|b| started.elapsed() >= b) {
            // The CLI cancels the job on the daemon when interrupted.
            let sent = Command::new("kill")
                .args(["-INT", &running.id().to_string()])
                .status()
                .is_ok_and(|s| s.success());
            assert!(sent, "kill -INT {} failed", running.id());
            stopped = true;
            break;
        }
    }
    let out = running.wait_with_output().expect("waiting for the job");
    let job_s = started.elapsed().as_secs_f64();
    let metrics = server.metrics();
    let sample = |prefix: &str| {
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(prefix))
            .and_then(|v| v.trim().parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    println!(
        "  background reads: {:.0} MB read, {:.1} s waited for the rate{}",
        sample("arbor_pool_background_read_bytes_total ") / 1e6,
        sample("arbor_pool_background_wait_seconds_total "),
        if stopped {
            " (the job stopped, as asked)"
        } else {
            ""
        }
    );
    assert!(
        stopped || out.status.success(),
        "the live {name} failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    println!(
        "  the {name}: {job_s:.1} s, {}; server RSS {rss_before:.0} MiB before, {:.0} MiB after, peak {:.0} MiB",
        String::from_utf8_lossy(&out.stdout)
            .trim()
            .replace('\n', "; "),
        process_status_mib(&pid, "VmRSS:"),
        process_status_mib(&pid, "VmHWM:")
    );
    let after = view(&format!("after the {name}"));
    // Views that did not converge count as the slowest.
    during.sort_by(f64::total_cmp);
    let seconds =
        |t: Option<f64>| t.map_or_else(|| "NOT converged".into(), |t| format!("{t:.2} s"));
    println!(
        "  views converged in {} before the {name}, {} after; while it ran: median {} of {} views (its threads count in the server CPU above)",
        seconds(before),
        seconds(after),
        seconds(
            during
                .get(during.len() / 2)
                .copied()
                .filter(|t| t.is_finite())
        ),
        during.len()
    );
}

/// Where cgroup v1 keeps its memory controller.
const MEMORY_CGROUPS: &str = "/sys/fs/cgroup/memory";

/// A fresh memory cgroup (v1) limited to `mib` MiB; needs root, says so loudly otherwise.
fn memory_cgroup(mib: u64, tag: &str) -> std::path::PathBuf {
    fresh_cgroup(
        "ARBOR_SCALE_RESTART",
        MEMORY_CGROUPS,
        tag,
        "memory.limit_in_bytes",
        (mib << 20).to_string(),
    )
}

/// `ARBOR_SCALE_RESTART=N`: N rounds of a restarted server, with and without the hot-page list
/// its predecessor left, in turns. The servers run in a memory cgroup of
/// `ARBOR_SCALE_RESTART_MEMORY_MIB` (default 1024, below the city's 1.47 GB pool, so the whole
/// pool is never read at start); the first view comes `ARBOR_SCALE_RESTART_VIEW_AFTER_MS`
/// (default 10,000) after the restart.
fn restart_and_stream(
    server_bin: &str,
    pool: &Path,
    scene: &str,
    rounds: u32,
    runtime: &tokio::runtime::Runtime,
) {
    let mib: u64 = std::env::var("ARBOR_SCALE_RESTART_MEMORY_MIB")
        .ok()
        .map_or(1024, |v| {
            v.parse().expect("ARBOR_SCALE_RESTART_MEMORY_MIB is MiB")
        });
    let after = Duration::from_millis(
        std::env::var("ARBOR_SCALE_RESTART_VIEW_AFTER_MS")
            .ok()
            .map_or(10_000, |v| {
                v.parse().expect("ARBOR_SCALE_RESTART_VIEW_AFTER_MS is ms")
            }),
    );
    println!();
    println!(
        "restart: the server in a {mib} MiB memory cgroup, one view, SIGTERM, page cache dropped, \
         restarted on the same data directory; its first view {} ms after it serves again:",
        after.as_millis()
    );
    let mut times: [Vec<Option<f64>>; 2] = [Vec::new(), Vec::new()];
    for round in 0..rounds {
        for (i, keep) in [true, false].into_iter().enumerate() {
            let state = tempfile::tempdir().unwrap();
            let cgroup = memory_cgroup(mib, &format!("{round}-{i}"));
            let before =
                Server::start_confined(server_bin, pool, scene, None, (state.path(), &cgroup), &[]);
            stream_view(&before, "  before the restart", runtime);
            before.stop();
            let list = state.path().join("pool-hot-pages.json");
            let saved = std::fs::metadata(&list).map_or(0, |m| m.len());
            assert!(
                saved > 0,
                "the stopped server left no hot-page list at {}",
                list.display()
            );
            if !keep {
                std::fs::remove_file(&list).unwrap();
            }
            drop_page_cache("ARBOR_SCALE_RESTART");
            let cgroup = memory_cgroup(mib, &format!("{round}-{i}-after"));
            let after_server =
                Server::start_confined(server_bin, pool, scene, None, (state.path(), &cgroup), &[]);
            println!(
                "  restarted: serving {:.2} s after its start",
                after_server.serving_after.as_secs_f64()
            );
            std::thread::sleep(after);
            let what = if keep {
                "  restarted with the hot-page list"
            } else {
                "  restarted without it (removed)"
            };
            times[i].push(stream_view(&after_server, what, runtime));
        }
    }
    let show = |t: &[Option<f64>]| {
        t.iter()
            .map(|t| t.map_or("NOT".to_string(), |t| format!("{t:.2}")))
            .collect::<Vec<_>>()
            .join(", ")
    };
    println!(
        "restart, first view seconds: with the list {} | without {}",
        show(&times[0]),
        show(&times[1])
    );
}
