//! Streaming while the daemon imports: a client of lion (1 KiB treelets, 256², CPU backend,
//! budget 1.5× what the view needs) converges from scratch, again and again, alternating runs
//! with the daemon idle and runs while it imports a tiled point set (the scale bench's 10⁷-point
//! city when it exists under target/scale, else lion and autzen copies) into the same pool.
//! Figures per run: time to exact convergence, treelets received, treelets/s; then the medians
//! of both kinds side by side.
//!
//! `cargo bench -p arbor-tests --bench live_import` (ARBOR_LIVE_RUNS=N: runs per kind, 3;
//! ARBOR_LIVE_PRIORITY=low: the daemon runs imports at `--import-priority low`, else `idle`).

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_core::camera::CameraPath;
use arbor_client_core::slots::SlotBuffer;
use arbor_client_session::headless::run_headless;
use arbor_server::daemon::DaemonOptions;
use arbor_server::live_import::ImportPriority;
use arbor_tests::streaming::{Served, admin_request, full, headless, needed_treelets, serve_with};

async fn http(addr: SocketAddr, method: &str, path: &str, body: &str) -> serde_json::Value {
    admin_request(addr, method, path, body).await.1
}

/// One convergence from scratch: seconds, treelets received.
async fn converge_once(served: &Arc<Served>, budget: u64) -> (f64, u64) {
    let mut cfg = headless(served.server.quic_addr, served, CameraPath::Static, budget);
    cfg.width = 256;
    cfg.height = 256;
    cfg.until_converged = true;
    cfg.cycles = 2000;
    let handle = tokio::runtime::Handle::current();
    let t0 = Instant::now();
    let run = tokio::task::spawn_blocking(move || run_headless(cfg, &handle))
        .await
        .unwrap()
        .unwrap();
    assert!(run.converged_at.is_some(), "did not converge");
    (t0.elapsed().as_secs_f64(), run.client.treelets_received)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let runs: usize = std::env::var("ARBOR_LIVE_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let made = tempfile::tempdir().unwrap();
    let shared = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/points");
    let scale = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/scale");
    // The import root must hold the tiles themselves (a symlink leading out is refused).
    let (root, input) = if scale.join("tiles-10000000/complete").exists() {
        (scale, "tiles-10000000")
    } else {
        std::fs::create_dir(made.path().join("tiles")).unwrap();
        for i in 0..4 {
            std::fs::copy(
                shared.join("lion_takanawa.copc.laz"),
                made.path().join(format!("tiles/l{i}.laz")),
            )
            .unwrap();
        }
        (made.path().to_owned(), "tiles")
    };
    println!("importing {input} under {}", root.display());
    let options = DaemonOptions {
        import_root: Some(root),
        import_scratch: None,
        import_priority: match std::env::var("ARBOR_LIVE_PRIORITY").as_deref() {
            Ok("low") => ImportPriority::Low,
            _ => ImportPriority::Idle,
        },
        ..DaemonOptions::default()
    };
    let served = Arc::new(serve_with("points/lion_takanawa.copc.laz", "lion", 1024, options).await);
    let admin = served.server.admin_addr.unwrap();
    let full = full(&served);
    let needed = needed_treelets(&served, &full, &CameraPath::Static, 0);
    let budget = u64::from(needed + needed / 2)
        * SlotBuffer::slot_bytes(served.scene.treelet_nodes, served.scene.layout.channels());
    let (mut idle, mut busy) = (Vec::new(), Vec::new());
    for run in 0..runs {
        let (s, n) = converge_once(&served, budget).await;
        println!(
            "run {run} idle:      converged in {s:.2} s, {n} treelets, {:.0} treelets/s",
            n as f64 / s
        );
        idle.push((s, n as f64 / s));
        let body = format!(r#"{{"scene":"city{run}","inputs":["{input}"],"depth":"auto"}}"#);
        let answer = http(admin, "POST", "/v1/scenes", &body).await;
        let id: u64 = answer["id"]
            .as_u64()
            .unwrap_or_else(|| panic!("import refused: {answer}"));
        // Let the import get going, then stream while it runs.
        tokio::time::sleep(Duration::from_millis(300)).await;
        let (s, n) = converge_once(&served, budget).await;
        let status = http(admin, "GET", &format!("/v1/imports/{id}"), "").await;
        println!(
            "run {run} importing: converged in {s:.2} s, {n} treelets, {:.0} treelets/s (import {} at the end: {})",
            n as f64 / s,
            id,
            status["phase"]
        );
        busy.push((s, n as f64 / s));
        loop {
            let st = http(admin, "GET", &format!("/v1/imports/{id}"), "").await;
            if st["phase"] == "done" || st["phase"] == "failed" {
                println!(
                    "  import {id}: {} in {:.1} s",
                    st["phase"],
                    st["seconds"].as_f64().unwrap_or(0.0)
                );
                break;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        let _ = http(admin, "DELETE", &format!("/v1/scenes/city{run}"), "").await;
    }
    let m = |v: &[(f64, f64)], k: usize| {
        median(v.iter().map(|x| if k == 0 { x.0 } else { x.1 }).collect())
    };
    println!();
    println!("| lion 256², 1 KiB | median time to converge | median treelets/s |");
    println!("|---|---|---|");
    println!(
        "| daemon idle | {:.2} s | {:.0} |",
        m(&idle, 0),
        m(&idle, 1)
    );
    println!(
        "| daemon importing | {:.2} s | {:.0} |",
        m(&busy, 0),
        m(&busy, 1)
    );
}
