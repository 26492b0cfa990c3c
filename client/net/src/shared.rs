//! State shared by the caller's handle and the connection task: counters, the current scene,
//! the received-bytes budget (backpressure) and request times (latency).

use std::collections::VecDeque;
use std::collections::hash_map::Entry;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use arbor_proto::{SceneDescription, TreeletId, TreeletMap};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::event::{ClientEvent, ClientStats};

/// Events on their way to the caller, with the budget their treelet bytes hold until the last
/// of them is taken. A stream reader sends the treelets it found complete in what it read at
/// once as one entry: one channel operation and one budget release per batch, not per treelet.
#[derive(Debug)]
pub(crate) struct Queued {
    pub events: VecDeque<ClientEvent>,
    pub lease: Option<BufferLease>,
}

impl Queued {
    pub fn plain(event: ClientEvent) -> Self {
        Self {
            events: VecDeque::from([event]),
            lease: None,
        }
    }
}

#[derive(Debug)]
pub(crate) struct Shared {
    stats: Mutex<ClientStats>,
    scene: Mutex<Option<Arc<SceneDescription>>>,
    latency: Mutex<LatencyTracker>,
    /// One permit per buffered byte, `capacity` in all.
    budget: Arc<Semaphore>,
    capacity: usize,
}

impl Shared {
    pub fn new(max_buffered_bytes: usize) -> Self {
        let capacity = max_buffered_bytes.clamp(1, u32::MAX as usize);
        Self {
            stats: Mutex::default(),
            scene: Mutex::default(),
            latency: Mutex::default(),
            budget: Arc::new(Semaphore::new(capacity)),
            capacity,
        }
    }

    /// The counters, for updating. Never held across an await.
    pub fn stats(&self) -> MutexGuard<'_, ClientStats> {
        lock(&self.stats)
    }

    pub fn scene(&self) -> Option<Arc<SceneDescription>> {
        lock(&self.scene).clone()
    }

    pub fn set_scene(&self, scene: Arc<SceneDescription>) {
        *lock(&self.scene) = Some(scene);
    }

    pub fn latency(&self) -> MutexGuard<'_, LatencyTracker> {
        lock(&self.latency)
    }

    /// Waits until some budget is free: the stream acceptor's gate, so that no new stream is
    /// taken while the buffer is full.
    pub async fn wait_for_room(&self) {
        // The semaphore is fair: this waits behind readers waiting for their messages' bytes.
        drop(
            self.budget
                .acquire()
                .await
                .expect("the budget is never closed"),
        );
    }

    /// Budget for a message about to be read (all of it for a message larger than the whole
    /// budget), if it is free now.
    pub fn try_permit(&self, bytes: usize) -> Option<OwnedSemaphorePermit> {
        let permits = bytes.min(self.capacity) as u32;
        self.budget.clone().try_acquire_many_owned(permits).ok()
    }

    /// Budget for a message about to be read (all of it for a message larger than the whole
    /// budget), waiting while the buffer is full.
    pub async fn permit(&self, bytes: usize) -> OwnedSemaphorePermit {
        let permits = bytes.min(self.capacity) as u32;
        self.budget
            .clone()
            .acquire_many_owned(permits)
            .await
            .expect("the budget is never closed")
    }

    /// `permit` now holds `bytes` of `treelets` received treelets on their way to the caller:
    /// the counters are updated under one lock, and the lease gives the budget back when it
    /// drops.
    pub fn lease(
        self: &Arc<Self>,
        permit: OwnedSemaphorePermit,
        bytes: usize,
        treelets: usize,
    ) -> BufferLease {
        {
            let mut s = self.stats();
            s.treelets_received += treelets as u64;
            s.bytes_received += bytes as u64;
            s.buffered_bytes += bytes;
            s.peak_buffered_bytes = s.peak_buffered_bytes.max(s.buffered_bytes);
        }
        BufferLease {
            shared: self.clone(),
            _permit: permit,
            bytes,
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // The data behind these locks stays consistent even if a holder panicked.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Budget held by buffered treelet bytes; given back when dropped (the caller took the event,
/// or the read was abandoned).
pub(crate) struct BufferLease {
    shared: Arc<Shared>,
    _permit: OwnedSemaphorePermit,
    bytes: usize,
}

impl std::fmt::Debug for BufferLease {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BufferLease({} bytes)", self.bytes)
    }
}

impl Drop for BufferLease {
    fn drop(&mut self) {
        let mut s = self.shared.stats();
        s.buffered_bytes -= self.bytes;
    }
}

/// When each wanted treelet was first named by a list sent, so its latency can be reported on
/// arrival. Knows the ids of the latest list and of the one before it (whose treelets may still
/// be in flight): an id named by neither is forgotten.
///
/// One map holds them all, each id with the number of the last list naming it, so a list costs
/// one hash lookup per id and an arrival one removal (two maps, the latest list's and the one
/// before, took up to three lookups per id and a map built per list), and the map is a
/// [`TreeletMap`]: lists and arrivals go in nearly ascending id order. Ids two lists old are
/// pruned in one sweep once they could make up half the map, so the map stays within about
/// twice the two lists and the sweep costs O(1) per id listed. Times are nanoseconds since the
/// first list, so an arrival's latency is an integer difference (an `Instant` difference per
/// treelet was a fifth of a batch's hand-over, callgrind) and an entry is 16 bytes, not 24.
#[derive(Debug, Default)]
pub(crate) struct LatencyTracker {
    named: TreeletMap<Named>,
    /// Lists sent, wrapping (compared by difference, and an entry is pruned long before 2³²
    /// lists pass).
    lists: u32,
    /// Ids in the latest list and in the one before it, duplicates included.
    listed: [usize; 2],
    /// When the first list was sent: the zero of the times kept.
    base: Option<Instant>,
}

#[derive(Clone, Copy, Debug)]
struct Named {
    /// When a list first named the treelet (since it last arrived), nanoseconds since
    /// [`LatencyTracker::base`].
    since: u64,
    /// The number of the last list naming it.
    list: u32,
}

/// Whether an id last named by list `list` is still known when `latest` is the latest list:
/// named by it or by the one before.
fn still_known(latest: u32, list: u32) -> bool {
    latest.wrapping_sub(list) <= 1
}

impl LatencyTracker {
    /// `now` in nanoseconds since the first list (0 before it: no treelet is named then).
    /// Read once per batch of arrivals, for [`LatencyTracker::arrived`].
    pub fn nanos(&self, now: Instant) -> u64 {
        self.base.map_or(0, |base| {
            u64::try_from(now.saturating_duration_since(base).as_nanos()).unwrap_or(u64::MAX)
        })
    }

    /// A list naming `ids` was sent at `now`.
    pub fn list_sent(&mut self, ids: impl IntoIterator<Item = TreeletId>, now: Instant) {
        self.base.get_or_insert(now);
        let now = self.nanos(now);
        let ids = ids.into_iter();
        self.lists = self.lists.wrapping_add(1);
        let list = self.lists;
        // Room for the ids beyond those held: all of a first list, none of a list repeated.
        let (least, most) = ids.size_hint();
        let held = self.named.len();
        self.named
            .reserve(most.unwrap_or(least).saturating_sub(held));
        let mut count = 0;
        for id in ids {
            count += 1;
            match self.named.entry(id) {
                Entry::Occupied(slot) => {
                    let slot = slot.into_mut();
                    // Named by this list already (a duplicate) or by the one before: it keeps
                    // its first time. Older: forgotten, so it starts again.
                    if !still_known(list, slot.list) {
                        slot.since = now;
                    }
                    slot.list = list;
                }
                Entry::Vacant(slot) => {
                    slot.insert(Named { since: now, list });
                }
            }
        }
        self.listed = [count, self.listed[0]];
        // Every entry not named by the last two lists is stale; sweep once they could be half.
        if self.named.len() > 2 * (self.listed[0] + self.listed[1]) + 64 {
            let latest = self.lists;
            self.named
                .retain(|_, named| still_known(latest, named.list));
        }
    }

    /// Treelet `id` arrived at `now` ([`LatencyTracker::nanos`]): its latency, zero if no list
    /// named it.
    pub fn arrived(&mut self, id: TreeletId, now: u64) -> Duration {
        match self.named.remove(&id) {
            Some(named) if still_known(self.lists, named.list) => {
                Duration::from_nanos(now.saturating_sub(named.since))
            }
            _ => Duration::ZERO,
        }
    }

    /// Treelets known (named by the last two lists and not arrived), stale entries included.
    #[cfg(test)]
    fn held(&self) -> usize {
        self.named.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn arrived(l: &mut LatencyTracker, id: TreeletId, now: Instant) -> Duration {
        let now = l.nanos(now);
        l.arrived(id, now)
    }

    #[test]
    fn latency_counts_from_the_first_list_naming_a_treelet() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut l = LatencyTracker::default();
        l.list_sent([TreeletId(1), TreeletId(2), TreeletId(2)], t0);
        l.list_sent([TreeletId(2), TreeletId(3)], t0 + ms(10));
        // 2 keeps its first time; 1 (dropped from the list) is still known, 3 is new.
        assert_eq!(arrived(&mut l, TreeletId(2), t0 + ms(30)), ms(30));
        assert_eq!(arrived(&mut l, TreeletId(1), t0 + ms(30)), ms(30));
        assert_eq!(arrived(&mut l, TreeletId(3), t0 + ms(30)), ms(20));
        // Arrived treelets are forgotten; unknown ones get zero.
        assert_eq!(arrived(&mut l, TreeletId(2), t0 + ms(40)), Duration::ZERO);
        l.list_sent([TreeletId(4)], t0 + ms(50));
        l.list_sent([TreeletId(5)], t0 + ms(60));
        l.list_sent([TreeletId(6)], t0 + ms(70));
        // Two lists later, 4 is forgotten: the tracker holds at most two lists.
        assert_eq!(arrived(&mut l, TreeletId(4), t0 + ms(80)), Duration::ZERO);
        assert_eq!(arrived(&mut l, TreeletId(5), t0 + ms(80)), ms(20));
        // Named again after being forgotten: its time starts again.
        l.list_sent([TreeletId(4)], t0 + ms(90));
        assert_eq!(arrived(&mut l, TreeletId(4), t0 + ms(95)), ms(5));
    }

    #[test]
    fn latency_tracker_stays_within_about_two_lists() {
        let t0 = Instant::now();
        let mut l = LatencyTracker::default();
        // Lists of 100 new ids each, none arriving: the stale ones are swept.
        for n in 0..1000u32 {
            l.list_sent((n * 100..n * 100 + 100).map(TreeletId), t0);
            assert!(l.held() <= 2 * 200 + 64 + 100, "{} held", l.held());
        }
        // The last two lists are still known, the one before is not.
        let later = t0 + Duration::from_millis(7);
        assert_eq!(
            arrived(&mut l, TreeletId(999 * 100), later),
            Duration::from_millis(7)
        );
        assert_eq!(
            arrived(&mut l, TreeletId(998 * 100), later),
            Duration::from_millis(7)
        );
        assert_eq!(arrived(&mut l, TreeletId(997 * 100), later), Duration::ZERO);
    }

    #[tokio::test]
    async fn budget_is_given_back_when_leases_drop() {
        let s = Arc::new(Shared::new(100));
        let a = s.lease(s.permit(60).await, 60, 1);
        let b = s.lease(s.try_permit(40).unwrap(), 40, 2);
        assert_eq!(s.stats().buffered_bytes, 100);
        assert_eq!(s.stats().treelets_received, 3);
        assert_eq!(s.stats().bytes_received, 100);
        // Full: a third reservation fails at once or waits.
        assert!(s.try_permit(1).is_none());
        let pending = tokio::time::timeout(Duration::from_millis(50), s.permit(1)).await;
        assert!(pending.is_err());
        drop(a);
        assert_eq!(s.stats().buffered_bytes, 40);
        // Larger than the budget: waits until all of it is free, then takes it alone.
        let big = tokio::spawn({
            let s = s.clone();
            async move { s.lease(s.permit(500).await, 500, 1) }
        });
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!big.is_finished());
        assert!(s.try_permit(500).is_none());
        drop(b);
        let c = big.await.unwrap();
        assert_eq!(s.stats().buffered_bytes, 500);
        assert_eq!(s.stats().peak_buffered_bytes, 500);
        drop(c);
        assert_eq!(s.stats().buffered_bytes, 0);
        s.wait_for_room().await;
    }
}
