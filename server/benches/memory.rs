//! Memory bound of the builder: peak anonymous memory of whole imports of synthetic point clouds
//! (no normals in the file, so normal estimation runs too) at two input sizes and two memory
//! budgets. Each variant runs in a fresh child process (this binary re-executed), so its peak is
//! its own. Figures: input size, peak anonymous RSS, peak of id lists held, bytes spilled.
//!
//! `cargo bench -p arbor-server --bench memory` (ARBOR_BENCH_POINTS=N sets the larger size,
//! default 4,000,000; the smaller is a quarter of it).

use std::io::Write;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use arbor_server::octree::BuildOptions;
use arbor_server::pipeline::{SceneImport, import_scene};
use arbor_server::pool::Pool;

/// Points on a unit sphere (Fibonacci lattice) with a little deterministic roughness.
fn write_cloud(path: &Path, n: usize) {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    write!(
        f,
        "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    .unwrap();
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    for i in 0..n {
        let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
        let r = (1.0 - y * y).sqrt();
        let t = golden * i as f64;
        let bump = 1.0 + 0.01 * ((i as f64 * 0.618_033_988_7).fract() - 0.5);
        for v in [r * t.cos() * bump, y * bump, r * t.sin() * bump] {
            f.write_all(&(v as f32).to_le_bytes()).unwrap();
        }
    }
}

fn child(budget_mib: usize, input: &Path) {
    let started = Instant::now();
    let pool_dir = tempfile::tempdir().unwrap();
    let pool = Pool::open(pool_dir.path()).unwrap();
    let request = SceneImport {
        name: "cloud".into(),
        input: input.to_path_buf(),
        build: BuildOptions {
            memory_budget: budget_mib << 20,
            ..BuildOptions::default()
        },
        ..SceneImport::default()
    };
    let desc = import_scene(&pool, &request).unwrap().description;
    let anon = desc.stats.peak_anon_bytes;
    println!(
        "RESULT {} {} {} {} {:.2} {} {}",
        anon,
        desc.stats.peak_list_bytes,
        desc.stats.spilled_bytes,
        arbor_server::memory::peak_rss_bytes(),
        started.elapsed().as_secs_f64(),
        desc.stats.voxels,
        desc.treelet_count
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--child") {
        child(args[i + 1].parse().unwrap(), Path::new(&args[i + 2]));
        return;
    }
    let big: usize = std::env::var("ARBOR_BENCH_POINTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(4_000_000);
    let dir = tempfile::tempdir().unwrap();
    println!(
        "Arbor memory bound: whole import of a synthetic point cloud (binary PLY, xyz only), one child process per variant"
    );
    println!(
        "{:>10} {:>10} {:>8} | {:>12} {:>12} {:>12} {:>12} | {:>8} {:>9} {:>9}",
        "points",
        "input MiB",
        "budget",
        "anon peak",
        "VmHWM",
        "lists peak",
        "spilled",
        "seconds",
        "voxels",
        "treelets"
    );
    let exe = std::env::current_exe().unwrap();
    for n in [big / 4, big] {
        let input = dir.path().join(format!("cloud-{n}.ply"));
        write_cloud(&input, n);
        let input_mib = std::fs::metadata(&input).unwrap().len() as f64 / f64::from(1 << 20);
        for budget in [8usize, 1024] {
            let out = Command::new(&exe)
                .args(["--child", &budget.to_string(), input.to_str().unwrap()])
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            let text = String::from_utf8_lossy(&out.stdout);
            let line = text
                .lines()
                .find(|l| l.starts_with("RESULT "))
                .expect("child result");
            let v: Vec<&str> = line.split_whitespace().skip(1).collect();
            let mib = |s: &str| s.parse::<f64>().unwrap() / f64::from(1 << 20);
            println!(
                "{:>10} {:>10.1} {:>5}MiB | {:>9.1}MiB {:>9.1}MiB {:>9.1}MiB {:>9.1}MiB | {:>8} {:>9} {:>9}",
                n,
                input_mib,
                budget,
                mib(v[0]),
                mib(v[3]),
                mib(v[1]),
                mib(v[2]),
                v[4],
                v[5],
                v[6]
            );
        }
    }
    println!(
        "anon peak: sampled RssAnon (what the importer holds); VmHWM also counts mapped source pages"
    );
}
