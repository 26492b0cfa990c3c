//! Scale: a city-sized tiled LAZ set made from the real scans (`scale/city.rs`), imported as one
//! scene by the real `arbor-server import` binary in a fresh process, side by side with
//! PotreeConverter 2 on the same tiles (alternating, best of N), then verified, served and
//! streamed.
//!
//! `cargo bench -p arbor-server --bench scale` — 10⁸ points by default. Knobs (environment):
//! * `ARBOR_SCALE_POINTS` — points in the set (default 100000000);
//! * `ARBOR_SCALE_DIR` — where tiles, pools and outputs go (default `target/scale`; tiles are
//!   made once per count and reused);
//! * `ARBOR_SCALE_RUNS` — imports per tool, alternating, best kept (default 1);
//! * `ARBOR_SCALE_BUDGET_MIB` — `--memory-budget-mib` of the import (default 256);
//! * `ARBOR_POTREE_CONVERTER` — the PotreeConverter 2 binary (default
//!   `target/peer/PotreeConverter`, built there by `scripts/build-potree-converter` when missing,
//!   from `ARBOR_POTREE_SRC` or a clone of its public repository: it is not part of this
//!   project). When it cannot be had the comparison row says SKIPPED, loudly;
//! * `ARBOR_SCALE_STREAM=0` — skip serving and streaming;
//! * `ARBOR_SCALE_STREAM_ONLY=1` — only serve and stream, from the pool a previous run left in
//!   `ARBOR_SCALE_DIR` (no tiles, import or verify);
//! * `ARBOR_SCALE_SERVER_BIN=PATH` — the stream step serves from this `arbor-server` instead of
//!   the one built with the bench (another build's, to compare two in turns);
//! * `ARBOR_SCALE_PLAIN_VIEWS=0` — the stream step skips its two plain servers' views (only
//!   the jobs' and restarts' below);
//! * `ARBOR_SCALE_FIRST_VIEW_AFTER_MS=N` — the stream step's first view waits N ms after its
//!   server started (a client that comes a while after a restart; default 0);
//! * `ARBOR_SCALE_READ_IOPS=N` — the stream step's servers read the pool's disk at most N times
//!   a second (a cgroup v1 blkio limit; root), with the page cache dropped as each starts: a
//!   cloud disk past its burst (docs/measurements.md, stop 68); `ARBOR_SCALE_READ_BPS=B` the
//!   same for bytes a second (a throughput baseline; both may be set);
//! * `ARBOR_SCALE_RESTART=N` — after the stream step's views, N rounds of a restart: a server in
//!   a memory cgroup of `ARBOR_SCALE_RESTART_MEMORY_MIB` (default 1024, less than the city's
//!   pool) serves one view and is stopped with SIGTERM, the page cache is dropped, and its
//!   successor on the same data directory serves the timed first view
//!   (`ARBOR_SCALE_RESTART_VIEW_AFTER_MS` after it serves, default 10000), in turns with and
//!   without the hot-page list the first left (root, cgroup v1);
//! * `ARBOR_SCALE_CHECK=0` — skip the view streamed while the server checks the scene
//!   (`verify --server`); `ARBOR_SCALE_COPY=0` — the same while it copies its pool (`copy
//!   --server`); `ARBOR_SCALE_JOB_RATE=RATE` — those servers' `--background-read-rate` (`20MB`);
//!   `ARBOR_SCALE_JOB_MEMORY_MIB`, `ARBOR_SCALE_JOB_SECONDS`, `ARBOR_SCALE_JOB_COLD_VIEWS`,
//!   `ARBOR_SCALE_JOB_CONFIG`: in a memory cgroup, stopped after a while, each view from the
//!   disk, with server settings of its own (`scale/stream.rs`);
//! * `ARBOR_SCALE_SERVER_LOG=FILE` — append the stream step's servers' logs (stderr, with
//!   `RUST_LOG` as set) to FILE instead of dropping them.
//!
//! Figures: points/s of each tool, Arbor's time per phase of each run (from its log's phase
//! lines), peak anonymous RSS (sampled `RssAnon` of the child), peak scratch bytes on disk, pool
//! bytes (compressed blocks), sled's size on disk, `verify` time; then a 1024×768 view streamed
//! at a 64 MiB budget from a server with visible cuts on and one with them off: time from its
//! start until it serves (sled's open), time to converge, the server's CPU time per view,
//! client peak RSS.

#[path = "scale/city.rs"]
mod city;
#[path = "scale/monitor.rs"]
mod monitor;
#[path = "scale/stream.rs"]
mod stream;

use std::path::{Path, PathBuf};
use std::process::Command;

use monitor::{Measured, run_measured};

fn env_u64(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.replace('_', "").parse().ok())
        .unwrap_or(default)
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The PotreeConverter 2 binary: `ARBOR_POTREE_CONVERTER`, else `target/peer/PotreeConverter`,
/// built there first by `scripts/build-potree-converter` when it is missing (from
/// `ARBOR_POTREE_SRC` or a clone of the public repository; installs cmake, g++ and TBB). `None`
/// when it cannot be had: the row is then skipped, loudly.
fn potree() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("ARBOR_POTREE_CONVERTER").map(PathBuf::from) {
        return p.is_file().then_some(p);
    }
    let p = root().join("target/peer/PotreeConverter");
    if !p.is_file() {
        println!("PotreeConverter is not built yet: running scripts/build-potree-converter");
        match Command::new(root().join("scripts/build-potree-converter")).status() {
            Ok(s) if s.success() => {}
            Ok(s) => println!("scripts/build-potree-converter failed ({s})"),
            Err(e) => println!("scripts/build-potree-converter did not run: {e}"),
        }
    }
    p.is_file().then_some(p)
}

fn arbor_import(tiles: &Path, pool: &Path, scratch: &Path, budget: u64) -> Measured {
    let _ = std::fs::remove_dir_all(pool);
    let _ = std::fs::remove_dir_all(scratch);
    std::fs::create_dir_all(scratch).unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_arbor-server"));
    cmd.args(["import", "--quiet", "--scene", "city", "--db"])
        .arg(pool)
        .arg("--scratch")
        .arg(scratch)
        .args(["--memory-budget-mib", &budget.to_string()])
        .arg(tiles);
    run_measured(cmd, Some(scratch))
}

fn potree_convert(bin: &Path, tiles: &Path, out: &Path) -> Measured {
    let _ = std::fs::remove_dir_all(out);
    let mut cmd = Command::new(bin);
    cmd.arg(tiles).arg("-o").arg(out);
    run_measured(cmd, None)
}

/// Where an import's time went, from the phase lines of its log (`seconds=` fields): reading
/// and decoding ends where placing starts (the placing line's arrival less its seconds); the
/// fill line's seconds include the sort and the normals; the rest is commit and exit.
fn phases(m: &Measured) -> String {
    let find = |message: &str| {
        m.stderr_lines.iter().find_map(|(at, line)| {
            if !line.contains(message) {
                return None;
            }
            let seconds = line.split("seconds=").nth(1)?.split_whitespace().next()?;
            Some((*at, seconds.parse::<f64>().ok()?))
        })
    };
    let (
        Some((placed_at, placing)),
        Some((_, sort)),
        Some((_, normals)),
        Some((_, fill)),
        Some((stored_at, store)),
    ) = (
        find("placing (bounds, resolution) done"),
        find("points sorted by leaf cell"),
        find(": normals seconds="),
        find("fill (with sorting and normals) done"),
        find("store (attributes, dictionary, compression) done"),
    )
    else {
        return "not in its log (RUST_LOG must let `info` through)".into();
    };
    format!(
        "read and decode {:.1} s, placing {placing:.1}, sort {sort:.1}, normals {normals:.1}, \
         fill {:.1}, store {store:.1}, commit and exit {:.1}",
        placed_at - placing,
        fill - sort - normals,
        m.seconds - stored_at
    )
}

fn dir_bytes(dir: &Path) -> u64 {
    monitor::dir_bytes(dir)
}

fn mib(b: u64) -> f64 {
    b as f64 / f64::from(1 << 20)
}

fn main() {
    let points = env_u64("ARBOR_SCALE_POINTS", 100_000_000);
    let runs = env_u64("ARBOR_SCALE_RUNS", 1).max(1);
    let budget = env_u64("ARBOR_SCALE_BUDGET_MIB", 256);
    let base = std::env::var_os("ARBOR_SCALE_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("target/scale"));
    if env_u64("ARBOR_SCALE_STREAM_ONLY", 0) != 0 {
        let pool = base.join("pool");
        assert!(
            pool.exists(),
            "ARBOR_SCALE_STREAM_ONLY: no pool at {} (run the bench once without it)",
            pool.display()
        );
        stream::serve_and_stream(&stream_server_bin(), &pool, "city");
        return;
    }
    let tiles_dir = base.join(format!("tiles-{points}"));
    let t0 = std::time::Instant::now();
    let tiles = city::city(&root().join("../shared/data"), &tiles_dir, points);
    let input_bytes: u64 = tiles
        .iter()
        .map(|t| std::fs::metadata(t).unwrap().len())
        .sum();
    println!(
        "input: {} LAZ tiles, {points} points, {:.1} MiB ({:.1} s to make or find)",
        tiles.len(),
        mib(input_bytes),
        t0.elapsed().as_secs_f64()
    );
    let pool = base.join("pool");
    let scratch = base.join("scratch");
    let peer = potree();
    if peer.is_none() {
        println!(
            "SKIPPED: PotreeConverter not found at {} and it could not be built (set ARBOR_POTREE_CONVERTER, or ARBOR_POTREE_SRC for scripts/build-potree-converter; it is not part of this project)",
            std::env::var("ARBOR_POTREE_CONVERTER").unwrap_or_else(|_| root()
                .join("target/peer/PotreeConverter")
                .display()
                .to_string())
        );
    }
    let (mut best_arbor, mut best_peer): (Option<Measured>, Option<Measured>) = (None, None);
    for run in 0..runs {
        let a = arbor_import(&tiles_dir, &pool, &scratch, budget);
        assert!(
            a.success,
            "arbor-server import failed:\n{}",
            a.stderr_tail()
        );
        println!(
            "run {run}: arbor {:.2} s ({:.0} points/s), peak anon {:.1} MiB, scratch peak {:.1} MiB, CPU {:.0} %",
            a.seconds,
            points as f64 / a.seconds,
            mib(a.peak_anon),
            mib(a.peak_dir),
            a.cpu_percent
        );
        println!("run {run}: arbor phases: {}", phases(&a));
        if best_arbor.as_ref().is_none_or(|b| a.seconds < b.seconds) {
            best_arbor = Some(a);
        }
        if let Some(bin) = &peer {
            let p = potree_convert(bin, &tiles_dir, &base.join("potree"));
            assert!(p.success, "PotreeConverter failed:\n{}", p.stderr_tail());
            println!(
                "run {run}: PotreeConverter {:.2} s ({:.0} points/s), peak anon {:.1} MiB, output {:.1} MiB, CPU {:.0} %",
                p.seconds,
                points as f64 / p.seconds,
                mib(p.peak_anon),
                mib(dir_bytes(&base.join("potree"))),
                p.cpu_percent
            );
            if best_peer.as_ref().is_none_or(|b| p.seconds < b.seconds) {
                best_peer = Some(p);
            }
        }
    }
    let a = best_arbor.expect("one run");
    let figures = pool_figures(&pool);
    let verify = std::time::Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_arbor-server"))
        .args(["verify", "--scene", "city", "--db"])
        .arg(&pool)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "verify failed: {}",
        String::from_utf8_lossy(&out.stdout)
    );
    let verify_s = verify.elapsed().as_secs_f64();
    println!();
    println!(
        "| input | points | Arbor points/s | PotreeConverter points/s | ratio | Arbor peak anon RSS | scratch peak | pool bytes | sled on disk | verify |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let (peer_rate, ratio) = match &best_peer {
        Some(p) => (
            format!("{:.0}", points as f64 / p.seconds),
            format!("{:.2}", p.seconds / a.seconds),
        ),
        None => ("SKIPPED".into(), "—".into()),
    };
    println!(
        "| city {} tiles | {points} | {:.0} | {peer_rate} | {ratio} | {:.1} MiB (budget {budget}) | {:.1} MiB | {} | {} | {:.1} s |",
        tiles.len(),
        points as f64 / a.seconds,
        mib(a.peak_anon),
        mib(a.peak_dir),
        figures.0,
        figures.1,
        verify_s
    );
    println!("{}", figures.2);
    if env_u64("ARBOR_SCALE_STREAM", 1) != 0 {
        stream::serve_and_stream(&stream_server_bin(), &pool, "city");
    }
}

/// Pool bytes (compressed blocks), sled's size on disk, and `arbor-server info`'s lines.
fn pool_figures(pool: &Path) -> (u64, u64, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_arbor-server"))
        .args(["info", "--scene", "city", "--db"])
        .arg(pool)
        .output()
        .unwrap();
    let info = String::from_utf8_lossy(&out.stdout).into_owned();
    let field = |prefix: &str| -> u64 {
        info.lines()
            .find_map(|l| l.strip_prefix(prefix))
            .and_then(|r| r.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (field("bytes            "), dir_bytes(pool), info)
}

/// The `arbor-server` the stream step serves from (`ARBOR_SCALE_SERVER_BIN`, else this build's).
fn stream_server_bin() -> String {
    std::env::var("ARBOR_SCALE_SERVER_BIN")
        .unwrap_or_else(|_| env!("CARGO_BIN_EXE_arbor-server").to_owned())
}
