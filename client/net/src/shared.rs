//! State shared by the caller's handle and the connection task: counters, the current scene,
//! the received-bytes budget (backpressure) and request times (latency).

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use arbor_proto::{SceneDescription, TreeletId};
use rustc_hash::FxHashMap;
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
/// arrival. Holds the ids of the latest list and of the one before it (whose treelets may still
/// be in flight), so it never grows beyond two lists.
#[derive(Debug, Default)]
pub(crate) struct LatencyTracker {
    current: FxHashMap<TreeletId, Instant>,
    previous: FxHashMap<TreeletId, Instant>,
    /// The map before `previous`, emptied, kept for its allocation: the next list is built in
    /// it (a list is sent every client cycle, and a whole-scene list grew a fresh map through
    /// several rehashes on the way to the wire).
    spare: FxHashMap<TreeletId, Instant>,
}

impl LatencyTracker {
    /// A list naming `ids` was sent at `now`.
    pub fn list_sent(&mut self, ids: impl IntoIterator<Item = TreeletId>, now: Instant) {
        let ids = ids.into_iter();
        let mut next = std::mem::take(&mut self.spare);
        next.reserve(ids.size_hint().0);
        for id in ids {
            if let std::collections::hash_map::Entry::Vacant(slot) = next.entry(id) {
                let first = self
                    .current
                    .remove(&id)
                    .or_else(|| self.previous.remove(&id))
                    .unwrap_or(now);
                slot.insert(first);
            }
        }
        let mut older = std::mem::replace(
            &mut self.previous,
            std::mem::replace(&mut self.current, next),
        );
        older.clear();
        self.spare = older;
    }

    /// Treelet `id` arrived at `now`: its latency, zero if no list named it.
    pub fn arrived(&mut self, id: TreeletId, now: Instant) -> Duration {
        self.current
            .remove(&id)
            .or_else(|| self.previous.remove(&id))
            .map_or(Duration::ZERO, |t| now.saturating_duration_since(t))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_counts_from_the_first_list_naming_a_treelet() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut l = LatencyTracker::default();
        l.list_sent([TreeletId(1), TreeletId(2), TreeletId(2)], t0);
        l.list_sent([TreeletId(2), TreeletId(3)], t0 + ms(10));
        // 2 keeps its first time; 1 (dropped from the list) is still known, 3 is new.
        assert_eq!(l.arrived(TreeletId(2), t0 + ms(30)), ms(30));
        assert_eq!(l.arrived(TreeletId(1), t0 + ms(30)), ms(30));
        assert_eq!(l.arrived(TreeletId(3), t0 + ms(30)), ms(20));
        // Arrived treelets are forgotten; unknown ones get zero.
        assert_eq!(l.arrived(TreeletId(2), t0 + ms(40)), Duration::ZERO);
        l.list_sent([TreeletId(4)], t0 + ms(50));
        l.list_sent([TreeletId(5)], t0 + ms(60));
        l.list_sent([TreeletId(6)], t0 + ms(70));
        // Two lists later, 4 is forgotten: the tracker holds at most two lists.
        assert_eq!(l.arrived(TreeletId(4), t0 + ms(80)), Duration::ZERO);
        assert_eq!(l.arrived(TreeletId(5), t0 + ms(80)), ms(20));
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
