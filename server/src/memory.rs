//! Memory figures of this process, for the import report. `VmHWM` (peak resident set) counts the
//! memory-mapped source columns too, which the kernel can drop at any time; the peak of
//! *anonymous* resident memory (`RssAnon`, sampled) is what the builder itself holds.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

fn status_kib(field: &str) -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines()
        .find(|l| l.starts_with(field))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|kb| kb.parse::<u64>().ok())
}

/// Peak resident set size of this process (Linux `VmHWM`), 0 where unknown.
pub fn peak_rss_bytes() -> u64 {
    status_kib("VmHWM:").map_or(0, |kb| kb * 1024)
}

/// Samples `RssAnon` every 10 ms on a background thread and keeps the maximum.
#[derive(Debug)]
pub struct AnonPeakSampler {
    stop: Arc<AtomicBool>,
    peak: Arc<AtomicU64>,
    thread: Option<JoinHandle<()>>,
}

impl AnonPeakSampler {
    pub fn start() -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let peak = Arc::new(AtomicU64::new(0));
        let (s, p) = (stop.clone(), peak.clone());
        let thread = std::thread::Builder::new()
            .name("rss-sampler".into())
            .spawn(move || {
                while !s.load(Ordering::Relaxed) {
                    if let Some(kb) = status_kib("RssAnon:") {
                        p.fetch_max(kb * 1024, Ordering::Relaxed);
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
            })
            .ok();
        Self { stop, peak, thread }
    }

    /// Stops sampling and returns the peak seen (0 where unknown).
    pub fn finish(mut self) -> u64 {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        if let Some(kb) = status_kib("RssAnon:") {
            self.peak.fetch_max(kb * 1024, Ordering::Relaxed);
        }
        self.peak.load(Ordering::Relaxed)
    }
}
