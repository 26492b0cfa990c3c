//! The treelet service: QUIC endpoint, accept loop with a connection cap, the dispatcher that
//! drives the shared [`Scheduler`](super::schedule::Scheduler), and graceful shutdown. The admin API is mounted beside it by
//! [`crate::daemon`], on the same shutdown broadcast.
//!
//! # Tasks
//!
//! * **Supervisor** (one): accepts connections. Within the cap (a semaphore of
//!   `max_connections` permits, held by each connection task until it ends) it spawns a
//!   connection task ([`super::connection`]); beyond it, or once shutdown began, it completes the
//!   handshake only to close the connection with `ServerBusy` / `ShuttingDown` (so the client
//!   sees an application code; at most [`MAX_REFUSALS`] such handshakes at once, beyond that
//!   quinn refuses at the transport level). Refusals count in `connections_rejected`.
//! * **Dispatcher** (one): waits on a [`Notify`](tokio::sync::Notify), then calls
//!   [`Scheduler::poll_batch`](super::schedule::Scheduler::poll_batch) until `None` and hands
//!   each connection's batch to that connection's task through an unbounded channel, one message
//!   per batch — never blocking on any connection (the scheduler's window bounds what each
//!   channel can hold).
//! * **Connection tasks** (one per connection) and their **stream tasks** (one per batch in
//!   flight).
//!
//! # Why a slow reader cannot starve anyone
//!
//! A connection whose client stops reading stalls its own stream tasks (flow control and the
//! client's stream limit block `open_uni`/`write`); those tasks hold only that connection's
//! in-flight slots. The scheduler's server-wide cap is set to
//! `max_connections × window_max`, i.e. the sum of the largest windows every connection can
//! have, so the cap never binds before each connection's own window does: slots held by a
//! stalled connection are never slots another connection needed. The cap remains a memory
//! bound. The stalled connection is closed with `SlowReader` after `slow_reader_timeout_ms`
//! without progress on any of its streams, which frees its slots.
//!
//! # Shutdown
//!
//! [`RunningService::shutdown`] (or SIGTERM/SIGINT in the CLI): readiness goes false, the accept
//! loop stops (newcomers are refused with `ShuttingDown`), the dispatcher stops starting
//! treelets; each connection lets its in-flight streams finish until `shutdown_grace_ms`,
//! resets what is left, sends `Goodbye { ShuttingDown }` on its control stream and closes with
//! `ShuttingDown`. The supervisor waits for every connection task (drop-to-finish channel), then
//! `endpoint.wait_idle()` for at most [`WAIT_IDLE_BOUND`] (the daemon then gives its admin server
//! at most 300 ms). Total: at most grace + 1.3 s (grace + 0.1 s when every client acknowledges at once).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use arbor_proto::wire::ErrorCode;
use tokio::sync::Semaphore;
use tokio::task::JoinHandle;

use super::access::{AccessPolicy, SceneAccess};
use super::certificate::{LiveCertificate, PresentedCertificate};
use super::config::{ConfigError, ServeConfig};
use super::connection;
use super::path_memory;
use super::shared::{CLOSE_FLUSH, Core, Shared};
use super::shutdown::{self, Shutdown, ShutdownTrigger};
use super::state::ServiceState;
use super::tls::{self, IdentityOrigin, TlsError};
use crate::pool::{POOL_LOCK_WAIT, POOL_SEGMENT_BYTES, Pool, PoolError};

/// Most handshakes completed at once only to refuse the connection with an application code.
pub const MAX_REFUSALS: usize = 32;
/// How long `shutdown` waits for the endpoint to drain after closing every connection.
pub const WAIT_IDLE_BOUND: Duration = Duration::from_millis(500);

/// Why the service could not start.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The configuration is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The pool directory does not exist (serving never creates a pool; `import` does).
    #[error("no pool at {} (create one with `arbor-server import`)", path.display())]
    NoPool { path: PathBuf },
    /// The pool could not be opened (missing, corrupt, or locked by another process: sled
    /// allows one server per pool directory).
    #[error("opening pool {}: {source}", path.display())]
    Pool {
        path: PathBuf,
        #[source]
        source: PoolError,
    },
    /// The TLS identity could not be loaded or created.
    #[error(transparent)]
    Tls(#[from] TlsError),
    /// The admin token file could not be read or created, or is empty.
    #[error("admin token {}: {reason}", path.display())]
    AdminToken { path: PathBuf, reason: String },
    /// A listener could not be bound.
    #[error("binding the {what} listener on {addr}: {source}")]
    Bind {
        what: &'static str,
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    /// The daemon's scene manager (imports, checks, copies) could not start.
    #[error(transparent)]
    Manager(#[from] crate::live_import::ManagerError),
    /// The threads that read the pool could not be started.
    #[error("starting the pool's reader threads: {0}")]
    Readers(#[source] std::io::Error),
}

/// Puts new scene rules in force while the service runs ([`RunningService::access_handle`]).
#[derive(Clone, Debug)]
pub struct AccessHandle {
    access: Arc<SceneAccess<quinn::Connection>>,
    state: Arc<ServiceState>,
}

impl AccessHandle {
    /// Puts `config`'s scene rules in force ([`super::access`]): the next `Hello` is answered
    /// by them, and the sessions they no longer admit are closed with `Unauthorized`.
    pub fn reload(&self, config: &ServeConfig) -> AccessReload {
        let shut_out = self.access.replace(AccessPolicy::of(config));
        for (id, grant, conn) in &shut_out {
            let reason = format!("access to scene {:?} revoked", grant.scene);
            tracing::warn!(connection = id, "closed: {reason}");
            conn.close(
                quinn::VarInt::from_u32(ErrorCode::Unauthorized.to_u32()),
                reason.as_bytes(),
            );
            self.state.metrics.error(ErrorCode::Unauthorized);
        }
        AccessReload {
            shut_out: shut_out.len(),
            kept: self.access.sessions(),
        }
    }
}

/// What putting new scene rules in force did ([`AccessHandle::reload`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AccessReload {
    /// Sessions closed: their token no longer opens their scene.
    pub shut_out: usize,
    /// Sessions the new rules still admit.
    pub kept: usize,
}

/// A started service. Dropping it without [`RunningService::shutdown`] leaves the tasks
/// running until the runtime ends.
#[derive(Debug)]
pub struct RunningService {
    /// The bound QUIC (UDP) address.
    pub quic_addr: SocketAddr,
    /// SHA-256 of the server certificate at start, lowercase hex: what clients pin (after a
    /// reload, `state.fingerprint()`).
    pub fingerprint: String,
    /// Where the TLS identity came from.
    pub tls_origin: IdentityOrigin,
    /// Metrics, sessions and readiness.
    pub state: Arc<ServiceState>,
    access: Arc<SceneAccess<quinn::Connection>>,
    certificate: Arc<LiveCertificate>,
    pool: Pool,
    trigger: ShutdownTrigger,
    shutdown: Shutdown,
    task: JoinHandle<()>,
}

impl RunningService {
    /// The pool being served (read-only use).
    pub fn pool(&self) -> &Pool {
        &self.pool
    }

    /// A handle that starts graceful shutdown from elsewhere (e.g. a signal handler).
    pub fn shutdown_trigger(&self) -> ShutdownTrigger {
        self.trigger.clone()
    }

    /// What puts new scene rules in force while the service runs.
    pub fn access_handle(&self) -> AccessHandle {
        AccessHandle {
            access: self.access.clone(),
            state: self.state.clone(),
        }
    }

    /// The certificate QUIC clients are shown: [`LiveCertificate::replace`] renews it for the
    /// next handshakes.
    pub fn certificate(&self) -> Arc<LiveCertificate> {
        self.certificate.clone()
    }

    /// Graceful shutdown, as on SIGTERM; returns when the service has stopped (within the grace
    /// plus 1.3 s).
    pub async fn shutdown(self) {
        self.trigger.trigger();
        self.wait().await;
    }

    /// Listens for the shutdown broadcast (what the daemon's admin server stops on).
    pub(crate) fn shutdown_signal(&self) -> Shutdown {
        self.shutdown.clone()
    }

    /// Waits until the service stops (after a trigger from [`RunningService::shutdown_trigger`]).
    pub async fn wait(self) {
        if let Err(e) = self.task.await {
            tracing::error!("the service supervisor failed: {e}");
        }
    }
}

/// The QUIC transport of every connection; `congestion` builds its congestion controller
/// (Cubic from `initial_window`, or a resumed path's, see [`super::path_memory`]).
pub(crate) fn transport_config(
    config: &ServeConfig,
    congestion: Arc<dyn quinn::congestion::ControllerFactory + Send + Sync>,
) -> quinn::TransportConfig {
    let plan = config.memory_plan();
    let varint = |v: u64| quinn::VarInt::from_u64(v).unwrap_or(quinn::VarInt::MAX);
    let mut t = quinn::TransportConfig::default();
    t.max_concurrent_bidi_streams(1u32.into())
        .max_concurrent_uni_streams(0u32.into())
        .stream_receive_window(varint(plan.receive_window))
        .receive_window(varint(plan.receive_window))
        .send_window(plan.send_window)
        .max_idle_timeout(quinn::IdleTimeout::try_from(config.idle_timeout()).ok())
        .datagram_receive_buffer_size(None);
    // A treelet batch leaves the window when the client has acknowledged all of it; with the
    // default 25 ms ACK delay the last packet of a batch waited that long for its ACK, which
    // capped one connection near 20k treelets/s on loopback. Asking the client (ACK frequency
    // extension) to acknowledge within ACK_DELAY keeps the window turning.
    let mut acks = quinn::AckFrequencyConfig::default();
    acks.max_ack_delay(Some(ACK_DELAY));
    t.ack_frequency_config(Some(acks));
    t.congestion_controller_factory(congestion);
    t
}

/// The controller factory of a connection: Cubic from `initial_window`, the random-loss filter
/// unless `random_loss_tolerance` is off, and what path memory gives it (`resume`, `observer`;
/// neither for the common config).
pub(crate) fn path_factory(
    config: &ServeConfig,
    state: &ServiceState,
    resume: Option<path_memory::Resume>,
    observer: Option<Arc<path_memory::PathObserver>>,
) -> path_memory::PathFactory {
    let mut cubic = quinn::congestion::CubicConfig::default();
    cubic.initial_window(config.initial_window);
    path_memory::PathFactory {
        cubic: Arc::new(cubic),
        resume,
        counters: state.metrics.path_resumes.clone(),
        observer,
        losses: config
            .random_loss_tolerance
            .then(|| state.metrics.loss_events.clone()),
    }
}

/// Longest delay the server asks clients to hold an ACK back (see `transport_config`).
pub const ACK_DELAY: Duration = Duration::from_millis(1);

async fn open_pool(db: &Path, cache_bytes: u64) -> Result<Pool, ServeError> {
    let t0 = std::time::Instant::now();
    loop {
        match Pool::open_with_cache(db, cache_bytes) {
            Ok(p) => return Ok(p),
            Err(PoolError::InUse(_)) if t0.elapsed() < POOL_LOCK_WAIT => {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(source) => {
                return Err(ServeError::Pool {
                    path: db.to_owned(),
                    source,
                });
            }
        }
    }
}

/// Starts the service: opens the pool, loads or creates the TLS identity, binds QUIC and spawns
/// the tasks on the current tokio runtime.
pub async fn start_service(config: ServeConfig) -> Result<RunningService, ServeError> {
    config.validate()?;
    tls::install_crypto_provider();
    if !config.db.is_dir() {
        return Err(ServeError::NoPool {
            path: config.db.clone(),
        });
    }
    let pool = open_pool(&config.db, config.pool_cache_bytes).await?;
    if pool.segment_bytes() < POOL_SEGMENT_BYTES {
        let segments = pool
            .disk_bytes()
            .map_or(0, |b| b.div_ceil(pool.segment_bytes() as u64));
        tracing::warn!(
            db = %config.db.display(),
            segment_kib = pool.segment_bytes() >> 10,
            segments,
            "this pool was made with small log segments, and opening it reads every segment's \
             header (on a disk held to a few hundred reads a second, seconds to minutes before \
             the server serves): with the server stopped, `arbor-server copy --db POOL --to NEW` \
             makes a copy with {} MiB segments",
            POOL_SEGMENT_BYTES >> 20
        );
    }
    match pool.scenes() {
        Ok(s) if s.is_empty() => {
            tracing::warn!(db = %config.db.display(), "the pool holds no scenes")
        }
        Ok(s) => tracing::info!(
            scenes = ?s.iter().map(|d| d.name.as_str()).collect::<Vec<_>>(),
            "pool opened"
        ),
        Err(source) => {
            return Err(ServeError::Pool {
                path: config.db.clone(),
                source,
            });
        }
    }
    let identity = tls::load_or_create(&config.tls, config.data_dir())?;
    let presented = Arc::new(PresentedCertificate::of(&identity)?);
    let certificate = Arc::new(LiveCertificate::new(presented));
    let state = Arc::new(ServiceState::new(identity.fingerprint.clone()));
    state.present_certificate("quic", certificate.clone());
    // Without path memory every connection shares this config; its controller filters random
    // loss all the same (`super::random_loss`).
    let common = path_factory(&config, &state, None, None);
    let transport = transport_config(&config, Arc::new(common));
    let server_config = tls::quic_server_config(certificate.clone(), transport)?;
    let endpoint_config = super::reset::endpoint_config(&identity);
    let endpoint = std::net::UdpSocket::bind(config.listen)
        .and_then(|socket| {
            let runtime = quinn::default_runtime()
                .ok_or_else(|| std::io::Error::other("no async runtime"))?;
            quinn::Endpoint::new(
                endpoint_config,
                Some(server_config.clone()),
                socket,
                runtime,
            )
        })
        .map_err(|source| ServeError::Bind {
            what: "QUIC",
            addr: config.listen,
            source,
        })?;
    let bind_err = |what, addr| move |source| ServeError::Bind { what, addr, source };
    let quic_addr = endpoint
        .local_addr()
        .map_err(bind_err("QUIC", config.listen))?;
    if !config.listen.ip().is_loopback() && config.default_access == super::config::Access::Public {
        tracing::warn!(
            listen = %config.listen,
            "scenes without a [scenes.NAME] entry are public and the service listens beyond loopback"
        );
    }

    let (trigger, shutdown) = shutdown::channel(config.shutdown_grace());
    let shared = Arc::new(
        Shared::new(config, pool.clone(), state.clone())
            .map_err(ServeError::Readers)?
            .with_server_config(server_config),
    );

    load_paths(&shared);
    let dispatcher = tokio::spawn(dispatch(shared.clone(), shutdown.clone()));
    state.set_ready(true);
    tracing::info!(
        quic = %quic_addr,
        fingerprint = %identity.fingerprint,
        db = %shared.config.db.display(),
        "serving"
    );
    let access = shared.access.clone();
    let task = tokio::spawn(supervise(shared, endpoint, shutdown.clone(), dispatcher));
    Ok(RunningService {
        quic_addr,
        access,
        certificate,
        fingerprint: identity.fingerprint,
        tls_origin: identity.origin,
        state,
        pool,
        trigger,
        shutdown,
        task,
    })
}

/// Hands every treelet the scheduler releases to its connection's task.
async fn dispatch(shared: Arc<Shared>, mut shutdown: Shutdown) {
    loop {
        tokio::select! {
            _ = shared.wake.notified() => {}
            _ = shutdown.recv() => return,
        }
        let now = std::time::Instant::now();
        let mut core = shared.core();
        let Core { sched, routes } = &mut *core;
        let mut batch = Vec::new();
        while let Some(c) = sched.poll_batch(now, &mut batch) {
            let routed = routes
                .get(&c)
                .is_some_and(|tx| tx.send(std::mem::take(&mut batch)).is_ok());
            if !routed {
                // The connection is ending: forget it, or its treelets would be offered forever.
                sched.remove_connection(c);
                routes.remove(&c);
            }
        }
    }
}

/// Completes a handshake only to close the connection with `code`.
async fn refuse(incoming: quinn::Incoming, code: ErrorCode, shared: Arc<Shared>) {
    let peer = incoming.remote_address();
    let Ok(connecting) = incoming.accept() else {
        return;
    };
    match tokio::time::timeout(shared.config.hello_timeout(), connecting).await {
        Ok(Ok(conn)) => {
            conn.close(
                quinn::VarInt::from_u32(code.to_u32()),
                code.name().as_bytes(),
            );
            shared.state.metrics.error(code);
            tracing::info!(%peer, %code, "connection refused");
        }
        Ok(Err(e)) => tracing::debug!(%peer, "refused connection's handshake failed: {e}"),
        Err(_) => tracing::debug!(%peer, "refused connection's handshake timed out"),
    }
}

fn spawn_refusal(
    incoming: quinn::Incoming,
    code: ErrorCode,
    shared: &Arc<Shared>,
    refusals: &Arc<Semaphore>,
) {
    shared
        .state
        .metrics
        .connections_rejected
        .fetch_add(1, Ordering::Relaxed);
    match refusals.clone().try_acquire_owned() {
        Ok(permit) => {
            let shared = shared.clone();
            tokio::spawn(async move {
                refuse(incoming, code, shared).await;
                drop(permit);
            });
        }
        Err(_) => incoming.refuse(),
    }
}

async fn supervise(
    shared: Arc<Shared>,
    endpoint: quinn::Endpoint,
    mut shutdown: Shutdown,
    dispatcher: JoinHandle<()>,
) {
    let permits = Arc::new(Semaphore::new(shared.config.max_connections));
    let refusals = Arc::new(Semaphore::new(MAX_REFUSALS));
    let (done_tx, mut done_rx) = shutdown::done_channel();
    let deadline = loop {
        tokio::select! {
            incoming = endpoint.accept() => {
                let Some(incoming) = incoming else {
                    tracing::error!("the QUIC endpoint stopped accepting");
                    break std::time::Instant::now();
                };
                match permits.clone().try_acquire_owned() {
                    Ok(permit) => {
                        let task = connection::run(
                            shared.clone(),
                            incoming,
                            shutdown.clone(),
                            done_tx.clone(),
                        );
                        tokio::spawn(async move {
                            task.await;
                            drop(permit);
                        });
                    }
                    Err(_) => spawn_refusal(incoming, ErrorCode::ServerBusy, &shared, &refusals),
                }
            }
            deadline = shutdown.recv() => break deadline,
        }
    };

    tracing::info!(
        grace_ms = shared.config.shutdown_grace_ms,
        connections = shared
            .state
            .metrics
            .connections_open
            .load(Ordering::Relaxed),
        "shutting down"
    );
    shared.state.begin_shutdown();
    shared.state.set_ready(false);
    // Keep answering newcomers, with ShuttingDown, while the connections drain.
    let refuser = {
        let endpoint = endpoint.clone();
        let shared = shared.clone();
        tokio::spawn(async move {
            while let Some(incoming) = endpoint.accept().await {
                spawn_refusal(incoming, ErrorCode::ShuttingDown, &shared, &refusals);
            }
        })
    };
    drop(done_tx);
    let bound = tokio::time::Instant::from_std(deadline) + CLOSE_FLUSH + Duration::from_millis(200);
    if tokio::time::timeout_at(bound, done_rx.recv())
        .await
        .is_err()
    {
        tracing::warn!("connections still open after the grace; closing them");
    }
    refuser.abort();
    endpoint.close(
        quinn::VarInt::from_u32(ErrorCode::ShuttingDown.to_u32()),
        ErrorCode::ShuttingDown.name().as_bytes(),
    );
    if tokio::time::timeout(WAIT_IDLE_BOUND, endpoint.wait_idle())
        .await
        .is_err()
    {
        tracing::debug!("endpoint not idle within {WAIT_IDLE_BOUND:?}");
    }
    dispatcher.abort();
    save_paths(&shared);
    if let Some(prewarm) = &shared.prewarm {
        prewarm.save_hot_pages();
    }
    tracing::info!("stopped");
}

/// Reads the path memory a previous run saved (`path_memory::PATHS_FILE`); a file that cannot
/// be read is logged, and the service starts without it.
fn load_paths(shared: &Shared) {
    if shared.config.path_memory().is_zero() {
        return;
    }
    let file = shared.config.data_dir().join(path_memory::PATHS_FILE);
    match shared.state.paths().load(&file, std::time::Instant::now()) {
        Ok(0) => {}
        Ok(n) => {
            tracing::info!(file = %file.display(), "remembering the paths of {n} client addresses")
        }
        Err(e) => tracing::warn!("path memory not loaded, starting without it: {e}"),
    }
}

/// Writes the path memory for the next run, once every connection has ended.
fn save_paths(shared: &Shared) {
    if shared.config.path_memory().is_zero() {
        return;
    }
    let file = shared.config.data_dir().join(path_memory::PATHS_FILE);
    match shared.state.paths().save(&file, std::time::Instant::now()) {
        Ok(n) => tracing::debug!(file = %file.display(), "saved the paths of {n} client addresses"),
        Err(e) => tracing::warn!("path memory not saved: {e}"),
    }
}
