//! Shared helpers of the service tests: a real bunny pool (and one damaged on disk), a server
//! started as the daemon is (with its background jobs if asked), a configuration for tests, and
//! a raw quinn client (fingerprint pinning, control frames, treelet streams) written against
//! the wire protocol only — not the client library; certificates with a given expiry.
#![allow(dead_code, reason = "each test binary uses a different subset")]

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_net::tls::{PinnedCertVerifier, parse_fingerprint};
use arbor_proto::frame::{self, FrameDecoder};
use arbor_proto::limits::MAX_TREELET_MESSAGE_BYTES;
use arbor_proto::wire::{ALPN, ErrorCode, Frame, PROTOCOL_VERSION, ViewHint};
use arbor_proto::{Channel, SceneDescription, TreeletId};
use arbor_server::daemon::RunningServer;
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_server::pipeline::{SceneImport, import_scene};
use arbor_server::pool::Pool;
use arbor_server::service::ServeConfig;
use arbor_server::service::config::SceneAccess;
use rustls::pki_types::CertificateDer;

pub const SCENE: &str = "bunny";
pub const TOKEN: &str = "bunny-token";

pub fn bunny_path() -> PathBuf {
    let p = Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/meshes/stanford-bunny.obj"
    ))
    .to_owned();
    assert!(p.exists(), "the real scans in ../shared/data are required");
    p
}

/// Imports the bunny (depth 6, 1 KiB treelets) as scene [`SCENE`], and as each of `copies`,
/// into a new pool in `dir`.
pub fn build_pool(dir: &Path, copies: &[&str]) {
    let pool = Pool::open(dir).unwrap();
    for name in std::iter::once(&SCENE).chain(copies) {
        import_bunny(&pool, name);
    }
    pool.flush().unwrap();
}

/// Imports the bunny (depth 6, 1 KiB treelets) as scene `name`.
pub fn import_bunny(pool: &Pool, name: &str) {
    let request = SceneImport {
        name: name.into(),
        input: bunny_path(),
        build: BuildOptions {
            depth: DepthChoice::Fixed(6),
            treelet_bytes: 1024,
            progress: false,
            ..BuildOptions::default()
        },
        ..SceneImport::default()
    };
    import_scene(pool, &request).unwrap();
}

/// A pool with the bunny and a data dir, both removed on drop.
pub struct TestPool {
    pub dir: tempfile::TempDir,
}

impl TestPool {
    pub fn new() -> TestPool {
        Self::with_copies(&[])
    }

    /// A pool with the bunny as [`SCENE`] and as each of `copies`.
    pub fn with_copies(copies: &[&str]) -> TestPool {
        let dir = tempfile::tempdir().unwrap();
        build_pool(&dir.path().join("pool"), copies);
        TestPool { dir }
    }

    pub fn db(&self) -> PathBuf {
        self.dir.path().join("pool")
    }

    pub fn data_dir(&self) -> PathBuf {
        self.dir.path().join("state")
    }

    /// Test settings: loopback, ephemeral ports, short timeouts, the bunny behind [`TOKEN`],
    /// every other scene refused.
    pub fn config(&self) -> ServeConfig {
        let mut c = ServeConfig::new(self.db());
        c.data_dir = Some(self.data_dir());
        c.listen = "127.0.0.1:0".parse().unwrap();
        c.admin_listen = Some("127.0.0.1:0".parse().unwrap());
        c.hello_timeout_ms = 2_000;
        c.slow_reader_timeout_ms = 1_500;
        c.shutdown_grace_ms = 1_000;
        c.default_access = arbor_server::service::config::Access::Token;
        c.scenes
            .insert(SCENE.into(), SceneAccess::Tokens(vec![TOKEN.into()]));
        c
    }
}

/// Starts a server, retrying while sled's flusher thread of the just-dropped import handle
/// still holds the pool's lock.
pub async fn start(config: ServeConfig) -> RunningServer {
    start_with(config, arbor_server::daemon::DaemonOptions::default()).await
}

/// [`start`], with the daemon's background jobs as `options` say.
pub async fn start_with(
    config: ServeConfig,
    options: arbor_server::daemon::DaemonOptions,
) -> RunningServer {
    let t0 = Instant::now();
    loop {
        match arbor_server::daemon::start_with(config.clone(), options.clone()).await {
            Ok(s) => return s,
            Err(arbor_server::service::ServeError::Pool { .. })
                if t0.elapsed() < Duration::from_secs(10) =>
            {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(e) => panic!("start: {e}"),
        }
    }
}

/// The bunny's pool with two more copies, damaged before the daemon opens it: `holes` lost a
/// pack of attribute blocks (broken invariants), `garbage` has a node pack that does not decode
/// (the pool cannot be read).
pub fn damaged_pool() -> TestPool {
    let pool = TestPool::with_copies(&["holes", "garbage"]);
    // Opened as soon as the import's handle has let go of sled's lock.
    fn when_unlocked<T, E>(open: impl Fn() -> Result<T, E>) -> T {
        (0..100)
            .find_map(|_| {
                open()
                    .map_err(|_| std::thread::sleep(Duration::from_millis(50)))
                    .ok()
            })
            .expect("sled lock released")
    }
    let (holes, garbage, channel) = {
        let p = when_unlocked(|| arbor_server::pool::Pool::open(&pool.db()));
        let holes = p.scene("holes").unwrap();
        let garbage = p.scene("garbage").unwrap();
        let channel = holes.description.layout.channels()[0];
        (holes.generation, garbage.generation, channel)
    };
    let db = when_unlocked(|| {
        sled::Config::new()
            .path(pool.db())
            .segment_size(arbor_server::pool::POOL_SEGMENT_BYTES)
            .open()
    });
    let attributes = db
        .open_tree(format!("g{holes}:ch:{}", channel.name()))
        .unwrap();
    let (key, _) = attributes.first().unwrap().expect("an attribute pack");
    attributes.remove(key).unwrap();
    let nodes = db.open_tree(format!("g{garbage}:nodes")).unwrap();
    let (key, _) = nodes.first().unwrap().expect("a node pack");
    nodes.insert(key, vec![0xAB; 40]).unwrap();
    db.flush().unwrap();
    pool
}

// ---------------------------------------------------------------------------------------------
// Raw quinn client
// ---------------------------------------------------------------------------------------------

/// SHA-256 of a DER certificate, lowercase hex (computed here, independently of the server).
pub fn sha256_hex(der: &[u8]) -> String {
    ring::digest::digest(&ring::digest::SHA256, der)
        .as_ref()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// How a test client connects.
pub struct ClientOptions {
    pub alpn: Vec<u8>,
    pub transport: quinn::TransportConfig,
}

impl Default for ClientOptions {
    fn default() -> Self {
        let mut transport = quinn::TransportConfig::default();
        transport.max_concurrent_uni_streams(1024u32.into());
        ClientOptions {
            alpn: ALPN.to_vec(),
            transport,
        }
    }
}

/// A connected raw client (the endpoint is kept alive with the connection).
pub struct Client {
    pub endpoint: quinn::Endpoint,
    pub conn: quinn::Connection,
}

pub fn client_config(fingerprint: &str, opts: ClientOptions) -> quinn::ClientConfig {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut tls = rustls::ClientConfig::builder_with_provider(provider.clone())
        .with_protocol_versions(&[&rustls::version::TLS13])
        .unwrap()
        .dangerous()
        // The client library's pinning verifier: accepts exactly the leaf with this SHA-256 and
        // still checks handshake signatures.
        .with_custom_certificate_verifier(Arc::new(PinnedCertVerifier::new(
            parse_fingerprint(fingerprint).expect("a valid fingerprint"),
            &provider,
        )))
        .with_no_client_auth();
    tls.alpn_protocols = vec![opts.alpn];
    let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(tls).unwrap();
    let mut c = quinn::ClientConfig::new(Arc::new(crypto));
    c.transport_config(Arc::new(opts.transport));
    c
}

pub async fn connect_with(
    addr: SocketAddr,
    fingerprint: &str,
    opts: ClientOptions,
) -> Result<Client, quinn::ConnectionError> {
    let endpoint = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
    let connecting = endpoint
        .connect_with(client_config(fingerprint, opts), addr, "localhost")
        .unwrap();
    let conn = connecting.await?;
    Ok(Client { endpoint, conn })
}

pub async fn connect(addr: SocketAddr, fingerprint: &str) -> Client {
    connect_with(addr, fingerprint, ClientOptions::default())
        .await
        .unwrap()
}

/// The client's control stream.
pub struct Control {
    pub send: quinn::SendStream,
    pub recv: quinn::RecvStream,
    decoder: FrameDecoder,
    pending: Vec<u8>,
}

impl Control {
    pub async fn open(conn: &quinn::Connection) -> Control {
        let (send, recv) = conn.open_bi().await.unwrap();
        Control {
            send,
            recv,
            decoder: FrameDecoder::for_client(),
            pending: Vec::new(),
        }
    }

    pub async fn send(&mut self, f: &Frame) {
        self.send_raw(&frame::encode(f).unwrap()).await;
    }

    /// Writes bytes; a failure (the server closed us) is ignored: the close code tells.
    pub async fn send_raw(&mut self, bytes: &[u8]) {
        let _ = self.send.write_all(bytes).await;
    }

    /// The next server frame, `None` at the end of the stream or on any error.
    pub async fn read(&mut self) -> Option<Frame> {
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            if !self.pending.is_empty() {
                let n = self.decoder.push(&self.pending);
                self.pending.drain(..n);
            }
            match self.decoder.next() {
                Ok(Some(f)) => return Some(f),
                Ok(None) => {}
                Err(e) => panic!("server sent a bad frame: {e}"),
            }
            if self.pending.is_empty() {
                match self.recv.read(&mut buf).await {
                    Ok(Some(n)) => self.pending.extend_from_slice(&buf[..n]),
                    _ => return None,
                }
            }
        }
    }
}

pub fn hello_frame(scene: &str, channels: &[Channel], token: &str) -> Frame {
    hello_frame_with(scene, channels, token, 0, None)
}

/// A `Hello` with `flags` and a view.
pub fn hello_frame_with(
    scene: &str,
    channels: &[Channel],
    token: &str,
    flags: u8,
    view: Option<ViewHint>,
) -> Frame {
    Frame::Hello {
        version: PROTOCOL_VERSION,
        scene: scene.into(),
        channels: channels.to_vec(),
        token: token.into(),
        flags,
        view,
    }
}

/// Opens the control stream, says `Hello` and returns the `SceneInfo`'s description, or the
/// first frame the server sent instead.
pub async fn hello(
    conn: &quinn::Connection,
    scene: &str,
    channels: &[Channel],
    token: &str,
) -> (Control, Result<SceneDescription, Option<Frame>>) {
    let mut c = Control::open(conn).await;
    c.send(&hello_frame(scene, channels, token)).await;
    let answer = match c.read().await {
        Some(Frame::SceneInfo { description }) => Ok(*description),
        other => Err(other),
    };
    (c, answer)
}

/// The application close code the connection ends with (waits up to `within`), or a
/// description of how else it ended.
pub async fn close_code(conn: &quinn::Connection, within: Duration) -> Result<u64, String> {
    match tokio::time::timeout(within, conn.closed()).await {
        Err(_) => Err(format!("still open after {within:?}")),
        Ok(quinn::ConnectionError::ApplicationClosed(c)) => Ok(c.error_code.into_inner()),
        Ok(e) => Err(format!("ended otherwise: {e}")),
    }
}

/// [`close_code`] with the reason the close frame gives.
pub async fn close_code_and_reason(
    conn: &quinn::Connection,
    within: Duration,
) -> Result<(u64, String), String> {
    match tokio::time::timeout(within, conn.closed()).await {
        Err(_) => Err(format!("still open after {within:?}")),
        Ok(quinn::ConnectionError::ApplicationClosed(c)) => Ok((
            c.error_code.into_inner(),
            String::from_utf8_lossy(&c.reason).into_owned(),
        )),
        Ok(e) => Err(format!("ended otherwise: {e}")),
    }
}

pub fn code(c: ErrorCode) -> Result<u64, String> {
    Ok(u64::from(c.to_u32()))
}

/// A received treelet message: id and the whole message.
pub type Received = (TreeletId, Vec<u8>);

/// Accepts unidirectional streams until at least `n` complete treelet messages arrived (reset
/// streams are skipped; streams accepted by then are read to their end too) or `within` passed.
pub async fn receive(
    conn: &quinn::Connection,
    n: usize,
    within: Duration,
) -> Result<Vec<Received>, String> {
    let deadline = tokio::time::Instant::now() + within;
    let mut readers = tokio::task::JoinSet::new();
    let mut got = Vec::with_capacity(n);
    while got.len() < n {
        tokio::select! {
            s = conn.accept_uni() => {
                let mut s = s.map_err(|e| format!("accept_uni after {} treelets: {e}", got.len()))?;
                // A stream carries one or a few messages back to back.
                readers.spawn(async move { s.read_to_end(64 * MAX_TREELET_MESSAGE_BYTES).await });
            }
            Some(r) = readers.join_next(), if !readers.is_empty() => {
                if let Ok(Ok(bytes)) = r {
                    got.extend(split_messages(&bytes)?);
                }
            }
            _ = tokio::time::sleep_until(deadline) => {
                return Err(format!("{} of {n} treelets within {within:?}", got.len()));
            }
        }
    }
    // Streams accepted while the last one was read carry treelets too: read them rather than
    // drop them (a caller asking for one treelet would otherwise lose a whole batch).
    while !readers.is_empty() {
        match tokio::time::timeout_at(deadline, readers.join_next()).await {
            Ok(Some(Ok(Ok(bytes)))) => got.extend(split_messages(&bytes)?),
            Ok(Some(_)) => {}
            Ok(None) | Err(_) => break,
        }
    }
    Ok(got)
}

/// The treelet messages of one stream's bytes, each checked and decoded.
pub fn split_messages(mut bytes: &[u8]) -> Result<Vec<Received>, String> {
    let mut out = Vec::new();
    while !bytes.is_empty() {
        let len = frame::check_treelet_message(bytes)
            .map_err(|e| format!("bad treelet message: {e}"))?
            .ok_or("a stream ends inside a treelet message")?;
        let m = frame::decode_treelet_message(&bytes[..len])
            .map_err(|e| format!("bad treelet message: {e}"))?;
        out.push((m.id, bytes[..len].to_vec()));
        bytes = &bytes[len..];
    }
    Ok(out)
}

/// Sends a list of `ids` (priority = position from the top) and receives exactly those; returns
/// the time it took.
pub async fn round(
    client: &Client,
    control: &mut Control,
    seq: u64,
    ids: &[TreeletId],
) -> Result<Duration, String> {
    let t0 = Instant::now();
    let items = ids
        .iter()
        .enumerate()
        .map(|(i, &t)| (t, (ids.len() - i) as f32))
        .collect();
    control.send(&Frame::RequestList { seq, items }).await;
    let got = receive(&client.conn, ids.len(), Duration::from_secs(20)).await?;
    let mut want: Vec<u32> = ids.iter().map(|t| t.0).collect();
    let mut have: Vec<u32> = got.iter().map(|(t, _)| t.0).collect();
    want.sort_unstable();
    have.sort_unstable();
    if want != have {
        return Err("received a different set of treelets".into());
    }
    Ok(t0.elapsed())
}

/// All treelet ids of a scene.
pub fn all_ids(d: &SceneDescription) -> Vec<TreeletId> {
    (0..d.treelet_count).map(TreeletId).collect()
}

/// A certificate for `localhost` and 127.0.0.1 valid until the first of January of `year`,
/// written as `cert.pem` and `key.pem` in `dir` (replacing what was there); its DER.
pub fn write_pair(dir: &Path, year: i32) -> CertificateDer<'static> {
    let key = rcgen::KeyPair::generate().unwrap();
    let mut params =
        rcgen::CertificateParams::new(vec!["localhost".into(), "127.0.0.1".into()]).unwrap();
    params.not_after = rcgen::date_time_ymd(year, 1, 1);
    let cert = params.self_signed(&key).unwrap();
    std::fs::write(dir.join("cert.pem"), cert.pem()).unwrap();
    std::fs::write(dir.join("key.pem"), key.serialize_pem()).unwrap();
    cert.der().clone()
}

/// Seconds since the Unix epoch of the first of January of `year`, UTC.
pub fn new_year(year: i16) -> f64 {
    let midnight = jiff::civil::DateTime::new(year, 1, 1, 0, 0, 0, 0).unwrap();
    jiff::tz::TimeZone::UTC
        .to_timestamp(midnight)
        .unwrap()
        .as_second() as f64
}
