//! Which treelet to send next, to whom: the service's scheduling core, with no I/O.
//!
//! A [`Scheduler`] holds every connection's latest request list and the treelets it has in
//! flight. The service feeds it events and polls it:
//!
//! * [`Scheduler::handle_request_list`] — a `RequestList` arrived. It **replaces** the
//!   connection's previous list; a list whose `seq` is not above the last accepted one is stale
//!   and ignored.
//!   [`Scheduler::handle_list_with_prefetch`] does the same for a list whose lowest-ranked
//!   items are prefetch (see *In-flight window*).
//! * [`Scheduler::poll_transmit`] — the next `(connection, treelet)` to start sending, or `None`.
//!   The treelet enters the connection's in-flight window at once. [`Scheduler::poll_batch`]
//!   takes the next connection's next few treelets at once, one stream's batch (what the service
//!   uses).
//! * [`Scheduler::handle_sent`] — all its bytes were handed to the transport (still in flight).
//! * [`Scheduler::handle_delivered`] — the peer acknowledged it: it leaves the window
//!   ([`Scheduler::handle_delivered_all`] for a stream's whole batch at once).
//! * [`Scheduler::handle_cancelled`] — its stream was reset or failed: it leaves the window and is
//!   queued again if the current list still wants it.
//!
//! # Per-connection queue
//!
//! The queue is *the latest list minus the treelets in flight*, highest priority first, ties by
//! lower id (deterministic). Lists are replaced wholesale, so on arrival the list is cleaned (ids
//! [`TreeletId::NONE`] and non-finite priorities dropped — the wire decoder already rejects them),
//! duplicates are collapsed to their **largest** priority, it is sorted once, cut to the
//! `max_queue` highest-priority items, and treelets in flight are left out. Sending then walks a
//! cursor down the sorted vector. A treelet whose transfer is cancelled while the current list
//! still wants it goes into a small retry heap that is merged with the cursor by rank.
//!
//! Complexity, for a list of `n` items, `w` in flight, `c` connections: a list costs
//! O(n log n) (a sort by id to collapse duplicates, a merge with the previous list, a rank sort
//! of what can be sent) plus O(d) for the `d` deliveries since the connection's last list
//! (indexed by treelet then, for the redelivery guard), and O(n) memory (24 + 24 bytes per
//! item: the by-id index and the queue, each item with since when it is wanted);
//! `poll_transmit` is O(1) amortized per treelet
//! (`poll_batch` likewise) plus O(log r) for `r` retried treelets; `handle_sent`/
//! `handle_delivered` are O(1) expected (hash maps); `handle_cancelled` is O(log n) (binary
//! search of the list by id); `remove_connection` is O(c) (ring cleanup).
//!
//! # What is never sent
//!
//! * A treelet in flight is never started again while it is in flight, whatever the lists say.
//! * A treelet not in the connection's current list is never started. After a replacement list,
//!   treelets of the old list that the new one lacks can still *arrive* only if they were already
//!   in flight; [`ListOutcome::Applied::obsolete_in_flight`] names them so the service may reset
//!   their streams.
//! * **Written, then not wanted.** The service does not reset a stream whose bytes all went to
//!   the transport (a reset would abandon what is unsent or unacknowledged, and the client
//!   drops what it has not read yet): it completes and counts as delivered, under the
//!   redelivery guard.
//! * **Re-requests.** A treelet started under the current list is not started again under that
//!   list (the cursor has passed it) unless its transfer was cancelled. A *new* list may request
//!   a delivered treelet again — the client may have evicted it — and it is then sent again,
//!   except within the connection's `redelivery_guard` after its delivery: a client builds each
//!   list before it has seen the treelets already on their way, so lists arriving up to about one
//!   round trip (plus one client cycle) after a delivery still name it. The service sets the
//!   guard from its RTT estimate; `Duration::ZERO` turns it off. Such a treelet, and one a new
//!   list names while it is still in flight, is *deferred*, not dropped: if the list still
//!   names it once it is delivered and the guard has passed, the client really wants it again
//!   (it had evicted it), and [`Scheduler::release_deferred`] queues it, once. A client
//!   sends a list only when it changes, so a dropped one stayed unsent for good, and the
//!   client's view stalled with a full buffer (on a 16-core machine, loopback views in
//!   `client_e2e` stalled in 6 of 8 runs).
//!
//! # In-flight window
//!
//! A connection may have at most `window` treelets in flight (started and not yet delivered or
//! cancelled). Everything in flight is committed: a new list takes effect after at most `window`
//! more treelets. Sizing the window to the bandwidth-delay product keeps the link busy while
//! making that about one round trip; see [`window_for`]. Of a list's prefetch (the client's
//! guesses for later views, ranked below everything else), at most a
//! [`PREFETCH_SHARE_OF_WINDOW`]th of the window is in flight: prefetch fills the link's idle
//! room without standing between a new view's list and the link.
//!
//! # Fairness
//!
//! Connections that have something to send *and* window room form a ring; `poll_transmit` serves
//! them round-robin, one treelet per turn (`poll_batch`: one batch of at most [`batch_limit`]
//! per turn), so a connection with a 100,000-item list and one with 10 items alternate. (Turns
//! are per treelet or batch, not per byte: treelets are 1–16 KiB and compress to similar sizes
//! within a scene, so such turns are close to byte-fair.) A server-wide cap
//! on treelets in flight ([`SchedulerConfig::max_in_flight`]) makes the service's send capacity
//! the shared resource that the ring divides.

use std::cmp::Ordering;
use std::collections::hash_map::Entry;
use std::collections::{BinaryHeap, VecDeque};
use std::fmt;
use std::time::{Duration, Instant};

use arbor_proto::TreeletId;
use arbor_proto::limits::MAX_REQUEST_ITEMS;
use rustc_hash::{FxHashMap, FxHashSet};

use super::treelets::MAX_TREELETS_PER_STREAM;

/// Batches hold at most this share of a connection's window, so several are in flight and the
/// window refills while a batch is acknowledged.
pub const BATCHES_PER_WINDOW: usize = 4;

/// Prefetch treelets hold at most this share of a connection's window
/// ([`Scheduler::handle_list_with_prefetch`]): engine's jump over the link emulator took
/// 0.22 s with prefetch unbounded and 0.15 s at an eighth (docs/measurements.md, stop 47).
pub const PREFETCH_SHARE_OF_WINDOW: usize = 8;

/// The most treelets [`Scheduler::poll_batch`] hands out at once to a connection with `window`:
/// a quarter of the window, at least 1, at most [`MAX_TREELETS_PER_STREAM`].
pub fn batch_limit(window: usize) -> usize {
    (window / BATCHES_PER_WINDOW).clamp(1, MAX_TREELETS_PER_STREAM)
}

/// Whether a delivery at `at` is within a redelivery guard that began at `start`: strictly
/// less than the guard ago (a zero guard holds nothing).
fn within_guard(at: Instant, start: Option<Instant>) -> bool {
    start.is_none_or(|s| at > s)
}

/// A connection, as the service numbers them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ConnectionId(pub u64);

impl fmt::Display for ConnectionId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "#{}", self.0)
    }
}

/// Mistakes of the caller (the service), never of a client.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ScheduleError {
    /// The connection was never added or was removed.
    #[error("connection {0} is not known to the scheduler")]
    UnknownConnection(ConnectionId),
    /// [`Scheduler::add_connection`] with an id already present.
    #[error("connection {0} is already known to the scheduler")]
    DuplicateConnection(ConnectionId),
}

/// Server-wide settings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SchedulerConfig {
    /// Most treelets in flight over all connections; `poll_transmit` returns `None` at the cap.
    pub max_in_flight: usize,
}

impl Default for SchedulerConfig {
    fn default() -> Self {
        Self {
            max_in_flight: usize::MAX,
        }
    }
}

/// Per-connection settings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConnectionConfig {
    /// Most treelets in flight on this connection ([`window_for`]). 0 pauses the connection.
    pub window: usize,
    /// Most items kept from one list: a longer list is cut to its `max_queue` highest-priority
    /// items (after collapsing duplicates). Bounds the connection's memory.
    pub max_queue: usize,
    /// A treelet delivered less than this before a list arrives is not sent again for that list
    /// (see the module docs). About one RTT plus one client cycle.
    pub redelivery_guard: Duration,
    /// Remember every delivery ([`Scheduler::was_delivered`], up to [`DELIVERIES_REMEMBERED`]):
    /// only the service's visible cuts ask, so connections without them keep no record.
    pub remember_deliveries: bool,
    /// Most deliveries the redelivery record keeps (also at most four lists' worth: four
    /// times the larger of `max_queue` and `window`); older ones within the guard are
    /// forgotten, and a list naming one gets it again. The memory plan sizes it
    /// (`MemoryPlan::recent_deliveries`; [`recent_record_bytes`]).
    pub recent_deliveries: usize,
}

/// Most deliveries a connection remembers for [`Scheduler::was_delivered`] (about 400 KB);
/// past it the record starts afresh, and a push may repeat a treelet the client holds (the
/// client drops the duplicate).
pub const DELIVERIES_REMEMBERED: usize = 1 << 16;

/// Most deliveries a connection's redelivery record keeps however fast it is served: what a
/// connection delivering 650,000 treelets/s delivers within a 50 ms guard (the client's cycle
/// over loopback). About 3.8 MB with the record's index at most ([`recent_record_bytes`]);
/// until stop 57 it was four lists' worth, up to 262,144 deliveries and about 30 MB, which no
/// memory plan counted.
pub const RECENT_DELIVERIES_KEPT: usize = 1 << 15;

/// The most bytes a redelivery record of at most `entries` deliveries and its by-id index
/// hold: the record's queue (a delivery's time and id, 24 bytes; a batch of up to
/// [`MAX_TREELETS_PER_STREAM`] is recorded before the record is pruned, and a growing queue
/// doubles its room) and the index (16 bytes and a control byte per bucket, at least 8 buckets
/// per 7 entries, a power of two of them; up to three times the record's entries and 64 more
/// before it is built afresh, see `Conn::index_recent`).
pub fn recent_record_bytes(entries: usize) -> u64 {
    if entries == 0 {
        return 0;
    }
    let recorded = (entries + MAX_TREELETS_PER_STREAM) as u64;
    let queue = 2 * recorded * 24;
    let indexed = 3 * recorded + 64;
    let buckets = (indexed * 8).div_ceil(7).next_power_of_two();
    queue + buckets * 17 + 16
}

impl Default for ConnectionConfig {
    fn default() -> Self {
        Self {
            window: 16,
            max_queue: MAX_REQUEST_ITEMS,
            redelivery_guard: Duration::from_millis(100),
            remember_deliveries: false,
            recent_deliveries: RECENT_DELIVERIES_KEPT,
        }
    }
}

/// A connection's counters and current state, for metrics and the admin API.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ConnectionStats {
    /// Lists applied (not counting stale ones).
    pub lists_received: u64,
    /// Lists ignored because their `seq` was not above the last applied one.
    pub lists_stale: u64,
    /// Items in applied lists, as received (before collapsing duplicates and truncation).
    pub items_received: u64,
    /// Items dropped from applied lists: invalid, duplicate, or beyond `max_queue`.
    pub items_dropped: u64,
    /// Treelets handed out by `poll_transmit`.
    pub treelets_started: u64,
    /// Treelets reported by `handle_sent`.
    pub treelets_sent: u64,
    /// Treelets reported by `handle_delivered`.
    pub treelets_delivered: u64,
    /// Treelets reported by `handle_cancelled`.
    pub treelets_cancelled: u64,
    /// Treelets waiting to be started now.
    pub queue_depth: usize,
    /// Treelets in flight now.
    pub in_flight: usize,
    /// The window now.
    pub window: usize,
    /// `seq` of the list in force.
    pub last_seq: Option<u64>,
}

/// What [`Scheduler::handle_request_list`] did with a list.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ListOutcome {
    /// Ignored: `seq` was not above `last_seq`.
    Stale { last_seq: u64 },
    /// The list replaced the previous one.
    Applied {
        /// Treelets queued to be sent (list minus in flight and recently delivered).
        queued: usize,
        /// Items dropped: invalid, duplicate, or beyond `max_queue`.
        dropped: usize,
        /// Treelets in flight that the new list no longer names, ascending; they may still
        /// arrive unless the service cancels them.
        obsolete_in_flight: Vec<TreeletId>,
    },
}

/// In-flight window for a link: enough treelets to fill the bandwidth-delay product, so the link
/// stays busy, and no more, so that a new list takes effect within about one round trip:
///
/// `window ≈ clamp(⌈bandwidth × rtt / treelet_bytes⌉, min, max)`
///
/// `treelet_bytes` is the mean bytes sent per treelet (compressed nodes + requested channels).
/// Unknown or nonsensical inputs (zero, negative, NaN bandwidth, zero treelet size) give `min`.
pub fn window_for(
    bandwidth_bytes_per_s: f64,
    rtt: Duration,
    treelet_bytes: usize,
    min: usize,
    max: usize,
) -> usize {
    let max = max.max(min);
    if !(bandwidth_bytes_per_s.is_finite() && bandwidth_bytes_per_s > 0.0) || treelet_bytes == 0 {
        return min;
    }
    let w = (bandwidth_bytes_per_s * rtt.as_secs_f64() / treelet_bytes as f64).ceil();
    // Non-negative here; `as` saturates (+∞ included).
    (w as usize).clamp(min, max)
}

/// Send order: higher priority first, then lower id.
fn rank(a: &(TreeletId, f32), b: &(TreeletId, f32)) -> Ordering {
    b.1.total_cmp(&a.1).then(a.0.cmp(&b.0))
}

/// A retried treelet; the heap's maximum is the one to send first.
#[derive(Clone, Copy, Debug)]
struct Retry(TreeletId, f32);

impl PartialEq for Retry {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Retry {}
impl PartialOrd for Retry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Retry {
    fn cmp(&self, other: &Self) -> Ordering {
        rank(&(other.0, other.1), &(self.0, self.1))
    }
}

/// One item of the current list, in the by-id index.
#[derive(Clone, Copy, Debug)]
struct Wanted {
    id: TreeletId,
    priority: f32,
    /// Since when the client has asked for it in an unbroken run of lists.
    since: Instant,
}

#[derive(Clone, Copy, Debug)]
struct Flight {
    /// When the client first asked for it (see [`Wanted::since`]).
    since: Instant,
    sent: bool,
    /// Started as prefetch ([`Scheduler::handle_list_with_prefetch`]).
    prefetch: bool,
}

#[derive(Debug)]
struct Conn {
    config: ConnectionConfig,
    /// The current list, collapsed and truncated, sorted by id.
    by_id: Vec<Wanted>,
    /// The current list's sendable items in send order; `queue[cursor..]` are still to start.
    /// Each carries its `since`, so starting it needs no search of `by_id`.
    queue: Vec<Wanted>,
    cursor: usize,
    /// Cancelled treelets the current list still wants.
    retry: BinaryHeap<Retry>,
    /// Treelets the current list wants that were delivered within the redelivery guard before
    /// it came, each with the end of its guard.
    deferred: Vec<(Instant, TreeletId)>,
    in_flight: FxHashMap<TreeletId, Flight>,
    /// Deliveries within the redelivery guard, oldest first.
    recent: VecDeque<(Instant, TreeletId)>,
    /// Deliveries ever pushed to `recent`: the one at `recent[i]` is number
    /// `recent_pushed - recent.len() + i`.
    recent_pushed: u64,
    /// The number of the latest delivery of each treelet among those numbered below
    /// `indexed` (some of them already pruned from `recent`; a delivery's time
    /// is in `recent` while it is kept there). Only a list (or the tick's deferred treelets)
    /// asks who was delivered within the guard, so the deliveries since the last such question
    /// are indexed then ([`Conn::index_recent`]), not one by one as they come: a whole-scene
    /// fetch's single list comes before any delivery and never pays for one, and a list costs
    /// the deliveries since the list before, not all those within the guard (with 32,000 of
    /// them and a list every 16 ms, a list took 561–613 µs when the view was rebuilt from
    /// `recent` for each, 137–150 µs so; `cargo bench -p arbor-server --bench schedule`).
    recent_index: FxHashMap<TreeletId, u64>,
    /// Deliveries numbered from here on are not in `recent_index` yet.
    indexed: u64,
    /// Every treelet delivered on this connection when it remembers deliveries (forgotten all
    /// at once at [`Conn::delivered_cap`]): pushes planned from a visible cut leave them out.
    delivered_ever: FxHashSet<TreeletId>,
    /// Items of the current list ranked below this are prefetch
    /// ([`Scheduler::handle_list_with_prefetch`]); `None`: nothing is.
    prefetch_below: Option<f32>,
    /// Flights started as prefetch.
    prefetch_in_flight: usize,
    in_ring: bool,
    stats: ConnectionStats,
}

impl Conn {
    fn new(config: ConnectionConfig) -> Self {
        Self {
            config,
            by_id: Vec::new(),
            queue: Vec::new(),
            cursor: 0,
            retry: BinaryHeap::new(),
            deferred: Vec::new(),
            in_flight: FxHashMap::default(),
            recent: VecDeque::new(),
            recent_pushed: 0,
            recent_index: FxHashMap::default(),
            indexed: 0,
            delivered_ever: FxHashSet::default(),
            prefetch_below: None,
            prefetch_in_flight: 0,
            in_ring: false,
            stats: ConnectionStats::default(),
        }
    }

    /// Most deliveries remembered in `delivered_ever`: four lists' worth, at most
    /// [`DELIVERIES_REMEMBERED`].
    fn delivered_cap(&self) -> usize {
        self.config
            .max_queue
            .max(self.config.window)
            .saturating_mul(4)
            .min(DELIVERIES_REMEMBERED)
    }

    fn queue_depth(&self) -> usize {
        self.queue.len() - self.cursor + self.retry.len()
    }

    fn has_work(&self) -> bool {
        self.cursor < self.queue.len() || !self.retry.is_empty()
    }

    fn eligible(&self) -> bool {
        self.has_work() && self.in_flight.len() < self.config.window && !self.prefetch_held()
    }

    /// Prefetch treelets this connection may have in flight: [`PREFETCH_SHARE_OF_WINDOW`] of
    /// its window, at least one.
    fn prefetch_window(&self) -> usize {
        (self.config.window / PREFETCH_SHARE_OF_WINDOW).max(1)
    }

    /// Whether an item of `priority` is prefetch in the current list.
    fn is_prefetch(&self, priority: f32) -> bool {
        self.prefetch_below.is_some_and(|below| priority < below)
    }

    /// Whether the next item is prefetch and the prefetch window is full. Prefetch ranks below
    /// everything else of its list, so nothing else waits behind it.
    fn prefetch_held(&self) -> bool {
        self.prefetch_below.is_some()
            && self.prefetch_in_flight >= self.prefetch_window()
            && self.peek().is_some_and(|(_, p)| self.is_prefetch(p))
    }

    /// The item [`Conn::pop`] would take, with its priority.
    fn peek(&self) -> Option<(TreeletId, f32)> {
        let head = self.queue.get(self.cursor).map(|h| (h.id, h.priority));
        let retry = self.retry.peek().map(|r| (r.0, r.1));
        match (head, retry) {
            (Some(h), Some(r)) if rank(&r, &h) == Ordering::Less => Some(r),
            (Some(h), _) => Some(h),
            (None, r) => r,
        }
    }

    /// Takes the best of the cursor and the retry heap: the treelet, since when it is wanted,
    /// and its priority.
    fn pop(&mut self, now: Instant) -> Option<(TreeletId, Instant, f32)> {
        let (id, priority) = self.peek()?;
        match self.queue.get(self.cursor) {
            Some(head) if head.id == id => {
                self.cursor += 1;
                Some((id, head.since, priority))
            }
            _ => {
                self.retry.pop();
                Some((id, self.wanted(id).map_or(now, |w| w.since), priority))
            }
        }
    }

    /// Puts `treelet` in flight.
    fn start(&mut self, treelet: TreeletId, since: Instant, priority: f32) {
        let prefetch = self.is_prefetch(priority);
        self.prefetch_in_flight += usize::from(prefetch);
        self.in_flight.insert(
            treelet,
            Flight {
                since,
                sent: false,
                prefetch,
            },
        );
    }

    /// Takes `treelet` out of flight.
    fn finish(&mut self, treelet: TreeletId) -> Option<Flight> {
        let flight = self.in_flight.remove(&treelet)?;
        self.prefetch_in_flight -= usize::from(flight.prefetch);
        Some(flight)
    }

    /// `treelet` is sent in full at `now`: its request-to-send latency, unless it is not in
    /// flight or was reported already.
    fn mark_sent(&mut self, treelet: TreeletId, now: Instant) -> Option<Duration> {
        let flight = self.in_flight.get_mut(&treelet)?;
        if flight.sent {
            return None;
        }
        flight.sent = true;
        self.stats.treelets_sent += 1;
        Some(now.saturating_duration_since(flight.since))
    }

    fn wanted(&self, id: TreeletId) -> Option<&Wanted> {
        self.by_id
            .binary_search_by_key(&id, |w| w.id)
            .ok()
            .map(|i| &self.by_id[i])
    }

    /// `treelet`, just taken out of the window, reached the client (or is about to) at `now`:
    /// counted, remembered for `was_delivered`, and lists within the redelivery guard do not
    /// get it again. The caller prunes the redelivery record afterwards (once per batch).
    fn record_delivery(&mut self, treelet: TreeletId, now: Instant) {
        self.stats.treelets_delivered += 1;
        if !self.config.redelivery_guard.is_zero() {
            self.recent.push_back((now, treelet));
            self.recent_pushed += 1;
        }
        if self.config.remember_deliveries {
            if self.delivered_ever.len() >= self.delivered_cap() {
                self.delivered_ever.clear();
            }
            self.delivered_ever.insert(treelet);
        }
    }

    /// The earliest delivery time still within the redelivery guard at `now` (`None`: every
    /// delivery is). Comparing instants with it is cheaper than a duration per delivery.
    fn guard_start(&self, now: Instant) -> Option<Instant> {
        now.checked_sub(self.config.redelivery_guard)
    }

    /// Forgets deliveries older than the guard (and keeps the record bounded however `now`
    /// moves).
    fn prune_recent(&mut self, now: Instant) {
        let start = self.guard_start(now);
        let cap = self
            .config
            .max_queue
            .max(self.config.window)
            .saturating_mul(4)
            .min(self.config.recent_deliveries);
        while let Some(&(t, _)) = self.recent.front() {
            if within_guard(t, start) && self.recent.len() <= cap {
                break;
            }
            self.recent.pop_front();
        }
    }

    /// The number of the oldest delivery still in `recent`.
    fn oldest_kept(&self) -> u64 {
        self.recent_pushed - self.recent.len() as u64
    }

    /// Brings [`Conn::recent_index`] up to date with `recent`, for
    /// [`Conn::recently_delivered`]. Entries of deliveries pruned since stay until the index
    /// holds twice as many as `recent` (plus a little); then it is built afresh, so its size
    /// stays bounded and each delivery is indexed a constant number of times on average: at
    /// most about twice the entries, of 16 bytes, the view rebuilt per list had (24 bytes).
    fn index_recent(&mut self) {
        let oldest = self.oldest_kept();
        if self.recent_index.len() > 2 * self.recent.len() + 64 {
            self.recent_index.clear();
            self.indexed = oldest;
        }
        // Deliveries pruned before they were indexed need no entry.
        let first = self.indexed.max(oldest);
        let new = self.recent.range((first - oldest) as usize..);
        for (number, &(_, id)) in (first..).zip(new) {
            self.recent_index.insert(id, number);
        }
        self.indexed = self.recent_pushed;
    }

    /// When `treelet` was last delivered, if it still is in `recent` and within the guard that
    /// began at `start` ([`Conn::guard_start`]). Needs [`Conn::index_recent`] first.
    fn recently_delivered(&self, treelet: TreeletId, start: Option<Instant>) -> Option<Instant> {
        debug_assert_eq!(self.indexed, self.recent_pushed, "index_recent first");
        let number = *self.recent_index.get(&treelet)?;
        // A later delivery would have replaced this one: if this one was pruned (by age or by
        // the record's cap) or is past the guard, so is every earlier one.
        let kept = usize::try_from(number.checked_sub(self.oldest_kept())?).ok()?;
        let &(at, _) = self.recent.get(kept)?;
        within_guard(at, start).then_some(at)
    }

    fn snapshot(&self) -> ConnectionStats {
        ConnectionStats {
            queue_depth: self.queue_depth(),
            in_flight: self.in_flight.len(),
            window: self.config.window,
            ..self.stats.clone()
        }
    }
}

/// The scheduling state of every connection. See the module docs.
#[derive(Debug)]
pub struct Scheduler {
    config: SchedulerConfig,
    conns: FxHashMap<ConnectionId, Conn>,
    /// Connections that have work and window room, in round-robin order.
    ring: VecDeque<ConnectionId>,
    total_in_flight: usize,
}

impl Default for Scheduler {
    fn default() -> Self {
        Self::new(SchedulerConfig::default())
    }
}

impl Scheduler {
    pub fn new(config: SchedulerConfig) -> Self {
        Self {
            config,
            conns: FxHashMap::default(),
            ring: VecDeque::new(),
            total_in_flight: 0,
        }
    }

    /// Registers a connection with an empty list.
    pub fn add_connection(
        &mut self,
        id: ConnectionId,
        config: ConnectionConfig,
    ) -> Result<(), ScheduleError> {
        match self.conns.entry(id) {
            Entry::Occupied(_) => Err(ScheduleError::DuplicateConnection(id)),
            Entry::Vacant(v) => {
                v.insert(Conn::new(config));
                Ok(())
            }
        }
    }

    /// Forgets a connection and everything it had in flight; returns its final counters.
    pub fn remove_connection(&mut self, id: ConnectionId) -> Option<ConnectionStats> {
        let conn = self.conns.remove(&id)?;
        self.total_in_flight -= conn.in_flight.len();
        if conn.in_ring {
            self.ring.retain(|&c| c != id);
        }
        Some(conn.snapshot())
    }

    /// Connections known, in no particular order.
    pub fn connections(&self) -> impl Iterator<Item = ConnectionId> + '_ {
        self.conns.keys().copied()
    }

    /// Number of connections.
    pub fn len(&self) -> usize {
        self.conns.len()
    }

    pub fn is_empty(&self) -> bool {
        self.conns.is_empty()
    }

    /// Treelets in flight over all connections.
    pub fn total_in_flight(&self) -> usize {
        self.total_in_flight
    }

    /// A connection's counters and state.
    pub fn stats(&self, id: ConnectionId) -> Option<ConnectionStats> {
        self.conns.get(&id).map(Conn::snapshot)
    }

    /// Changes a connection's window (e.g. from a new RTT or bandwidth estimate). Shrinking it
    /// below the treelets in flight stops new starts until enough are delivered.
    pub fn set_window(&mut self, id: ConnectionId, window: usize) -> Result<(), ScheduleError> {
        let conn = self
            .conns
            .get_mut(&id)
            .ok_or(ScheduleError::UnknownConnection(id))?;
        conn.config.window = window;
        self.wake(id);
        Ok(())
    }

    /// Connection `id` remembers its deliveries from now on
    /// ([`ConnectionConfig::remember_deliveries`]).
    pub fn remember_deliveries(&mut self, id: ConnectionId) -> Result<(), ScheduleError> {
        let conn = self
            .conns
            .get_mut(&id)
            .ok_or(ScheduleError::UnknownConnection(id))?;
        conn.config.remember_deliveries = true;
        Ok(())
    }

    /// Changes a connection's redelivery guard (from a new RTT estimate).
    pub fn set_redelivery_guard(
        &mut self,
        id: ConnectionId,
        guard: Duration,
    ) -> Result<(), ScheduleError> {
        let conn = self
            .conns
            .get_mut(&id)
            .ok_or(ScheduleError::UnknownConnection(id))?;
        conn.config.redelivery_guard = guard;
        Ok(())
    }

    /// A request list arrived at `now`. It replaces the connection's list unless `seq` is not
    /// above the last applied one.
    pub fn handle_request_list(
        &mut self,
        id: ConnectionId,
        seq: u64,
        items: Vec<(TreeletId, f32)>,
        now: Instant,
    ) -> Result<ListOutcome, ScheduleError> {
        self.apply_list(id, seq, items, None, now, false)
    }

    /// [`Scheduler::handle_request_list`], or with `replan` [`Scheduler::handle_replanned_list`],
    /// for a list whose items ranked below `prefetch_below` are **prefetch**: guesses at what a
    /// later view may need. At most [`PREFETCH_SHARE_OF_WINDOW`] of the window (at least one)
    /// of them are in flight at once; the connection sends nothing more until one is
    /// delivered or cancelled. Prefetch ranks below everything else of its list, so only
    /// prefetch waits: the link keeps room, and a new view's list is not queued behind
    /// prefetch already on it (measured: engine's camera jump over the link emulator, docs/
    /// measurements.md, stop 47). A non-finite `prefetch_below` is ignored.
    pub fn handle_list_with_prefetch(
        &mut self,
        id: ConnectionId,
        seq: u64,
        items: Vec<(TreeletId, f32)>,
        prefetch_below: f32,
        replan: bool,
        now: Instant,
    ) -> Result<ListOutcome, ScheduleError> {
        let below = prefetch_below.is_finite().then_some(prefetch_below);
        self.apply_list(id, seq, items, below, now, replan)
    }

    /// The service re-planned the pushes of the list it accepted last, `seq` (a view's visible
    /// cut became available after the list was applied): `items` replace that list like a new
    /// one would, with the same rules. Stale if a newer list was accepted meanwhile (or `seq`
    /// was never accepted). Not counted as a list received.
    pub fn handle_replanned_list(
        &mut self,
        id: ConnectionId,
        seq: u64,
        items: Vec<(TreeletId, f32)>,
        now: Instant,
    ) -> Result<ListOutcome, ScheduleError> {
        self.apply_list(id, seq, items, None, now, true)
    }

    fn apply_list(
        &mut self,
        id: ConnectionId,
        seq: u64,
        mut items: Vec<(TreeletId, f32)>,
        prefetch_below: Option<f32>,
        now: Instant,
        replan: bool,
    ) -> Result<ListOutcome, ScheduleError> {
        let conn = self
            .conns
            .get_mut(&id)
            .ok_or(ScheduleError::UnknownConnection(id))?;
        let stale = match conn.stats.last_seq {
            Some(last_seq) if replan => seq != last_seq,
            Some(last_seq) => seq <= last_seq,
            None => replan,
        };
        if stale {
            if !replan {
                conn.stats.lists_stale += 1;
            }
            return Ok(ListOutcome::Stale {
                last_seq: conn.stats.last_seq.unwrap_or(0),
            });
        }
        conn.stats.last_seq = Some(seq);
        let received = items.len();
        if !replan {
            conn.stats.lists_received += 1;
            conn.stats.items_received += received as u64;
        }

        // Clean, collapse duplicates to their largest priority, rank, truncate.
        items.retain(|&(t, p)| !t.is_none() && p.is_finite());
        items.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(b.1.total_cmp(&a.1)));
        items.dedup_by_key(|x| x.0);
        if items.len() > conn.config.max_queue {
            items.sort_unstable_by(rank);
            items.truncate(conn.config.max_queue);
            items.sort_unstable_by_key(|x| x.0);
        }
        let dropped = received - items.len();
        conn.stats.items_dropped += dropped as u64;

        // The by-id index (the items are in id order), carrying over since when each item has
        // been wanted.
        let mut old = conn.by_id.iter().peekable();
        let by_id: Vec<Wanted> = items
            .iter()
            .map(|&(id, priority)| {
                while old.next_if(|o| o.id < id).is_some() {}
                let since = old.next_if(|o| o.id == id).map_or(now, |o| o.since);
                Wanted {
                    id,
                    priority,
                    since,
                }
            })
            .collect();
        conn.by_id = by_id;

        let mut obsolete_in_flight: Vec<TreeletId> = conn
            .in_flight
            .keys()
            .copied()
            .filter(|&t| conn.wanted(t).is_none())
            .collect();
        obsolete_in_flight.sort_unstable();

        conn.prune_recent(now);
        conn.index_recent();
        let start = conn.guard_start(now);
        let guard = conn.config.redelivery_guard;
        // A replan is the same list ranked anew, not the client naming its items again: what
        // was sent for the list since it came is not sent again when its guard passes. Only
        // what the list found in flight or just delivered when it came (deferred then) stays
        // deferred.
        let deferred_by_the_list: FxHashSet<TreeletId> = if replan {
            conn.deferred.iter().map(|&(_, t)| t).collect()
        } else {
            FxHashSet::default()
        };
        let mut deferred = Vec::new();
        let mut queue: Vec<Wanted> = conn
            .by_id
            .iter()
            .filter(|w| {
                // In flight, the client may already hold it (and have evicted it): wanted
                // again once delivered and its guard has passed.
                let guard_end = if conn.in_flight.contains_key(&w.id) {
                    Some(now + guard)
                } else {
                    conn.recently_delivered(w.id, start).map(|at| at + guard)
                };
                let Some(end) = guard_end else {
                    return true;
                };
                if !replan || deferred_by_the_list.contains(&w.id) {
                    deferred.push((end, w.id));
                }
                false
            })
            .copied()
            .collect();
        conn.deferred = deferred;
        queue.sort_unstable_by(|a, b| rank(&(a.id, a.priority), &(b.id, b.priority)));
        conn.queue = queue;
        conn.cursor = 0;
        conn.retry.clear();
        conn.prefetch_below = prefetch_below;
        let queued = conn.queue.len();
        self.wake(id);
        Ok(ListOutcome::Applied {
            queued,
            dropped,
            obsolete_in_flight,
        })
    }

    /// Queues the deferred treelets of connection `id` that are neither in flight nor within a
    /// redelivery guard at `now` and that its current list still names (see the module docs),
    /// each once per list; returns how many. The service calls it on its tick.
    pub fn release_deferred(&mut self, id: ConnectionId, now: Instant) -> usize {
        let Some(conn) = self.conns.get_mut(&id) else {
            return 0;
        };
        if conn.deferred.is_empty() {
            return 0;
        }
        conn.index_recent();
        let start = conn.guard_start(now);
        let mut released = 0;
        let mut deferred = std::mem::take(&mut conn.deferred);
        deferred.retain(|&(end, treelet)| {
            // Still on its way, or delivered (again, a push say) within a guard: wait for that
            // guard to pass too.
            if end > now
                || conn.in_flight.contains_key(&treelet)
                || conn.recently_delivered(treelet, start).is_some()
            {
                return true;
            }
            if let Some(w) = conn.wanted(treelet) {
                conn.retry.push(Retry(w.id, w.priority));
                released += 1;
            }
            false
        });
        conn.deferred = deferred;
        if released > 0 {
            self.wake(id);
        }
        released
    }

    /// Whether `treelet` was delivered on connection `id` (as far as the bounded record
    /// remembers); `false` for an unknown connection.
    pub fn was_delivered(&self, id: ConnectionId, treelet: TreeletId) -> bool {
        self.conns
            .get(&id)
            .is_some_and(|c| c.delivered_ever.contains(&treelet))
    }

    /// The next treelet to start sending, and to whom; it is in flight from now on. `None` when
    /// no connection has both something to send and window room, or at the server-wide cap.
    pub fn poll_transmit(&mut self, now: Instant) -> Option<(ConnectionId, TreeletId)> {
        let mut one = Vec::with_capacity(1);
        let id = self.poll_up_to(now, 1, &mut one)?;
        Some((id, one[0]))
    }

    /// The next connection's next treelets to start sending, as one stream's batch: put into
    /// `batch` (cleared first), in rank order, at most [`batch_limit`] of its window and never
    /// beyond its window room or the server-wide cap; all in flight from now on. The ring turns
    /// once per batch. `None` (and `batch` empty) when no connection can send.
    ///
    /// One call per stream, not per treelet: the service hands a batch to its connection's
    /// task in one message (measured on a whole-scene fetch of lion-4k: per-treelet hand-overs
    /// cost a channel send, a route lookup and two connection lookups each).
    pub fn poll_batch(&mut self, now: Instant, batch: &mut Vec<TreeletId>) -> Option<ConnectionId> {
        self.poll_up_to(now, usize::MAX, batch)
    }

    /// [`Scheduler::poll_batch`] with at most `most` treelets.
    fn poll_up_to(
        &mut self,
        now: Instant,
        most: usize,
        batch: &mut Vec<TreeletId>,
    ) -> Option<ConnectionId> {
        batch.clear();
        while self.total_in_flight < self.config.max_in_flight
            && let Some(id) = self.ring.pop_front()
        {
            let Some(conn) = self.conns.get_mut(&id) else {
                continue;
            };
            conn.in_ring = false;
            let most = most
                .min(batch_limit(conn.config.window))
                .min(self.config.max_in_flight - self.total_in_flight);
            // The service hands each batch's vector on, so it comes back empty: room for the
            // whole batch at once, not grown push by push.
            batch.reserve(most);
            while batch.len() < most
                && conn.eligible()
                && let Some((treelet, since, priority)) = conn.pop(now)
            {
                conn.start(treelet, since, priority);
                batch.push(treelet);
            }
            if conn.eligible() {
                conn.in_ring = true;
                self.ring.push_back(id);
            }
            if !batch.is_empty() {
                conn.stats.treelets_started += batch.len() as u64;
                self.total_in_flight += batch.len();
                return Some(id);
            }
        }
        None
    }

    /// All bytes of `treelet` were handed to the transport at `now`; it stays in flight until
    /// delivered. Returns the time since the client first asked for it (request-to-send
    /// latency), or `None` if it was not in flight or already reported sent.
    pub fn handle_sent(
        &mut self,
        id: ConnectionId,
        treelet: TreeletId,
        now: Instant,
    ) -> Option<Duration> {
        self.conns.get_mut(&id)?.mark_sent(treelet, now)
    }

    /// [`Scheduler::handle_sent`] for every treelet of a stream's batch, written together at
    /// `now`: one lookup of the connection. Appends to `latencies` the request-to-send latency
    /// of each treelet that was in flight and not reported sent yet.
    pub fn handle_sent_all(
        &mut self,
        id: ConnectionId,
        treelets: &[TreeletId],
        now: Instant,
        latencies: &mut Vec<Duration>,
    ) {
        if let Some(conn) = self.conns.get_mut(&id) {
            latencies.extend(treelets.iter().filter_map(|&t| conn.mark_sent(t, now)));
        }
    }

    /// The peer acknowledged `treelet` at `now`: it leaves the window. Returns the time since the
    /// client first asked for it, or `None` if it was not in flight.
    pub fn handle_delivered(
        &mut self,
        id: ConnectionId,
        treelet: TreeletId,
        now: Instant,
    ) -> Option<Duration> {
        let (conn, flight) = self.leave_window(id, treelet)?;
        conn.record_delivery(treelet, now);
        conn.prune_recent(now);
        self.wake(id);
        Some(now.saturating_duration_since(flight.since))
    }

    /// [`Scheduler::handle_delivered`] for every treelet of a stream's batch, acknowledged
    /// together at `now`: one lookup of the connection, one prune of the redelivery record and
    /// one wake for the batch, not one per treelet, and no latency arithmetic (the service's
    /// delivery path: on a whole-scene fetch of lion-4k it took a quarter off the scheduler's
    /// instructions, callgrind). Returns how many of `treelets` were in flight; the others are
    /// ignored.
    pub fn handle_delivered_all(
        &mut self,
        id: ConnectionId,
        treelets: &[TreeletId],
        now: Instant,
    ) -> usize {
        let Some(conn) = self.conns.get_mut(&id) else {
            return 0;
        };
        let mut delivered = 0;
        for &t in treelets {
            if conn.finish(t).is_some() {
                conn.record_delivery(t, now);
                delivered += 1;
            }
        }
        if delivered > 0 {
            conn.prune_recent(now);
            self.total_in_flight -= delivered;
            self.wake(id);
        }
        delivered
    }

    /// The transfer of `treelet` was cancelled (stream reset, write failed): it leaves the window
    /// and, if the current list still names it, is queued again. Returns whether it was in
    /// flight.
    pub fn handle_cancelled(&mut self, id: ConnectionId, treelet: TreeletId) -> bool {
        let Some((conn, _)) = self.leave_window(id, treelet) else {
            return false;
        };
        conn.stats.treelets_cancelled += 1;
        if let Some(w) = conn.wanted(treelet) {
            conn.retry.push(Retry(w.id, w.priority));
        }
        self.wake(id);
        true
    }

    /// Takes `treelet` out of connection `id`'s window: the connection and its flight, if it was
    /// in flight there.
    fn leave_window(
        &mut self,
        id: ConnectionId,
        treelet: TreeletId,
    ) -> Option<(&mut Conn, Flight)> {
        let conn = self.conns.get_mut(&id)?;
        let flight = conn.finish(treelet)?;
        self.total_in_flight -= 1;
        Some((conn, flight))
    }

    /// Puts a connection in the ring if it can send and is not there yet.
    fn wake(&mut self, id: ConnectionId) {
        if let Some(conn) = self.conns.get_mut(&id)
            && !conn.in_ring
            && conn.eligible()
        {
            conn.in_ring = true;
            self.ring.push_back(id);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::{HashMap as Map, HashSet};

    const A: ConnectionId = ConnectionId(1);
    const B: ConnectionId = ConnectionId(2);

    fn t(i: u32) -> TreeletId {
        TreeletId(i)
    }

    fn cfg(window: usize) -> ConnectionConfig {
        ConnectionConfig {
            window,
            max_queue: MAX_REQUEST_ITEMS,
            redelivery_guard: Duration::ZERO,
            remember_deliveries: false,
            recent_deliveries: RECENT_DELIVERIES_KEPT,
        }
    }

    fn list(items: &[(u32, f32)]) -> Vec<(TreeletId, f32)> {
        items.iter().map(|&(i, p)| (t(i), p)).collect()
    }

    /// Polls until `None`, returning the treelets started (all for one connection).
    fn drain(s: &mut Scheduler, now: Instant) -> Vec<(ConnectionId, u32)> {
        std::iter::from_fn(|| s.poll_transmit(now))
            .map(|(c, x)| (c, x.0))
            .collect()
    }

    fn one(conn: ConnectionId, window: usize) -> Scheduler {
        let mut s = Scheduler::default();
        s.add_connection(conn, cfg(window)).unwrap();
        s
    }

    #[test]
    fn prefetch_beyond_its_share_of_the_window_waits_and_nothing_else_does() {
        let now = Instant::now();
        // Window 16: two prefetch treelets in flight at most.
        let mut s = one(A, 16);
        let items = list(&[(1, 10.0), (2, 9.0), (3, 1.0), (4, 0.9), (5, 0.8), (6, 0.7)]);
        s.handle_list_with_prefetch(A, 1, items.clone(), 2.0, false, now)
            .unwrap();
        assert_eq!(
            drain(&mut s, now),
            [(A, 1), (A, 2), (A, 3), (A, 4)],
            "everything above the mark, and two below it"
        );
        // A delivered prefetch makes room for one more; a delivered listed item does not.
        s.handle_delivered(A, t(1), now);
        assert_eq!(drain(&mut s, now), []);
        s.handle_delivered(A, t(3), now);
        assert_eq!(drain(&mut s, now), [(A, 5)]);
        // A cancelled prefetch leaves the window and comes back first, in its rank.
        assert!(s.handle_cancelled(A, t(4)));
        assert_eq!(drain(&mut s, now), [(A, 4)]);
        // A list ranked above the mark is never held: the same items, nothing set apart, go on
        // although two prefetch treelets are still in flight (counted until they end).
        s.handle_request_list(A, 2, items.clone(), now).unwrap();
        assert_eq!(drain(&mut s, now), [(A, 1), (A, 3), (A, 6)]);
        // A replanned list keeps the rule, and a non-finite mark sets nothing apart.
        let mut s = one(A, 8);
        s.handle_request_list(A, 1, items.clone(), now).unwrap();
        s.handle_list_with_prefetch(A, 1, items.clone(), 2.0, true, now)
            .unwrap();
        assert_eq!(drain(&mut s, now), [(A, 1), (A, 2), (A, 3)]);
        let mut s = one(A, 8);
        s.handle_list_with_prefetch(A, 1, items, f32::NAN, false, now)
            .unwrap();
        assert_eq!(drain(&mut s, now).len(), 6);
    }

    #[test]
    fn a_replanned_list_replaces_the_last_one_unless_a_newer_one_came() {
        let now = Instant::now();
        let mut s = one(A, 1);
        assert!(matches!(
            s.handle_replanned_list(A, 0, list(&[(1, 1.0)]), now),
            Ok(ListOutcome::Stale { .. })
        ));
        s.handle_request_list(A, 5, list(&[(1, 1.0)]), now).unwrap();
        let replanned = s.handle_replanned_list(A, 5, list(&[(2, 2.0), (1, 1.0)]), now);
        assert!(matches!(
            replanned,
            Ok(ListOutcome::Applied { queued: 2, .. })
        ));
        assert_eq!(
            drain(&mut s, now),
            vec![(A, 2)],
            "the replanned order, window 1"
        );
        assert!(matches!(
            s.handle_replanned_list(A, 4, list(&[(3, 1.0)]), now),
            Ok(ListOutcome::Stale { last_seq: 5 })
        ));
        s.handle_request_list(A, 6, list(&[(1, 1.0)]), now).unwrap();
        assert!(matches!(
            s.handle_replanned_list(A, 5, list(&[(3, 1.0)]), now),
            Ok(ListOutcome::Stale { last_seq: 6 })
        ));
        // Replans are not lists the client sent.
        let stats = s.stats(A).unwrap();
        assert_eq!((stats.lists_received, stats.lists_stale), (2, 0));
    }

    #[test]
    fn a_replanned_list_does_not_send_again_what_was_sent_for_it() {
        let now = Instant::now();
        let later = now + Duration::from_secs(10);
        // 1 is sent and delivered under list 1; list 2 names it again (the client may have
        // evicted it) along with 2, which is sent and delivered under list 2.
        let sent_for_list_2 = || {
            let mut s = one(A, 4);
            s.set_redelivery_guard(A, Duration::from_millis(100))
                .unwrap();
            s.handle_request_list(A, 1, list(&[(1, 1.0)]), now).unwrap();
            assert_eq!(drain(&mut s, now), [(A, 1)]);
            s.handle_delivered(A, t(1), now);
            s.handle_request_list(A, 2, list(&[(1, 2.0), (2, 1.0)]), now)
                .unwrap();
            assert_eq!(
                drain(&mut s, now),
                [(A, 2)],
                "1 is deferred: just delivered"
            );
            s.handle_delivered(A, t(2), now);
            s
        };
        let planned = list(&[(1, 2.0), (2, 1.0), (3, 0.5)]);
        // List 2 replanned with a push: 2, sent for the list, is not sent again; 1, which the
        // list itself named while it was just delivered, still is once its guard passes.
        let mut s = sent_for_list_2();
        s.handle_replanned_list(A, 2, planned.clone(), now).unwrap();
        assert_eq!(drain(&mut s, now), [(A, 3)]);
        assert_eq!(s.release_deferred(A, later), 1);
        assert_eq!(drain(&mut s, later), [(A, 1)]);
        // The same items as a new list: the client named 2 again, so it is sent again too.
        let mut s = sent_for_list_2();
        s.handle_request_list(A, 3, planned, now).unwrap();
        assert_eq!(drain(&mut s, now), [(A, 3)]);
        assert_eq!(s.release_deferred(A, later), 2);
        let mut again = drain(&mut s, later);
        again.sort_unstable();
        assert_eq!(again, [(A, 1), (A, 2)]);
    }

    #[test]
    fn deliveries_are_remembered_until_the_record_is_full() {
        let now = Instant::now();
        let mut s = Scheduler::default();
        let config = ConnectionConfig {
            window: 4,
            max_queue: 2,
            redelivery_guard: Duration::ZERO,
            remember_deliveries: true,
            recent_deliveries: RECENT_DELIVERIES_KEPT,
        };
        s.add_connection(A, config).unwrap();
        assert!(!s.was_delivered(A, t(1)));
        assert!(!s.was_delivered(B, t(1)), "unknown connection");
        s.handle_request_list(A, 1, list(&[(1, 2.0), (2, 1.0)]), now)
            .unwrap();
        for (_, x) in drain(&mut s, now) {
            s.handle_sent(A, t(x), now);
            s.handle_delivered(A, t(x), now).unwrap();
        }
        assert!(s.was_delivered(A, t(1)) && s.was_delivered(A, t(2)));
        assert!(!s.was_delivered(A, t(3)));
        // The record holds 4 × max(max_queue, window) = 16; the 17th delivery starts it afresh.
        for i in 0..15u32 {
            let id = 10 + i;
            s.handle_request_list(A, 2 + u64::from(i), list(&[(id, 1.0)]), now)
                .unwrap();
            assert_eq!(drain(&mut s, now), vec![(A, id)]);
            s.handle_delivered(A, t(id), now).unwrap();
        }
        assert!(!s.was_delivered(A, t(1)), "forgotten at the cap");
        assert!(s.was_delivered(A, t(24)));
        // Turned on later: only what is delivered from then on.
        let mut s = one(A, 4);
        s.handle_request_list(A, 1, list(&[(1, 2.0), (2, 1.0)]), now)
            .unwrap();
        assert_eq!(drain(&mut s, now), [(A, 1), (A, 2)]);
        s.handle_delivered(A, t(1), now).unwrap();
        s.remember_deliveries(A).unwrap();
        assert!(s.remember_deliveries(B).is_err(), "unknown connection");
        s.handle_delivered(A, t(2), now).unwrap();
        assert!(!s.was_delivered(A, t(1)) && s.was_delivered(A, t(2)));
        // With the largest lists the record stops at DELIVERIES_REMEMBERED.
        let mut s = Scheduler::default();
        s.add_connection(
            A,
            ConnectionConfig {
                remember_deliveries: true,
                ..cfg(1)
            },
        )
        .unwrap();
        assert_eq!(s.conns[&A].delivered_cap(), DELIVERIES_REMEMBERED);
        // A connection that does not remember keeps no record.
        let mut s = one(B, 1);
        s.handle_request_list(B, 1, list(&[(1, 1.0)]), now).unwrap();
        assert_eq!(drain(&mut s, now), vec![(B, 1)]);
        s.handle_delivered(B, t(1), now).unwrap();
        assert!(!s.was_delivered(B, t(1)));
    }

    #[test]
    fn highest_priority_first_ties_by_lower_id() {
        let now = Instant::now();
        let mut s = one(A, 100);
        s.handle_request_list(
            A,
            1,
            list(&[(5, 1.0), (3, 2.0), (9, 2.0), (1, -1.0), (2, 0.0), (7, 2.0)]),
            now,
        )
        .unwrap();
        let got: Vec<u32> = drain(&mut s, now).into_iter().map(|x| x.1).collect();
        assert_eq!(got, vec![3, 7, 9, 5, 2, 1]);
    }

    #[test]
    fn duplicates_collapse_to_the_largest_priority_and_bad_items_are_dropped() {
        let now = Instant::now();
        let mut s = one(A, 100);
        let out = s
            .handle_request_list(
                A,
                1,
                list(&[
                    (1, 1.0),
                    (2, 5.0),
                    (1, 9.0),
                    (1, 3.0),
                    (3, f32::NAN),
                    (u32::MAX, 1.0),
                ]),
                now,
            )
            .unwrap();
        assert_eq!(
            out,
            ListOutcome::Applied {
                queued: 2,
                dropped: 4,
                obsolete_in_flight: vec![]
            }
        );
        let got: Vec<u32> = drain(&mut s, now).into_iter().map(|x| x.1).collect();
        assert_eq!(got, vec![1, 2]);
    }

    #[test]
    fn window_bounds_in_flight_and_delivery_reopens_it() {
        let now = Instant::now();
        let mut s = one(A, 3);
        s.handle_request_list(A, 1, (0..10).map(|i| (t(i), -(i as f32))).collect(), now)
            .unwrap();
        assert_eq!(drain(&mut s, now), vec![(A, 0), (A, 1), (A, 2)]);
        assert_eq!(s.stats(A).unwrap().in_flight, 3);
        assert_eq!(s.stats(A).unwrap().queue_depth, 7);
        // Sent is not delivered: the window stays full.
        assert!(s.handle_sent(A, t(1), now).is_some());
        assert!(s.handle_sent(A, t(1), now).is_none(), "reported once");
        assert_eq!(s.poll_transmit(now), None);
        assert!(s.handle_delivered(A, t(1), now).is_some());
        assert!(s.handle_delivered(A, t(1), now).is_none());
        assert_eq!(drain(&mut s, now), vec![(A, 3)]);
        // Shrinking the window below what is in flight stops starts until enough leave.
        s.set_window(A, 1).unwrap();
        for x in [0, 2] {
            assert_eq!(s.poll_transmit(now), None);
            s.handle_delivered(A, t(x), now);
        }
        assert_eq!(s.poll_transmit(now), None);
        s.handle_delivered(A, t(3), now);
        assert_eq!(drain(&mut s, now), vec![(A, 4)]);
        // A window of 0 pauses the connection.
        s.set_window(A, 0).unwrap();
        s.handle_delivered(A, t(4), now);
        assert_eq!(s.poll_transmit(now), None);
        s.set_window(A, 2).unwrap();
        assert_eq!(drain(&mut s, now), vec![(A, 5), (A, 6)]);
    }

    #[test]
    fn replacement_list_never_starts_treelets_it_dropped() {
        let now = Instant::now();
        let mut s = one(A, 4);
        s.handle_request_list(
            A,
            1,
            (0..100).map(|i| (t(i), 100.0 - i as f32)).collect(),
            now,
        )
        .unwrap();
        assert_eq!(drain(&mut s, now).len(), 4); // 0..4 in flight
        // The new list keeps 2 and 50..60, drops the rest of the old list.
        let new: Vec<_> = std::iter::once((t(2), 1.0))
            .chain((50..60).map(|i| (t(i), i as f32)))
            .collect();
        let out = s.handle_request_list(A, 2, new, now).unwrap();
        assert_eq!(
            out,
            ListOutcome::Applied {
                queued: 10,
                dropped: 0,
                obsolete_in_flight: vec![t(0), t(1), t(3)]
            }
        );
        let mut started = vec![];
        for round in 0..100u32 {
            for (c, x) in drain(&mut s, now) {
                assert_eq!(c, A);
                started.push(x);
            }
            // Deliver everything in flight, old and new.
            for x in 0..100 {
                s.handle_delivered(A, t(x), now + Duration::from_millis(round.into()));
            }
        }
        // Only the new list's treelets were started, highest first; 2 was in flight and is not
        // started again.
        assert_eq!(started, (50..60).rev().collect::<Vec<_>>());
        assert_eq!(s.stats(A).unwrap().queue_depth, 0);
    }

    #[test]
    fn in_flight_treelets_are_never_duplicated() {
        let now = Instant::now();
        let mut s = one(A, 10);
        s.handle_request_list(A, 1, list(&[(1, 3.0), (2, 2.0), (3, 1.0)]), now)
            .unwrap();
        assert_eq!(s.poll_transmit(now), Some((A, t(1))));
        // The client asks again (it has not received 1 yet) with 1 now lower.
        s.handle_request_list(A, 2, list(&[(3, 5.0), (1, 4.0), (2, 0.5)]), now)
            .unwrap();
        assert_eq!(drain(&mut s, now), vec![(A, 3), (A, 2)]);
        // Cancelled while still wanted: queued again, in rank order with the rest.
        s.handle_request_list(A, 3, list(&[(1, 4.0), (4, 4.5), (5, 3.0)]), now)
            .unwrap();
        assert!(s.handle_cancelled(A, t(1)));
        assert!(!s.handle_cancelled(A, t(1)));
        assert_eq!(drain(&mut s, now), vec![(A, 4), (A, 1), (A, 5)]);
        // Cancelled and no longer wanted: gone.
        s.handle_request_list(A, 4, list(&[(9, 1.0)]), now).unwrap();
        assert!(s.handle_cancelled(A, t(5)));
        assert_eq!(drain(&mut s, now), vec![(A, 9)]);
        let st = s.stats(A).unwrap();
        assert_eq!(st.treelets_started, 7);
        assert_eq!(st.treelets_cancelled, 2);
    }

    #[test]
    fn delivered_treelets_are_not_resent_under_the_same_list_but_a_new_list_may_ask_again() {
        let now = Instant::now();
        let mut s = one(A, 10);
        s.handle_request_list(A, 1, list(&[(1, 1.0), (2, 1.0)]), now)
            .unwrap();
        assert_eq!(drain(&mut s, now).len(), 2);
        s.handle_delivered(A, t(1), now);
        s.handle_delivered(A, t(2), now);
        assert_eq!(s.poll_transmit(now), None, "same list: not again");
        // Guard off: a new list naming 1 gets it again (the client evicted it).
        s.handle_request_list(A, 2, list(&[(1, 1.0)]), now).unwrap();
        assert_eq!(drain(&mut s, now), vec![(A, 1)]);
    }

    /// A connection with a 100 ms redelivery guard that has started treelets 1 and 2 at 0 ms,
    /// and the clock in ms from then.
    fn guarded_with_two_in_flight() -> (Scheduler, impl Fn(u64) -> Instant) {
        let t0 = Instant::now();
        let ms = move |m: u64| t0 + Duration::from_millis(m);
        let mut s = Scheduler::default();
        s.add_connection(
            A,
            ConnectionConfig {
                redelivery_guard: Duration::from_millis(100),
                ..cfg(10)
            },
        )
        .unwrap();
        s.handle_request_list(A, 1, list(&[(1, 1.0), (2, 1.0)]), ms(0))
            .unwrap();
        assert_eq!(drain(&mut s, ms(0)).len(), 2);
        (s, ms)
    }

    #[test]
    fn redelivery_guard_covers_lists_built_before_the_client_saw_the_treelet() {
        let (mut s, ms) = guarded_with_two_in_flight();
        s.handle_delivered(A, t(1), ms(10));
        s.handle_delivered(A, t(2), ms(10));
        // Lists built before the client saw them still name them: not resent within the guard.
        let out = s
            .handle_request_list(A, 2, list(&[(1, 1.0), (2, 1.0), (3, 0.0)]), ms(50))
            .unwrap();
        assert!(matches!(out, ListOutcome::Applied { queued: 1, .. }));
        assert_eq!(drain(&mut s, ms(50)), vec![(A, 3)]);
        // Well after the guard, a list naming 1 means the client wants it again.
        s.handle_request_list(A, 3, list(&[(1, 1.0)]), ms(200))
            .unwrap();
        assert_eq!(drain(&mut s, ms(200)), vec![(A, 1)]);
        assert!(s.conns[&A].recent.len() <= 1, "old deliveries forgotten");
    }

    #[test]
    fn a_list_that_still_names_a_guarded_treelet_after_the_guard_gets_it() {
        let (mut s, ms) = guarded_with_two_in_flight();
        s.handle_delivered(A, t(1), ms(10));
        s.handle_delivered(A, t(2), ms(10));
        // The client evicted 1 and 2 and wants them again with 3; the list comes within the
        // guard, and (unchanged) is the last the client sends.
        s.handle_request_list(A, 2, list(&[(1, 2.0), (2, 1.0), (3, 0.0)]), ms(50))
            .unwrap();
        assert_eq!(drain(&mut s, ms(50)), vec![(A, 3)]);
        assert_eq!(s.release_deferred(A, ms(100)), 0, "guard not over");
        assert_eq!(drain(&mut s, ms(100)), vec![]);
        // 2 was sent again meanwhile (say as a push): only 1 is released, 2 after its new
        // guard.
        assert_eq!(s.poll_transmit(ms(105)), None);
        s.conns.get_mut(&A).unwrap().record_delivery(t(2), ms(105));
        assert_eq!(s.release_deferred(A, ms(111)), 1);
        assert_eq!(drain(&mut s, ms(111)), vec![(A, 1)]);
        assert_eq!(s.release_deferred(A, ms(200)), 0);
        assert_eq!(s.release_deferred(A, ms(206)), 1);
        assert_eq!(drain(&mut s, ms(206)), vec![(A, 2)]);
        assert_eq!(s.release_deferred(A, ms(500)), 0, "released once");
        // A new list replaces what was deferred.
        s.handle_delivered(A, t(1), ms(520));
        s.handle_request_list(A, 3, list(&[(1, 1.0)]), ms(530))
            .unwrap();
        s.handle_request_list(A, 4, list(&[(4, 1.0)]), ms(540))
            .unwrap();
        assert_eq!(s.release_deferred(A, ms(700)), 0);
        assert_eq!(drain(&mut s, ms(700)), vec![(A, 4)]);
    }

    #[test]
    fn deliveries_the_record_bound_forgot_are_sent_again_within_the_guard() {
        // A record bounded at four lists' worth: max_queue 2, window 2, so 8 deliveries.
        let t0 = Instant::now();
        let ms = |m: u64| t0 + Duration::from_millis(m);
        let mut s = Scheduler::default();
        s.add_connection(
            A,
            ConnectionConfig {
                max_queue: 2,
                redelivery_guard: Duration::from_millis(100),
                ..cfg(2)
            },
        )
        .unwrap();
        // Treelets 0..10 delivered in pairs, each pair under a list of its own, all within the
        // guard of the last: 0 and 1 drop out of the record.
        for k in 0..5u32 {
            let now = ms(u64::from(k));
            s.handle_request_list(
                A,
                u64::from(k) + 1,
                list(&[(2 * k, 1.0), (2 * k + 1, 0.5)]),
                now,
            )
            .unwrap();
            let sent = drain(&mut s, now);
            assert_eq!(sent, vec![(A, 2 * k), (A, 2 * k + 1)]);
            s.handle_delivered_all(A, &[t(2 * k), t(2 * k + 1)], now);
        }
        assert_eq!(s.conns[&A].recent.len(), 8);
        // 1 is forgotten: sent again. 2, the oldest remembered, is not.
        let out = s
            .handle_request_list(A, 6, list(&[(1, 1.0), (2, 0.5)]), ms(10))
            .unwrap();
        assert!(
            matches!(out, ListOutcome::Applied { queued: 1, .. }),
            "{out:?}"
        );
        assert_eq!(drain(&mut s, ms(10)), vec![(A, 1)]);
    }

    #[test]
    fn the_redelivery_record_stays_within_its_planned_bytes_at_any_rate() {
        // Long lists and a long guard: only `recent_deliveries` bounds the record. Treelets
        // delivered in batches under lists that each name new ones and some delivered before.
        let t0 = Instant::now();
        let kept = 1024;
        let mut s = Scheduler::default();
        s.add_connection(
            A,
            ConnectionConfig {
                redelivery_guard: Duration::from_secs(10),
                recent_deliveries: kept,
                ..cfg(MAX_TREELETS_PER_STREAM * 4)
            },
        )
        .unwrap();
        let planned = recent_record_bytes(kept);
        let mut most = 0u64;
        for k in 0..40u32 {
            let now = t0 + Duration::from_micros(u64::from(k));
            // 600 new treelets and 50 of the oldest the record may still hold.
            let fresh = (600 * k..600 * (k + 1)).map(|i| (i, 1.0));
            let again = (600 * k.saturating_sub(2)..).take(50).map(|i| (i, 0.5));
            let items: Vec<(u32, f32)> = fresh.chain(again).collect();
            s.handle_request_list(A, u64::from(k) + 1, list(&items), now)
                .unwrap();
            let mut batch = Vec::new();
            while s.poll_batch(now, &mut batch).is_some() {
                s.handle_delivered_all(A, &batch, now);
                let c = &s.conns[&A];
                assert!(c.recent.len() <= kept, "{} deliveries kept", c.recent.len());
                let index_buckets = (c.recent_index.capacity() * 8 / 7).next_power_of_two();
                let bytes = (c.recent.capacity() * 24 + index_buckets * 17) as u64;
                most = most.max(bytes);
                assert!(bytes <= planned, "{bytes} bytes against {planned} planned");
            }
        }
        assert!(
            most > planned / 4,
            "the flood filled the record: {most} of {planned}"
        );
        // The oldest deliveries are forgotten although within the guard: a list naming one
        // gets it again; one the record still holds is left out.
        let now = t0 + Duration::from_millis(1);
        let out = s
            .handle_request_list(A, 100, list(&[(0, 1.0), (600 * 40 - 1, 0.5)]), now)
            .unwrap();
        assert!(
            matches!(out, ListOutcome::Applied { queued: 1, .. }),
            "{out:?}"
        );
        assert_eq!(drain(&mut s, now), vec![(A, 0)]);
    }

    #[test]
    fn lists_leave_out_exactly_what_the_guard_holds_over_many_lists() {
        // Many lists and deliveries, the guard's by-id index kept up list by list and rebuilt
        // as deliveries age out, against the deliveries themselves searched by brute force.
        let t0 = Instant::now();
        let guard = Duration::from_millis(30);
        let mut s = Scheduler::default();
        s.add_connection(
            A,
            ConnectionConfig {
                redelivery_guard: guard,
                ..cfg(16)
            },
        )
        .unwrap();
        let mut delivered: Vec<(Instant, u32)> = Vec::new();
        let mut rng = arbor_proto::rng::SplitMix64::new(7);
        for seq in 1..400u64 {
            let now = t0 + Duration::from_millis(seq);
            let items: Vec<(u32, f32)> = (0..24)
                // Ids from a sliding range: new treelets all the time, some named again.
                .map(|k| (seq as u32 * 3 + rng.next_u64() as u32 % 60, k as f32))
                .collect();
            let out = s.handle_request_list(A, seq, list(&items), now).unwrap();
            let ListOutcome::Applied { queued, .. } = out else {
                panic!("list {seq} not applied: {out:?}");
            };
            let start = now - guard;
            let ids: HashSet<u32> = items.iter().map(|i| i.0).collect();
            let in_flight: HashSet<u32> = s.conns[&A].in_flight.keys().map(|t| t.0).collect();
            let expected = ids
                .iter()
                .filter(|id| !in_flight.contains(id))
                .filter(|&&id| !delivered.iter().any(|&(at, d)| d == id && at > start))
                .count();
            assert_eq!(queued, expected, "list {seq}");
            // Deliver some of what is in flight, oldest batch first.
            let mut batch = Vec::new();
            while s.poll_batch(now, &mut batch).is_some() {
                let half = batch.len().div_ceil(2);
                s.handle_delivered_all(A, &batch[..half], now);
                delivered.extend(batch[..half].iter().map(|t| (now, t.0)));
            }
        }
        let c = &s.conns[&A];
        assert!(
            c.recent_index.len() <= 2 * c.recent.len() + 64 + 64,
            "the index stays bounded: {} entries for {} deliveries",
            c.recent_index.len(),
            c.recent.len()
        );
    }

    #[test]
    fn a_list_naming_a_treelet_in_flight_gets_it_after_its_delivery_and_guard() {
        let (mut s, ms) = guarded_with_two_in_flight();
        // The client already holds 1 (its delivery not yet acknowledged), evicted it and asks
        // again: not started twice while in flight.
        s.handle_request_list(A, 2, list(&[(1, 1.0)]), ms(5))
            .unwrap();
        assert_eq!(drain(&mut s, ms(5)), vec![]);
        assert_eq!(s.release_deferred(A, ms(150)), 0, "still in flight");
        s.handle_delivered(A, t(1), ms(160));
        assert_eq!(s.release_deferred(A, ms(200)), 0, "within the guard");
        assert_eq!(s.release_deferred(A, ms(261)), 1);
        assert_eq!(drain(&mut s, ms(261)), vec![(A, 1)]);
        assert_eq!(s.release_deferred(A, ms(900)), 0, "released once");
    }

    #[test]
    fn stale_lists_are_ignored() {
        let now = Instant::now();
        let mut s = one(A, 10);
        s.handle_request_list(A, 5, list(&[(1, 1.0)]), now).unwrap();
        for seq in [5, 4, 0] {
            assert_eq!(
                s.handle_request_list(A, seq, list(&[(2, 1.0)]), now),
                Ok(ListOutcome::Stale { last_seq: 5 })
            );
        }
        assert_eq!(drain(&mut s, now), vec![(A, 1)]);
        let st = s.stats(A).unwrap();
        assert_eq!((st.lists_received, st.lists_stale), (1, 3));
        assert_eq!(st.last_seq, Some(5));
        // The first list may have any seq, 0 included.
        s.add_connection(B, cfg(1)).unwrap();
        assert!(matches!(
            s.handle_request_list(B, 0, list(&[(1, 1.0)]), now),
            Ok(ListOutcome::Applied { .. })
        ));
    }

    #[test]
    fn a_huge_list_does_not_starve_a_small_one() {
        let now = Instant::now();
        let mut s = Scheduler::new(SchedulerConfig { max_in_flight: 2 });
        let big = ConnectionConfig {
            max_queue: 100_000,
            ..cfg(1000)
        };
        s.add_connection(A, big).unwrap();
        s.add_connection(B, cfg(1000)).unwrap();
        s.handle_request_list(A, 1, (0..100_000).map(|i| (t(i), 1.0)).collect(), now)
            .unwrap();
        s.handle_request_list(B, 1, (0..10).map(|i| (t(i), 0.0)).collect(), now)
            .unwrap();
        let mut order = vec![];
        for _ in 0..40 {
            let (c, x) = s.poll_transmit(now).unwrap();
            order.push(c);
            s.handle_delivered(c, x, now);
        }
        // B's ten treelets all go within the first twenty sends, alternating with A.
        let b_positions: Vec<usize> = order
            .iter()
            .enumerate()
            .filter(|(_, c)| **c == B)
            .map(|(i, _)| i)
            .collect();
        assert_eq!(b_positions.len(), 10);
        assert!(b_positions.iter().all(|&i| i < 20), "{order:?}");
        assert_eq!(s.stats(B).unwrap().queue_depth, 0);
        assert_eq!(s.stats(A).unwrap().queue_depth, 100_000 - 30);
    }

    #[test]
    fn round_robin_fills_windows_evenly() {
        let now = Instant::now();
        let mut s = Scheduler::default();
        for c in 0..4 {
            s.add_connection(ConnectionId(c), cfg(3)).unwrap();
            s.handle_request_list(
                ConnectionId(c),
                1,
                (0..50).map(|i| (t(i), 0.0)).collect(),
                now,
            )
            .unwrap();
        }
        let got = drain(&mut s, now);
        assert_eq!(got.len(), 12);
        // Each round serves every connection once before any gets a second turn.
        for round in got.chunks(4) {
            let cs: HashSet<_> = round.iter().map(|x| x.0).collect();
            assert_eq!(cs.len(), 4);
        }
        assert_eq!(s.total_in_flight(), 12);
    }

    #[test]
    fn batches_take_a_quarter_of_the_window_in_rank_order_and_connections_alternate() {
        let now = Instant::now();
        let mut s = Scheduler::default();
        s.add_connection(A, cfg(20)).unwrap();
        s.add_connection(B, cfg(8)).unwrap();
        s.handle_request_list(A, 1, (0..30).map(|i| (t(i), i as f32)).collect(), now)
            .unwrap();
        s.handle_request_list(B, 1, list(&[(7, 1.0), (8, 3.0), (9, 2.0)]), now)
            .unwrap();
        let mut batch = Vec::new();
        let mut got = Vec::new();
        while let Some(c) = s.poll_batch(now, &mut batch) {
            got.push((c, batch.iter().map(|x| x.0).collect::<Vec<_>>()));
        }
        assert_eq!(
            got,
            vec![
                (A, vec![29, 28, 27, 26, 25]),
                (B, vec![8, 9]),
                (A, vec![24, 23, 22, 21, 20]),
                (B, vec![7]),
                (A, vec![19, 18, 17, 16, 15]),
                (A, vec![14, 13, 12, 11, 10]),
            ]
        );
        // Both windows are full: A's 20, and B's list is done.
        assert_eq!(s.total_in_flight(), 23);
        // A delivered batch frees its room for one more batch.
        assert_eq!(s.handle_delivered_all(A, &[t(29), t(28), t(27)], now), 3);
        assert_eq!(s.poll_batch(now, &mut batch), Some(A));
        assert_eq!(batch, vec![t(9), t(8), t(7)]);
        assert_eq!(s.poll_batch(now, &mut batch), None);
        assert!(batch.is_empty());
        assert_eq!(batch_limit(0), 1);
        assert_eq!(batch_limit(7), 1);
        assert_eq!(batch_limit(1000), 250);
        assert_eq!(batch_limit(4096), MAX_TREELETS_PER_STREAM);
    }

    #[test]
    fn a_batch_is_reported_sent_once_per_treelet_with_its_latency() {
        let t0 = Instant::now();
        let mut s = one(A, 8);
        s.handle_request_list(A, 1, list(&[(1, 3.0), (2, 2.0), (3, 1.0)]), t0)
            .unwrap();
        let mut batch = Vec::new();
        assert_eq!(s.poll_batch(t0, &mut batch), Some(A));
        assert_eq!(batch, vec![t(1), t(2)]);
        let later = t0 + Duration::from_millis(30);
        let mut latencies = Vec::new();
        // Treelet 3 is not in flight, 2 is named twice: two latencies.
        s.handle_sent_all(A, &[t(1), t(3), t(2), t(2)], later, &mut latencies);
        assert_eq!(latencies, vec![Duration::from_millis(30); 2]);
        s.handle_sent_all(A, &batch, later, &mut latencies);
        assert_eq!(latencies.len(), 2);
        assert_eq!(s.stats(A).unwrap().treelets_sent, 2);
        // An unknown connection changes nothing.
        s.handle_sent_all(B, &batch, later, &mut latencies);
        assert_eq!(latencies.len(), 2);
    }

    #[test]
    fn global_cap_limits_in_flight_over_all_connections() {
        let now = Instant::now();
        let mut s = Scheduler::new(SchedulerConfig { max_in_flight: 5 });
        s.add_connection(A, cfg(10)).unwrap();
        s.add_connection(B, cfg(10)).unwrap();
        for c in [A, B] {
            s.handle_request_list(c, 1, (0..20).map(|i| (t(i), 0.0)).collect(), now)
                .unwrap();
        }
        assert_eq!(drain(&mut s, now).len(), 5);
        s.handle_delivered(A, t(0), now);
        assert_eq!(drain(&mut s, now).len(), 1);
        // A batch stops at the cap too, whatever its window would allow (40: 10 per batch).
        let mut s = Scheduler::new(SchedulerConfig { max_in_flight: 6 });
        s.add_connection(A, cfg(40)).unwrap();
        s.handle_request_list(A, 1, (0..30).map(|i| (t(i), 0.0)).collect(), now)
            .unwrap();
        let mut batch = Vec::new();
        assert_eq!(s.poll_batch(now, &mut batch), Some(A));
        assert_eq!(batch.len(), 6);
        assert_eq!(s.poll_batch(now, &mut batch), None);
        assert_eq!(s.total_in_flight(), 6);
    }

    #[test]
    fn removal_frees_the_window_and_the_ring() {
        let now = Instant::now();
        let mut s = Scheduler::new(SchedulerConfig { max_in_flight: 4 });
        s.add_connection(A, cfg(4)).unwrap();
        s.add_connection(B, cfg(4)).unwrap();
        s.handle_request_list(A, 1, (0..10).map(|i| (t(i), 0.0)).collect(), now)
            .unwrap();
        assert_eq!(drain(&mut s, now).len(), 4);
        s.handle_request_list(B, 1, (0..10).map(|i| (t(i), 0.0)).collect(), now)
            .unwrap();
        assert_eq!(s.poll_transmit(now), None, "at the global cap");
        let last = s.remove_connection(A).unwrap();
        assert_eq!((last.in_flight, last.treelets_started), (4, 4));
        assert_eq!(s.remove_connection(A), None);
        assert_eq!(s.total_in_flight(), 0);
        assert!(drain(&mut s, now).iter().all(|x| x.0 == B));
        // Events for a removed connection are ignored; a re-added id starts afresh.
        assert_eq!(s.handle_delivered(A, t(0), now), None);
        assert!(!s.handle_cancelled(A, t(0)));
        assert_eq!(
            s.handle_request_list(A, 2, vec![], now),
            Err(ScheduleError::UnknownConnection(A))
        );
        assert_eq!(
            s.add_connection(B, cfg(1)),
            Err(ScheduleError::DuplicateConnection(B))
        );
        s.add_connection(A, cfg(1)).unwrap();
        assert_eq!(
            s.stats(A).unwrap(),
            ConnectionStats {
                window: 1,
                ..ConnectionStats::default()
            }
        );
        assert_eq!(s.len(), 2);
        assert!(s.ring.iter().filter(|&&c| c == A).count() <= 1);
    }

    #[test]
    fn stats_count_everything() {
        let t0 = Instant::now();
        let mut s = Scheduler::default();
        s.add_connection(
            A,
            ConnectionConfig {
                max_queue: 3,
                ..cfg(2)
            },
        )
        .unwrap();
        let out = s
            .handle_request_list(
                A,
                1,
                list(&[(1, 1.0), (2, 2.0), (3, 3.0), (4, 4.0), (4, 0.0)]),
                t0,
            )
            .unwrap();
        // Truncated to the three highest-priority distinct items: 4, 3, 2.
        assert!(matches!(
            out,
            ListOutcome::Applied {
                queued: 3,
                dropped: 2,
                ..
            }
        ));
        assert_eq!(drain(&mut s, t0), vec![(A, 4), (A, 3)]);
        let later = t0 + Duration::from_millis(30);
        assert_eq!(
            s.handle_sent(A, t(4), later),
            Some(Duration::from_millis(30))
        );
        assert_eq!(
            s.handle_delivered(A, t(4), later + Duration::from_millis(5)),
            Some(Duration::from_millis(35))
        );
        // A second list that keeps 3 keeps its request time.
        s.handle_request_list(A, 2, list(&[(3, 1.0), (7, 1.0)]), later)
            .unwrap();
        assert_eq!(
            s.handle_delivered(A, t(3), later + Duration::from_millis(10)),
            Some(Duration::from_millis(40))
        );
        assert_eq!(
            s.stats(A).unwrap(),
            ConnectionStats {
                lists_received: 2,
                lists_stale: 0,
                items_received: 7,
                items_dropped: 2,
                treelets_started: 2,
                treelets_sent: 1,
                treelets_delivered: 2,
                treelets_cancelled: 0,
                queue_depth: 1,
                in_flight: 0,
                window: 2,
                last_seq: Some(2),
            }
        );
        assert_eq!(s.stats(B), None);
    }

    #[test]
    fn window_formula() {
        let rtt = Duration::from_millis(50);
        // 100 Mbit/s × 50 ms = 625 kB; 4 KiB treelets → 153.
        assert_eq!(window_for(12.5e6, rtt, 4096, 4, 1024), 153);
        assert_eq!(window_for(12.5e6, rtt, 4096, 4, 100), 100);
        assert_eq!(window_for(1e3, rtt, 4096, 4, 100), 4);
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert_eq!(window_for(bad, rtt, 4096, 4, 100), 4);
        }
        assert_eq!(window_for(1e9, rtt, 0, 4, 100), 4);
        assert_eq!(window_for(1e300, Duration::MAX, 1, 4, 100), 100);
        assert_eq!(window_for(1e9, rtt, 4096, 8, 2), 8, "min wins over max");
    }

    // ---- property test: random interleavings against a model ----

    #[derive(Clone, Debug)]
    enum Op {
        List {
            conn: u64,
            seq: u64,
            items: Vec<(u32, i8)>,
            /// Items ranked below this are prefetch ([`Scheduler::handle_list_with_prefetch`]).
            prefetch_below: Option<i8>,
        },
        Poll,
        PollBatch,
        Sent {
            conn: u64,
            pick: usize,
        },
        SentAll {
            conn: u64,
            picks: Vec<usize>,
        },
        Delivered {
            conn: u64,
            pick: usize,
        },
        DeliveredAll {
            conn: u64,
            picks: Vec<usize>,
        },
        Cancelled {
            conn: u64,
            pick: usize,
        },
        Window {
            conn: u64,
            window: usize,
        },
        Remove {
            conn: u64,
        },
        Add {
            conn: u64,
            window: usize,
        },
        Advance {
            ms: u64,
        },
    }

    fn op() -> impl Strategy<Value = Op> {
        let conn = 0u64..3;
        prop_oneof![
            3 => (
                conn.clone(),
                0u64..12,
                proptest::collection::vec((0u32..24, -3i8..4), 0..20),
                proptest::option::of(-3i8..5),
            )
                .prop_map(|(conn, seq, items, prefetch_below)| Op::List {
                    conn,
                    seq,
                    items,
                    prefetch_below,
                }),
            6 => Just(Op::Poll),
            3 => Just(Op::PollBatch),
            2 => (conn.clone(), any::<usize>()).prop_map(|(conn, pick)| Op::Sent { conn, pick }),
            1 => (conn.clone(), proptest::collection::vec(any::<usize>(), 0..4))
                .prop_map(|(conn, picks)| Op::SentAll { conn, picks }),
            4 => (conn.clone(), any::<usize>()).prop_map(|(conn, pick)| Op::Delivered { conn, pick }),
            2 => (conn.clone(), proptest::collection::vec(any::<usize>(), 0..4))
                .prop_map(|(conn, picks)| Op::DeliveredAll { conn, picks }),
            1 => (conn.clone(), any::<usize>()).prop_map(|(conn, pick)| Op::Cancelled { conn, pick }),
            // Windows of 8 and more give batches of two and more (a quarter of the window).
            1 => (conn.clone(), 0usize..13).prop_map(|(conn, window)| Op::Window { conn, window }),
            1 => conn.clone().prop_map(|conn| Op::Remove { conn }),
            1 => (conn, 0usize..13).prop_map(|(conn, window)| Op::Add { conn, window }),
            1 => (0u64..80).prop_map(|ms| Op::Advance { ms }),
        ]
    }

    #[derive(Default)]
    struct Model {
        window: usize,
        last_seq: Option<u64>,
        current: Map<u32, f32>,
        in_flight: HashSet<u32>,
        /// Not to be started under the current list: recently delivered at list time, or
        /// delivered since.
        blocked: HashSet<u32>,
        delivered_at: Map<u32, Instant>,
        /// The current list's prefetch mark.
        prefetch_below: Option<f32>,
        /// In flight, started as prefetch.
        prefetch: HashSet<u32>,
    }

    impl Model {
        fn is_prefetch(&self, priority: f32) -> bool {
            self.prefetch_below.is_some_and(|b| priority < b)
        }

        fn prefetch_window(&self) -> usize {
            (self.window / PREFETCH_SHARE_OF_WINDOW).max(1)
        }

        /// The queue's head is prefetch and the prefetch window is full.
        fn held(&self) -> bool {
            self.prefetch.len() >= self.prefetch_window()
                && self.queue().first().is_some_and(|x| self.is_prefetch(x.1))
        }

        /// Starts `x`, as prefetch if its priority says so.
        fn start(&mut self, x: u32) {
            if self.is_prefetch(self.current[&x]) {
                self.prefetch.insert(x);
            }
            self.in_flight.insert(x);
        }

        fn end(&mut self, x: u32) -> bool {
            self.prefetch.remove(&x);
            self.in_flight.remove(&x)
        }

        fn queue(&self) -> Vec<(TreeletId, f32)> {
            let mut q: Vec<_> = self
                .current
                .iter()
                .filter(|(id, _)| !self.in_flight.contains(id) && !self.blocked.contains(id))
                .map(|(&id, &p)| (t(id), p))
                .collect();
            q.sort_by(rank);
            q
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

        #[test]
        fn random_interleavings_keep_the_invariants(
            ops in proptest::collection::vec(op(), 1..200),
            max_in_flight in 1usize..16,
            guard_ms in prop_oneof![Just(0u64), 1u64..60],
        ) {
            let guard = Duration::from_millis(guard_ms);
            let t0 = Instant::now();
            let mut now = t0;
            let mut s = Scheduler::new(SchedulerConfig { max_in_flight });
            let mut model: Map<u64, Model> = Map::new();
            let conf = |window| ConnectionConfig {
                window,
                max_queue: 1000,
                redelivery_guard: guard,
                remember_deliveries: false,
                recent_deliveries: RECENT_DELIVERIES_KEPT,
            };
            for c in 0..2u64 {
                s.add_connection(ConnectionId(c), conf(2)).unwrap();
                model.insert(c, Model { window: 2, ..Model::default() });
            }
            let pick = |m: &Model, pick: usize| -> u32 {
                let mut v: Vec<u32> = m.in_flight.iter().copied().collect();
                v.sort_unstable();
                if v.is_empty() { 1000 } else { v[pick % v.len()] }
            };
            for op in ops {
                match op {
                    Op::List { conn, seq, items, prefetch_below } => {
                        let listed = items.iter().map(|&(i, p)| (t(i), f32::from(p))).collect();
                        let r = match prefetch_below {
                            None => s.handle_request_list(ConnectionId(conn), seq, listed, now),
                            Some(b) => s.handle_list_with_prefetch(
                                ConnectionId(conn),
                                seq,
                                listed,
                                f32::from(b),
                                false,
                                now,
                            ),
                        };
                        let Some(m) = model.get_mut(&conn) else {
                            prop_assert!(r.is_err());
                            continue;
                        };
                        let r = r.unwrap();
                        if m.last_seq.is_some_and(|l| seq <= l) {
                            prop_assert_eq!(r, ListOutcome::Stale { last_seq: m.last_seq.unwrap() });
                            continue;
                        }
                        m.last_seq = Some(seq);
                        m.prefetch_below = prefetch_below.map(f32::from);
                        m.current.clear();
                        for &(i, p) in &items {
                            let e = m.current.entry(i).or_insert(f32::from(p));
                            *e = e.max(f32::from(p));
                        }
                        m.blocked = m
                            .delivered_at
                            .iter()
                            .filter(|&(id, &at)| now.saturating_duration_since(at) < guard
                                && !m.in_flight.contains(id))
                            .map(|(&id, _)| id)
                            .collect();
                        let mut obsolete: Vec<_> = m
                            .in_flight
                            .iter()
                            .filter(|id| !m.current.contains_key(id))
                            .map(|&id| t(id))
                            .collect();
                        obsolete.sort_unstable();
                        let ListOutcome::Applied { queued, obsolete_in_flight, .. } = r else {
                            return Err(TestCaseError::fail("list not applied"));
                        };
                        prop_assert_eq!(queued, m.queue().len());
                        prop_assert_eq!(obsolete_in_flight, obsolete);
                    }
                    Op::Poll => {
                        let total: usize = model.values().map(|m| m.in_flight.len()).sum();
                        prop_assert_eq!(s.total_in_flight(), total);
                        match s.poll_transmit(now) {
                            Some((c, x)) => {
                                prop_assert!(total < max_in_flight, "global cap");
                                let m = model.get_mut(&c.0).unwrap();
                                prop_assert!(m.in_flight.len() < m.window, "window exceeded");
                                prop_assert!(m.current.contains_key(&x.0), "not in the current list");
                                prop_assert!(!m.in_flight.contains(&x.0), "in flight twice");
                                prop_assert!(!m.blocked.contains(&x.0), "resent under the same list");
                                prop_assert!(!m.held(), "prefetch beyond its window");
                                let best = m.queue()[0];
                                prop_assert_eq!(best.0, x, "not the highest-ranked");
                                m.start(x.0);
                            }
                            None => {
                                for m in model.values() {
                                    prop_assert!(
                                        total >= max_in_flight
                                            || m.in_flight.len() >= m.window
                                            || m.queue().is_empty()
                                            || m.held(),
                                        "idle with work and room"
                                    );
                                }
                            }
                        }
                    }
                    Op::PollBatch => {
                        let total: usize = model.values().map(|m| m.in_flight.len()).sum();
                        let mut batch = vec![t(999)];
                        match s.poll_batch(now, &mut batch) {
                            Some(c) => {
                                let m = model.get_mut(&c.0).unwrap();
                                // The connection's best treelets, as many as its batch limit,
                                // its window room, the global room and its queue allow, up to
                                // the first prefetch beyond the prefetch window.
                                let most = batch_limit(m.window)
                                    .min(m.window.saturating_sub(m.in_flight.len()))
                                    .min(max_in_flight.saturating_sub(total));
                                let mut expected = Vec::new();
                                while expected.len() < most && !m.held() {
                                    let Some(&(x, _)) = m.queue().first() else { break };
                                    m.start(x.0);
                                    expected.push(x);
                                }
                                prop_assert!(!expected.is_empty(), "a batch without room or work");
                                prop_assert_eq!(&batch, &expected);
                            }
                            None => {
                                prop_assert!(batch.is_empty());
                                for m in model.values() {
                                    prop_assert!(
                                        total >= max_in_flight
                                            || m.in_flight.len() >= m.window
                                            || m.queue().is_empty()
                                            || m.held(),
                                        "idle with work and room"
                                    );
                                }
                            }
                        }
                    }
                    Op::Sent { conn, pick: p } => {
                        let x = model.get(&conn).map_or(1000, |m| pick(m, p));
                        let r = s.handle_sent(ConnectionId(conn), t(x), now);
                        let was = model.get(&conn).is_some_and(|m| m.in_flight.contains(&x));
                        prop_assert!(r.is_none() || was);
                    }
                    Op::SentAll { conn, picks } => {
                        // Picks may repeat, and one in four names a treelet not in flight.
                        let xs: Vec<u32> = model.get(&conn).map_or_else(Vec::new, |m| {
                            picks
                                .iter()
                                .map(|&p| if p % 4 == 3 { 1000 } else { pick(m, p) })
                                .collect()
                        });
                        let ids: Vec<TreeletId> = xs.iter().map(|&x| t(x)).collect();
                        let mut latencies = Vec::new();
                        s.handle_sent_all(ConnectionId(conn), &ids, now, &mut latencies);
                        let distinct: HashSet<u32> = xs
                            .iter()
                            .copied()
                            .filter(|x| model.get(&conn).is_some_and(|m| m.in_flight.contains(x)))
                            .collect();
                        prop_assert!(latencies.len() <= distinct.len());
                        // Each is reported sent once.
                        let mut again = Vec::new();
                        s.handle_sent_all(ConnectionId(conn), &ids, now, &mut again);
                        prop_assert!(again.is_empty());
                        for &x in &distinct {
                            prop_assert!(s.handle_sent(ConnectionId(conn), t(x), now).is_none());
                        }
                    }
                    Op::Delivered { conn, pick: p } => {
                        let Some(m) = model.get_mut(&conn) else {
                            prop_assert!(s.handle_delivered(ConnectionId(conn), t(0), now).is_none());
                            continue;
                        };
                        let x = pick(m, p);
                        let r = s.handle_delivered(ConnectionId(conn), t(x), now);
                        prop_assert_eq!(r.is_some(), m.end(x));
                        if r.is_some() {
                            m.blocked.insert(x);
                            m.delivered_at.insert(x, now);
                        }
                    }
                    Op::DeliveredAll { conn, picks } => {
                        let Some(m) = model.get_mut(&conn) else {
                            prop_assert_eq!(s.handle_delivered_all(ConnectionId(conn), &[t(0)], now), 0);
                            continue;
                        };
                        // Picks may repeat, and one in four names a treelet not in flight.
                        let xs: Vec<u32> = picks
                            .iter()
                            .map(|&p| if p % 4 == 3 { 1000 } else { pick(m, p) })
                            .collect();
                        let ids: Vec<TreeletId> = xs.iter().map(|&x| t(x)).collect();
                        let n = s.handle_delivered_all(ConnectionId(conn), &ids, now);
                        let mut expected = 0;
                        for x in xs {
                            if m.end(x) {
                                expected += 1;
                                m.blocked.insert(x);
                                m.delivered_at.insert(x, now);
                            }
                        }
                        prop_assert_eq!(n, expected);
                    }
                    Op::Cancelled { conn, pick: p } => {
                        let Some(m) = model.get_mut(&conn) else {
                            prop_assert!(!s.handle_cancelled(ConnectionId(conn), t(0)));
                            continue;
                        };
                        let x = pick(m, p);
                        prop_assert_eq!(s.handle_cancelled(ConnectionId(conn), t(x)), m.end(x));
                    }
                    Op::Window { conn, window } => {
                        let r = s.set_window(ConnectionId(conn), window);
                        match model.get_mut(&conn) {
                            Some(m) => { r.unwrap(); m.window = window; }
                            None => prop_assert!(r.is_err()),
                        }
                    }
                    Op::Remove { conn } => {
                        let r = s.remove_connection(ConnectionId(conn));
                        prop_assert_eq!(r.is_some(), model.remove(&conn).is_some());
                    }
                    Op::Add { conn, window } => {
                        let r = s.add_connection(ConnectionId(conn), conf(window));
                        if let std::collections::hash_map::Entry::Vacant(v) = model.entry(conn) {
                            r.unwrap();
                            v.insert(Model { window, ..Model::default() });
                        } else {
                            prop_assert!(r.is_err());
                        }
                    }
                    Op::Advance { ms } => now += Duration::from_millis(ms),
                }
                for (&c, m) in &model {
                    let st = s.stats(ConnectionId(c)).unwrap();
                    prop_assert_eq!(st.in_flight, m.in_flight.len());
                    prop_assert_eq!(st.queue_depth, m.queue().len());
                    prop_assert_eq!(st.window, m.window);
                }
            }
        }
    }
}
