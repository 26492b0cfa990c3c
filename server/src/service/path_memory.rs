//! What the server remembers of each client's network path, so that a returning client's
//! connection starts near the rate the last one reached instead of slow-starting again.
//!
//! A new QUIC connection starts with the configured initial window (`initial_window`, 128 KiB)
//! and doubles it every round trip. On a 100 Mbit/s link with 50 ms round trips that takes four
//! round trips to fill the pipe, a fifth of a typical first view's time (docs/measurements.md,
//! stop 45). A viewer reconnects to the same server often: another scene, a restarted viewer, a
//! replica. This module is the careful-resume scheme of the IETF (draft-ietf-tsvwg-careful-resume),
//! done by the sender, keyed by the client's IP address:
//!
//! 1. Every connection's controller is a [`PathCubic`], which notes the smallest round trip of
//!    any acknowledged packet in the connection's [`PathObserver`]. When the connection ends,
//!    [`PathMemory::handle_close`] keeps its congestion window and that minimum RTT for the
//!    client's address, for `path_memory_secs` (bounded in entries, the oldest forgotten
//!    first). The minimum, not the smoothed RTT: a queue the connection built inflates the
//!    smoothed one (1.1–1.9× the path's 50 ms in the refine bench), and the next connection's
//!    first round trip, before any queue, would then look like another path.
//! 2. A new connection from that address gets a [`PathCubic`] holding a [`Resume`]
//!    ([`PathMemory::poll_resume`]). It starts like any other, with the initial window
//!    (*reconnaissance*). Its first acknowledgement measures the path: if that packet's round
//!    trip lies within half to ten times the saved one, the path is taken for the same and the
//!    window jumps to half the saved window (*unvalidated*); quinn's pacer spreads it over the
//!    round trip. Otherwise the connection goes on as a new one.
//! 3. The jump ends when Cubic's own window — which slow start grows by every acknowledged
//!    byte, so it reaches the jump once the jump's bytes are acknowledged — catches up (the
//!    path carried it), or at the first congestion event, when Cubic's window of what was
//!    really acknowledged, reduced, takes over (*safe retreat*), or after [`UNVALIDATED_RTTS`]
//!    round trips of a connection that had too little to send to validate it.
//!
//! [`ResumeState`] is that decision as plain data, tested without quinn; [`PathCubic`] is the
//! thin [`Controller`] around Cubic that feeds it, and feeds the random-loss filter
//! ([`super::random_loss`]) too. With path memory off every connection still gets a
//! [`PathCubic`], with no resume and no observer, so the filter applies all the same.
//!
//! A graceful shutdown writes the records to [`PATHS_FILE`] in the data directory
//! ([`PathMemory::save`]) and the next start reads them back ([`PathMemory::load`]), ages
//! carried over, so a rolling restart does not send every returning client back to slow start.
//! The file is a hint: one that cannot be read or parsed is logged and ignored, never a reason
//! not to serve.

use std::any::Any;
use std::collections::HashMap;
use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant, SystemTime};

use serde::{Deserialize, Serialize};

use super::random_loss::{LossCounters, RandomLossFilter};
use super::state_file::{ReadState, read_json, write_json};
use quinn::congestion::{Controller, ControllerFactory, ControllerMetrics, Cubic, CubicConfig};

/// Most client addresses remembered; beyond it the oldest record is forgotten.
pub const MAX_PATHS: usize = 4096;
/// Largest window a resumed connection jumps to, bytes.
pub const MAX_JUMP: u64 = 8 << 20;
/// RTTs below this count as this when paths are compared (quinn's timer granularity), so two
/// loopback connections are the same path however their microseconds differ.
pub const RTT_FLOOR: Duration = Duration::from_millis(1);
/// How many saved RTTs the jump may last without being validated.
pub const UNVALIDATED_RTTS: u32 = 8;

/// The file in the data directory a graceful shutdown writes the records to.
pub const PATHS_FILE: &str = "path-memory.json";
/// Largest [`PATHS_FILE`] read back (4,096 records take about 400 KB).
pub const MAX_PATHS_FILE_BYTES: u64 = 4 << 20;
/// Format version of [`PATHS_FILE`].
const PATHS_FILE_VERSION: u32 = 1;

/// Why [`PathMemory::load`] or [`PathMemory::save`] failed.
#[derive(Debug, thiserror::Error)]
pub enum PathFileError {
    /// The file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is larger than [`MAX_PATHS_FILE_BYTES`].
    #[error("{}: {bytes} bytes, more than the {MAX_PATHS_FILE_BYTES} a path memory takes", path.display())]
    TooLarge { path: PathBuf, bytes: u64 },
    /// The file is not a path memory of this format.
    #[error("{}: not a path memory: {reason}", path.display())]
    Format { path: PathBuf, reason: String },
}

/// [`PATHS_FILE`]'s contents.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SavedPaths {
    version: u32,
    /// When the file was written, milliseconds since the Unix epoch.
    saved_at_unix_ms: u64,
    records: Vec<SavedPath>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SavedPath {
    addr: IpAddr,
    window: u64,
    rtt_ns: u64,
    /// The record's age when the file was written, milliseconds.
    age_ms: u64,
}

/// What a path taught its last connection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathRecord {
    /// The congestion window when the connection ended, bytes.
    pub window: u64,
    /// The smallest round trip of an acknowledged packet over the connection.
    pub rtt: Duration,
    /// When it was recorded.
    pub at: Instant,
}

/// One remembered path as the admin API shows it (`GET /v1/paths`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PathView {
    /// The client's IP address.
    pub addr: IpAddr,
    /// The congestion window its last connection ended with, bytes.
    pub window_bytes: u64,
    /// What its next connection would jump to once the path is confirmed, bytes; 0: no jump
    /// (half the window is not above the initial window).
    pub jump_bytes: u64,
    /// The smallest round trip of its last connection, milliseconds.
    pub rtt_ms: f64,
    /// Seconds since the record was made.
    pub age_s: f64,
}

/// What a new connection on a remembered path may start with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resume {
    /// The window to jump to once the path is confirmed, bytes: half the saved window.
    pub jump: u64,
    /// The saved RTT the first measurement is compared with.
    pub rtt: Duration,
}

/// Congestion windows and RTTs of recent connections, by client address.
#[derive(Debug)]
pub struct PathMemory {
    records: HashMap<IpAddr, PathRecord>,
    /// How long a record is used; zero: nothing is remembered.
    lifetime: Duration,
    capacity: usize,
    /// The window connections start with, for what [`PathMemory::snapshot`] says they would
    /// jump to.
    initial_window: u64,
}

impl Default for PathMemory {
    fn default() -> Self {
        PathMemory::new(Duration::ZERO, MAX_PATHS)
    }
}

impl PathMemory {
    /// A memory keeping records for `lifetime` (zero: off), at most `capacity` of them.
    pub fn new(lifetime: Duration, capacity: usize) -> Self {
        PathMemory {
            records: HashMap::new(),
            lifetime,
            capacity: capacity.max(1),
            initial_window: 0,
        }
    }

    /// Changes how long records are used (zero turns the memory off and forgets everything).
    pub fn set_lifetime(&mut self, lifetime: Duration) {
        self.lifetime = lifetime;
        if lifetime.is_zero() {
            self.records.clear();
        }
    }

    /// Sets the window connections start with (what [`PathMemory::snapshot`] compares with).
    pub fn set_initial_window(&mut self, initial_window: u64) {
        self.initial_window = initial_window;
    }

    /// A connection from `peer` ended with `window` bytes of congestion window and `rtt`.
    /// Replaces what was known of `peer`; a window or RTT of zero teaches nothing.
    pub fn handle_close(&mut self, peer: IpAddr, now: Instant, window: u64, rtt: Duration) {
        if self.lifetime.is_zero() || window == 0 || rtt.is_zero() {
            return;
        }
        self.expire(now);
        if self.records.len() >= self.capacity && !self.records.contains_key(&peer) {
            let oldest = self
                .records
                .iter()
                .min_by_key(|(_, r)| r.at)
                .map(|(a, _)| *a);
            if let Some(oldest) = oldest {
                self.records.remove(&oldest);
            }
        }
        self.records.insert(
            peer,
            PathRecord {
                window,
                rtt,
                at: now,
            },
        );
    }

    /// What a new connection from `peer` may resume: `None` when nothing recent is known or
    /// the jump would not exceed the initial window ([`PathMemory::set_initial_window`]).
    pub fn poll_resume(&mut self, peer: IpAddr, now: Instant) -> Option<Resume> {
        self.expire(now);
        let record = self.records.get(&peer)?;
        Some(Resume {
            jump: self.jump(record)?,
            rtt: record.rtt,
        })
    }

    /// The window a connection on `record`'s path jumps to: half the saved window, at most
    /// [`MAX_JUMP`]; `None` when that is not above the initial window.
    fn jump(&self, record: &PathRecord) -> Option<u64> {
        let jump = (record.window / 2).min(MAX_JUMP);
        (jump > self.initial_window).then_some(jump)
    }

    /// The records in use at `now`, newest first, with what each would resume.
    pub fn snapshot(&mut self, now: Instant) -> Vec<PathView> {
        self.expire(now);
        let mut views: Vec<PathView> = self
            .records
            .iter()
            .map(|(addr, r)| PathView {
                addr: *addr,
                window_bytes: r.window,
                jump_bytes: self.jump(r).unwrap_or(0),
                rtt_ms: r.rtt.as_secs_f64() * 1e3,
                age_s: now.saturating_duration_since(r.at).as_secs_f64(),
            })
            .collect();
        views.sort_by(|a, b| a.age_s.total_cmp(&b.age_s).then(a.addr.cmp(&b.addr)));
        views
    }

    /// The record of `peer`, if one is kept.
    pub fn get(&self, peer: IpAddr) -> Option<&PathRecord> {
        self.records.get(&peer)
    }

    /// Records kept.
    pub fn len(&self) -> usize {
        self.records.len()
    }

    /// Whether no record is kept.
    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// Forgets every path (benchmarks measure first contacts with it; `DELETE /v1/paths`);
    /// returns how many were kept.
    pub fn clear(&mut self) -> usize {
        let n = self.records.len();
        self.records.clear();
        n
    }

    /// Writes the records still in use at `now` to `path` (a temporary file, then renamed):
    /// addresses, windows, RTTs and ages, with the wall-clock time of writing.
    pub fn save(&mut self, path: &Path, now: Instant) -> Result<usize, PathFileError> {
        self.expire(now);
        let io = |source| PathFileError::Io {
            path: path.to_owned(),
            source,
        };
        let saved = SavedPaths {
            version: PATHS_FILE_VERSION,
            saved_at_unix_ms: unix_ms(SystemTime::now()),
            records: self
                .records
                .iter()
                .map(|(addr, r)| SavedPath {
                    addr: *addr,
                    window: r.window,
                    rtt_ns: u64::try_from(r.rtt.as_nanos()).unwrap_or(u64::MAX),
                    age_ms: u64::try_from(now.saturating_duration_since(r.at).as_millis())
                        .unwrap_or(u64::MAX),
                })
                .collect(),
        };
        write_json(path, &saved).map_err(io)?;
        Ok(saved.records.len())
    }

    /// Reads records written by [`PathMemory::save`] from `path`, each aged by its age then
    /// plus the wall-clock time since; those past the lifetime, with a zero window or RTT, or
    /// beyond the capacity (the oldest first) are left out. A missing file is no record.
    /// Returns how many records the memory holds then.
    pub fn load(&mut self, path: &Path, now: Instant) -> Result<usize, PathFileError> {
        let format = |reason: String| PathFileError::Format {
            path: path.to_owned(),
            reason,
        };
        let io = |source| PathFileError::Io {
            path: path.to_owned(),
            source,
        };
        let saved: SavedPaths = match read_json(path, MAX_PATHS_FILE_BYTES).map_err(io)? {
            ReadState::Missing => return Ok(0),
            ReadState::TooLarge(bytes) => {
                return Err(PathFileError::TooLarge {
                    path: path.to_owned(),
                    bytes,
                });
            }
            ReadState::Malformed(reason) => return Err(format(reason)),
            ReadState::Read(saved) => saved,
        };
        if saved.version != PATHS_FILE_VERSION {
            return Err(format(format!(
                "version {} (this server reads {PATHS_FILE_VERSION})",
                saved.version
            )));
        }
        // A clock set back since the file was written counts as no time passed.
        let since_saved = unix_ms(SystemTime::now()).saturating_sub(saved.saved_at_unix_ms);
        let mut records: Vec<(IpAddr, u64, Duration, Duration)> = saved
            .records
            .into_iter()
            .map(|r| {
                let age = Duration::from_millis(r.age_ms.saturating_add(since_saved));
                (r.addr, r.window, Duration::from_nanos(r.rtt_ns), age)
            })
            .filter(|&(_, window, rtt, age)| window > 0 && !rtt.is_zero() && age < self.lifetime)
            .collect();
        records.sort_by_key(|&(_, _, _, age)| std::cmp::Reverse(age));
        for (addr, window, rtt, age) in records {
            // Oldest first, so beyond the capacity the newest stay. An age reaching back
            // before this machine's monotonic clock began cannot be placed: left out.
            if let Some(at) = now.checked_sub(age) {
                self.handle_close(addr, at, window, rtt);
            }
        }
        Ok(self.records.len())
    }

    fn expire(&mut self, now: Instant) {
        let lifetime = self.lifetime;
        self.records
            .retain(|_, r| now.saturating_duration_since(r.at) < lifetime);
    }
}

fn unix_ms(t: SystemTime) -> u64 {
    t.duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

/// Where a resumed connection stands (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// The initial window, until the first acknowledgement measures the path.
    Reconnaissance,
    /// The jump is in effect, since the given time.
    Unvalidated { since: Instant },
    /// An ordinary connection from here on.
    Done,
}

/// What happened to a resumption, for the counters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ResumeEvent {
    /// The path was confirmed and the window jumped.
    Jumped,
    /// The path's RTT differed too much from the saved one: no jump.
    Refused,
    /// A congestion event during the jump ended it.
    Retreated,
}

/// The careful-resume decision as plain data, with time and measurements passed in.
#[derive(Clone, Copy, Debug)]
pub struct ResumeState {
    resume: Resume,
    phase: Phase,
}

impl ResumeState {
    pub fn new(resume: Resume) -> Self {
        ResumeState {
            resume,
            phase: Phase::Reconnaissance,
        }
    }

    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// An acknowledgement arrived for a packet that took `rtt` to be acknowledged; Cubic's own
    /// window is now `inner_window`.
    pub fn handle_ack(
        &mut self,
        now: Instant,
        rtt: Duration,
        inner_window: u64,
    ) -> Option<ResumeEvent> {
        match self.phase {
            Phase::Reconnaissance => {
                let (now_rtt, saved) = (rtt.max(RTT_FLOOR), self.resume.rtt.max(RTT_FLOOR));
                if now_rtt * 2 < saved || now_rtt > saved * 10 {
                    self.phase = Phase::Done;
                    Some(ResumeEvent::Refused)
                } else {
                    self.phase = Phase::Unvalidated { since: now };
                    Some(ResumeEvent::Jumped)
                }
            }
            Phase::Unvalidated { since } => {
                let bound = self.resume.rtt.max(RTT_FLOOR) * UNVALIDATED_RTTS;
                if inner_window >= self.resume.jump || now.saturating_duration_since(since) > bound
                {
                    self.phase = Phase::Done;
                }
                None
            }
            Phase::Done => None,
        }
    }

    /// Packets were lost or marked congested.
    pub fn handle_congestion(&mut self) -> Option<ResumeEvent> {
        let retreat = matches!(self.phase, Phase::Unvalidated { .. });
        self.phase = Phase::Done;
        retreat.then_some(ResumeEvent::Retreated)
    }

    /// The window in effect, given Cubic's own.
    pub fn window(&self, inner_window: u64) -> u64 {
        match self.phase {
            Phase::Unvalidated { .. } => inner_window.max(self.resume.jump),
            _ => inner_window,
        }
    }
}

/// Counts of what resumed connections did (the service's metrics hold one).
#[derive(Debug, Default)]
pub struct ResumeCounters {
    /// Connections whose window jumped.
    pub jumped: AtomicU64,
    /// Connections whose path's RTT did not match the saved one.
    pub refused: AtomicU64,
    /// Jumps ended by a congestion event.
    pub retreated: AtomicU64,
}

impl ResumeCounters {
    fn count(&self, event: ResumeEvent) {
        let counter = match event {
            ResumeEvent::Jumped => &self.jumped,
            ResumeEvent::Refused => &self.refused,
            ResumeEvent::Retreated => &self.retreated,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }
}

/// What one connection's controller saw of its path, read when the connection ends.
#[derive(Debug, Default)]
pub struct PathObserver {
    /// The smallest round trip of an acknowledged packet, nanoseconds; 0 before the first.
    min_rtt_nanos: AtomicU64,
}

impl PathObserver {
    /// An acknowledged packet took `rtt` from sending to its acknowledgement.
    pub fn handle_rtt(&self, rtt: Duration) {
        let nanos = u64::try_from(rtt.as_nanos()).unwrap_or(u64::MAX).max(1);
        let _ = self
            .min_rtt_nanos
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |m| {
                (m == 0 || nanos < m).then_some(nanos)
            });
    }

    /// The smallest round trip seen, if any packet was acknowledged.
    pub fn min_rtt(&self) -> Option<Duration> {
        match self.min_rtt_nanos.load(Ordering::Relaxed) {
            0 => None,
            n => Some(Duration::from_nanos(n)),
        }
    }
}

/// Builds the [`PathCubic`] controller of one connection.
#[derive(Debug)]
pub struct PathFactory {
    pub cubic: Arc<CubicConfig>,
    /// What the connection may resume; `None`: an ordinary start.
    pub resume: Option<Resume>,
    pub counters: Arc<ResumeCounters>,
    /// Where the connection's round trips are noted; `None`: nowhere (path memory is off).
    pub observer: Option<Arc<PathObserver>>,
    /// Filter random loss (`super::random_loss`), counting its verdicts here; `None`: every
    /// loss reaches Cubic.
    pub losses: Option<Arc<LossCounters>>,
}

impl ControllerFactory for PathFactory {
    fn build(self: Arc<Self>, now: Instant, current_mtu: u16) -> Box<dyn Controller> {
        Box::new(PathCubic {
            inner: Cubic::new(self.cubic.clone(), now, current_mtu),
            losses: self
                .losses
                .clone()
                .map(|counters| (RandomLossFilter::default(), counters)),
            state: self.resume.map(ResumeState::new),
            counters: self.counters.clone(),
            observer: self.observer.clone(),
        })
    }
}

/// Cubic that notes its path's round trips, may resume a remembered window (module docs) and
/// may keep its window through random loss ([`super::random_loss`]).
#[derive(Clone, Debug)]
pub struct PathCubic {
    inner: Cubic,
    losses: Option<(RandomLossFilter, Arc<LossCounters>)>,
    state: Option<ResumeState>,
    counters: Arc<ResumeCounters>,
    observer: Option<Arc<PathObserver>>,
}

impl PathCubic {
    fn note(&self, event: Option<ResumeEvent>) {
        if let (Some(event), Some(state)) = (event, &self.state) {
            self.counters.count(event);
            tracing::debug!(?event, jump = state.resume.jump, "path resume");
        }
    }
}

impl Controller for PathCubic {
    fn on_sent(&mut self, now: Instant, bytes: u64, last_packet_number: u64) {
        self.inner.on_sent(now, bytes, last_packet_number);
    }

    fn on_ack(
        &mut self,
        now: Instant,
        sent: Instant,
        bytes: u64,
        app_limited: bool,
        rtt: &quinn_proto::RttEstimator,
    ) {
        self.inner.on_ack(now, sent, bytes, app_limited, rtt);
        // The acknowledged packet's own round trip: the estimator may not have a sample yet
        // (it then reports the configured initial RTT, 333 ms, which would pass for any path).
        let measured = now.saturating_duration_since(sent);
        if let Some(o) = &self.observer {
            o.handle_rtt(measured);
        }
        if let Some((filter, _)) = &mut self.losses {
            filter.handle_ack(measured);
        }
        let inner_window = self.inner.window();
        let event = self
            .state
            .as_mut()
            .and_then(|s| s.handle_ack(now, measured, inner_window));
        self.note(event);
    }

    fn on_end_acks(
        &mut self,
        now: Instant,
        in_flight: u64,
        app_limited: bool,
        largest_packet_num_acked: Option<u64>,
    ) {
        self.inner
            .on_end_acks(now, in_flight, app_limited, largest_packet_num_acked);
        if let Some((filter, _)) = &mut self.losses {
            filter.handle_end_acks();
        }
    }

    fn on_congestion_event(
        &mut self,
        now: Instant,
        sent: Instant,
        is_persistent_congestion: bool,
        lost_bytes: u64,
    ) {
        if let Some((filter, counters)) = &mut self.losses {
            let verdict = filter.handle_congestion(now, sent, is_persistent_congestion, lost_bytes);
            counters.count(verdict);
            tracing::trace!(?verdict, queue = ?filter.queue_delay(), "loss event");
            if !verdict.reaches_controller() {
                return;
            }
        }
        self.inner
            .on_congestion_event(now, sent, is_persistent_congestion, lost_bytes);
        let event = self.state.as_mut().and_then(ResumeState::handle_congestion);
        self.note(event);
    }

    fn on_mtu_update(&mut self, new_mtu: u16) {
        self.inner.on_mtu_update(new_mtu);
    }

    fn window(&self) -> u64 {
        let inner = self.inner.window();
        self.state.as_ref().map_or(inner, |s| s.window(inner))
    }

    fn metrics(&self) -> ControllerMetrics {
        let mut m = self.inner.metrics();
        m.congestion_window = self.window();
        m
    }

    fn clone_box(&self) -> Box<dyn Controller> {
        Box::new(self.clone())
    }

    fn initial_window(&self) -> u64 {
        self.inner.initial_window()
    }

    fn into_any(self: Box<Self>) -> Box<dyn Any> {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::Ipv4Addr;

    const MS: Duration = Duration::from_millis(1);

    fn ip(last: u8) -> IpAddr {
        IpAddr::V4(Ipv4Addr::new(10, 0, 0, last))
    }

    #[test]
    fn a_returning_address_resumes_at_half_its_window_until_the_record_expires() {
        let t0 = Instant::now();
        let mut m = PathMemory::new(Duration::from_secs(600), 16);
        m.set_initial_window(128 << 10);
        assert_eq!(m.poll_resume(ip(1), t0), None, "nothing known");
        m.handle_close(ip(1), t0, 1 << 20, 50 * MS);
        assert_eq!(
            m.poll_resume(ip(1), t0 + MS),
            Some(Resume {
                jump: 512 << 10,
                rtt: 50 * MS
            })
        );
        assert_eq!(m.poll_resume(ip(2), t0), None, "another address");
        // A window not worth a jump: half of it is below the initial window.
        m.handle_close(ip(3), t0, 200 << 10, 50 * MS);
        assert_eq!(m.poll_resume(ip(3), t0), None);
        // Huge windows are capped.
        m.handle_close(ip(4), t0, u64::MAX, 50 * MS);
        assert_eq!(m.poll_resume(ip(4), t0).unwrap().jump, MAX_JUMP);
        // Nothing learned from zeros.
        m.handle_close(ip(5), t0, 0, 50 * MS);
        m.handle_close(ip(6), t0, 1 << 20, Duration::ZERO);
        assert!(m.get(ip(5)).is_none() && m.get(ip(6)).is_none());
        // Expired after the lifetime.
        assert_eq!(m.poll_resume(ip(1), t0 + Duration::from_secs(600)), None);
        assert!(m.is_empty(), "expired records are dropped");
    }

    #[test]
    fn the_memory_stays_within_its_capacity_forgetting_the_oldest() {
        let t0 = Instant::now();
        let mut m = PathMemory::new(Duration::from_secs(600), 3);
        for i in 0..10u8 {
            m.handle_close(ip(i), t0 + u32::from(i) * MS, 1 << 20, 10 * MS);
            assert!(m.len() <= 3);
        }
        assert!(m.get(ip(9)).is_some() && m.get(ip(7)).is_some());
        assert!(m.get(ip(6)).is_none() && m.get(ip(0)).is_none());
        // A known address is updated in place, evicting nothing.
        m.handle_close(ip(8), t0 + 20 * MS, 4 << 20, 10 * MS);
        assert_eq!(m.len(), 3);
        assert_eq!(m.get(ip(8)).unwrap().window, 4 << 20);
    }

    #[test]
    fn an_off_memory_keeps_nothing() {
        let t0 = Instant::now();
        let mut m = PathMemory::default();
        m.handle_close(ip(1), t0, 1 << 20, 10 * MS);
        assert!(m.is_empty());
        let mut m = PathMemory::new(Duration::from_secs(1), 8);
        m.handle_close(ip(1), t0, 1 << 20, 10 * MS);
        m.set_lifetime(Duration::ZERO);
        assert!(m.is_empty());
    }

    fn resume() -> Resume {
        Resume {
            jump: 512 << 10,
            rtt: 50 * MS,
        }
    }

    #[test]
    fn a_confirmed_path_jumps_and_hands_over_once_cubic_catches_up() {
        let t0 = Instant::now();
        let mut s = ResumeState::new(resume());
        assert_eq!(
            s.window(128 << 10),
            128 << 10,
            "reconnaissance: the initial window"
        );
        assert_eq!(
            s.handle_ack(t0, 60 * MS, 130 << 10),
            Some(ResumeEvent::Jumped)
        );
        assert_eq!(s.window(130 << 10), 512 << 10);
        assert_eq!(s.handle_ack(t0 + 10 * MS, 55 * MS, 400 << 10), None);
        assert!(matches!(s.phase(), Phase::Unvalidated { .. }));
        assert_eq!(s.window(400 << 10), 512 << 10);
        // Slow start carried Cubic's own window to the jump: validated.
        assert_eq!(s.handle_ack(t0 + 60 * MS, 55 * MS, 520 << 10), None);
        assert_eq!(s.phase(), Phase::Done);
        assert_eq!(s.window(520 << 10), 520 << 10);
        assert_eq!(s.window(100 << 10), 100 << 10, "Cubic's from here on");
    }

    #[test]
    fn a_different_rtt_refuses_the_jump_on_both_sides_of_the_band() {
        for rtt in [24 * MS, 501 * MS] {
            let mut s = ResumeState::new(resume());
            assert_eq!(
                s.handle_ack(Instant::now(), rtt, 130 << 10),
                Some(ResumeEvent::Refused),
                "{rtt:?}"
            );
            assert_eq!(s.window(130 << 10), 130 << 10);
            assert_eq!(s.phase(), Phase::Done);
        }
        for rtt in [25 * MS, 500 * MS] {
            let mut s = ResumeState::new(resume());
            assert_eq!(
                s.handle_ack(Instant::now(), rtt, 130 << 10),
                Some(ResumeEvent::Jumped),
                "{rtt:?} is within the band"
            );
        }
        // Sub-millisecond paths (loopback) compare at the floor.
        let mut s = ResumeState::new(Resume {
            jump: 512 << 10,
            rtt: Duration::from_micros(90),
        });
        assert_eq!(
            s.handle_ack(Instant::now(), Duration::from_micros(30), 130 << 10),
            Some(ResumeEvent::Jumped)
        );
    }

    #[test]
    fn a_loss_during_the_jump_retreats_to_cubics_window() {
        let t0 = Instant::now();
        let mut s = ResumeState::new(resume());
        s.handle_ack(t0, 50 * MS, 130 << 10);
        assert_eq!(s.handle_congestion(), Some(ResumeEvent::Retreated));
        assert_eq!(s.window(91 << 10), 91 << 10);
        assert_eq!(s.handle_congestion(), None, "once");
        // Before the jump, a loss just ends the resumption.
        let mut s = ResumeState::new(resume());
        assert_eq!(s.handle_congestion(), None);
        assert_eq!(s.handle_ack(t0, 50 * MS, 130 << 10), None);
        assert_eq!(s.window(130 << 10), 130 << 10);
    }

    #[test]
    fn saved_records_come_back_with_their_ages_and_expired_ones_do_not() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join(PATHS_FILE);
        let t0 = Instant::now();
        let later = t0 + Duration::from_secs(500);
        let mut m = PathMemory::new(Duration::from_secs(600), 16);
        m.handle_close(ip(1), t0, 1 << 20, 50 * MS);
        m.handle_close(ip(2), t0 + Duration::from_secs(400), 2 << 20, 80 * MS);
        assert_eq!(m.save(&file, later).unwrap(), 2);

        let now = Instant::now() + Duration::from_secs(1000);
        let mut back = PathMemory::new(Duration::from_secs(600), 16);
        assert_eq!(back.load(&file, now).unwrap(), 2);
        let r1 = *back.get(ip(1)).unwrap();
        assert_eq!((r1.window, r1.rtt), (1 << 20, 50 * MS));
        let age = now.duration_since(r1.at);
        assert!(
            (Duration::from_secs(500)..Duration::from_secs(510)).contains(&age),
            "the age carried over: {age:?}"
        );
        assert_eq!(back.get(ip(2)).unwrap().window, 2 << 20);

        // A shorter lifetime leaves out what is older than it; a small capacity keeps the newest.
        let mut short = PathMemory::new(Duration::from_secs(300), 16);
        assert_eq!(short.load(&file, now).unwrap(), 1);
        assert!(short.get(ip(1)).is_none() && short.get(ip(2)).is_some());
        let mut one = PathMemory::new(Duration::from_secs(600), 1);
        assert_eq!(one.load(&file, now).unwrap(), 1);
        assert!(one.get(ip(2)).is_some());
    }

    #[test]
    fn a_bad_paths_file_is_an_error_naming_it_and_loads_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join(PATHS_FILE);
        let mut m = PathMemory::new(Duration::from_secs(600), 16);
        m.set_initial_window(128 << 10);
        assert_eq!(
            m.load(&file, Instant::now()).unwrap(),
            0,
            "no file: no record"
        );
        for text in [
            "not json",
            r#"{"version":2,"saved_at_unix_ms":0,"records":[]}"#,
            r#"{"version":1,"saved_at_unix_ms":0,"records":[{"addr":"x","window":1,"rtt_ns":1,"age_ms":0}]}"#,
            r#"{"version":1,"saved_at_unix_ms":0,"records":[],"extra":1}"#,
            r#"{"version":1,"saved_at_unix_ms":0,"records":[{"addr":"10.0.0.1","window":-1,"rtt_ns":1,"age_ms":0}]}"#,
        ] {
            std::fs::write(&file, text).unwrap();
            let e = m.load(&file, Instant::now()).unwrap_err();
            assert!(matches!(e, PathFileError::Format { .. }), "{text}: {e}");
            assert!(e.to_string().contains(PATHS_FILE), "{e}");
        }
        std::fs::write(&file, vec![b' '; MAX_PATHS_FILE_BYTES as usize + 1]).unwrap();
        assert!(matches!(
            m.load(&file, Instant::now()),
            Err(PathFileError::TooLarge { .. })
        ));
        // Absurd values in a well-formed file are left out, not trusted.
        std::fs::write(
            &file,
            format!(
                r#"{{"version":1,"saved_at_unix_ms":{},"records":[
                {{"addr":"10.0.0.1","window":0,"rtt_ns":1000000,"age_ms":0}},
                {{"addr":"10.0.0.2","window":1000000,"rtt_ns":0,"age_ms":0}},
                {{"addr":"10.0.0.3","window":1000000,"rtt_ns":1000000,"age_ms":18446744073709551615}},
                {{"addr":"10.0.0.4","window":18446744073709551615,"rtt_ns":18446744073709551615,"age_ms":0}}]}}"#,
                unix_ms(SystemTime::now())
            ),
        )
        .unwrap();
        assert_eq!(m.load(&file, Instant::now()).unwrap(), 1);
        assert_eq!(m.poll_resume(ip(4), Instant::now()).unwrap().jump, MAX_JUMP);
        assert_eq!(m.len(), 1);
    }

    #[test]
    fn the_observer_keeps_the_smallest_round_trip() {
        let o = PathObserver::default();
        assert_eq!(o.min_rtt(), None);
        o.handle_rtt(80 * MS);
        o.handle_rtt(50 * MS);
        o.handle_rtt(90 * MS);
        assert_eq!(o.min_rtt(), Some(50 * MS));
        o.handle_rtt(Duration::ZERO);
        assert_eq!(
            o.min_rtt(),
            Some(Duration::from_nanos(1)),
            "zero counts as 1 ns"
        );
    }

    #[test]
    fn an_unvalidated_jump_ends_after_its_round_trips() {
        let t0 = Instant::now();
        let mut s = ResumeState::new(resume());
        s.handle_ack(t0, 50 * MS, 130 << 10);
        s.handle_ack(t0 + 50 * MS * UNVALIDATED_RTTS, 50 * MS, 130 << 10);
        assert!(
            matches!(s.phase(), Phase::Unvalidated { .. }),
            "not past the bound yet"
        );
        s.handle_ack(t0 + 50 * MS * UNVALIDATED_RTTS + MS, 50 * MS, 130 << 10);
        assert_eq!(s.phase(), Phase::Done);
        assert_eq!(s.window(130 << 10), 130 << 10);
    }
}
