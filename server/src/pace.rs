//! The pace of the daemon's background reads: the bytes per second that scene checks
//! ([`crate::live_verify`]) and pool copies ([`crate::live_copy`]) may read from the served pool
//! together (`serve --background-read-rate`, `PUT /v1/background-reads`).
//!
//! Why: a background job reads the pool as fast as the disk allows; on a pool bigger than the
//! page cache that is the disk's whole bandwidth, and a client's treelet read then waits behind
//! it. The CPU priority of the job's thread (`SCHED_IDLE`) does nothing for the disk. A pace
//! bounds what the jobs take and leaves the rest to serving; a job under it lasts its bytes
//! divided by the rate.
//!
//! * [`TokenBucket`] is the arithmetic alone, time passed in, so tests drive it without sleeping.
//! * [`ReadPace`] is what jobs share: one bucket behind a lock, the waiting done by the reader
//!   itself in short slices, so a new rate (or no rate) takes effect at once, and a cancelled
//!   job stops waiting (it ends the batch in hand at full speed and stops).
//! * Bytes are counted whether a rate is set or not; `/metrics` shows them, the time jobs waited,
//!   and the rate ([`ReadPace::figures`]).
//! * What is counted is the packs' bytes as a job reads them by `get`, from the disk or from the
//!   page cache alike. A check lists the stored ids by iterating the nodes tree a batch ahead of
//!   its reads, so its disk reads may run one batch (a few MB) ahead of the rate, never further.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use serde::Serialize;

/// The slowest pace accepted, bytes per second.
pub const MIN_RATE: u64 = 1_000;
/// The fastest pace accepted, bytes per second (beyond any disk: leave the rate off instead).
pub const MAX_RATE: u64 = 1_000_000_000_000;
/// How long a waiting reader sleeps before it looks again at the rate and at its job's stop flag.
const SLICE: Duration = Duration::from_millis(20);
/// The time of reads at the rate a full bucket holds: reads within it go at once.
const BURST: Duration = Duration::from_millis(50);
/// The least a full bucket holds, bytes: a pool's pack at a low rate goes in one take.
const MIN_BURST: u64 = 64 * 1024;

/// Why a rate was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PaceError {
    /// Outside [`MIN_RATE`]..=[`MAX_RATE`].
    #[error("a background read rate of {0} bytes/s is outside 1 kB/s to 1 TB/s")]
    OutOfRange(u64),
    /// Not a number of bytes with an optional unit, nor `off`.
    #[error(
        "'{0}': expected a rate such as 20MB, 512KiB, 1GB or 1500000 (bytes per second), or off"
    )]
    Unreadable(String),
}

/// Checks a rate against [`MIN_RATE`]..=[`MAX_RATE`]; `None` is no limit.
pub fn validate(rate: Option<u64>) -> Result<Option<u64>, PaceError> {
    match rate {
        Some(r) if !(MIN_RATE..=MAX_RATE).contains(&r) => Err(PaceError::OutOfRange(r)),
        other => Ok(other),
    }
}

/// Reads a rate as the command line writes it: `off`, or a whole number of bytes per second
/// with an optional unit `K`/`KB`, `M`/`MB`, `G`/`GB` (powers of 1000) or `KiB`, `MiB`, `GiB`
/// (powers of 1024) and an optional `/s`.
pub fn parse_rate(s: &str) -> Result<Option<u64>, PaceError> {
    let unreadable = || PaceError::Unreadable(s.to_owned());
    let text = s.trim();
    if text.eq_ignore_ascii_case("off") {
        return Ok(None);
    }
    let text = text.strip_suffix("/s").unwrap_or(text);
    let digits = text.bytes().take_while(u8::is_ascii_digit).count();
    let (number, unit) = text.split_at(digits);
    let factor: u64 = match unit.trim() {
        "" | "B" => 1,
        "K" | "KB" | "k" | "kB" => 1_000,
        "M" | "MB" => 1_000_000,
        "G" | "GB" => 1_000_000_000,
        "KiB" => 1 << 10,
        "MiB" => 1 << 20,
        "GiB" => 1 << 30,
        _ => return Err(unreadable()),
    };
    let n: u64 = number.parse().map_err(|_| unreadable())?;
    let rate = n
        .checked_mul(factor)
        .ok_or(PaceError::OutOfRange(u64::MAX))?;
    validate(Some(rate))
}

/// A rate for people: `20.0 MB/s`, `512.0 kB/s`, or `off`.
pub fn describe_rate(rate: Option<u64>) -> String {
    match rate {
        None => "off".to_owned(),
        Some(r) if r >= 1_000_000_000 => format!("{:.1} GB/s", r as f64 / 1e9),
        Some(r) if r >= 1_000_000 => format!("{:.1} MB/s", r as f64 / 1e6),
        Some(r) => format!("{:.1} kB/s", r as f64 / 1e3),
    }
}

/// A token bucket of bytes: it fills at `rate` bytes per second up to a burst, and a take of
/// more than it holds leaves a debt that the taker waits off. Time is passed in.
#[derive(Debug, Clone)]
pub struct TokenBucket {
    rate: u64,
    burst: f64,
    /// Bytes that may be read now; negative: owed.
    tokens: f64,
    last: Instant,
}

impl TokenBucket {
    /// A full bucket for `rate` bytes per second (at least 1).
    pub fn new(rate: u64, now: Instant) -> TokenBucket {
        let rate = rate.max(1);
        let burst = (rate as f64 * BURST.as_secs_f64()).max(MIN_BURST as f64);
        TokenBucket {
            rate,
            burst,
            tokens: burst,
            last: now,
        }
    }

    pub fn rate(&self) -> u64 {
        self.rate
    }

    /// Takes `bytes` at `now` and answers how long the taker waits before its next read so that
    /// reads average at most the rate: zero while the bucket holds them.
    pub fn take(&mut self, now: Instant, bytes: u64) -> Duration {
        let elapsed = now.saturating_duration_since(self.last).as_secs_f64();
        self.last = self.last.max(now);
        self.tokens = (self.tokens + elapsed * self.rate as f64).min(self.burst);
        self.tokens -= bytes as f64;
        if self.tokens >= 0.0 {
            Duration::ZERO
        } else {
            Duration::from_secs_f64(-self.tokens / self.rate as f64)
        }
    }
}

/// What `/metrics` and `GET /v1/background-reads` report.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PaceFigures {
    /// Bytes per second allowed; `None`: no limit.
    pub read_bytes_per_second: Option<u64>,
    /// Bytes the background jobs read since the daemon started.
    pub read_bytes: u64,
    /// Seconds the jobs' readers waited for the pace since the daemon started.
    pub waited_seconds: f64,
}

/// The pace every background job of a daemon shares (module docs).
#[derive(Debug)]
pub struct ReadPace {
    /// `None`: no limit.
    bucket: Mutex<Option<TokenBucket>>,
    /// Bumped at every new rate: a reader waiting under the old one stops waiting.
    epoch: AtomicU64,
    read_bytes: AtomicU64,
    waited_nanos: AtomicU64,
}

impl ReadPace {
    /// A pace of `rate` bytes per second (`None`: no limit; see [`validate`]).
    pub fn new(rate: Option<u64>) -> ReadPace {
        ReadPace {
            bucket: Mutex::new(rate.map(|r| TokenBucket::new(r, Instant::now()))),
            epoch: AtomicU64::new(0),
            read_bytes: AtomicU64::new(0),
            waited_nanos: AtomicU64::new(0),
        }
    }

    fn bucket(&self) -> std::sync::MutexGuard<'_, Option<TokenBucket>> {
        self.bucket.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The rate now, bytes per second.
    pub fn rate(&self) -> Option<u64> {
        self.bucket().as_ref().map(TokenBucket::rate)
    }

    /// Sets a new rate (`None`: no limit), forgiving what readers owed under the old one.
    pub fn set_rate(&self, rate: Option<u64>) {
        let mut bucket = self.bucket();
        *bucket = rate.map(|r| TokenBucket::new(r, Instant::now()));
        self.epoch.fetch_add(1, Ordering::AcqRel);
        tracing::info!(rate = %describe_rate(rate), "background read rate set");
    }

    /// Counts `bytes` just read and, under a rate, waits until reading them keeps the jobs at
    /// it. Returns at once when `stop` is set (a cancelled job) or the rate changes.
    pub fn take(&self, bytes: u64, stop: Option<&AtomicBool>) {
        self.read_bytes.fetch_add(bytes, Ordering::Relaxed);
        let (wait, epoch) = {
            let mut bucket = self.bucket();
            let epoch = self.epoch.load(Ordering::Acquire);
            match bucket.as_mut() {
                Some(b) => (b.take(Instant::now(), bytes), epoch),
                None => return,
            }
        };
        if wait.is_zero() {
            return;
        }
        let mut counted = Instant::now();
        let until = counted + wait;
        loop {
            // Counted slice by slice, so `/metrics` shows a long wait while it lasts (a pack's
            // debt at a low rate is a minute), not only once it ended.
            let now = Instant::now();
            let slept = u64::try_from((now - counted).as_nanos()).unwrap_or(u64::MAX);
            self.waited_nanos.fetch_add(slept, Ordering::Relaxed);
            counted = now;
            let stopped = stop.is_some_and(|s| s.load(Ordering::Acquire));
            if now >= until || stopped || self.epoch.load(Ordering::Acquire) != epoch {
                break;
            }
            std::thread::sleep(SLICE.min(until - now));
        }
    }

    pub fn figures(&self) -> PaceFigures {
        PaceFigures {
            read_bytes_per_second: self.rate(),
            read_bytes: self.read_bytes.load(Ordering::Relaxed),
            waited_seconds: self.waited_nanos.load(Ordering::Relaxed) as f64 / 1e9,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bucket_lets_its_burst_through_then_holds_reads_to_the_rate() {
        let t0 = Instant::now();
        let mut b = TokenBucket::new(1_000_000, t0);
        // 50 ms at 1 MB/s is 50 kB, below the 64 KiB floor: the floor is the burst.
        assert_eq!(b.take(t0, 65_536), Duration::ZERO);
        // Empty now: 10 kB more is owed, 10 ms at the rate.
        let wait = b.take(t0, 10_000);
        assert!((wait.as_secs_f64() - 0.010).abs() < 1e-9, "{wait:?}");
        // Reads taken each as soon as allowed average the rate over any stretch.
        let mut now = t0 + wait;
        let mut total = 0u64;
        for _ in 0..1000 {
            now += b.take(now, 4_096);
            total += 4_096;
        }
        let seconds = now.duration_since(t0 + wait).as_secs_f64();
        let rate = total as f64 / seconds;
        assert!(
            (rate - 1e6).abs() / 1e6 < 0.002,
            "{rate} B/s over {seconds} s"
        );
    }

    #[test]
    fn a_bucket_fills_while_idle_but_never_past_its_burst() {
        let t0 = Instant::now();
        let mut b = TokenBucket::new(10_000_000, t0);
        let burst = 500_000;
        assert_eq!(b.take(t0, burst), Duration::ZERO);
        // An hour idle refills to the burst only.
        let later = t0 + Duration::from_secs(3_600);
        assert_eq!(b.take(later, burst), Duration::ZERO);
        let wait = b.take(later, 1_000_000);
        assert!((wait.as_secs_f64() - 0.1).abs() < 1e-9, "{wait:?}");
        // A clock that goes back (another thread's `now`, taken earlier) adds nothing.
        let wait = b.take(t0, 0);
        assert!((wait.as_secs_f64() - 0.1).abs() < 1e-9, "{wait:?}");
    }

    #[test]
    fn the_slowest_and_fastest_rates_keep_their_sums_finite() {
        let t0 = Instant::now();
        let mut slow = TokenBucket::new(MIN_RATE, t0);
        let wait = slow.take(t0, u64::from(u32::MAX));
        assert!(wait.as_secs_f64().is_finite() && wait > Duration::from_secs(4_000_000));
        let mut fast = TokenBucket::new(MAX_RATE, t0);
        assert_eq!(fast.take(t0, 1 << 30), Duration::ZERO);
        let zero = TokenBucket::new(0, t0);
        assert_eq!(zero.rate(), 1);
    }

    #[test]
    fn rates_read_as_written() {
        assert_eq!(parse_rate("off"), Ok(None));
        assert_eq!(parse_rate("OFF"), Ok(None));
        assert_eq!(parse_rate("20MB"), Ok(Some(20_000_000)));
        assert_eq!(parse_rate("20M/s"), Ok(Some(20_000_000)));
        assert_eq!(parse_rate("512KiB"), Ok(Some(524_288)));
        assert_eq!(parse_rate("1GB/s"), Ok(Some(1_000_000_000)));
        assert_eq!(parse_rate("2GiB"), Ok(Some(2 << 30)));
        assert_eq!(parse_rate("1500000"), Ok(Some(1_500_000)));
        assert_eq!(parse_rate(" 64 kB "), Ok(Some(64_000)));
        assert_eq!(parse_rate("999"), Err(PaceError::OutOfRange(999)));
        assert_eq!(parse_rate("0"), Err(PaceError::OutOfRange(0)));
        assert_eq!(
            parse_rate("2000TB"),
            Err(PaceError::Unreadable("2000TB".into()))
        );
        assert_eq!(
            parse_rate("99999999999999999999"),
            Err(PaceError::Unreadable("99999999999999999999".into()))
        );
        assert_eq!(
            parse_rate("99999999999G"),
            Err(PaceError::OutOfRange(u64::MAX))
        );
        for bad in ["", "MB", "-5MB", "1.5MB", "20 mb", "fast", "20MBps"] {
            assert_eq!(
                parse_rate(bad),
                Err(PaceError::Unreadable(bad.into())),
                "{bad}"
            );
        }
        assert_eq!(
            validate(Some(MAX_RATE + 1)),
            Err(PaceError::OutOfRange(MAX_RATE + 1))
        );
        assert_eq!(validate(None), Ok(None));
        assert_eq!(describe_rate(Some(20_000_000)), "20.0 MB/s");
        assert_eq!(describe_rate(Some(1_500)), "1.5 kB/s");
        assert_eq!(describe_rate(Some(2_000_000_000)), "2.0 GB/s");
        assert_eq!(describe_rate(None), "off");
    }

    #[test]
    fn a_waiting_reader_stops_waiting_when_its_job_stops_or_the_rate_changes() {
        let pace = ReadPace::new(Some(MIN_RATE));
        // The burst goes at once.
        let t0 = Instant::now();
        pace.take(MIN_BURST, None);
        assert!(t0.elapsed() < Duration::from_secs(1));
        // 10 kB at 1 kB/s owes 10 s; the stop flag set from another thread ends the wait, which
        // the figures show while it lasts.
        let stop = AtomicBool::new(false);
        std::thread::scope(|s| {
            s.spawn(|| {
                std::thread::sleep(Duration::from_millis(100));
                let waiting = pace.figures().waited_seconds;
                stop.store(true, Ordering::Release);
                assert!(waiting >= 0.03, "{waiting} s counted 100 ms into a wait");
            });
            let t0 = Instant::now();
            pace.take(10_000, Some(&stop));
            let waited = t0.elapsed();
            assert!(
                waited >= Duration::from_millis(90) && waited < Duration::from_secs(5),
                "{waited:?}"
            );
        });
        // Owing again; the rate lifted from another thread ends the wait.
        std::thread::scope(|s| {
            s.spawn(|| {
                std::thread::sleep(Duration::from_millis(100));
                pace.set_rate(None);
            });
            let t0 = Instant::now();
            pace.take(10_000, None);
            assert!(t0.elapsed() < Duration::from_secs(5));
        });
        assert_eq!(pace.rate(), None);
        let f = pace.figures();
        assert_eq!(f.read_bytes_per_second, None);
        assert_eq!(f.read_bytes, MIN_BURST + 20_000);
        assert!(f.waited_seconds >= 0.18 && f.waited_seconds < 10.0, "{f:?}");
        // Without a rate nothing waits, and bytes are still counted.
        let t0 = Instant::now();
        pace.take(1 << 40, None);
        assert!(t0.elapsed() < Duration::from_secs(1));
        assert_eq!(pace.figures().read_bytes, MIN_BURST + 20_000 + (1 << 40));
    }

    #[test]
    fn readers_sharing_a_pace_read_at_its_rate_together() {
        // Two threads, 40 takes of 25 kB each at 2 MB/s: 2 MB after a burst of 100 kB takes
        // about 0.95 s, whoever takes.
        let pace = ReadPace::new(Some(2_000_000));
        let t0 = Instant::now();
        std::thread::scope(|s| {
            for _ in 0..2 {
                s.spawn(|| {
                    for _ in 0..40 {
                        pace.take(25_000, None);
                    }
                });
            }
        });
        let seconds = t0.elapsed().as_secs_f64();
        assert!(seconds > 0.9, "{seconds} s: faster than the rate");
        assert_eq!(pace.figures().read_bytes, 2_000_000);
    }
}
