//! What the service's tasks share: the configuration, the pool, the metrics, and the scheduler
//! with the routes to every connection's task under one lock.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use arbor_proto::TreeletId;
use rustc_hash::FxHashMap;
use tokio::sync::{Notify, mpsc};

use super::access::{AccessPolicy, SceneAccess};
use super::config::ServeConfig;
use super::path_memory::PathObserver;
use super::prewarm::Prewarm;
use super::readers::PoolReaders;
use super::schedule::{ConnectionId, Scheduler, SchedulerConfig};
use super::server::{path_factory, transport_config};
use super::state::{ServiceCaches, ServiceState};
use super::treelets::ServedScene;
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
    /// As the service started; the scene rules in force are `access`'s.
    pub config: ServeConfig,
    /// The scene rules in force and the sessions they let in ([`super::access`]).
    pub access: Arc<SceneAccess<quinn::Connection>>,
    pub pool: Pool,
    pub state: Arc<ServiceState>,
    core: Mutex<Core>,
    /// Wakes the dispatcher: a list arrived, a treelet left the window, a window changed.
    pub wake: Notify,
    /// The threads that read treelet messages from the pool ([`super::readers`]).
    pub readers: PoolReaders,
    /// The start's read of the pool into the page cache, stopped when the service ends, and
    /// the saving of its hot-page list ([`super::prewarm`]).
    pub prewarm: Option<Prewarm>,
    /// The served form of each scene some connection uses, by name: held by the connections,
    /// so a scene's served state (its prepared dictionaries, a visible cut's node buffer) lives
    /// as long as someone is served it, not for the rest of the process.
    scenes: Mutex<HashMap<String, Weak<ServedScene>>>,
    /// Built treelet messages and decoded treelet shapes of every scene, each bounded in bytes
    /// (`message_cache_bytes`, `shape_cache_bytes`); the same ones `/metrics` reports.
    caches: ServiceCaches,
    next_id: AtomicU64,
    /// What every connection is accepted with; a connection resuming a remembered path gets a
    /// copy with its own congestion controller. `None` (tests of the shared state alone): no
    /// resumption.
    server_config: Option<quinn::ServerConfig>,
}

impl Shared {
    /// The shared state of a service about to start: an empty scheduler whose server-wide
    /// in-flight cap is the sum of the largest windows every connection can have, and the
    /// pool's reader threads (the one thing that can fail).
    pub(crate) fn new(
        config: ServeConfig,
        pool: Pool,
        state: Arc<ServiceState>,
    ) -> std::io::Result<Self> {
        let readers = PoolReaders::start(config.pool_readers, state.metrics.pool_reads.clone())?;
        let prewarm = super::prewarm::start(
            &config.db,
            config.data_dir(),
            config.pool_prewarm,
            state.metrics.pool_reads.clone(),
            state.metrics.pool_prewarm.clone(),
        );
        let max_in_flight = config.max_connections.saturating_mul(config.window_max);
        let caches = ServiceCaches::for_config(&config);
        state.set_caches(caches.clone());
        let scenes = pool.scenes().map_or(0, |s| s.len());
        let bound = config.memory_bound(scenes);
        let mib = |b: u64| b >> 20;
        tracing::info!(
            total_mib = mib(bound.total()),
            connections_mib = mib(bound.connections),
            caches_mib = mib(bound.message_cache + bound.shape_cache + bound.cut_node_cache),
            cut_buffers_mib = mib(bound.cut_buffers()),
            pool_cache_mib = mib(bound.pool_cache),
            scenes,
            "memory bound (runtime, allocator slack and admin API on top)"
        );
        state.set_memory_bound(bound);
        state.set_limits(super::state::ServiceLimits {
            max_connections: config.max_connections,
            pool_readers: config.pool_readers,
        });
        {
            let mut paths = state.paths();
            paths.set_lifetime(config.path_memory());
            paths.set_initial_window(config.initial_window);
        }
        Ok(Self {
            pool,
            state,
            core: Mutex::new(Core {
                sched: Scheduler::new(SchedulerConfig { max_in_flight }),
                routes: FxHashMap::default(),
            }),
            wake: Notify::new(),
            readers,
            prewarm,
            scenes: Mutex::new(HashMap::new()),
            caches,
            next_id: AtomicU64::new(1),
            access: Arc::new(SceneAccess::new(AccessPolicy::of(&config))),
            config,
            server_config: None,
        })
    }

    /// The shared state accepting connections with `server_config`.
    pub(crate) fn with_server_config(mut self, server_config: quinn::ServerConfig) -> Self {
        self.server_config = Some(server_config);
        self
    }

    /// The server config for a new connection from `peer`, with its own congestion
    /// controller: one that notes the path's round trips in the returned observer and, when
    /// the path is remembered, may resume it ([`super::path_memory`]). `None` without a server
    /// config or with the memory off: the common config.
    pub(crate) fn server_config_for(
        &self,
        peer: IpAddr,
    ) -> Option<(Arc<quinn::ServerConfig>, Arc<PathObserver>)> {
        let base = self.server_config.as_ref()?;
        if self.config.path_memory().is_zero() {
            return None;
        }
        let resume = self.state.paths().poll_resume(peer, Instant::now());
        let observer = Arc::new(PathObserver::default());
        let factory = path_factory(&self.config, &self.state, resume, Some(observer.clone()));
        let mut own = base.clone();
        own.transport_config(Arc::new(transport_config(&self.config, Arc::new(factory))));
        Some((Arc::new(own), observer))
    }

    /// A connection from `peer` ended; remembers its path's window and smallest round trip.
    pub(crate) fn handle_close(
        &self,
        peer: IpAddr,
        conn: &quinn::Connection,
        observer: Option<&PathObserver>,
    ) {
        let Some(rtt) = observer.and_then(PathObserver::min_rtt) else {
            return;
        };
        let window = conn.stats().path.cwnd;
        self.state
            .paths()
            .handle_close(peer, Instant::now(), window, rtt);
    }

    pub(crate) fn core(&self) -> MutexGuard<'_, Core> {
        // Every critical section leaves the scheduler consistent or panics inside the
        // scheduler itself (a bug); continuing with a poisoned lock is the better failure.
        self.core.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub(crate) fn next_connection_id(&self) -> ConnectionId {
        ConnectionId(self.next_id.fetch_add(1, Ordering::Relaxed))
    }

    /// The served form of a stored scene, shared by its connections while any holds it
    /// (rebuilt when the scene's generation changed, i.e. it was re-imported, or when no
    /// connection held it any more).
    pub(crate) fn served_scene(&self, stored: StoredScene) -> Arc<ServedScene> {
        let mut scenes = self.scenes.lock().unwrap_or_else(|p| p.into_inner());
        let name = stored.description.name.clone();
        if let Some(s) = scenes.get(&name).and_then(Weak::upgrade)
            && s.stored.generation == stored.generation
        {
            return s;
        }
        // Scenes nobody is served any more (removed, replaced, or just idle) leave the map
        // here, so it holds no more names than scenes in use plus this one.
        scenes.retain(|_, s| s.strong_count() > 0);
        let s = Arc::new(ServedScene::with_caches(stored, &self.caches));
        scenes.insert(name, Arc::downgrade(&s));
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::{BuildOptions, DepthChoice};
    use crate::pipeline::{SceneImport, import_scene};
    use crate::service::treelets::CachedBatch;

    /// The bunny built into a fresh pool, and the shared state serving it.
    fn bunny() -> (tempfile::TempDir, Shared, StoredScene) {
        let dir = tempfile::tempdir().unwrap();
        let pool = Pool::open(dir.path()).unwrap();
        let input = std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../shared/data/meshes/stanford-bunny.obj"
        ));
        assert!(
            input.exists(),
            "the real scans in ../shared/data are required"
        );
        let request = SceneImport {
            name: "bunny".into(),
            input: input.to_path_buf(),
            build: BuildOptions {
                depth: DepthChoice::Fixed(4),
                progress: false,
                ..BuildOptions::default()
            },
            ..SceneImport::default()
        };
        import_scene(&pool, &request).unwrap();
        let stored = pool.scene("bunny").unwrap();
        let shared = Shared::new(
            ServeConfig::new(dir.path()),
            pool,
            Arc::new(ServiceState::default()),
        )
        .unwrap();
        (dir, shared, stored)
    }

    #[test]
    fn a_batch_the_cache_holds_in_part_is_read_once_and_counted_once() {
        let (_dir, shared, stored) = bunny();
        let count = stored.description.treelet_count;
        assert!(count >= 4, "the bunny has {count} treelets");
        let scene = shared.served_scene(stored);
        let channels = scene.stored.description.layout.channels().to_vec();
        let figures = || shared.caches.messages.figures();
        let ids = |r: std::ops::Range<u32>| r.map(TreeletId).collect::<Vec<_>>();
        let whole = |b: CachedBatch| match b {
            CachedBatch::Whole(chunks) => chunks.concat(),
            CachedBatch::Partial(_) => panic!("the cache held the whole batch"),
        };
        let one_by_one = |r: std::ops::Range<u32>| -> Vec<u8> {
            r.flat_map(|t| scene.message(TreeletId(t), &channels).unwrap().to_vec())
                .collect()
        };
        // Nothing held: a partial batch, its misses counted; read, it is the messages.
        let CachedBatch::Partial(first) = scene.cached_batch(&ids(0..3), &channels) else {
            panic!("an empty cache held a batch");
        };
        let (_, hits, misses) = figures();
        assert_eq!((hits, misses), (0, 3));
        let read = scene.complete_batch(first, &channels).unwrap().concat();
        assert_eq!(
            (figures().1, figures().2),
            (0, 3),
            "reading counts nothing more"
        );
        // Held now, whole.
        assert_eq!(whole(scene.cached_batch(&ids(0..3), &channels)), read);
        assert_eq!((figures().1, figures().2), (3, 3));
        // Two held, one not: counted once, read once, the same bytes as one by one.
        let CachedBatch::Partial(part) = scene.cached_batch(&ids(1..4), &channels) else {
            panic!("treelet 3 was never read");
        };
        assert_eq!((figures().1, figures().2), (5, 4));
        let read = scene.complete_batch(part, &channels).unwrap().concat();
        assert_eq!((figures().1, figures().2), (5, 4));
        assert_eq!(read, one_by_one(1..4));
    }

    #[test]
    fn a_served_scene_lives_as_long_as_a_connection_holds_it() {
        let (_dir, shared, stored) = bunny();
        let held = |name: &str| {
            let scenes = shared.scenes.lock().unwrap();
            scenes.get(name).map(Weak::strong_count)
        };

        let a = shared.served_scene(stored.clone());
        let b = shared.served_scene(stored.clone());
        assert!(Arc::ptr_eq(&a, &b), "connections of one scene share it");
        drop((a, b));
        assert_eq!(
            held("bunny"),
            Some(0),
            "nothing keeps it once they are gone"
        );

        // Another scene (a rename of the same trees) while nobody holds the first: the first
        // leaves the map.
        let mut other = stored.clone();
        other.description.name = "other".into();
        let c = shared.served_scene(other);
        assert_eq!(held("bunny"), None);
        assert_eq!(held("other"), Some(1));
        let d = shared.served_scene(stored);
        assert_eq!(held("bunny"), Some(1));
        assert_eq!(held("other"), Some(1), "still held by its connection");
        assert_eq!(d.stored.description.name, "bunny");
        drop(c);
        assert_eq!(shared.scenes.lock().unwrap().len(), 2);
    }
}
