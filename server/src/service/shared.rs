//! What the service's tasks share: the configuration, the pool, the metrics, and the scheduler
//! with the routes to every connection's task under one lock.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use arbor_proto::TreeletId;
use rustc_hash::FxHashMap;
use tokio::sync::{Notify, mpsc};

use super::config::ServeConfig;
use super::schedule::{ConnectionId, Scheduler, SchedulerConfig};
use super::shapes::ShapeCache;
use super::state::{ServiceCaches, ServiceState};
use super::treelets::{MessageCache, ServedScene};
use crate::pool::{Pool, StoredScene};

/// How long a closing connection waits for its last control frame (`Error`, `Goodbye`) to be
/// acknowledged before closing, so the frame is not discarded by the close.
pub const CLOSE_FLUSH: Duration = Duration::from_millis(300);

/// The scheduler and the routes to each connection's task, under one lock. Lock order: this
/// lock is never held across an `.await` nor while taking the session lock.
#[derive(Debug)]
pub(crate) struct Core {
    pub sched: Scheduler,
    /// Looked up once per dispatched batch; keyed by the server's own connection counter, so a
    /// fast non-keyed hash is safe here.
    pub routes: FxHashMap<ConnectionId, mpsc::UnboundedSender<Vec<TreeletId>>>,
}

/// Everything the service's tasks share.
#[derive(Debug)]
pub(crate) struct Shared {
    pub config: ServeConfig,
    pub pool: Pool,
    pub state: Arc<ServiceState>,
    core: Mutex<Core>,
    /// Wakes the dispatcher: a list arrived, a treelet left the window, a window changed.
    pub wake: Notify,
    scenes: Mutex<HashMap<String, Arc<ServedScene>>>,
    /// Built treelet messages of every scene, bounded by `message_cache_bytes`.
    pub messages: Arc<MessageCache>,
    /// Decoded treelet shapes of every scene for the push plans, bounded by
    /// `shape_cache_bytes`.
    pub shapes: Arc<ShapeCache>,
    next_id: AtomicU64,
}

impl Shared {
    /// The shared state of a service about to start: an empty scheduler whose server-wide
    /// in-flight cap is the sum of the largest windows every connection can have.
    pub(crate) fn new(config: ServeConfig, pool: Pool, state: Arc<ServiceState>) -> Self {
        let max_in_flight = config.max_connections.saturating_mul(config.window_max);
        let caches = ServiceCaches {
            messages: Arc::new(MessageCache::new(
                usize::try_from(config.message_cache_bytes).unwrap_or(usize::MAX),
            )),
            shapes: Arc::new(ShapeCache::new(
                usize::try_from(config.shape_cache_bytes).unwrap_or(usize::MAX),
            )),
        };
        state.set_caches(caches.clone());
        Self {
            pool,
            state,
            core: Mutex::new(Core {
                sched: Scheduler::new(SchedulerConfig { max_in_flight }),
                routes: FxHashMap::default(),
            }),
            wake: Notify::new(),
            scenes: Mutex::new(HashMap::new()),
            messages: caches.messages,
            shapes: caches.shapes,
            next_id: AtomicU64::new(1),
            config,
        }
    }

    pub(crate) fn core(&self) -> MutexGuard<'_, Core> {
        // Every critical section leaves the scheduler consistent or panics inside the
        // scheduler itself (a bug); continuing with a poisoned lock is the better failure.
        self.core.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub(crate) fn next_connection_id(&self) -> ConnectionId {
        ConnectionId(self.next_id.fetch_add(1, Ordering::Relaxed))
    }

    /// The served form of a stored scene, shared by its connections (rebuilt when the scene's
    /// generation changed, i.e. it was re-imported).
    pub(crate) fn served_scene(&self, stored: StoredScene) -> Arc<ServedScene> {
        let mut scenes = self.scenes.lock().unwrap_or_else(|p| p.into_inner());
        let name = stored.description.name.clone();
        if let Some(s) = scenes.get(&name)
            && s.stored.generation == stored.generation
        {
            return s.clone();
        }
        let s = Arc::new(ServedScene::with_caches(
            stored,
            self.messages.clone(),
            self.shapes.clone(),
        ));
        scenes.insert(name, s.clone());
        s
    }
}
