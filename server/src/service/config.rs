//! `arbor-server serve` configuration: a TOML file (every key optional) with CLI overrides.
//!
//! ```toml
//! db = "/var/lib/arbor/pool"            # pool directory (CLI --db)
//! data_dir = "/var/lib/arbor/state"     # cert.pem + key.pem + admin-token live here; default: db (CLI --data-dir)
//! listen = "0.0.0.0:4433"               # QUIC, UDP (CLI --listen); default 127.0.0.1:4433
//! admin_listen = "127.0.0.1:9090"       # admin HTTP (CLI --admin); "off" disables
//! admin_tls = "auto"                    # HTTPS unless admin_listen is loopback; "on" always; "off" cleartext (CLI --admin-tls)
//! admin_cert = "/etc/arbor/tls/admin.pem" # optional PEM chain + key for the admin HTTPS listener; default: the daemon's certificate
//! admin_key = "/etc/arbor/tls/admin-key.pem"
//! admin_token_file = "/etc/arbor/admin-token"   # or admin_token = "..."; neither: generated into <data_dir>/admin-token
//! cert = "/etc/arbor/tls/fullchain.pem" # optional PEM chain + key instead of the self-signed pair
//! key = "/etc/arbor/tls/key.pem"
//! max_connections = 256
//! idle_timeout_ms = 30000
//! hello_timeout_ms = 5000
//! max_connection_memory = 67108864
//! initial_window = 131072             # QUIC congestion window at the start, bytes
//! path_memory_secs = 600              # a returning client's address resumes its last window for this long; 0: off
//! config_watch_secs = 0               # reload when this file or the files it names change, checked this often; 0: on SIGHUP only
//! random_loss_tolerance = true        # a loss with no queue behind it cuts the window one time in eight; false: every time
//! pool_cache_bytes = 134217728        # pool pages sled keeps decoded, server-wide
//! pool_readers = 8                    # threads reading treelets from the pool, so a disk read never holds an async worker
//! pool_prewarm = "auto"              # read the pool's files into the page cache at start, the last run's cached pages first: "auto" (all if they fit in half the memory left, else only those pages), "always", "off" (CLI --pool-prewarm)
//! message_cache_bytes = 67108864      # built treelet messages kept for sending again, server-wide
//! shape_cache_bytes = 33554432        # decoded treelet shapes the push plans walk, server-wide
//! visibility_grid = 128               # rays along a resting view's longer side for the visible cut its pushes follow; 0: off
//! visibility_fine_grid = 512          # a second, finer cut of the same view once the first is out; 0: none
//! visibility_cache_bytes = 33554432   # node records per scene the visible cuts are cast through
//! visibility_node_cache_bytes = 67108864 # decoded node records kept between cuts, server-wide
//! visibility_follow_share = 0.5       # a cut is followed only if it holds at most this share of the frustum plan; 1: always
//! window_min = 8
//! window_max = 1024
//! slow_reader_timeout_ms = 10000
//! shutdown_grace_ms = 5000
//! transparent_huge_pages = false        # let the allocator ask for them (the kernel may stall to compact memory)
//! default_access = "token"              # scenes without a [scenes.NAME] entry: "token" or "public"
//!
//! [scenes.bunny]
//! tokens = ["change-me"]                # or token_files = ["/etc/arbor/bunny.token"]
//! [scenes.lion]
//! access = "public"
//! ```
//!
//! Without a config file `default_access` is `public` (a development setup; a warning is logged
//! when `listen` is not a loopback address). With a file it defaults to `token`, so a scene
//! nobody configured cannot be opened at all.
//!
//! Parsing rejects unknown keys and names the offending key in every error; [`ServeConfig::validate`]
//! checks the values. Access tokens are compared in constant time (an HMAC under a per-process
//! random key, verified with `ring::hmac::verify`), so response time does not reveal how much of
//! a guessed token was right.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use arbor_proto::limits::{MAX_FRAME_BYTES, MAX_REQUEST_ITEMS, MAX_TOKEN_BYTES};
use arbor_proto::scene::validate_scene_name;
use serde::Deserialize;

pub use super::prewarm::PoolPrewarm;

/// Default QUIC listen address.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:4433";
/// Default admin listen address.
pub const DEFAULT_ADMIN_LISTEN: &str = "127.0.0.1:9090";
/// Smallest accepted `max_connection_memory`: one maximal control frame in the decoder, a
/// maximal request list in the scheduler, the deliveries it remembers, and room for receive
/// and send buffers.
pub const MIN_CONNECTION_MEMORY: u64 = 8 << 20;
/// Fewest deliveries a connection's redelivery record keeps, whatever its memory bound
/// ([`ServeConfig::memory_plan`]).
const MIN_RECENT_DELIVERIES: usize = 1024;

/// What is wrong with a configuration. Every variant names the key it is about.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The config file (or a file it names) could not be read.
    #[error("`{key}`: cannot read {}: {source}", path.display())]
    Read {
        key: String,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The config file is not valid TOML, has an unknown key, or a value of the wrong type.
    #[error("{}: key `{key}`: {message}", path.display())]
    Parse {
        path: PathBuf,
        /// Dotted key the error is about (`scenes.bunny.tokens`), or `?` when the parser could
        /// not place it.
        key: String,
        message: String,
    },
    /// A value is out of range or contradicts another.
    #[error("key `{key}`: {reason}")]
    Invalid { key: String, reason: String },
}

fn invalid(key: impl Into<String>, reason: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key: key.into(),
        reason: reason.into(),
    }
}

/// Who may open a scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Access {
    /// Anyone; the token in `Hello` is ignored.
    Public,
    /// Only with one of the scene's tokens.
    Token,
}

/// Access rule of one scene, tokens resolved (token files read).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SceneAccess {
    Public,
    /// Any of these tokens opens the scene.
    Tokens(Vec<String>),
}

/// Where the admin bearer token comes from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum AdminTokenSource {
    /// `admin_token` in the config (or set by a program).
    Inline(String),
    /// `admin_token_file`: read at start and on reload, surrounding whitespace trimmed.
    File(PathBuf),
    /// Neither: generated into `<data_dir>/admin-token` (mode 0600) on first start, reused after.
    Generated,
}

/// Whether the admin listener speaks HTTPS (`admin_tls`, CLI `--admin-tls`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum AdminTls {
    /// HTTPS unless the admin address is a loopback address.
    #[default]
    Auto,
    /// HTTPS on any address.
    On,
    /// Cleartext HTTP on any address (a warning is logged off loopback).
    Off,
}

/// TLS identity source.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TlsSource {
    /// A self-signed pair created in the data dir on first start and reused after.
    SelfSigned,
    /// A PEM certificate chain and its private key.
    Files { cert: PathBuf, key: PathBuf },
}

/// The complete, validated configuration of `arbor-server serve`.
#[derive(Clone, Debug, PartialEq)]
pub struct ServeConfig {
    /// Pool directory.
    pub db: PathBuf,
    /// Where the self-signed pair and the generated admin token are kept; `None`: `db`.
    pub data_dir: Option<PathBuf>,
    /// QUIC (UDP) listen address.
    pub listen: SocketAddr,
    /// Admin HTTP listen address; `None`: no admin API.
    pub admin_listen: Option<SocketAddr>,
    pub admin_token: AdminTokenSource,
    /// HTTPS or cleartext on the admin listener.
    pub admin_tls: AdminTls,
    /// The admin listener's certificate when it differs from the daemon's (`admin_cert`,
    /// `admin_key`); `SelfSigned`: the daemon's identity, whatever `tls` is.
    pub admin_identity: TlsSource,
    /// A low-privilege token that opens only the admin API's `/readyz` (for orchestrator
    /// readiness probes, which cannot read secrets); `None`: `/readyz` needs the admin token.
    pub probe_token: Option<String>,
    pub tls: TlsSource,
    /// Connections served at once; more are refused with `ServerBusy`.
    pub max_connections: usize,
    pub idle_timeout_ms: u64,
    /// Time a client has from the start of the handshake to a complete `Hello`.
    pub hello_timeout_ms: u64,
    /// Per-connection memory bound in bytes (see [`ServeConfig::memory_plan`]).
    pub max_connection_memory: u64,
    /// QUIC congestion window a connection starts with, bytes. quinn's default (~14.7 KB, ten
    /// packets) needs eight slow-start round trips to carry a 3 MB view; a larger start is how
    /// content servers fill a fresh connection sooner.
    pub initial_window: u64,
    /// Whether `arbor-server serve` lets its allocator ask for transparent huge pages. Off by
    /// default: where the kernel compacts memory on demand for them (`defrag = madvise`, a
    /// common default), a fresh server's first views stalled on it at random — on the
    /// 10⁸-point city, first views took 0.89–1.53 s to converge with them and 0.88–1.02 s
    /// without (docs/measurements.md, stop 49).
    pub transparent_huge_pages: bool,
    /// How long a client address's last congestion window and RTT are remembered, seconds, so
    /// its next connection resumes at half that window once its first RTT confirms the same
    /// path (`service::path_memory`, careful resume); 0 turns it off.
    pub path_memory_secs: u64,
    /// Whether a loss that finds no queue on the path (round trips near the smallest) is taken
    /// for random loss, which cuts the congestion window only one time in
    /// [`super::random_loss::PASS_EVERY`] (`service::random_loss`). On: over a 10 Mbit/s,
    /// 80 ms link with 1 % loss, Cubic alone held a connection near 1.4 Mbit/s. Paths under
    /// [`super::random_loss::SHORT_PATH`] never take a loss for random. Off: every loss cuts the
    /// window, as plain Cubic does.
    pub random_loss_tolerance: bool,
    /// Bytes of the pool's pages sled keeps decoded ([`crate::pool::Pool::open_with_cache`];
    /// at least [`MIN_POOL_CACHE_BYTES`]). A treelet whose message is not in the message cache
    /// is read from the pool; a read whose page is not in this cache decodes the page from the
    /// file again. Size it to the machine for scans many times the message cache: on the
    /// 10⁸-point city (1.4 GB of pool) building a message on a miss took 2.2–3.5 µs per treelet
    /// with the default and 0.95–1.2 µs with 1 GiB (docs/measurements.md, stop 59).
    pub pool_cache_bytes: u64,
    /// Threads that read treelet messages from the pool for the streams (`service::readers`),
    /// so that a read waiting for the disk (a pool larger than the page cache) holds one of
    /// them, not an async worker; as many reads as this are in flight at once. More suits a
    /// disk with a deep queue (NVMe) and costs each thread's allocator heap; with the pool
    /// cached they only wait for the CPU.
    pub pool_readers: usize,
    /// Whether the pool's files are read into the page cache at start, front to back in large
    /// reads, so that a fresh server's treelet reads need not wait for a disk that limits its
    /// reads per second (`service::prewarm`); the pages the last run had cached
    /// (`service::hot_pages`, saved in the data directory) first. `auto` reads the whole pool
    /// when it fits in half of the memory the process may still use, else only those pages.
    pub pool_prewarm: PoolPrewarm,
    /// Bytes of built treelet messages kept server-wide, so a treelet sent again costs no pool
    /// read (0: none kept).
    pub message_cache_bytes: u64,
    /// Bytes of decoded treelet shapes (root voxel and refinable leaves) kept server-wide for
    /// the deep-request push plans, so a plan walks its tree without a pool read and a
    /// decompression per treelet (0: none kept, every lookup decodes). A shape's size follows
    /// its child treelets: about 1.3 KB with 64 of them, so the default holds some 25,000 of
    /// a city-scale scene's, far more than a few plans' walks touch.
    pub shape_cache_bytes: u64,
    /// Rays along the longer side of a resting deep-request view that the server casts through
    /// its own tree to find the view's visible cut, whose treelets it then pushes
    /// (`service::visibility`); 0 turns it off: pushes follow frustum and projected size alone.
    /// A resting list that leaves a cut nothing to decide (no free slots beyond its items, no
    /// prefetch: `push::cut_has_work`) gets none. Default [`DEFAULT_VISIBILITY_GRID`].
    /// Measured in docs/measurements.md (stops 27, 45 and 47): engine's static view over the
    /// link emulator converges at 1.8× the physical limit with cuts and 2.6× without; its
    /// camera jump, with the client's prefetch set apart (`push::cut_list`), at 1.6× the
    /// jump's limit.
    pub visibility_grid: u32,
    /// Rays along the longer side of a second cut of the same view, cast once the first one's
    /// pushes are out, for what the coarse grid's rays missed (cast from the coarse cut:
    /// `visibility::CutCaster::cut_from`); 0: none, else above `visibility_grid`. Default
    /// [`DEFAULT_VISIBILITY_FINE_GRID`]. Neither grid exceeds a client's own frame (the rays
    /// its hint implies, `visibility::frame_rays`). A scene whose fine cuts keep going unused
    /// casts only a few of them (`visibility::FineCutGate`).
    pub visibility_fine_grid: u32,
    /// Bytes of node records per served scene that visible cuts are cast through (allocated by
    /// a scene's first cut).
    pub visibility_cache_bytes: u64,
    /// Bytes of decoded node records kept server-wide between visible cuts
    /// (`visibility::NodeCache`), so that a cut reads from the pool and decodes only what no
    /// recent cut read (0: none kept). About 4.2 KB a treelet of 512 nodes. The default is
    /// twice `visibility_cache_bytes`: what one cut's buffer holds, read again, fits in the
    /// young generation while the old one keeps the cut before it (on the 10⁸-point city, 32
    /// MiB turned over within one fine cut and saved little; 64 and 128 MiB about the same,
    /// docs/measurements.md, stop 48).
    pub visibility_node_cache_bytes: u64,
    /// A view's visible cut is followed only when it holds at most this share of the treelets
    /// the frustum plan would push for the same view (`push::cut_saves`): a view that sees most
    /// of its frustum keeps the frustum plan, which also prefetches for the next view, and is
    /// not cast again at the fine grid. In (0, 1]; 1 follows every cut. Measured in
    /// docs/measurements.md (stop 30): lion's views hold 0.75–0.88 of their frustum plan,
    /// the engine's 0.16–0.26.
    pub visibility_follow_share: f64,
    /// Bounds of the per-connection in-flight window (treelets).
    pub window_min: usize,
    pub window_max: usize,
    /// A connection with treelets in flight and no progress on any of them for this long is
    /// closed with `SlowReader`.
    pub slow_reader_timeout_ms: u64,
    /// How long shutdown lets in-flight treelet streams finish.
    pub shutdown_grace_ms: u64,
    /// How often `arbor-server serve` looks at its configuration file and the files it names
    /// (token files, certificates and keys, the admin token) and reloads when they changed, as
    /// SIGHUP would ([`crate::config_watch`]), seconds; 0 (the default): only on SIGHUP.
    pub config_watch_secs: u64,
    /// Rule for scenes without an entry in `scenes`.
    pub default_access: Access,
    /// Per-scene rules.
    pub scenes: BTreeMap<String, SceneAccess>,
}

/// Values given on the command line; each replaces the file's value.
#[derive(Clone, Debug, Default)]
pub struct ConfigOverrides {
    pub db: Option<PathBuf>,
    pub listen: Option<SocketAddr>,
    /// `Some(None)`: `--admin off`.
    pub admin_listen: Option<Option<SocketAddr>>,
    pub admin_tls: Option<AdminTls>,
    pub data_dir: Option<PathBuf>,
    pub pool_prewarm: Option<PoolPrewarm>,
}

/// How [`ServeConfig::max_connection_memory`] is divided (bytes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryPlan {
    /// Control-frame decoder buffer: one maximal client frame (fixed by the protocol).
    pub decoder: u64,
    /// Scheduler state for the longest request list (fixed by the protocol).
    pub request_list: u64,
    /// The deliveries a connection remembers once it sends deep lists with visible cuts on
    /// (`schedule::DELIVERIES_REMEMBERED`).
    pub deliveries: u64,
    /// Most deliveries the scheduler's redelivery record keeps
    /// (`schedule::ConnectionConfig::recent_deliveries`).
    pub recent_deliveries: usize,
    /// That record and its index at most (`schedule::recent_record_bytes`).
    pub redelivery_record: u64,
    /// QUIC connection- and stream-level receive window (what the client may send unread).
    pub receive_window: u64,
    /// QUIC send window: unacknowledged treelet bytes buffered for this connection.
    pub send_window: u64,
}

/// The most memory the service's own bounds let it hold, by part (bytes): what a replica's
/// memory limit must cover, with the runtime, the allocator's slack and the admin API on top
/// (deploy/README.md, *Memory*). Logged when the service starts; `/metrics` reports it as
/// `arbor_memory_bound_bytes` for the scenes the pool holds at the scrape.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryBound {
    /// sled's page cache (`pool_cache_bytes`) and the buffer its log is written from (one
    /// segment, [`crate::pool::POOL_SEGMENT_BYTES`]).
    pub pool_cache: u64,
    /// `max_connections` × `max_connection_memory`.
    pub connections: u64,
    /// Built treelet messages (`message_cache_bytes`).
    pub message_cache: u64,
    /// Decoded treelet shapes (`shape_cache_bytes`).
    pub shape_cache: u64,
    /// Decoded node records of the visible cuts (`visibility_node_cache_bytes`; 0 with cuts
    /// off).
    pub cut_node_cache: u64,
    /// One scene's visible-cut buffers: at most
    /// [`MAX_CUTS_RUNNING`](super::treelets::MAX_CUTS_RUNNING) cast at once, each of
    /// `visibility_cache_bytes` (0 with cuts off).
    pub cut_buffers_per_scene: u64,
    /// Scenes that may be served at once: every scene of the pool.
    pub scenes: u64,
}

impl MemoryBound {
    /// Every scene's visible-cut buffers.
    pub fn cut_buffers(&self) -> u64 {
        self.cut_buffers_per_scene.saturating_mul(self.scenes)
    }

    /// The same bound for a pool of `scenes` scenes (a live import adds some).
    pub fn with_scenes(self, scenes: usize) -> MemoryBound {
        MemoryBound {
            scenes: scenes as u64,
            ..self
        }
    }

    /// The parts by name, as `/metrics` labels them.
    pub fn parts(&self) -> [(&'static str, u64); 6] {
        [
            ("pool_cache", self.pool_cache),
            ("connections", self.connections),
            ("message_cache", self.message_cache),
            ("shape_cache", self.shape_cache),
            ("cut_node_cache", self.cut_node_cache),
            ("cut_buffers", self.cut_buffers()),
        ]
    }

    /// All parts together.
    pub fn total(&self) -> u64 {
        self.parts()
            .iter()
            .fold(0u64, |sum, &(_, b)| sum.saturating_add(b))
    }
}

/// Default [`ServeConfig::initial_window`]: 128 KiB.
pub const DEFAULT_INITIAL_WINDOW: u64 = 128 << 10;
/// Smallest accepted [`ServeConfig::pool_cache_bytes`]: 1 MiB, a few dozen of sled's pages.
pub const MIN_POOL_CACHE_BYTES: u64 = 1 << 20;
/// Default [`ServeConfig::pool_readers`]: with the city's pool outside the page cache, 8
/// readers served its soak as fast as a cached pool, 16 no faster for 50 MB more resident
/// (docs/measurements.md, stop 66).
pub const DEFAULT_POOL_READERS: usize = 8;
/// Most [`ServeConfig::pool_readers`].
pub const MAX_POOL_READERS: usize = 256;
/// Default [`ServeConfig::message_cache_bytes`]: 64 MiB.
pub const DEFAULT_MESSAGE_CACHE_BYTES: u64 = 64 << 20;
/// Default [`ServeConfig::shape_cache_bytes`]: 32 MiB.
pub const DEFAULT_SHAPE_CACHE_BYTES: u64 = 32 << 20;
/// Largest accepted [`ServeConfig::visibility_grid`] and [`ServeConfig::visibility_fine_grid`]
/// (a 1024×1024 cast takes about half a second of CPU per view).
pub const MAX_VISIBILITY_GRID: u32 = 1024;
/// Default [`ServeConfig::visibility_grid`].
pub const DEFAULT_VISIBILITY_GRID: u32 = 128;
/// Default [`ServeConfig::visibility_fine_grid`]: a 512² client frame's own rays.
pub const DEFAULT_VISIBILITY_FINE_GRID: u32 = 512;
/// Default [`ServeConfig::visibility_follow_share`]: a cut must save at least half.
pub const DEFAULT_VISIBILITY_FOLLOW_SHARE: f64 = 0.5;
/// Default [`ServeConfig::visibility_cache_bytes`]: 32 MiB.
pub const DEFAULT_VISIBILITY_CACHE_BYTES: u64 = 32 << 20;
/// Default [`ServeConfig::visibility_node_cache_bytes`]: 64 MiB, twice
/// [`DEFAULT_VISIBILITY_CACHE_BYTES`].
pub const DEFAULT_VISIBILITY_NODE_CACHE_BYTES: u64 = 2 * DEFAULT_VISIBILITY_CACHE_BYTES;
/// Smallest accepted [`ServeConfig::visibility_cache_bytes`]: room for the largest treelets'
/// top levels.
pub const MIN_VISIBILITY_CACHE_BYTES: u64 = 1 << 20;
/// Default [`ServeConfig::path_memory_secs`]: ten minutes.
pub const DEFAULT_PATH_MEMORY_SECS: u64 = 600;
/// Largest accepted [`ServeConfig::path_memory_secs`]: a day (paths change).
pub const MAX_PATH_MEMORY_SECS: u64 = 86_400;
/// Largest accepted [`ServeConfig::config_watch_secs`]: a day.
pub const MAX_CONFIG_WATCH_SECS: u64 = 86_400;
/// Smallest accepted initial window (two full-size packets).
pub const MIN_INITIAL_WINDOW: u64 = 2400;
/// Largest accepted initial window.
pub const MAX_INITIAL_WINDOW: u64 = 16 << 20;

/// Parses `off` or a socket address.
pub fn parse_admin_listen(s: &str) -> Result<Option<SocketAddr>, String> {
    if s.eq_ignore_ascii_case("off") {
        return Ok(None);
    }
    s.parse()
        .map(Some)
        .map_err(|_| format!("'{s}' is neither an address like 127.0.0.1:9090 nor \"off\""))
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileConfig {
    db: Option<PathBuf>,
    data_dir: Option<PathBuf>,
    listen: Option<SocketAddr>,
    admin_listen: Option<String>,
    admin_token: Option<String>,
    admin_token_file: Option<PathBuf>,
    admin_tls: Option<AdminTls>,
    admin_cert: Option<PathBuf>,
    admin_key: Option<PathBuf>,
    probe_token: Option<String>,
    cert: Option<PathBuf>,
    key: Option<PathBuf>,
    max_connections: Option<usize>,
    idle_timeout_ms: Option<u64>,
    hello_timeout_ms: Option<u64>,
    max_connection_memory: Option<u64>,
    initial_window: Option<u64>,
    path_memory_secs: Option<u64>,
    random_loss_tolerance: Option<bool>,
    transparent_huge_pages: Option<bool>,
    pool_cache_bytes: Option<u64>,
    pool_readers: Option<usize>,
    pool_prewarm: Option<PoolPrewarm>,
    message_cache_bytes: Option<u64>,
    shape_cache_bytes: Option<u64>,
    visibility_grid: Option<u32>,
    visibility_fine_grid: Option<u32>,
    visibility_cache_bytes: Option<u64>,
    visibility_node_cache_bytes: Option<u64>,
    visibility_follow_share: Option<f64>,
    window_min: Option<usize>,
    window_max: Option<usize>,
    slow_reader_timeout_ms: Option<u64>,
    shutdown_grace_ms: Option<u64>,
    config_watch_secs: Option<u64>,
    default_access: Option<Access>,
    #[serde(default)]
    scenes: BTreeMap<String, SceneFile>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    access: Option<Access>,
    tokens: Option<Vec<String>>,
    token_files: Option<Vec<PathBuf>>,
}

/// The dotted key whose line holds byte `offset` of `src` (the parser's error span), for
/// messages: the text before `=` on that line (or the nearest line above with one, for values
/// spanning lines), prefixed by the table header above it.
fn key_at(src: &str, offset: usize) -> Option<String> {
    let offset = offset.min(src.len());
    let upto = src.get(..offset)?;
    let line_start = upto.rfind('\n').map_or(0, |i| i + 1);
    let mut lines_above: Vec<&str> = src[..line_start].lines().collect();
    let this_line = src[line_start..].lines().next().unwrap_or("");
    let clean = |k: &str| {
        k.trim()
            .split('.')
            .map(|p| p.trim().trim_matches('"').trim_matches('\''))
            .collect::<Vec<_>>()
            .join(".")
    };
    let header = |l: &str| {
        let t = l.trim();
        (t.starts_with('[') && !t.contains('='))
            .then(|| clean(t.trim_start_matches('[').trim_end_matches(']')))
    };
    if let Some(h) = header(this_line) {
        return Some(h);
    }
    let mut key = this_line.split_once('=').map(|(k, _)| clean(k));
    while key.is_none() {
        let l = lines_above.pop()?;
        if header(l).is_some() {
            lines_above.push(l);
            break;
        }
        key = l.split_once('=').map(|(k, _)| clean(k));
    }
    let key = key?;
    let table = lines_above.iter().rev().find_map(|l| header(l));
    Some(match table {
        Some(t) if !t.is_empty() => format!("{t}.{key}"),
        _ => key,
    })
}

/// A PEM pair from two optional keys, both or neither.
fn tls_source(
    cert: Option<PathBuf>,
    key: Option<PathBuf>,
    (cert_key, key_key): (&str, &str),
) -> Result<TlsSource, ConfigError> {
    match (cert, key) {
        (Some(cert), Some(key)) => Ok(TlsSource::Files { cert, key }),
        (None, None) => Ok(TlsSource::SelfSigned),
        (Some(_), None) => Err(invalid(
            key_key,
            format!("`{cert_key}` is set but `{key_key}` is not"),
        )),
        (None, Some(_)) => Err(invalid(
            cert_key,
            format!("`{key_key}` is set but `{cert_key}` is not"),
        )),
    }
}

/// Reads a token file: surrounding whitespace trimmed, must not be empty.
fn read_token_file(key: &str, path: &Path) -> Result<String, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        key: key.to_owned(),
        path: path.to_owned(),
        source,
    })?;
    let t = text.trim();
    if t.is_empty() {
        return Err(invalid(
            key,
            format!("token file {} is empty", path.display()),
        ));
    }
    Ok(t.to_owned())
}

impl ServeConfig {
    /// The built-in defaults for a pool, as without a config file (`default_access` public).
    pub fn new(db: impl Into<PathBuf>) -> ServeConfig {
        ServeConfig {
            db: db.into(),
            data_dir: None,
            listen: DEFAULT_LISTEN.parse().expect("valid default"),
            admin_listen: Some(DEFAULT_ADMIN_LISTEN.parse().expect("valid default")),
            admin_token: AdminTokenSource::Generated,
            admin_tls: AdminTls::Auto,
            admin_identity: TlsSource::SelfSigned,
            probe_token: None,
            tls: TlsSource::SelfSigned,
            max_connections: 256,
            idle_timeout_ms: 30_000,
            hello_timeout_ms: 5_000,
            max_connection_memory: 64 << 20,
            initial_window: DEFAULT_INITIAL_WINDOW,
            path_memory_secs: DEFAULT_PATH_MEMORY_SECS,
            config_watch_secs: 0,
            random_loss_tolerance: true,
            transparent_huge_pages: false,
            pool_cache_bytes: crate::pool::POOL_CACHE_BYTES,
            pool_readers: DEFAULT_POOL_READERS,
            pool_prewarm: PoolPrewarm::Auto,
            message_cache_bytes: DEFAULT_MESSAGE_CACHE_BYTES,
            shape_cache_bytes: DEFAULT_SHAPE_CACHE_BYTES,
            visibility_grid: DEFAULT_VISIBILITY_GRID,
            visibility_fine_grid: DEFAULT_VISIBILITY_FINE_GRID,
            visibility_cache_bytes: DEFAULT_VISIBILITY_CACHE_BYTES,
            visibility_node_cache_bytes: DEFAULT_VISIBILITY_NODE_CACHE_BYTES,
            visibility_follow_share: DEFAULT_VISIBILITY_FOLLOW_SHARE,
            window_min: 8,
            window_max: 1024,
            slow_reader_timeout_ms: 10_000,
            shutdown_grace_ms: 5_000,
            default_access: Access::Public,
            scenes: BTreeMap::new(),
        }
    }

    /// Parses a config file's text; `path` only names it in errors. Token files it names are
    /// read. The result is validated.
    pub fn from_toml(
        text: &str,
        path: &Path,
        overrides: &ConfigOverrides,
    ) -> Result<ServeConfig, ConfigError> {
        let file: FileConfig = toml::from_str(text).map_err(|e| {
            let key = e
                .span()
                .and_then(|s| key_at(text, s.start))
                .unwrap_or_else(|| "?".into());
            ConfigError::Parse {
                path: path.to_owned(),
                key,
                message: e.message().trim().to_owned(),
            }
        })?;
        Self::resolve(Some(file), overrides)
    }

    /// Loads the configuration: the file if given (else the defaults), then the overrides.
    pub fn load(
        file: Option<&Path>,
        overrides: &ConfigOverrides,
    ) -> Result<ServeConfig, ConfigError> {
        match file {
            Some(path) => {
                let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
                    key: "--config".into(),
                    path: path.to_owned(),
                    source,
                })?;
                Self::from_toml(&text, path, overrides)
            }
            None => Self::resolve(None, overrides),
        }
    }

    fn resolve(
        file: Option<FileConfig>,
        overrides: &ConfigOverrides,
    ) -> Result<ServeConfig, ConfigError> {
        let have_file = file.is_some();
        let f = file.unwrap_or_default();
        let db = overrides
            .db
            .clone()
            .or(f.db)
            .ok_or_else(|| invalid("db", "no pool directory: pass --db or set `db`"))?;
        let mut c = ServeConfig::new(db);
        c.data_dir = overrides.data_dir.clone().or(f.data_dir);
        if let Some(l) = overrides.listen.or(f.listen) {
            c.listen = l;
        }
        c.admin_listen = match (&overrides.admin_listen, &f.admin_listen) {
            (Some(a), _) => *a,
            (None, Some(s)) => parse_admin_listen(s).map_err(|r| invalid("admin_listen", r))?,
            (None, None) => c.admin_listen,
        };
        c.admin_token = match (f.admin_token, f.admin_token_file) {
            (Some(_), Some(_)) => {
                return Err(invalid(
                    "admin_token",
                    "set either admin_token or admin_token_file, not both",
                ));
            }
            (Some(t), None) => AdminTokenSource::Inline(t),
            (None, Some(p)) => AdminTokenSource::File(p),
            (None, None) => AdminTokenSource::Generated,
        };
        c.probe_token = f.probe_token;
        c.tls = tls_source(f.cert, f.key, ("cert", "key"))?;
        c.admin_tls = overrides.admin_tls.or(f.admin_tls).unwrap_or_default();
        c.pool_prewarm = overrides
            .pool_prewarm
            .or(f.pool_prewarm)
            .unwrap_or_default();
        c.admin_identity = tls_source(f.admin_cert, f.admin_key, ("admin_cert", "admin_key"))?;
        macro_rules! take {
            ($($field:ident),*) => { $( if let Some(v) = f.$field { c.$field = v; } )* };
        }
        take!(
            max_connections,
            idle_timeout_ms,
            hello_timeout_ms,
            max_connection_memory,
            initial_window,
            path_memory_secs,
            random_loss_tolerance,
            transparent_huge_pages,
            pool_cache_bytes,
            pool_readers,
            message_cache_bytes,
            shape_cache_bytes,
            visibility_grid,
            visibility_fine_grid,
            visibility_cache_bytes,
            visibility_node_cache_bytes,
            visibility_follow_share,
            window_min,
            window_max,
            slow_reader_timeout_ms,
            shutdown_grace_ms,
            config_watch_secs
        );
        c.default_access = f.default_access.unwrap_or(if have_file {
            Access::Token
        } else {
            Access::Public
        });
        for (name, s) in f.scenes {
            let key = format!("scenes.{name}");
            let has_tokens = s.tokens.is_some() || s.token_files.is_some();
            let access = s.access.unwrap_or(Access::Token);
            let rule = match access {
                Access::Public if has_tokens => {
                    return Err(invalid(
                        key,
                        "access = \"public\" together with tokens; remove one",
                    ));
                }
                Access::Public => SceneAccess::Public,
                Access::Token => {
                    let mut tokens = s.tokens.unwrap_or_default();
                    for p in s.token_files.unwrap_or_default() {
                        tokens.push(read_token_file(&format!("{key}.token_files"), &p)?);
                    }
                    SceneAccess::Tokens(tokens)
                }
            };
            c.scenes.insert(name, rule);
        }
        c.validate()?;
        Ok(c)
    }

    /// Checks every value: non-zero limits, `window_min ≤ window_max`, memory bound large
    /// enough, valid scene names, non-empty tokens within the protocol's limit, a token-access
    /// scene with at least one token, admin token file readable and non-empty.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let nonzero = |key: &str, v: u64| {
            if v == 0 {
                Err(invalid(key, "must be greater than 0"))
            } else {
                Ok(())
            }
        };
        nonzero("max_connections", self.max_connections as u64)?;
        nonzero("idle_timeout_ms", self.idle_timeout_ms)?;
        nonzero("hello_timeout_ms", self.hello_timeout_ms)?;
        nonzero("window_min", self.window_min as u64)?;
        nonzero("window_max", self.window_max as u64)?;
        nonzero("slow_reader_timeout_ms", self.slow_reader_timeout_ms)?;
        // QUIC idle timeouts are varints of milliseconds.
        if self.idle_timeout_ms >= 1 << 62 {
            return Err(invalid("idle_timeout_ms", "too large"));
        }
        if !(MIN_INITIAL_WINDOW..=MAX_INITIAL_WINDOW).contains(&self.initial_window) {
            return Err(invalid(
                "initial_window",
                format!("{MIN_INITIAL_WINDOW}..={MAX_INITIAL_WINDOW} bytes"),
            ));
        }
        if self.config_watch_secs > MAX_CONFIG_WATCH_SECS {
            return Err(invalid(
                "config_watch_secs",
                format!("at most {MAX_CONFIG_WATCH_SECS} seconds (0: only on SIGHUP)"),
            ));
        }
        if self.path_memory_secs > MAX_PATH_MEMORY_SECS {
            return Err(invalid(
                "path_memory_secs",
                format!("at most {MAX_PATH_MEMORY_SECS} seconds (0 turns it off)"),
            ));
        }
        if self.visibility_grid > MAX_VISIBILITY_GRID {
            return Err(invalid(
                "visibility_grid",
                format!("at most {MAX_VISIBILITY_GRID} rays (0 turns visible cuts off)"),
            ));
        }
        if self.visibility_fine_grid != 0
            && !(self.visibility_grid + 1..=MAX_VISIBILITY_GRID)
                .contains(&self.visibility_fine_grid)
        {
            return Err(invalid(
                "visibility_fine_grid",
                format!(
                    "0 (none) or above visibility_grid ({}) and at most {MAX_VISIBILITY_GRID}",
                    self.visibility_grid
                ),
            ));
        }
        if !(1..=MAX_POOL_READERS).contains(&self.pool_readers) {
            return Err(invalid(
                "pool_readers",
                format!("1..={MAX_POOL_READERS} threads"),
            ));
        }
        if self.pool_cache_bytes < MIN_POOL_CACHE_BYTES {
            return Err(invalid(
                "pool_cache_bytes",
                format!("at least {MIN_POOL_CACHE_BYTES} bytes"),
            ));
        }
        if self.visibility_cache_bytes < MIN_VISIBILITY_CACHE_BYTES {
            return Err(invalid(
                "visibility_cache_bytes",
                format!("at least {MIN_VISIBILITY_CACHE_BYTES} bytes"),
            ));
        }
        if !(self.visibility_follow_share > 0.0 && self.visibility_follow_share <= 1.0) {
            return Err(invalid(
                "visibility_follow_share",
                format!(
                    "{} is not a share in (0, 1] (1 follows every visible cut)",
                    self.visibility_follow_share
                ),
            ));
        }
        if self.window_min > self.window_max {
            return Err(invalid(
                "window_min",
                format!(
                    "window_min {} exceeds window_max {}",
                    self.window_min, self.window_max
                ),
            ));
        }
        if self.window_max > MAX_REQUEST_ITEMS {
            return Err(invalid(
                "window_max",
                format!("at most {MAX_REQUEST_ITEMS} (the longest request list)"),
            ));
        }
        if self.max_connection_memory < MIN_CONNECTION_MEMORY {
            return Err(invalid(
                "max_connection_memory",
                format!(
                    "{} bytes is below the minimum of {MIN_CONNECTION_MEMORY} (one maximal frame, \
                     one maximal request list and QUIC buffers)",
                    self.max_connection_memory
                ),
            ));
        }
        if let AdminTokenSource::Inline(t) = &self.admin_token
            && t.trim().is_empty()
        {
            return Err(invalid("admin_token", "must not be empty"));
        }
        if let AdminTokenSource::File(p) = &self.admin_token {
            read_token_file("admin_token_file", p)?;
        }
        if let Some(t) = &self.probe_token
            && t.trim().is_empty()
        {
            return Err(invalid("probe_token", "must not be empty"));
        }
        for (name, rule) in &self.scenes {
            let key = format!("scenes.{name}");
            validate_scene_name(name).map_err(|e| invalid(&key, e.to_string()))?;
            if let SceneAccess::Tokens(tokens) = rule {
                if tokens.is_empty() {
                    return Err(invalid(
                        format!("{key}.tokens"),
                        "no tokens: give `tokens` or `token_files`, or set access = \"public\"",
                    ));
                }
                for t in tokens {
                    if t.is_empty() {
                        return Err(invalid(format!("{key}.tokens"), "empty token"));
                    }
                    if t.len() > MAX_TOKEN_BYTES {
                        return Err(invalid(
                            format!("{key}.tokens"),
                            format!("token longer than {MAX_TOKEN_BYTES} bytes"),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// The directory holding the self-signed pair and the generated admin token.
    pub fn data_dir(&self) -> &Path {
        self.data_dir.as_deref().unwrap_or(&self.db)
    }

    pub fn idle_timeout(&self) -> Duration {
        Duration::from_millis(self.idle_timeout_ms)
    }

    /// How long path records are used ([`ServeConfig::path_memory_secs`]; zero: off).
    pub fn path_memory(&self) -> Duration {
        Duration::from_secs(self.path_memory_secs)
    }

    pub fn hello_timeout(&self) -> Duration {
        Duration::from_millis(self.hello_timeout_ms)
    }

    pub fn slow_reader_timeout(&self) -> Duration {
        Duration::from_millis(self.slow_reader_timeout_ms)
    }

    pub fn shutdown_grace(&self) -> Duration {
        Duration::from_millis(self.shutdown_grace_ms)
    }

    /// Divides `max_connection_memory` among a connection's buffers: the decoder (one maximal
    /// frame) and the scheduler's copy of a maximal request list are fixed by the protocol; the
    /// redelivery record keeps up to `schedule::RECENT_DELIVERIES_KEPT` deliveries, fewer when
    /// that would take more than a quarter of what is left (a small bound); the receive window
    /// gets an eighth of the rest (at most 2 MiB: the client only sends control frames), the
    /// send window everything else.
    pub fn memory_plan(&self) -> MemoryPlan {
        use super::schedule::{RECENT_DELIVERIES_KEPT, recent_record_bytes};
        let decoder = (MAX_FRAME_BYTES + arbor_proto::limits::FRAME_HEADER_BYTES) as u64;
        // Scheduler: by-id index (16 B) + send queue (8 B) + hash/heap overhead per item.
        let request_list = MAX_REQUEST_ITEMS as u64 * 48;
        // Deliveries remembered for visible cuts: a 4-byte id and a control byte per bucket,
        // at most twice as many buckets as ids.
        let deliveries = super::schedule::DELIVERIES_REMEMBERED as u64 * 10;
        let fixed = decoder + request_list + deliveries;
        let spare = self.max_connection_memory.saturating_sub(fixed) / 4;
        let mut recent_deliveries = RECENT_DELIVERIES_KEPT;
        while recent_deliveries > MIN_RECENT_DELIVERIES
            && recent_record_bytes(recent_deliveries) > spare
        {
            recent_deliveries /= 2;
        }
        let redelivery_record = recent_record_bytes(recent_deliveries);
        let rest = self
            .max_connection_memory
            .saturating_sub(fixed + redelivery_record);
        let receive_window = (rest / 8).clamp(64 << 10, 2 << 20);
        let send_window = rest.saturating_sub(receive_window).max(256 << 10);
        MemoryPlan {
            decoder,
            request_list,
            deliveries,
            recent_deliveries,
            redelivery_record,
            receive_window,
            send_window,
        }
    }

    /// The most memory this configuration's bounds let the service hold with `scenes` scenes
    /// in the pool ([`MemoryBound`]).
    pub fn memory_bound(&self, scenes: usize) -> MemoryBound {
        let cuts = self.visibility_grid > 0;
        MemoryBound {
            pool_cache: self
                .pool_cache_bytes
                .saturating_add(crate::pool::POOL_SEGMENT_BYTES as u64),
            connections: (self.max_connections as u64).saturating_mul(self.max_connection_memory),
            message_cache: self.message_cache_bytes,
            shape_cache: self.shape_cache_bytes,
            cut_node_cache: if cuts {
                self.visibility_node_cache_bytes
            } else {
                0
            },
            cut_buffers_per_scene: if cuts {
                (super::treelets::MAX_CUTS_RUNNING as u64)
                    .saturating_mul(self.visibility_cache_bytes)
            } else {
                0
            },
            scenes: scenes as u64,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<ServeConfig, ConfigError> {
        ServeConfig::from_toml(text, Path::new("test.toml"), &ConfigOverrides::default())
    }

    fn err(text: &str) -> String {
        parse(text).unwrap_err().to_string()
    }

    #[test]
    fn the_documented_example_parses() {
        let dir = tempfile::tempdir().unwrap();
        let tf = dir.path().join("bunny.token");
        std::fs::write(&tf, "from-file\n").unwrap();
        let text = format!(
            r#"
db = "/var/lib/arbor/pool"
data_dir = "/var/lib/arbor/state"
listen = "0.0.0.0:4433"
admin_listen = "127.0.0.1:9090"
admin_token = "admin-secret"
cert = "/etc/arbor/tls/fullchain.pem"
key = "/etc/arbor/tls/key.pem"
max_connections = 256
idle_timeout_ms = 30000
hello_timeout_ms = 5000
max_connection_memory = 67108864
pool_cache_bytes = 1073741824
pool_readers = 32
pool_prewarm = "off"
shape_cache_bytes = 1048576
window_min = 8
window_max = 256
slow_reader_timeout_ms = 10000
shutdown_grace_ms = 5000
random_loss_tolerance = false
default_access = "token"

[scenes.bunny]
tokens = ["change-me"]
token_files = ["{}"]
[scenes.lion]
access = "public"
"#,
            tf.display()
        );
        let c = parse(&text).unwrap();
        assert_eq!(c.db, Path::new("/var/lib/arbor/pool"));
        assert_eq!(c.data_dir(), Path::new("/var/lib/arbor/state"));
        assert_eq!(c.listen, "0.0.0.0:4433".parse().unwrap());
        assert_eq!(c.admin_listen, Some("127.0.0.1:9090".parse().unwrap()));
        assert_eq!(
            c.admin_token,
            AdminTokenSource::Inline("admin-secret".into())
        );
        assert!(matches!(c.tls, TlsSource::Files { .. }));
        assert_eq!(c.shape_cache_bytes, 1 << 20);
        assert_eq!(c.pool_cache_bytes, 1 << 30);
        assert_eq!(c.pool_readers, 32);
        assert_eq!(c.pool_prewarm, PoolPrewarm::Off);
        assert!(!c.random_loss_tolerance);
        assert!(ServeConfig::new("p").random_loss_tolerance, "on by default");
        assert_eq!(c.default_access, Access::Token);
        assert_eq!(
            c.scenes["bunny"],
            SceneAccess::Tokens(vec!["change-me".into(), "from-file".into()])
        );
        assert_eq!(c.scenes["lion"], SceneAccess::Public);
    }

    /// The example configs shipped in deploy/ (systemd/host, container image, Kubernetes
    /// ConfigMap) parse with the implemented schema, so they cannot drift from it.
    #[test]
    fn shipped_example_configs_parse() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        // Secret files live on the target host (/run/credentials, /etc/arbor): point every
        // absolute path at one readable token file here.
        let dir = tempfile::tempdir().unwrap();
        let token = dir.path().join("token");
        std::fs::write(&token, "t0ken\n").unwrap();
        let parse = |text: &str, path: &Path| {
            let mut local = String::new();
            let mut rest = text;
            while let Some(i) = rest.find("\"/") {
                local.push_str(&rest[..=i]);
                let end = rest[i + 1..].find('"').map_or(rest.len(), |e| i + 1 + e);
                local.push_str(token.to_str().unwrap());
                rest = &rest[end..];
            }
            local.push_str(rest);
            ServeConfig::from_toml(&local, path, &ConfigOverrides::default())
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        };
        for rel in ["deploy/arbor.toml", "deploy/container/arbor.toml"] {
            let p = root.join(rel);
            parse(&std::fs::read_to_string(&p).unwrap(), &p);
        }
        let p = root.join("deploy/kubernetes/configmap.yaml");
        let cm = std::fs::read_to_string(&p).unwrap();
        let (_, rest) = cm.split_once("arbor.toml: |").expect("an arbor.toml key");
        let body: Vec<&str> = rest
            .lines()
            .skip(1)
            .take_while(|l| l.starts_with("    ") || l.trim().is_empty())
            .map(|l| l.get(4..).unwrap_or(""))
            .collect();
        let c = parse(&body.join("\n"), &p);
        assert!(
            c.probe_token.is_some(),
            "the ConfigMap sets the probe token"
        );
        // The replicas' memory limit covers the ConfigMap's memory bound for the scenes it
        // names, with room for the runtime, the allocator's slack and the admin API.
        let bound = c.memory_bound(c.scenes.len());
        let deployment =
            std::fs::read_to_string(root.join("deploy/kubernetes/deployment.yaml")).unwrap();
        let (_, server) = deployment
            .split_once("# Memory: worst case")
            .expect("the server container's memory comment");
        let (_, limits) = server.split_once("limits:").expect("its limits");
        let mib: u64 = limits
            .lines()
            .find_map(|l| {
                l.trim()
                    .strip_prefix("memory: ")?
                    .strip_suffix("Mi")?
                    .parse()
                    .ok()
            })
            .expect("a memory limit in Mi");
        const RUNTIME_ALLOWANCE: u64 = 128 << 20;
        assert!(
            bound.total() + RUNTIME_ALLOWANCE <= mib << 20,
            "limit {mib} MiB against a bound of {} MiB + the runtime: {bound:?}",
            bound.total() >> 20
        );
    }

    #[test]
    fn defaults_and_overrides() {
        let c = ServeConfig::load(
            None,
            &ConfigOverrides {
                db: Some("pool".into()),
                ..ConfigOverrides::default()
            },
        )
        .unwrap();
        assert_eq!(c, ServeConfig::new("pool"));
        assert_eq!(c.data_dir(), Path::new("pool"));
        assert_eq!(c.default_access, Access::Public, "no file: public");
        // A file without default_access: token.
        assert_eq!(parse("db = \"p\"").unwrap().default_access, Access::Token);
        let o = ConfigOverrides {
            db: Some("cli-db".into()),
            listen: Some("127.0.0.1:1".parse().unwrap()),
            admin_listen: Some(None),
            data_dir: Some("cli-data".into()),
            pool_prewarm: Some(PoolPrewarm::Always),
            ..ConfigOverrides::default()
        };
        let c = ServeConfig::from_toml(
            "db = \"file-db\"\nlisten = \"0.0.0.0:5\"\nadmin_listen = \"127.0.0.1:6\"\ndata_dir = \"d\"\npool_prewarm = \"off\"",
            Path::new("x"),
            &o,
        )
        .unwrap();
        assert_eq!(c.db, Path::new("cli-db"));
        assert_eq!(c.listen, "127.0.0.1:1".parse().unwrap());
        assert_eq!(c.admin_listen, None);
        assert_eq!(c.data_dir(), Path::new("cli-data"));
        assert_eq!(
            c.pool_prewarm,
            PoolPrewarm::Always,
            "the flag over the file"
        );
        assert_eq!(
            parse("db = \"p\"\nadmin_listen = \"off\"")
                .unwrap()
                .admin_listen,
            None
        );
        let e = ServeConfig::load(None, &ConfigOverrides::default()).unwrap_err();
        assert!(e.to_string().contains("`db`"), "{e}");
    }

    #[test]
    fn parse_errors_name_the_key() {
        let e = err("db = \"p\"\nmax_connections = \"many\"\n");
        assert!(e.contains("key `max_connections`"), "{e}");
        let e = err("db = \"p\"\nwindow_max = -3\n");
        assert!(e.contains("key `window_max`"), "{e}");
        let e = err("db = \"p\"\nlisten = \"not an address\"\n");
        assert!(e.contains("key `listen`"), "{e}");
        let e = err("db = \"p\"\n[scenes.bunny]\ntokens = [\n  \"a\",\n  3,\n]\n");
        assert!(e.contains("key `scenes.bunny.tokens`"), "{e}");
        let e = err("db = \"p\"\n[scenes.bunny]\naccess = \"sometimes\"\n");
        assert!(e.contains("key `scenes.bunny.access`"), "{e}");
        let e = err("db = \"p\"\ndefault_access = \"maybe\"\n");
        assert!(e.contains("default_access"), "{e}");
        let e = err("db = \"p\"\npool_prewarm = \"sometimes\"\n");
        assert!(e.contains("key `pool_prewarm`"), "{e}");
        // Syntax errors still say where.
        let e = err("db = \"p\"\nmax_connections = \n");
        assert!(e.contains("max_connections"), "{e}");
    }

    #[test]
    fn unknown_keys_are_rejected() {
        let e = err("db = \"p\"\nmax_conections = 3\n");
        assert!(e.contains("max_conections"), "{e}");
        assert!(e.contains("unknown field"), "{e}");
        let e = err("db = \"p\"\n[scenes.bunny]\ntoken = \"x\"\n");
        assert!(e.contains("scenes.bunny") && e.contains("token"), "{e}");
        assert!(e.contains("unknown field"), "{e}");
    }

    #[test]
    fn invalid_values_are_rejected() {
        for (text, key) in [
            ("max_connections = 0", "max_connections"),
            ("idle_timeout_ms = 0", "idle_timeout_ms"),
            ("hello_timeout_ms = 0", "hello_timeout_ms"),
            ("slow_reader_timeout_ms = 0", "slow_reader_timeout_ms"),
            ("window_min = 0", "window_min"),
            ("initial_window = 100", "initial_window"),
            ("visibility_grid = 5000", "visibility_grid"),
            (
                "visibility_grid = 128\nvisibility_fine_grid = 64",
                "visibility_fine_grid",
            ),
            ("visibility_fine_grid = 2000", "visibility_fine_grid"),
            ("visibility_cache_bytes = 1000", "visibility_cache_bytes"),
            ("pool_cache_bytes = 0", "pool_cache_bytes"),
            ("pool_readers = 0", "pool_readers"),
            ("pool_readers = 100000", "pool_readers"),
            ("pool_cache_bytes = 65536", "pool_cache_bytes"),
            ("pool_cache_bytes = -1", "pool_cache_bytes"),
            ("visibility_follow_share = 0.0", "visibility_follow_share"),
            ("visibility_follow_share = 1.5", "visibility_follow_share"),
            ("visibility_follow_share = nan", "visibility_follow_share"),
            ("visibility_follow_share = -0.5", "visibility_follow_share"),
            ("initial_window = 1000000000", "initial_window"),
            ("path_memory_secs = 100000", "path_memory_secs"),
            ("config_watch_secs = 86401", "config_watch_secs"),
            ("path_memory_secs = -1", "path_memory_secs"),
            ("window_min = 10\nwindow_max = 9", "window_min"),
            ("window_max = 1000000", "window_max"),
            ("max_connection_memory = 1000", "max_connection_memory"),
            ("admin_listen = \"nowhere\"", "admin_listen"),
            ("admin_token = \"  \"", "admin_token"),
            (
                "admin_token = \"a\"\nadmin_token_file = \"b\"",
                "admin_token",
            ),
            (
                "admin_token_file = \"/nonexistent/token\"",
                "admin_token_file",
            ),
            ("cert = \"c.pem\"", "key"),
            ("key = \"k.pem\"", "cert"),
            ("[scenes.bunny]\ntokens = []", "scenes.bunny.tokens"),
            ("[scenes.bunny]\ntokens = [\"\"]", "scenes.bunny.tokens"),
            ("[scenes.bunny]", "scenes.bunny.tokens"),
            (
                "[scenes.bunny]\naccess = \"public\"\ntokens = [\"x\"]",
                "scenes.bunny",
            ),
            (
                "[scenes.bunny]\ntoken_files = [\"/nonexistent/t\"]",
                "scenes.bunny.token_files",
            ),
            ("[scenes.\"../x\"]\naccess = \"public\"", "scenes.../x"),
        ] {
            let e = err(&format!("db = \"p\"\n{text}\n"));
            assert!(e.contains(&format!("`{key}`")), "{text}: {e}");
        }
        let dir = tempfile::tempdir().unwrap();
        let empty = dir.path().join("empty");
        std::fs::write(&empty, "\n  \n").unwrap();
        let e = err(&format!(
            "db = \"p\"\n[scenes.b]\ntoken_files = [\"{}\"]\n",
            empty.display()
        ));
        assert!(e.contains("is empty"), "{e}");
        // Grace 0 is allowed: stop at once.
        assert_eq!(
            parse("db = \"p\"\nshutdown_grace_ms = 0")
                .unwrap()
                .shutdown_grace_ms,
            0
        );
    }

    #[test]
    fn the_memory_bound_counts_every_bounded_part() {
        let mut c = ServeConfig::new("p");
        c.max_connections = 64;
        c.max_connection_memory = 16 << 20;
        let b = c.memory_bound(2);
        let mib = |v: u64| v >> 20;
        assert_eq!(
            (
                mib(b.pool_cache),
                mib(b.connections),
                mib(b.message_cache),
                mib(b.shape_cache),
                mib(b.cut_node_cache),
                mib(b.cut_buffers())
            ),
            (128 + 8, 1024, 64, 32, 64, 2 * 2 * 32),
            "the defaults with cuts on, two scenes (sled's cache and its 8 MiB write buffer)"
        );
        assert_eq!(mib(b.total()), 136 + 1024 + 64 + 32 + 64 + 128);
        assert_eq!(b.parts().iter().map(|p| p.1).sum::<u64>(), b.total());
        assert_eq!(b.with_scenes(5).cut_buffers(), 5 * 2 * (32 << 20));
        c.pool_cache_bytes = 1 << 30;
        assert_eq!(
            mib(c.memory_bound(2).pool_cache),
            1024 + 8,
            "the pool cache as configured"
        );
        c.visibility_grid = 0;
        let off = c.memory_bound(2);
        assert_eq!((off.cut_node_cache, off.cut_buffers()), (0, 0), "cuts off");
        c.max_connections = usize::MAX;
        c.max_connection_memory = u64::MAX;
        assert_eq!(c.memory_bound(usize::MAX).total(), u64::MAX, "saturates");
    }

    #[test]
    fn memory_plan_fits_the_bound() {
        for m in [MIN_CONNECTION_MEMORY, 64 << 20, 1 << 30] {
            let mut c = ServeConfig::new("p");
            c.max_connection_memory = m;
            let p = c.memory_plan();
            assert!(
                p.decoder
                    + p.request_list
                    + p.deliveries
                    + p.redelivery_record
                    + p.receive_window
                    + p.send_window
                    <= m,
                "{p:?}"
            );
            assert!(p.recent_deliveries >= MIN_RECENT_DELIVERIES, "{p:?}");
            assert_eq!(
                p.redelivery_record,
                crate::service::schedule::recent_record_bytes(p.recent_deliveries)
            );
            assert!(p.receive_window >= 64 << 10 && p.receive_window <= 2 << 20);
            assert!(p.send_window >= 256 << 10);
        }
    }

    #[test]
    fn key_at_finds_keys() {
        let src = "a = 1\n[t.u]\nb = [\n 1,\n 2]\nc=3\n";
        assert_eq!(key_at(src, 2).as_deref(), Some("a"));
        assert_eq!(
            key_at(src, src.find("2]").unwrap()).as_deref(),
            Some("t.u.b")
        );
        assert_eq!(
            key_at(src, src.find("c=").unwrap()).as_deref(),
            Some("t.u.c")
        );
        assert_eq!(
            key_at(src, src.find("[t").unwrap() + 1).as_deref(),
            Some("t.u")
        );
        assert_eq!(key_at(src, 10_000).as_deref(), Some("t.u.c"));
    }
}
