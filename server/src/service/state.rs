//! What the running service knows about itself, shared between the QUIC side (which updates it)
//! and the admin API (which reports it): Prometheus-style metrics, live sessions, readiness.
//!
//! Counters are atomics so the per-treelet path never takes a lock for them; the session table
//! is a mutex-guarded map touched once per request list and once per treelet.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::SystemTime;

use arbor_proto::Channel;
use arbor_proto::wire::ErrorCode;
use serde::Serialize;

use super::certificate::{LiveCertificate, PresentedCertificate};
use super::path_memory::{PathMemory, ResumeCounters};
use super::random_loss::LossCounters;
use super::shapes::ShapeCache;
use super::treelets::MessageCache;
use super::visibility::{FineCutGates, NodeCache};
use crate::prometheus::{Buckets, Histogram, Kind, PromText};

/// Upper bounds (seconds) of the request-to-send latency histogram buckets.
pub const LATENCY_BUCKETS: [f64; 14] = [
    0.000_5, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0,
];

/// The request-to-send latency's buckets ([`LATENCY_BUCKETS`]).
#[derive(Debug)]
pub struct LatencyBuckets;

impl Buckets for LatencyBuckets {
    const BOUNDS: &'static [f64] = &LATENCY_BUCKETS;
}

/// Service-wide counters.
#[derive(Debug, Default)]
pub struct Metrics {
    pub connections_accepted: AtomicU64,
    pub connections_rejected: AtomicU64,
    pub connections_open: AtomicU64,
    pub request_lists: AtomicU64,
    pub request_items: AtomicU64,
    pub treelets_sent: AtomicU64,
    pub treelet_bytes_sent: AtomicU64,
    /// Treelet streams written whole, each a batch of treelets adjacent in rank
    /// (`treelets_sent / treelet_streams` is the mean batch).
    pub treelet_streams: AtomicU64,
    pub treelets_cancelled: AtomicU64,
    /// Deep lists whose push plan needed the pool and was made on a reader, the list applied
    /// without its pushes meanwhile.
    pub plans_on_readers: AtomicU64,
    /// What the pool's reader threads did.
    pub pool_reads: Arc<super::ReadFigures>,
    /// How far the start's read of the pool into the page cache went (`service::prewarm`).
    pub pool_prewarm: Arc<super::prewarm::PrewarmFigures>,
    /// Treelets planned as pushes below deep request lists, summed over lists (a push still
    /// implied by the next list is planned again).
    pub pushes_planned: AtomicU64,
    /// Visible cuts computed for resting views (`service::visibility`).
    pub visible_cuts: AtomicU64,
    /// Fine cuts not cast because the scene's last fine cuts went unused
    /// (`visibility::FineCutGate`).
    pub fine_cuts_skipped: AtomicU64,
    /// Resting deep lists for which no cut was cast because it could not have changed them:
    /// no free slots beyond the listed items and no prefetch (`push::cut_has_work`).
    pub cuts_without_work: AtomicU64,
    /// Prefetch items of deep request lists set apart under a visible cut (sent after its
    /// pushes, few in flight: `push::cut_list`), summed over lists.
    pub prefetch_set_apart: AtomicU64,
    /// Request-to-send latency: from the first list naming a treelet to its stream finishing.
    pub request_to_send: Histogram<LatencyBuckets>,
    /// What connections resumed from a remembered path did (`service::path_memory`).
    pub path_resumes: Arc<ResumeCounters>,
    /// Loss events as the random-loss filter judged them (`service::random_loss`).
    pub loss_events: Arc<LossCounters>,
    errors: [AtomicU64; ErrorCode::ALL.len()],
}

impl Metrics {
    /// Counts an error of `code` (a connection closed or a stream reset with it).
    pub fn error(&self, code: ErrorCode) {
        if let Some(i) = ErrorCode::ALL.iter().position(|c| *c == code) {
            self.errors[i].fetch_add(1, Ordering::Relaxed);
        }
    }

    pub fn errors(&self, code: ErrorCode) -> u64 {
        ErrorCode::ALL
            .iter()
            .position(|c| *c == code)
            .map_or(0, |i| self.errors[i].load(Ordering::Relaxed))
    }
}

/// One live connection, as the admin API shows it.
#[derive(Debug, Clone, Serialize)]
pub struct SessionInfo {
    pub id: u64,
    pub peer: SocketAddr,
    /// Empty until the client's `Hello` was accepted.
    pub scene: String,
    pub channels: Vec<&'static str>,
    /// Seconds since the Unix epoch.
    pub connected_at: f64,
    pub request_lists: u64,
    pub treelets_sent: u64,
    pub bytes_sent: u64,
    pub queue_depth: u64,
    pub in_flight: u64,
}

impl SessionInfo {
    pub fn new(id: u64, peer: SocketAddr) -> Self {
        Self {
            id,
            peer,
            scene: String::new(),
            channels: Vec::new(),
            connected_at: unix_now(),
            request_lists: 0,
            treelets_sent: 0,
            bytes_sent: 0,
            queue_depth: 0,
            in_flight: 0,
        }
    }

    pub fn set_channels(&mut self, channels: &[Channel]) {
        self.channels = channels.iter().map(|c| c.name()).collect();
    }
}

/// Everything shared by the service's tasks and the admin API.
#[derive(Debug, Default)]
pub struct ServiceState {
    pub metrics: Metrics,
    sessions: Mutex<BTreeMap<u64, SessionInfo>>,
    ready: AtomicBool,
    shutting_down: AtomicBool,
    /// SHA-256 of the server certificate (DER), lowercase hex, when no listener registered
    /// its certificate ([`ServiceState::fingerprint`]).
    fingerprint: String,
    /// The certificates the listeners present, by listener (`quic`, `admin`).
    certificates: Mutex<Vec<(&'static str, Arc<LiveCertificate>)>>,
    /// Reloads of the configuration (SIGHUP) and how the last one went.
    reloads: Mutex<ReloadRecord>,
    /// Per-treelet timeline for benchmarks; off unless started.
    pub timeline: super::timeline::Timeline,
    /// The server-wide caches, reported in `/metrics`; set once by the service as it starts.
    caches: OnceLock<ServiceCaches>,
    /// The service's memory bound, with the scenes the pool held at the start; set once by
    /// the service as it starts.
    memory_bound: OnceLock<super::config::MemoryBound>,
    /// The configured limits `/metrics` reports beside the figures they bound; set once by the
    /// service as it starts.
    limits: OnceLock<ServiceLimits>,
    /// Congestion windows and RTTs of recent connections by client address; off (lifetime
    /// zero) until the service sets `path_memory_secs`.
    paths: Mutex<PathMemory>,
}

/// The configuration's reloads since the start ([`crate::daemon::Reloader`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReloadRecord {
    /// Reloads put in force.
    pub applied: u64,
    /// Reloads refused: something did not load, and nothing changed.
    pub failed: u64,
    /// Whether the last reload was put in force (true before the first: the start's
    /// configuration loaded).
    pub last_successful: bool,
    /// When the configuration in force was loaded, seconds since the Unix epoch.
    pub last_success_unix: f64,
}

impl Default for ReloadRecord {
    fn default() -> Self {
        Self {
            applied: 0,
            failed: 0,
            last_successful: true,
            last_success_unix: unix_now(),
        }
    }
}

fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// Limits of a running service that alerts compare its figures with (so the shipped rules
/// need no copy of the configuration).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ServiceLimits {
    /// `max_connections`: clients beyond it are refused.
    pub max_connections: usize,
    /// `pool_readers`: threads reading the pool.
    pub pool_readers: usize,
}

/// The caches every scene of a running service shares, and what it learned of each scene.
#[derive(Clone, Debug)]
pub struct ServiceCaches {
    /// Built treelet messages (`message_cache_bytes`).
    pub messages: Arc<MessageCache>,
    /// Decoded treelet shapes for the push plans (`shape_cache_bytes`).
    pub shapes: Arc<ShapeCache>,
    /// Decoded node records for the visible cuts (`visibility_node_cache_bytes`).
    pub cut_nodes: Arc<NodeCache>,
    /// What each scene's fine cuts have been worth lately (`visibility::FineCutGate`).
    pub fine_cuts: Arc<FineCutGates>,
}

impl ServiceCaches {
    /// Empty caches of the sizes `config` gives.
    pub fn for_config(config: &super::config::ServeConfig) -> ServiceCaches {
        let bytes = |b: u64| usize::try_from(b).unwrap_or(usize::MAX);
        ServiceCaches {
            messages: Arc::new(MessageCache::new(bytes(config.message_cache_bytes))),
            shapes: Arc::new(ShapeCache::for_shapes(bytes(config.shape_cache_bytes))),
            cut_nodes: Arc::new(NodeCache::for_nodes(bytes(
                config.visibility_node_cache_bytes,
            ))),
            fine_cuts: Arc::default(),
        }
    }
}

impl ServiceState {
    pub fn new(fingerprint: String) -> Self {
        Self {
            fingerprint,
            ..Self::default()
        }
    }

    /// SHA-256 of the certificate QUIC clients are shown now (lowercase hex): what they pin.
    pub fn fingerprint(&self) -> String {
        self.certificate("quic")
            .map_or_else(|| self.fingerprint.clone(), |c| c.fingerprint.clone())
    }

    /// The certificate `listener` presents now, once registered.
    pub fn certificate(&self, listener: &str) -> Option<Arc<PresentedCertificate>> {
        self.certificates
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .find(|(l, _)| *l == listener)
            .map(|(_, c)| c.current())
    }

    /// Registers the certificate `listener` presents, for [`ServiceState::fingerprint`] and
    /// `/metrics`; a second registration of a listener replaces the first.
    pub fn present_certificate(&self, listener: &'static str, certificate: Arc<LiveCertificate>) {
        let mut all = self.certificates.lock().unwrap_or_else(|p| p.into_inner());
        all.retain(|(l, _)| *l != listener);
        all.push((listener, certificate));
    }

    /// The certificate each listener presents now.
    pub fn certificates(&self) -> Vec<(&'static str, Arc<PresentedCertificate>)> {
        self.certificates
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .map(|(l, c)| (*l, c.current()))
            .collect()
    }

    /// Counts a reload of the configuration: put in force, or refused.
    pub fn record_reload(&self, applied: bool) {
        let mut r = self.reloads.lock().unwrap_or_else(|p| p.into_inner());
        if applied {
            r.applied += 1;
            r.last_success_unix = unix_now();
        } else {
            r.failed += 1;
        }
        r.last_successful = applied;
    }

    /// The reloads so far.
    pub fn reloads(&self) -> ReloadRecord {
        *self.reloads.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Ready: the pool is open, the QUIC endpoint is bound and shutdown has not begun.
    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire) && !self.is_shutting_down()
    }

    pub fn set_ready(&self, ready: bool) {
        self.ready.store(ready, Ordering::Release);
    }

    pub fn is_shutting_down(&self) -> bool {
        self.shutting_down.load(Ordering::Acquire)
    }

    pub fn begin_shutdown(&self) {
        self.shutting_down.store(true, Ordering::Release);
    }

    /// Makes `caches` the ones `/metrics` reports; a second call changes nothing (one service
    /// per state).
    pub fn set_caches(&self, caches: ServiceCaches) {
        let _ = self.caches.set(caches);
    }

    /// Records the service's memory bound (a second call changes nothing).
    pub fn set_memory_bound(&self, bound: super::config::MemoryBound) {
        let _ = self.memory_bound.set(bound);
    }

    /// Records the service's configured limits (once, at start).
    pub fn set_limits(&self, limits: ServiceLimits) {
        let _ = self.limits.set(limits);
    }

    /// The service's memory bound, once it started.
    pub fn memory_bound(&self) -> Option<super::config::MemoryBound> {
        self.memory_bound.get().copied()
    }

    /// What the service remembers of its clients' paths (benchmarks clear it to measure first
    /// contacts).
    pub fn paths(&self) -> std::sync::MutexGuard<'_, PathMemory> {
        self.paths.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub fn add_session(&self, info: SessionInfo) {
        self.lock().insert(info.id, info);
    }

    pub fn update_session(&self, id: u64, f: impl FnOnce(&mut SessionInfo)) {
        if let Some(s) = self.lock().get_mut(&id) {
            f(s);
        }
    }

    pub fn remove_session(&self, id: u64) -> Option<SessionInfo> {
        self.lock().remove(&id)
    }

    pub fn sessions(&self) -> Vec<SessionInfo> {
        self.lock().values().cloned().collect()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, SessionInfo>> {
        // A panic while holding the lock cannot leave the map inconsistent (single inserts and
        // removals), so a poisoned lock is still usable.
        self.sessions.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The metrics in Prometheus text exposition format (version 0.0.4).
    pub fn render_prometheus(&self) -> String {
        let mut p = PromText::default();
        self.write_prometheus(&mut p);
        p.finish()
    }

    /// The caches' figures (zeros before the service set them).
    fn write_cache_metrics(&self, p: &mut PromText) {
        let (messages, shapes, cut_nodes) = match self.caches.get() {
            Some(c) => (
                c.messages.figures(),
                c.shapes.figures(),
                c.cut_nodes.figures(),
            ),
            None => ((0, 0, 0), Default::default(), Default::default()),
        };
        p.single(
            "arbor_message_cache_bytes",
            Kind::Gauge,
            "Bytes of built treelet messages held, whole buffers as built (message_cache_bytes bounds it).",
            messages.0,
        )
        .single(
            "arbor_message_cache_hits_total",
            Kind::Counter,
            "Treelet messages sent from the message cache.",
            messages.1,
        )
        .single(
            "arbor_message_cache_misses_total",
            Kind::Counter,
            "Treelet messages built from the pool.",
            messages.2,
        )
        .single(
            "arbor_shape_cache_bytes",
            Kind::Gauge,
            "Bytes of decoded treelet shapes held for push plans (shape_cache_bytes bounds it).",
            shapes.bytes,
        )
        .single(
            "arbor_shape_cache_shapes",
            Kind::Gauge,
            "Decoded treelet shapes held for push plans.",
            shapes.entries,
        )
        .single(
            "arbor_shape_cache_hits_total",
            Kind::Counter,
            "Treelet shapes push plans found in the shape cache.",
            shapes.hits,
        )
        .single(
            "arbor_shape_cache_misses_total",
            Kind::Counter,
            "Treelet shapes push plans decoded from the pool.",
            shapes.misses,
        )
        .single(
            "arbor_cut_node_cache_bytes",
            Kind::Gauge,
            "Bytes of decoded node records held for visible cuts (visibility_node_cache_bytes bounds it).",
            cut_nodes.bytes,
        )
        .single(
            "arbor_cut_node_cache_treelets",
            Kind::Gauge,
            "Decoded treelets held for visible cuts.",
            cut_nodes.entries,
        )
        .single(
            "arbor_cut_node_cache_hits_total",
            Kind::Counter,
            "Treelets visible cuts found in the cut node cache.",
            cut_nodes.hits,
        )
        .single(
            "arbor_cut_node_cache_misses_total",
            Kind::Counter,
            "Treelets visible cuts read and decoded from the pool.",
            cut_nodes.misses,
        );
    }

    /// Writes the service's families into `p`.
    pub fn write_prometheus(&self, p: &mut PromText) {
        let m = &self.metrics;
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let resumes = &m.path_resumes;
        let losses = &m.loss_events;
        let reads = &m.pool_reads;
        let counters: [(&str, &str, &AtomicU64); 22] = [
            (
                "arbor_connections_accepted_total",
                "QUIC connections accepted.",
                &m.connections_accepted,
            ),
            (
                "arbor_connections_rejected_total",
                "QUIC connections refused (cap, shutdown).",
                &m.connections_rejected,
            ),
            (
                "arbor_request_lists_total",
                "Request lists received.",
                &m.request_lists,
            ),
            (
                "arbor_request_items_total",
                "Items in request lists received.",
                &m.request_items,
            ),
            (
                "arbor_treelets_sent_total",
                "Treelets sent completely.",
                &m.treelets_sent,
            ),
            (
                "arbor_treelet_bytes_sent_total",
                "Bytes of treelet messages sent.",
                &m.treelet_bytes_sent,
            ),
            (
                "arbor_treelet_streams_total",
                "Treelet streams written whole, each a batch of treelets adjacent in rank.",
                &m.treelet_streams,
            ),
            (
                "arbor_treelets_cancelled_total",
                "Treelet streams reset because the client no longer wanted them.",
                &m.treelets_cancelled,
            ),
            (
                "arbor_reader_jobs_total",
                "Reads run by the pool's readers: batches of treelet messages the message cache \
                 lacked, push plans that needed a shape the shape cache lacked.",
                &reads.run,
            ),
            (
                "arbor_reader_jobs_skipped_total",
                "Reads the pool's readers skipped because nobody waited for them any more \
                 (a batch cancelled by a newer list, a connection gone).",
                &reads.skipped,
            ),
            (
                "arbor_plans_on_readers_total",
                "Deep lists whose push plan needed a shape the shape cache lacked, made on a \
                 reader while the list went without its pushes.",
                &m.plans_on_readers,
            ),
            (
                "arbor_pushes_planned_total",
                "Treelets planned as pushes below deep request lists, summed over lists.",
                &m.pushes_planned,
            ),
            (
                "arbor_visible_cuts_total",
                "Visible cuts cast through the server's tree for resting views.",
                &m.visible_cuts,
            ),
            (
                "arbor_fine_cuts_skipped_total",
                "Fine visible cuts not cast because the scene's last fine cuts went unused \
                 (incomplete or not followed).",
                &m.fine_cuts_skipped,
            ),
            (
                "arbor_cuts_without_work_total",
                "Resting deep lists for which no visible cut was cast because it could not have \
                 changed them (no free slots beyond the listed items, no prefetch).",
                &m.cuts_without_work,
            ),
            (
                "arbor_prefetch_set_apart_total",
                "Prefetch items of deep request lists sent after a visible cut's pushes, summed \
                 over lists.",
                &m.prefetch_set_apart,
            ),
            (
                "arbor_path_resumes_total",
                "Connections that resumed a remembered path's congestion window.",
                &resumes.jumped,
            ),
            (
                "arbor_path_resumes_refused_total",
                "Connections from a remembered address whose RTT showed another path.",
                &resumes.refused,
            ),
            (
                "arbor_path_resume_retreats_total",
                "Resumed windows given up at a loss before the path confirmed them.",
                &resumes.retreated,
            ),
            (
                "arbor_loss_events_congestion_total",
                "Loss events with a queue behind them (or persistent congestion, or ECN marks): \
                 the congestion window was cut.",
                &losses.congestion,
            ),
            (
                "arbor_loss_events_random_passed_total",
                "Loss events without a queue behind them that still cut the congestion window \
                 (one in eight in a row).",
                &losses.random_passed,
            ),
            (
                "arbor_loss_events_random_ignored_total",
                "Loss events without a queue behind them, taken for random loss: the congestion \
                 window was kept.",
                &losses.random_ignored,
            ),
        ];
        for (name, help, value) in counters {
            p.single(name, Kind::Counter, help, load(value));
        }
        self.write_cache_metrics(p);
        p.single(
            "arbor_paths_remembered",
            Kind::Gauge,
            "Client addresses whose last congestion window is remembered.",
            self.paths().len() as u64,
        );
        let sessions = self.sessions();
        let queued: u64 = sessions.iter().map(|s| s.queue_depth).sum();
        let in_flight: u64 = sessions.iter().map(|s| s.in_flight).sum();
        p.single(
            "arbor_connections_open",
            Kind::Gauge,
            "Connections open now.",
            load(&m.connections_open),
        )
        .single(
            "arbor_reader_jobs_waiting",
            Kind::Gauge,
            "Reads queued for or running on the pool's readers now.",
            load(&reads.waiting),
        );
        if let Some(limits) = self.limits.get() {
            p.single(
                "arbor_connections_max",
                Kind::Gauge,
                "Connections the service accepts at most (max_connections); beyond, ServerBusy.",
                limits.max_connections as u64,
            )
            .single(
                "arbor_pool_readers",
                Kind::Gauge,
                "Threads reading the pool (pool_readers): reads waiting beyond them queue.",
                limits.pool_readers as u64,
            );
        }
        p.single(
            "arbor_pool_prewarm_total_bytes",
            Kind::Gauge,
            "Bytes of the pool's files the start's prewarm set out to read into the page cache \
             (0: it did not run; see pool_prewarm).",
            load(&m.pool_prewarm.total),
        )
        .single(
            "arbor_pool_prewarm_hot_bytes",
            Kind::Gauge,
            "Of those, the bytes of the pages the last run had in the page cache, read first \
             (its saved list of hot pages).",
            load(&m.pool_prewarm.hot),
        )
        .single(
            "arbor_pool_prewarm_read_bytes",
            Kind::Gauge,
            "Bytes of the pool's files the prewarm has read so far.",
            load(&m.pool_prewarm.read),
        )
        .single(
            "arbor_pool_prewarm_done",
            Kind::Gauge,
            "1 once the prewarm ended (read all, stopped, skipped or failed).",
            load(&m.pool_prewarm.done),
        )
        .single(
            "arbor_queue_depth",
            Kind::Gauge,
            "Treelets queued to send, over all connections.",
            queued,
        )
        .single(
            "arbor_in_flight",
            Kind::Gauge,
            "Treelets in flight, over all connections.",
            in_flight,
        );
        p.family(
            "arbor_errors_total",
            Kind::Counter,
            "Connections closed or streams reset, by error code.",
        );
        for code in ErrorCode::ALL {
            p.sample(
                "arbor_errors_total",
                &[("kind", code.name())],
                m.errors(code),
            );
        }
        m.request_to_send.write(
            p,
            "arbor_request_to_send_seconds",
            "From the first request list naming a treelet to its stream finishing.",
        );
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    #[test]
    fn prometheus_text_has_every_family_once() {
        let s = ServiceState::new("ab".into());
        s.metrics.treelets_sent.fetch_add(3, Ordering::Relaxed);
        s.metrics.error(ErrorCode::FrameTooLarge);
        s.metrics.request_to_send.observe(Duration::from_millis(3));
        s.add_session(SessionInfo::new(7, "127.0.0.1:1".parse().unwrap()));
        s.update_session(7, |x| x.queue_depth = 5);
        let t = s.render_prometheus();
        assert!(t.contains("arbor_treelets_sent_total 3\n"), "{t}");
        assert!(
            t.contains("arbor_errors_total{kind=\"frame_too_large\"} 1\n"),
            "{t}"
        );
        assert!(t.contains("arbor_queue_depth 5\n"), "{t}");
        assert!(
            t.contains("arbor_request_to_send_seconds_bucket{le=\"0.005\"} 1\n"),
            "{t}"
        );
        assert!(
            t.contains("arbor_request_to_send_seconds_bucket{le=\"0.002\"} 0\n"),
            "{t}"
        );
        assert!(t.contains("arbor_request_to_send_seconds_count 1\n"), "{t}");
        for family in t.lines().filter(|l| l.starts_with("# TYPE")) {
            let name = family.split_whitespace().nth(2).unwrap();
            assert_eq!(
                t.matches(&format!("# TYPE {name} ")).count(),
                1,
                "{name} declared twice"
            );
        }
        assert_eq!(s.remove_session(7).map(|x| x.queue_depth), Some(5));
        assert!(s.sessions().is_empty());
    }

    #[test]
    fn the_latency_histogram_renders_cumulative_buckets() {
        let s = ServiceState::new("ab".into());
        let h = &s.metrics.request_to_send;
        h.observe(Duration::from_micros(100));
        h.observe_all([
            Duration::from_millis(1),
            Duration::from_millis(3),
            Duration::from_millis(3),
            Duration::from_secs(60),
        ]);
        h.observe_all([]);
        let t = s.render_prometheus();
        let bucket = |le: &str| {
            let line = format!("arbor_request_to_send_seconds_bucket{{le=\"{le}\"}} ");
            t.lines()
                .find_map(|l| l.strip_prefix(&line))
                .unwrap_or_else(|| panic!("no bucket {le} in {t}"))
                .parse::<u64>()
                .unwrap()
        };
        assert_eq!(bucket("0.0005"), 1);
        // A bound is inclusive: 1 ms falls in the 0.001 bucket.
        assert_eq!(bucket("0.001"), 2);
        assert_eq!(bucket("0.002"), 2);
        assert_eq!(bucket("0.005"), 4);
        assert_eq!(bucket("10"), 4);
        // A minute is past the last bound: only in +Inf and the count.
        assert_eq!(bucket("+Inf"), 5);
        assert!(t.contains("arbor_request_to_send_seconds_count 5\n"), "{t}");
        assert!(
            t.contains("arbor_request_to_send_seconds_sum 60.0071\n"),
            "{t}"
        );
    }

    #[test]
    fn readiness_follows_shutdown() {
        let s = ServiceState::default();
        assert!(!s.is_ready());
        s.set_ready(true);
        assert!(s.is_ready());
        s.begin_shutdown();
        assert!(!s.is_ready());
    }
}
