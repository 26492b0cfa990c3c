//! The serving daemon: the QUIC treelet service ([`crate::service`]) and the admin HTTP API
//! ([`crate::admin`]) beside it, started together and stopped by one shutdown broadcast. The
//! daemon owns the pool: scenes are imported into it and removed while it serves
//! ([`crate::live_import`], driven by the admin API's `POST /v1/scenes`).
//!
//! The service knows nothing of the admin API; this module owns what joins them: the admin
//! bearer token (configured, read from a file, or generated once into the data dir), the admin
//! listener (HTTPS off loopback, `admin/https.rs`), and the order of shutdown (the service drains first, then the admin server gets at
//! most [`ADMIN_STOP_BOUND`]). [`Reloader`] puts a configuration read again (SIGHUP) in force
//! across both: the scene rules, the certificates of both listeners, the admin tokens.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use tokio::task::JoinHandle;

use crate::admin::{AdminContext, AdminCredentials, router_with_imports};
use crate::live_import::{ImportPriority, LiveImports};
use crate::pool::Pool;
use crate::service::certificate::{LiveCertificate, PresentedCertificate};
use crate::service::config::{AdminTokenSource, ConfigError, TlsSource};
use crate::service::shutdown::ShutdownTrigger;
use crate::service::state::ServiceState;
use crate::service::tls::{self, IdentityOrigin, read_pem};
use crate::service::{
    AccessHandle, AccessReload, RunningService, ServeConfig, ServeError, start_service,
};

/// File holding the generated admin token in the data dir.
pub const ADMIN_TOKEN_FILE: &str = "admin-token";
/// How long a stopping daemon waits for the admin server after the service stopped.
pub const ADMIN_STOP_BOUND: Duration = Duration::from_millis(300);

/// Where the admin token came from, for the operator.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum AdminTokenOrigin {
    /// `admin_token` in the configuration.
    Config,
    /// `admin_token_file`.
    File(PathBuf),
    /// Generated into the data dir now (`created`) or on an earlier start.
    Generated { path: PathBuf, created: bool },
}

/// A started daemon. Dropping it without [`RunningServer::shutdown`] leaves the tasks running
/// until the runtime ends.
#[derive(Debug)]
pub struct RunningServer {
    /// The bound QUIC (UDP) address.
    pub quic_addr: SocketAddr,
    /// The bound admin HTTP address; `None` when disabled.
    pub admin_addr: Option<SocketAddr>,
    /// Whether the admin listener speaks HTTPS.
    pub admin_https: bool,
    /// SHA-256 of the server certificate at start, lowercase hex: what clients pin (after a
    /// reload, `state.fingerprint()`).
    pub fingerprint: String,
    /// Bearer token of the admin API at start (a reload may replace it).
    pub admin_token: String,
    /// Where the admin token came from.
    pub admin_token_origin: AdminTokenOrigin,
    /// Where the TLS identity came from.
    pub tls_origin: IdentityOrigin,
    /// Metrics, sessions and readiness.
    pub state: Arc<ServiceState>,
    /// Scene management (imports, removals) of the pool being served.
    pub imports: LiveImports,
    reloader: Reloader,
    service: RunningService,
    admin: Option<JoinHandle<()>>,
}

impl RunningServer {
    /// The pool being served (read-only use).
    pub fn pool(&self) -> &Pool {
        self.service.pool()
    }

    /// A handle that starts graceful shutdown from elsewhere (e.g. a signal handler).
    pub fn shutdown_trigger(&self) -> ShutdownTrigger {
        self.service.shutdown_trigger()
    }

    /// What puts a configuration's scene rules, certificates and admin tokens in force while
    /// serving, also while the server is waited for: what `arbor-server serve` does on SIGHUP
    /// ([`Reloader::reload`]).
    pub fn reloader(&self) -> Reloader {
        self.reloader.clone()
    }

    /// Graceful shutdown, as on SIGTERM; returns when the daemon has stopped (within the grace
    /// plus 1.3 s).
    pub async fn shutdown(self) {
        self.service.shutdown_trigger().trigger();
        self.wait().await;
    }

    /// Waits until the daemon stops (after a trigger from [`RunningServer::shutdown_trigger`]).
    pub async fn wait(self) {
        self.service.wait().await;
        if let Some(admin) = self.admin {
            let abort = admin.abort_handle();
            if tokio::time::timeout(ADMIN_STOP_BOUND, admin).await.is_err() {
                abort.abort();
            }
        }
    }
}

/// What the daemon adds to the service's configuration: scene management.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct DaemonOptions {
    /// Directory under which `POST /v1/scenes` may read files; `None`: imports disabled.
    pub import_root: Option<PathBuf>,
    /// Where import scratch directories go (default: the system's temporary directory).
    pub import_scratch: Option<PathBuf>,
    /// How imports share the CPU with the service.
    pub import_priority: ImportPriority,
    /// Check every published scene this often (`None`: only the checks asked for through the
    /// admin API, unless `check_at` is set).
    pub check_every: Option<std::time::Duration>,
    /// Keep the checks of every scene to this UTC time of day (a day apart unless
    /// `check_every` says otherwise; [`crate::periodic`]).
    pub check_at: Option<crate::periodic::ClockTime>,
    /// Directory under which `POST /v1/copies` makes pool copies; `None`: copies disabled.
    pub copy_root: Option<PathBuf>,
    /// Bytes per second that checks and copies may read from the pool together (`None`: no
    /// limit; [`crate::pace`]). `PUT /v1/background-reads` changes it while serving.
    pub background_read_rate: Option<u64>,
    /// Copy every published scene under the copy root this often (`None`: only the copies
    /// asked for, unless `copy_at` is set); needs `copy_root`.
    pub copy_every: Option<std::time::Duration>,
    /// Keep the scheduled copies to this UTC time of day (a day apart unless `copy_every` says
    /// otherwise; [`crate::periodic`]); needs `copy_root`.
    pub copy_at: Option<crate::periodic::ClockTime>,
    /// Scheduled copies kept: after each one succeeds, older ones beyond this are removed
    /// (`None`: every one kept).
    pub copy_keep: Option<std::num::NonZeroUsize>,
}

/// Starts the daemon: the admin token, the treelet service, and (unless off) the admin listener
/// on the service's shutdown broadcast. Imports are disabled (see [`start_with`]).
pub async fn start(config: ServeConfig) -> Result<RunningServer, ServeError> {
    start_with(config, DaemonOptions::default()).await
}

/// [`start`], with scene management by the admin API ([`crate::live_import`]).
pub async fn start_with(
    config: ServeConfig,
    options: DaemonOptions,
) -> Result<RunningServer, ServeError> {
    for (key, root) in [
        ("--import-root", &options.import_root),
        ("--copy-root", &options.copy_root),
    ] {
        if let Some(root) = root
            && let Err(source) = std::fs::read_dir(root)
        {
            return Err(ServeError::Config(ConfigError::Read {
                key: key.into(),
                path: root.clone(),
                source,
            }));
        }
    }
    let admin_listen = config.admin_listen;
    let (admin_tls, admin_identity) = (config.admin_tls, config.admin_identity.clone());
    let probe_token = config.probe_token.clone();
    let token = config.admin_token.clone();
    let data_dir = config.data_dir().to_path_buf();
    let service = start_service(config).await?;
    let (admin_token, admin_token_origin) = match admin_token(&token, &data_dir) {
        Ok(t) => t,
        Err(e) => {
            service.shutdown().await;
            return Err(e);
        }
    };
    let imports = match LiveImports::new(
        service.pool().clone(),
        service.state.clone(),
        &options,
        &data_dir,
    ) {
        Ok(i) => i,
        Err(e) => {
            service.shutdown().await;
            return Err(e.into());
        }
    };
    let admin_https = admin_listen.is_some_and(|a| admin_tls.encrypts(a));
    let admin_certificate = if admin_https {
        match admin_certificate(&admin_identity, &service.certificate()) {
            Ok(c) => Some(c),
            Err(e) => {
                service.shutdown().await;
                return Err(e);
            }
        }
    } else {
        None
    };
    let https = match admin_certificate
        .clone()
        .map(crate::admin::https::rustls_config)
    {
        None => None,
        Some(Ok(c)) => Some(Arc::new(c)),
        Some(Err(e)) => {
            service.shutdown().await;
            return Err(e.into());
        }
    };
    if let Some(c) = &admin_certificate {
        service.state.present_certificate("admin", c.clone());
    }
    let credentials = AdminCredentials::new(&admin_token, probe_token.as_deref());
    let (admin, admin_addr) = match admin_listen {
        None => (None, None),
        Some(addr) => {
            let bound = async {
                let listener = tokio::net::TcpListener::bind(addr).await?;
                let local = listener.local_addr()?;
                Ok::<_, std::io::Error>((listener, local))
            }
            .await;
            let (listener, local) = match bound {
                Ok(b) => b,
                Err(source) => {
                    service.shutdown().await;
                    return Err(ServeError::Bind {
                        what: "admin",
                        addr,
                        source,
                    });
                }
            };
            let app = router_with_imports(
                AdminContext {
                    state: service.state.clone(),
                    pool: service.pool().clone(),
                    credentials: credentials.clone(),
                },
                Some(imports.clone()),
            );
            if !admin_https && !local.ip().is_loopback() {
                tracing::warn!(admin = %local, "admin API in cleartext off loopback (admin_tls = \"off\"): the token crosses the network unencrypted");
            }
            let mut stop = service.shutdown_signal();
            let task = tokio::spawn(async move {
                let stop = async move {
                    stop.recv().await;
                };
                if let Err(e) = crate::admin::https::serve(listener, https, app, stop).await {
                    tracing::error!("admin API failed: {e}");
                }
            });
            (Some(task), Some(local))
        }
    };
    let scheme = if admin_https { "https" } else { "http" };
    tracing::info!(admin = ?admin_addr, scheme, "admin API");
    let reloader = Reloader {
        access: service.access_handle(),
        quic: service.certificate(),
        admin: admin_certificate,
        credentials: admin_addr.map(|_| credentials),
        state: service.state.clone(),
        data_dir,
    };
    Ok(RunningServer {
        quic_addr: service.quic_addr,
        reloader,
        admin_addr,
        admin_https,
        fingerprint: service.fingerprint.clone(),
        admin_token,
        admin_token_origin,
        tls_origin: service.tls_origin.clone(),
        state: service.state.clone(),
        imports,
        service,
        admin,
    })
}

/// The admin listener's certificate: its own PEM pair when configured, else the one the
/// service presents (a listener of its own, renewed with it on reload).
fn admin_certificate(
    admin_identity: &TlsSource,
    service: &LiveCertificate,
) -> Result<Arc<LiveCertificate>, ServeError> {
    Ok(Arc::new(LiveCertificate::new(match admin_identity {
        TlsSource::Files { cert, key } => {
            Arc::new(PresentedCertificate::of(&read_pem(cert, key)?)?)
        }
        TlsSource::SelfSigned => service.current(),
    })))
}

fn read_token(path: &Path) -> Result<String, ServeError> {
    let err = |reason: String| ServeError::AdminToken {
        path: path.to_owned(),
        reason,
    };
    let t = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
    let t = t.trim();
    if t.is_empty() {
        return Err(err("empty".into()));
    }
    Ok(t.to_owned())
}

fn admin_token(
    source: &AdminTokenSource,
    data_dir: &Path,
) -> Result<(String, AdminTokenOrigin), ServeError> {
    let path = data_dir.join(ADMIN_TOKEN_FILE);
    let origin = match source {
        AdminTokenSource::Inline(_) => AdminTokenOrigin::Config,
        AdminTokenSource::File(p) => AdminTokenOrigin::File(p.clone()),
        AdminTokenSource::Generated if path.exists() => AdminTokenOrigin::Generated {
            path,
            created: false,
        },
        AdminTokenSource::Generated => {
            let err = |reason: String| ServeError::AdminToken {
                path: path.clone(),
                reason,
            };
            let mut bytes = [0u8; 32];
            ring::rand::SecureRandom::fill(&ring::rand::SystemRandom::new(), &mut bytes)
                .map_err(|_| err("the system random generator failed".into()))?;
            let token: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
            std::fs::create_dir_all(data_dir).map_err(|e| err(e.to_string()))?;
            use std::io::Write as _;
            use std::os::unix::fs::OpenOptionsExt as _;
            let mut f = std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .mode(0o600)
                .open(&path)
                .map_err(|e| err(e.to_string()))?;
            f.write_all(format!("{token}\n").as_bytes())
                .and_then(|()| f.sync_all())
                .map_err(|e| err(e.to_string()))?;
            return Ok((
                token,
                AdminTokenOrigin::Generated {
                    path,
                    created: true,
                },
            ));
        }
    };
    Ok((existing_admin_token(source, data_dir)?, origin))
}

/// Puts what a configuration says of who may connect and what they are shown in force while
/// the daemon serves ([`RunningServer::reloader`]; SIGHUP in `arbor-server serve`):
///
/// * the scene rules and scene tokens (`[scenes.NAME]`, `default_access`, the token files
///   read): [`AccessHandle::reload`], which closes the sessions they no longer admit;
/// * the TLS certificate and key (`cert`/`key`, or the self-signed pair in the data dir, read
///   again, never created) and the admin listener's (`admin_cert`/`admin_key`, else the same):
///   presented from the next handshake on, every open session going on
///   ([`crate::service::certificate`]);
/// * the admin and probe tokens (`admin_token`, `admin_token_file`, the generated file,
///   `probe_token`): required from the next request on.
///
/// Everything is read first and put in force only when all of it loaded: a file that does not
/// load (or a key that is not its certificate's) changes nothing. Either way the reload is
/// counted in `/metrics` (`arbor_config_reloads_total`, `arbor_config_last_reload_successful`).
/// The data dir is the one the daemon started with; the other settings apply at the next start.
#[derive(Clone, Debug)]
pub struct Reloader {
    access: AccessHandle,
    quic: Arc<LiveCertificate>,
    /// The admin listener's certificate, when it speaks HTTPS.
    admin: Option<Arc<LiveCertificate>>,
    /// The admin API's tokens, when it listens.
    credentials: Option<Arc<AdminCredentials>>,
    state: Arc<ServiceState>,
    data_dir: PathBuf,
}

/// What a reload put in force ([`Reloader::reload`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Reloaded {
    /// Sessions closed and kept by the scene rules.
    pub sessions: AccessReload,
    /// The fingerprint QUIC clients are shown from now on.
    pub fingerprint: String,
    /// Whether the QUIC certificate changed.
    pub certificate_changed: bool,
    /// Whether the admin listener's certificate changed (false without HTTPS).
    pub admin_certificate_changed: bool,
    /// Whether the admin token changed (false without an admin listener).
    pub admin_token_changed: bool,
}

impl Reloader {
    /// Reads `config`'s certificates and tokens and puts them and its scene rules in force, or
    /// changes nothing and says what did not load.
    pub fn reload(&self, config: &ServeConfig) -> Result<Reloaded, ServeError> {
        let outcome = self.load(config).map(|loaded| self.apply(config, loaded));
        self.state.record_reload(outcome.is_ok());
        outcome
    }

    /// Counts a reload whose configuration file did not load (nothing changed).
    pub fn record_unloadable(&self) {
        self.state.record_reload(false);
    }

    /// What a reload reads; `config_watch::named_files` names the same files, keep them in step.
    fn load(&self, config: &ServeConfig) -> Result<Loaded, ServeError> {
        let quic = Arc::new(PresentedCertificate::of(&tls::load_existing(
            &config.tls,
            &self.data_dir,
        )?)?);
        let admin = match (&self.admin, &config.admin_identity) {
            (None, _) => None,
            (Some(_), TlsSource::Files { cert, key }) => {
                Some(Arc::new(PresentedCertificate::of(&read_pem(cert, key)?)?))
            }
            (Some(_), TlsSource::SelfSigned) => Some(quic.clone()),
        };
        let tokens = match &self.credentials {
            None => None,
            Some(_) => Some((
                existing_admin_token(&config.admin_token, &self.data_dir)?,
                config.probe_token.clone(),
            )),
        };
        Ok(Loaded {
            quic,
            admin,
            tokens,
        })
    }

    fn apply(&self, config: &ServeConfig, loaded: Loaded) -> Reloaded {
        let sessions = self.access.reload(config);
        let fingerprint = loaded.quic.fingerprint.clone();
        let certificate_changed = self.quic.replace(loaded.quic);
        let admin_certificate_changed = match (&self.admin, loaded.admin) {
            (Some(live), Some(next)) => live.replace(next),
            _ => false,
        };
        let admin_token_changed = match (&self.credentials, &loaded.tokens) {
            (Some(c), Some((admin, probe))) => c.replace(admin, probe.as_deref()),
            _ => false,
        };
        Reloaded {
            sessions,
            fingerprint,
            certificate_changed,
            admin_certificate_changed,
            admin_token_changed,
        }
    }
}

/// What a reload read, before any of it is put in force.
struct Loaded {
    quic: Arc<PresentedCertificate>,
    admin: Option<Arc<PresentedCertificate>>,
    tokens: Option<(String, Option<String>)>,
}

/// The admin token as [`admin_token`] finds it, but never generated: a reload reads the
/// generated file, and a missing one is an error rather than a new token.
fn existing_admin_token(source: &AdminTokenSource, data_dir: &Path) -> Result<String, ServeError> {
    match source {
        AdminTokenSource::Inline(t) => Ok(t.trim().to_owned()),
        AdminTokenSource::File(p) => read_token(p),
        AdminTokenSource::Generated => read_token(&data_dir.join(ADMIN_TOKEN_FILE)),
    }
}
