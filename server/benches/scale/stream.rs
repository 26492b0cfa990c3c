//! Serving the imported scene with the real `arbor-server serve` (its own process) and
//! streaming one 1024×768 view into a 64 MiB slot buffer with the real headless client in this
//! process, until the view converges exactly. Figures: time to converge, cycles, treelets and
//! bytes received, client peak RSS (this process's `VmHWM`, against its RSS before the run).

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use arbor_client_core::analysis::AnalysisConfig;
use arbor_client_core::camera::CameraPath;
use arbor_client_core::cycle::CoreConfig;
use arbor_client_net::{ClientConfig, ServerUrl, Trust};
use arbor_client_session::headless::{HeadlessConfig, run_headless};

fn status_mib(field: &str) -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix(field))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        })
        .map_or(0.0, |kib| kib / 1024.0)
}

pub fn serve_and_stream(server_bin: &str, pool: &Path, scene: &str) {
    let state = tempfile::tempdir().unwrap();
    let mut server = Command::new(server_bin)
        .args(["serve", "--listen", "127.0.0.1:0", "--admin", "off", "--db"])
        .arg(pool)
        .arg("--data-dir")
        .arg(state.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting arbor-server serve");
    let mut lines = BufReader::new(server.stdout.take().unwrap()).lines();
    let (mut addr, mut fingerprint) = (None, None);
    while addr.is_none() || fingerprint.is_none() {
        let line = lines.next().expect("serve output").unwrap();
        if let Some(a) = line.strip_prefix("quic ") {
            addr = Some(a.parse::<std::net::SocketAddr>().unwrap());
        }
        if let Some(f) = line.strip_prefix("fingerprint ") {
            fingerprint = Some(f.to_owned());
        }
    }
    let addr = addr.unwrap();
    let url = ServerUrl {
        host: addr.ip().to_string(),
        port: addr.port(),
        scene: scene.to_owned(),
    };
    let budget = 64u64 << 20;
    let config = HeadlessConfig {
        client: ClientConfig::new(url, Trust::Fingerprint(fingerprint.unwrap())),
        core: CoreConfig {
            analysis: AnalysisConfig::default(),
            budget_bytes: budget,
            ..CoreConfig::default()
        },
        camera_path: CameraPath::Static,
        seed: 7,
        width: 1024,
        height: 768,
        cycles: 3000,
        min_cycle: Duration::ZERO,
        connect_timeout: Duration::from_secs(30),
        reference: None,
        until_converged: true,
        render_every: 50,
        device_replacements: 0,
    };
    let rss_before = status_mib("VmRSS:");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let run = run_headless(config, runtime.handle()).expect("headless run");
    let s = run.report.summary();
    let converged = run
        .converged_at
        .and_then(|c| run.report.records.get(c as usize))
        .map(|r| r.time_s);
    println!();
    println!(
        "stream 1024x768, budget 64 MiB: {} in {} cycles ({:.1} s); {} treelets, {:.1} MiB received; slots peak {} of {}",
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
    println!(
        "client RSS: peak {:.1} MiB (before the run {:.1} MiB; slot buffer {:.1} MiB)",
        status_mib("VmHWM:"),
        rss_before,
        (u64::from(run.capacity) * run.slot_bytes) as f64 / f64::from(1 << 20)
    );
    let _ = server.kill();
    let _ = server.wait();
}
