//! Soak: 64 clients on loopback against a real `arbor-server` process for 10 minutes
//! (`ARBOR_SOAK_SECS` to change), each replacing its request list every 100–300 ms with a new
//! random part of lion (4 KiB treelets; or of the pool `ARBOR_SOAK_POOL` names): 0 errors (no
//! disconnect, no undecodable or unasked treelet), the server's RSS flat (the slope of its
//! per-minute medians over the second half, after warm-up, is printed), and the p50/p99 latency
//! from sending a list to the first treelet of it arriving. The server's cache figures from
//! `/metrics` are printed at the end.
//!
//! Two soaks: plain request lists, and deep lists whose clients rest on a random view of the
//! scene for two to four lists before they move on, so the server casts visible cuts for them
//! (coarse and fine, through its node cache, with the fine-cut gate and the prefetch set
//! apart) while it serves everyone; the server's cut figures from `/metrics` are printed.
//!
//! Ignored (10 minutes each; `.config/nextest.toml` gives each 16 before it is stopped):
//! `cargo build -p arbor-server && cargo nextest run -p arbor-tests --test soak --run-ignored only --no-capture`
//!
//! `ARBOR_SOAK_POOL=DIR` serves an existing pool in place instead of lion (`ARBOR_SOAK_SCENE`
//! names its scene when it holds several): the scale bench's city (`target/scale/pool`, 1.27 M
//! treelets) makes nearly every treelet of a list a miss of the server's message cache and a
//! read of the pool. Its deep soak is a worst case for the push plans: a list's random
//! treelets have nothing to do with its random view, so each plan looks up the shapes of
//! treelets spread over the whole scene, most of them misses of the shape cache.
//! `ARBOR_SOAK_CONFIG=FILE` hands the server a configuration file, to compare its settings
//! under the same load (both paths absolute or relative to the workspace root).
//!
//! The server's log is kept in `target/soak/server-plain.log` or `server-resting.log`: a client
//! counts a closed connection as an error, and only the server's log says why it closed it.
//!
//! `ARBOR_SOAK_MEMORY_LIMIT=BYTES` (root, cgroup v1) confines the server's memory, page cache
//! included, so that a pool larger than the rest is read from disk (see [`confine`]):
//! `ARBOR_SOAK_POOL=target/scale/pool ARBOR_SOAK_MEMORY_LIMIT=600000000 ARBOR_SOAK_SECS=40 …`.

use std::collections::HashSet;
use std::io::{BufRead as _, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use arbor_client_net::{ClientConfig, ClientEvent, ServerUrl, TreeletClient, Trust};
use arbor_proto::rng::SplitMix64;
use arbor_proto::wire::ViewHint;
use arbor_proto::{SceneDescription, TreeletId};
use arbor_server::octree::BuildOptions;
use arbor_server::pool::Pool;
use arbor_tests::support::{build_file, copy_dir};
use tokio::sync::Mutex;

const CLIENTS: usize = 64;
/// Minutes of samples the RSS slope needs: the first minutes are warm-up.
const MIN_FLAT_MINUTES: usize = 4;
const LIST_ITEMS: u32 = 200;

fn server_binary() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let bin = exe
        .parent()
        .and_then(Path::parent)
        .unwrap()
        .join("arbor-server");
    assert!(
        bin.exists(),
        "{} is missing: build it first (cargo build [--release] -p arbor-server)",
        bin.display()
    );
    bin
}

/// The server process, and the memory cgroup it was moved into, if any (removed once the
/// server is gone).
struct Server(Child, Option<PathBuf>);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
        if let Some(cgroup) = &self.1 {
            let _ = std::fs::remove_dir(cgroup);
        }
    }
}

/// Where cgroup v1 keeps its memory controller (the only layout this has met).
const MEMORY_CGROUPS: &str = "/sys/fs/cgroup/memory";

/// `ARBOR_SOAK_MEMORY_LIMIT=BYTES`: the server is moved into a memory cgroup of that limit and
/// the page cache is dropped, so a pool larger than what is left is read from disk (stop 66:
/// the city's 1.47 GB pool with 600 MB for the plain soak, 900 MB for the resting one, whose
/// server holds about 550 MB). Needs root and cgroup v1's memory controller; says so loudly
/// when either is missing.
fn confine(pid: u32) -> Option<PathBuf> {
    let limit: u64 = std::env::var("ARBOR_SOAK_MEMORY_LIMIT")
        .ok()?
        .parse()
        .expect("ARBOR_SOAK_MEMORY_LIMIT is a number of bytes");
    let cgroup = Path::new(MEMORY_CGROUPS).join(format!("arbor-soak-{pid}"));
    let write = |file: &str, value: String| {
        std::fs::write(cgroup.join(file), &value).unwrap_or_else(|e| {
            panic!(
                "ARBOR_SOAK_MEMORY_LIMIT: writing {value} to {}: {e}",
                cgroup.join(file).display()
            )
        })
    };
    std::fs::create_dir(&cgroup).unwrap_or_else(|e| {
        panic!(
            "ARBOR_SOAK_MEMORY_LIMIT needs root and cgroup v1's memory controller at \
             {MEMORY_CGROUPS}: creating {}: {e}",
            cgroup.display()
        )
    });
    write("memory.limit_in_bytes", limit.to_string());
    write("cgroup.procs", pid.to_string());
    // What the server's start read of the pool is cached outside the cgroup: dropped.
    let synced = Command::new("sync").status().is_ok_and(|s| s.success());
    assert!(synced, "sync failed");
    std::fs::write("/proc/sys/vm/drop_caches", "3").expect("dropping the page cache");
    eprintln!(
        "soak: the server is confined to {limit} bytes ({}), the page cache dropped",
        cgroup.display()
    );
    Some(cgroup)
}

/// Resident set of a process, KiB.
fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .expect("VmRSS in /proc/PID/status")
}

/// Seconds between RSS samples.
const SAMPLE_SECS: u64 = 5;

/// Fewest samples a minute needs to have a median: half a minute's. The last sample, taken as
/// the run ends, starts a minute of its own, and alone it is exactly where one sample happened
/// to fall (a stop-60 run: every minute's median 169–183 MB, the lone last sample 215 MB, taken
/// while visible cuts held their buffers).
const MIN_SAMPLES_PER_MINUTE: usize = (60 / SAMPLE_SECS as usize) / 2;

/// The median of each minute's `(seconds, KiB)` samples, at the minute's middle: a resident
/// set that swings with buffers taken and given back (a visible cut holds 32 MiB while it is
/// cast) is judged by its typical level, not by where each sample happened to fall. Minutes
/// with fewer than [`MIN_SAMPLES_PER_MINUTE`] samples are left out.
fn per_minute_medians(samples: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut minutes: Vec<Vec<f64>> = Vec::new();
    for &(t, kib) in samples {
        let m = (t / 60.0) as usize;
        if minutes.len() <= m {
            minutes.resize(m + 1, Vec::new());
        }
        minutes[m].push(kib);
    }
    minutes
        .into_iter()
        .enumerate()
        .filter(|(_, v)| v.len() >= MIN_SAMPLES_PER_MINUTE)
        .map(|(m, mut v)| {
            v.sort_by(f64::total_cmp);
            (m as f64 * 60.0 + 30.0, v[v.len() / 2])
        })
        .collect()
}

/// Least-squares slope of `(seconds, KiB)` samples, KiB per minute.
fn slope_per_minute(samples: &[(f64, f64)]) -> f64 {
    let n = samples.len() as f64;
    let (mx, my) = samples
        .iter()
        .fold((0.0, 0.0), |a, s| (a.0 + s.0 / n, a.1 + s.1 / n));
    let (num, den) = samples.iter().fold((0.0, 0.0), |a, s| {
        (a.0 + (s.0 - mx) * (s.1 - my), a.1 + (s.0 - mx) * (s.0 - mx))
    });
    if den == 0.0 { 0.0 } else { num / den * 60.0 }
}

#[derive(Default)]
struct Tally {
    treelets: AtomicU64,
    bytes: AtomicU64,
    lists: AtomicU64,
    errors: AtomicU64,
}

/// Lists a client of the resting-view soak sends for one view before it moves on: at least
/// two (a view named twice in a row is resting, so the server casts its cut), at most this.
const LISTS_PER_VIEW: u64 = 4;

/// A random view of `scene` for a 256² frame: from a random direction, 1.2–3 edges from the
/// centre of its cube, looking at the centre.
fn random_view(scene: &SceneDescription, rng: &mut SplitMix64) -> ViewHint {
    let dir = loop {
        let v: [f64; 3] = std::array::from_fn(|_| rng.next_f64() * 2.0 - 1.0);
        let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if (0.1..=1.0).contains(&n) {
            break v.map(|x| x / n);
        }
    };
    let distance = scene.edge * (1.2 + 1.8 * rng.next_f64());
    let eye = std::array::from_fn(|i| scene.origin[i] + 0.5 * scene.edge + dir[i] * distance);
    let forward = dir.map(|x| -x);
    // Up: the axis least along the view, made orthogonal to it.
    let axis = (0..3)
        .min_by(|&a, &b| forward[a].abs().total_cmp(&forward[b].abs()))
        .unwrap();
    let mut up = [0.0; 3];
    up[axis] = 1.0;
    let along = up[axis] * forward[axis];
    let up = std::array::from_fn::<f64, 3, _>(|i| up[i] - along * forward[i]);
    let n = up.iter().map(|x| x * x).sum::<f64>().sqrt();
    let view = ViewHint {
        eye,
        forward: forward.map(|x| x as f32),
        up: up.map(|x| (x / n) as f32),
        tan_half_fov_y: 0.5,
        aspect: 1.0,
        footprint: 1.0 / 256.0,
        free_slots: 512,
    };
    view.check().expect("a valid view");
    view
}

/// What one soak client asks for.
#[derive(Clone)]
struct Plan {
    url: ServerUrl,
    fingerprint: String,
    /// Treelets in the scene.
    treelets: u32,
    /// Deep lists resting on views, else plain lists.
    resting_views: bool,
}

/// One client: a new random list every 100–300 ms until `stop`; latencies from each list to
/// the first treelet of it. With `resting_views`, deep lists: the same random view for two to
/// [`LISTS_PER_VIEW`] lists, then another, the last quarter of each list its prefetch.
async fn client(
    plan: Plan,
    seed: u64,
    stop: Arc<AtomicBool>,
    tally: Arc<Tally>,
    latencies: Arc<Mutex<Vec<f64>>>,
) {
    let Plan {
        url,
        fingerprint,
        treelets,
        resting_views,
    } = plan;
    let config = ClientConfig::new(url, Trust::Fingerprint(fingerprint))
        .with_channels([arbor_proto::Channel::Color]);
    let mut c = TreeletClient::start(config).unwrap();
    let mut rng = SplitMix64::new(seed);
    let mut wanted: HashSet<TreeletId> = HashSet::new();
    let mut sent_at: Option<Instant> = None;
    let mut next_list = Instant::now();
    let mut mine = Vec::new();
    // The view and how many more lists name it.
    let mut view: Option<(ViewHint, u64)> = None;
    while !stop.load(Ordering::Relaxed) {
        if Instant::now() >= next_list {
            let start = rng.below(u64::from(treelets)) as u32;
            let list: Vec<(TreeletId, f32)> = (0..LIST_ITEMS)
                .map(|i| {
                    let id = (start + i * 7) % treelets;
                    (TreeletId(id), rng.next_f64() as f32 * 100.0)
                })
                .collect();
            wanted = list.iter().map(|x| x.0).collect();
            match c.scene().filter(|_| resting_views) {
                Some(scene) => {
                    let (v, left) = match view.take() {
                        Some((v, left)) if left > 0 => (v, left),
                        _ => (
                            random_view(&scene, &mut rng),
                            2 + rng.below(LISTS_PER_VIEW - 1),
                        ),
                    };
                    view = Some((v, left - 1));
                    let prefetch_from = list.len() * 3 / 4;
                    let items = list.into_iter().map(|(id, p)| (id, p, 4.0)).collect();
                    c.request_deep(items, v, prefetch_from).unwrap();
                }
                None => c.request(list).unwrap(),
            }
            tally.lists.fetch_add(1, Ordering::Relaxed);
            sent_at = Some(Instant::now());
            next_list = Instant::now() + Duration::from_millis(100 + rng.below(200));
        }
        let wait = next_list.saturating_duration_since(Instant::now());
        match tokio::time::timeout(wait, c.next_event()).await {
            Ok(Some(ClientEvent::Treelet(t))) => {
                tally.treelets.fetch_add(1, Ordering::Relaxed);
                tally
                    .bytes
                    .fetch_add(t.wire_bytes as u64, Ordering::Relaxed);
                if wanted.contains(&t.id)
                    && let Some(at) = sent_at.take()
                {
                    mine.push(at.elapsed().as_secs_f64());
                }
            }
            Ok(Some(ClientEvent::Connected(_))) => {}
            Ok(Some(ClientEvent::Disconnected { reason, .. })) => {
                eprintln!("client {seed}: {reason}");
                tally.errors.fetch_add(1, Ordering::Relaxed);
            }
            Ok(None) => {
                tally.errors.fetch_add(1, Ordering::Relaxed);
                break;
            }
            Err(_) => {}
        }
    }
    latencies.lock().await.extend(mine);
    c.close().await;
}

/// The RSS judgement itself, on samples as a run takes them: every full minute has its median,
/// the lone sample taken as the run ends has none, and a spike in one sample moves nothing.
#[test]
fn each_full_minute_has_its_median_and_a_lone_last_sample_none() {
    let mut samples: Vec<(f64, f64)> = (1..=120)
        .map(|i| (i as f64 * 5.0 + 0.01, 100_000.0 + i as f64))
        .collect();
    samples[30].1 = 900_000.0;
    samples.push((600.02, 215_000.0));
    let medians = per_minute_medians(&samples);
    assert_eq!(medians.len(), 10, "{medians:?}");
    assert!(
        medians.iter().all(|&(_, kib)| kib < 100_200.0),
        "{medians:?}"
    );
    let slope = slope_per_minute(&medians[5..]);
    assert!(
        (slope - 12.0).abs() < 0.5,
        "12 samples a minute, 1 KiB each: {slope}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "10 minutes; run with --release -- --ignored --nocapture"]
async fn sixty_four_clients_for_ten_minutes() {
    soak(false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "10 minutes; run with --release -- --ignored --nocapture"]
async fn sixty_four_clients_resting_on_views_for_ten_minutes() {
    soak(true).await;
}

/// The value of metric `name` (no labels) in the server's `/metrics`, read over the admin
/// listener with its token (cleartext: it listens on loopback).
fn metric(admin: std::net::SocketAddr, token: &str, name: &str) -> f64 {
    use std::io::{Read as _, Write as _};
    let mut s = std::net::TcpStream::connect(admin).unwrap();
    write!(
        s,
        "GET /metrics HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer {token}\r\n\
         Connection: close\r\n\r\n"
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("{name} not in /metrics"))
}

/// The pool and scene of `ARBOR_SOAK_POOL` (a pool directory, absolute or relative to the
/// workspace root, served in place: the scale bench's city, say, a scan many times the
/// server's message cache) and `ARBOR_SOAK_SCENE` (default: the pool's only scene), if set.
fn given_pool() -> Option<(PathBuf, String)> {
    let pool = workspace_path(std::env::var_os("ARBOR_SOAK_POOL")?);
    assert!(
        pool.is_dir(),
        "ARBOR_SOAK_POOL={} is not a directory",
        pool.display()
    );
    Some((pool, std::env::var("ARBOR_SOAK_SCENE").unwrap_or_default()))
}

/// `path` as given, or relative to the workspace root, where the command is typed (a test runs
/// in its crate's directory).
fn workspace_path(path: impl AsRef<Path>) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(path)
}

/// The name and treelet count of `scene` in the pool at `dir` (of its only scene when `scene` is
/// empty), read before the server opens the pool.
fn given_scene(dir: &Path, scene: &str) -> (String, u32) {
    let pool = Pool::open(dir).unwrap_or_else(|e| panic!("opening {}: {e}", dir.display()));
    let scenes = pool.scenes().unwrap();
    let found = if scene.is_empty() {
        assert!(
            scenes.len() == 1,
            "{} holds {} scenes: name one with ARBOR_SOAK_SCENE",
            dir.display(),
            scenes.len()
        );
        &scenes[0]
    } else {
        scenes
            .iter()
            .find(|d| d.name == scene)
            .unwrap_or_else(|| panic!("{} holds no scene {scene}", dir.display()))
    };
    (found.name.clone(), found.treelet_count)
}

/// Lion with 4 KiB treelets in a pool at `pool`; its treelet count.
async fn build_lion(pool: PathBuf) -> u32 {
    tokio::task::spawn_blocking(move || {
        let built = build_file(
            "points/lion_takanawa.copc.laz",
            "lion",
            &BuildOptions {
                treelet_bytes: 4096,
                ..BuildOptions::default()
            },
        );
        let count = built.scene.description.treelet_count;
        built.pool.flush().unwrap();
        let from = built.pool_dir.path().to_owned();
        drop(built.scene);
        drop(built.pool);
        copy_dir(&from, &pool);
        drop(built.pool_dir);
        count
    })
    .await
    .unwrap()
}

async fn soak(resting_views: bool) {
    let secs: u64 = std::env::var("ARBOR_SOAK_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(600);
    let work = tempfile::tempdir().unwrap();
    let (pool, scene, treelets) = match given_pool() {
        Some((pool, scene)) => {
            let (scene, treelets) = tokio::task::spawn_blocking({
                let pool = pool.clone();
                move || given_scene(&pool, &scene)
            })
            .await
            .unwrap();
            (pool, scene, treelets)
        }
        None => (
            work.path().join("pool"),
            "lion".to_owned(),
            build_lion(work.path().join("pool")).await,
        ),
    };
    eprintln!(
        "soak: {CLIENTS} clients, scene {scene} ({treelets} treelets) in {}",
        pool.display()
    );
    let mut server = Command::new(server_binary());
    server
        .args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--admin",
            "127.0.0.1:0",
            "--db",
        ])
        .arg(&pool)
        .arg("--data-dir")
        .arg(work.path().join("state"));
    if let Some(config) = std::env::var_os("ARBOR_SOAK_CONFIG") {
        server.arg("--config").arg(workspace_path(config));
    }
    if std::env::var_os("ARBOR_SOAK_MEMORY_LIMIT").is_some() {
        // The server decides on its prewarm before it is confined, by the machine's memory;
        // a cold pool is what a confined soak measures.
        server.args(["--pool-prewarm", "off"]);
    }
    // Kept past the run: an error the clients count is explained only by the server's side.
    let log_path = workspace_path(format!(
        "target/soak/server-{}.log",
        if resting_views { "resting" } else { "plain" }
    ));
    std::fs::create_dir_all(log_path.parent().unwrap()).unwrap();
    let log = std::fs::File::create(&log_path).unwrap();
    eprintln!("soak: the server logs to {}", log_path.display());
    let mut child = server.stdout(Stdio::piped()).stderr(log).spawn().unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let (mut addr, mut fp, mut admin, mut token) = (None, None, None, None);
    while addr.is_none() || fp.is_none() || admin.is_none() || token.is_none() {
        let line = lines.next().expect("serve printed its lines").unwrap();
        if let Some(a) = line.strip_prefix("quic ") {
            addr = Some(a.parse::<std::net::SocketAddr>().unwrap());
        } else if let Some(f) = line.strip_prefix("fingerprint ") {
            fp = Some(f.to_owned());
        } else if let Some(a) = line.strip_prefix("admin ") {
            admin = Some(a.parse::<std::net::SocketAddr>().unwrap());
        } else if let Some(p) = line.strip_prefix("admin-token-file ") {
            token = Some(std::fs::read_to_string(p).unwrap().trim().to_owned());
        }
    }
    let (admin, token) = (admin.unwrap(), token.unwrap());
    std::thread::spawn(move || lines.for_each(drop));
    let pid = child.id();
    let _server = Server(child, confine(pid));
    let addr = addr.unwrap();
    let plan = Plan {
        url: ServerUrl {
            host: addr.ip().to_string(),
            port: addr.port(),
            scene,
        },
        fingerprint: fp.unwrap(),
        treelets,
        resting_views,
    };

    let stop = Arc::new(AtomicBool::new(false));
    let tally = Arc::new(Tally::default());
    let latencies = Arc::new(Mutex::new(Vec::new()));
    let mut tasks = Vec::new();
    for i in 0..CLIENTS {
        tasks.push(tokio::spawn(client(
            plan.clone(),
            i as u64 + 1,
            stop.clone(),
            tally.clone(),
            latencies.clone(),
        )));
    }
    let started = Instant::now();
    let mut samples = Vec::new();
    while started.elapsed() < Duration::from_secs(secs) {
        tokio::time::sleep(Duration::from_secs(SAMPLE_SECS)).await;
        let t = started.elapsed().as_secs_f64();
        let rss = rss_kib(pid);
        samples.push((t, rss as f64));
        if samples.len() % 12 == 0 {
            eprintln!(
                "{t:.0} s: server RSS {rss} KiB, {} treelets, {} lists, {} errors",
                tally.treelets.load(Ordering::Relaxed),
                tally.lists.load(Ordering::Relaxed),
                tally.errors.load(Ordering::Relaxed)
            );
        }
    }
    stop.store(true, Ordering::Relaxed);
    for t in tasks {
        t.await.unwrap();
    }
    let mut lat = std::mem::take(&mut *latencies.lock().await);
    lat.sort_by(f64::total_cmp);
    let q = |p: f64| lat[((lat.len() as f64 - 1.0) * p).round() as usize] * 1e3;
    // Each minute's median; the slope over the second half of them.
    let medians = per_minute_medians(&samples);
    let second_half = &medians[medians.len() / 2..];
    let slope = slope_per_minute(second_half);
    eprintln!(
        "server RSS, each minute's median (KiB): {:?}",
        medians.iter().map(|m| m.1 as u64).collect::<Vec<_>>()
    );
    let (first, last) = (samples[0].1, samples.last().unwrap().1);
    let elapsed = started.elapsed().as_secs_f64();
    eprintln!(
        "soak: {CLIENTS} clients, {elapsed:.0} s, {} lists, {} treelets ({:.1} MB, {:.0}/s), {} \
         errors; server RSS {first:.0} -> {last:.0} KiB, slope of the minutes' medians over the second half \
         {slope:+.1} KiB/min; list to first treelet p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms \
         ({} lists answered)",
        tally.lists.load(Ordering::Relaxed),
        tally.treelets.load(Ordering::Relaxed),
        tally.bytes.load(Ordering::Relaxed) as f64 / 1e6,
        tally.treelets.load(Ordering::Relaxed) as f64 / elapsed,
        tally.errors.load(Ordering::Relaxed),
        q(0.5),
        q(0.99),
        q(1.0),
        lat.len(),
    );
    let m = |name: &str| metric(admin, &token, name);
    eprintln!(
        "server: message cache {} hits / {} misses ({:.1} MB held), shape cache {} hits / {} \
         misses ({:.1} MB held)",
        m("arbor_message_cache_hits_total"),
        m("arbor_message_cache_misses_total"),
        m("arbor_message_cache_bytes") / 1e6,
        m("arbor_shape_cache_hits_total"),
        m("arbor_shape_cache_misses_total"),
        m("arbor_shape_cache_bytes") / 1e6,
    );
    eprintln!(
        "server: the pool's readers ran {} jobs and skipped {} nobody waited for any more; {} \
         push plans made on them",
        m("arbor_reader_jobs_total"),
        m("arbor_reader_jobs_skipped_total"),
        m("arbor_plans_on_readers_total"),
    );
    let cuts = m("arbor_visible_cuts_total");
    eprintln!(
        "server: {cuts} visible cuts, {} fine cuts skipped, cut node cache {} hits / {} \
         misses ({:.1} MB held), {} prefetch items set apart, {} pushes planned",
        m("arbor_fine_cuts_skipped_total"),
        m("arbor_cut_node_cache_hits_total"),
        m("arbor_cut_node_cache_misses_total"),
        m("arbor_cut_node_cache_bytes") / 1e6,
        m("arbor_prefetch_set_apart_total"),
        m("arbor_pushes_planned_total"),
    );
    assert_eq!(
        tally.errors.load(Ordering::Relaxed),
        0,
        "errors during the soak"
    );
    assert_eq!(
        cuts > 0.0,
        resting_views,
        "visible cuts are cast for resting views, and only for them"
    );
    assert!(!lat.is_empty(), "no list was ever answered");
    // Flat: the second half grows by less than 1 % of the resident set per minute. A run
    // shorter than MIN_FLAT_MINUTES (ARBOR_SOAK_SECS) is all warm-up: said, not judged.
    if medians.len() < MIN_FLAT_MINUTES {
        eprintln!(
            "NOT JUDGED: the RSS slope needs at least {MIN_FLAT_MINUTES} minutes of samples; \
             this run had {}",
            medians.len()
        );
        return;
    }
    assert!(
        slope < last / 100.0,
        "server RSS grows {slope:.0} KiB/min over the second half"
    );
}
