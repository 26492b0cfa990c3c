//! Runs a child process and samples it: wall time, CPU share, peak anonymous RSS (`RssAnon` from
//! /proc, every 50 ms) and the peak size of a directory it writes (scratch files).

use std::io::BufRead;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// What a measured child did.
#[derive(Debug)]
pub struct Measured {
    pub success: bool,
    pub seconds: f64,
    pub peak_anon: u64,
    pub peak_dir: u64,
    /// User + system CPU over wall time, percent (200 = both cores).
    pub cpu_percent: f64,
    /// Every line the child wrote to stderr, with the seconds since its start at which the line
    /// arrived.
    pub stderr_lines: Vec<(f64, String)>,
}

/// Bytes of the files under `dir` (allocated blocks, so sparse files count what they hold).
pub fn dir_bytes(dir: &Path) -> u64 {
    use std::os::unix::fs::MetadataExt;
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.metadata() {
            Ok(m) if m.is_dir() => dir_bytes(&e.path()),
            Ok(m) => m.blocks() * 512,
            Err(_) => 0,
        })
        .sum()
}

fn status_kib(pid: u32, field: &str) -> Option<u64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    s.lines()
        .find_map(|l| l.strip_prefix(field))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// The numeric fields of `/proc/{process}/stat` after the command (`process`: a pid or
/// `self`), so field `n` of proc(5) is at `n - 3`; empty if it cannot be read.
pub fn stat_fields(process: &str) -> Vec<u64> {
    let s = std::fs::read_to_string(format!("/proc/{process}/stat")).unwrap_or_default();
    let after = s.rsplit_once(')').map_or("", |(_, r)| r);
    after
        .split_whitespace()
        .map(|v| v.parse().unwrap_or(0))
        .collect()
}

/// Clock ticks of user + system time of the children this process has waited for.
fn children_cpu_ticks() -> u64 {
    let f = stat_fields("self");
    // Fields 16 and 17 (cutime, cstime).
    f.get(13).copied().unwrap_or(0) + f.get(14).copied().unwrap_or(0)
}

/// Runs `cmd` to its end, sampling it. Every dirty page is written back first, so that the
/// writeback of one run's output (the other tool's, alternating) is not billed to the next.
pub fn run_measured(mut cmd: Command, watch_dir: Option<&Path>) -> Measured {
    rustix::fs::sync();
    let cpu0 = children_cpu_ticks();
    let t0 = Instant::now();
    let mut child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("starting the child");
    let pid = child.id();
    let stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
            .map(|line| (t0.elapsed().as_secs_f64(), line))
            .collect::<Vec<_>>()
    });
    let (mut peak_anon, mut peak_dir) = (0u64, 0u64);
    let status = loop {
        if let Some(kib) = status_kib(pid, "RssAnon:") {
            peak_anon = peak_anon.max(kib * 1024);
        }
        if let Some(d) = watch_dir {
            peak_dir = peak_dir.max(dir_bytes(d));
        }
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let seconds = t0.elapsed().as_secs_f64();
    let ticks = children_cpu_ticks() - cpu0;
    let stderr_lines = reader.join().unwrap_or_default();
    Measured {
        success: status.success(),
        seconds,
        peak_anon,
        peak_dir,
        cpu_percent: ticks as f64 / 100.0 / seconds * 100.0,
        stderr_lines,
    }
}

impl Measured {
    /// The last 30 lines the child wrote to stderr (for a failure's message).
    pub fn stderr_tail(&self) -> String {
        let lines = &self.stderr_lines[self.stderr_lines.len().saturating_sub(30)..];
        lines
            .iter()
            .map(|(_, l)| l.as_str())
            .collect::<Vec<_>>()
            .join("\n")
    }
}
