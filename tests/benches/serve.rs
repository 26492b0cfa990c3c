//! Serving throughput, in one run, on loopback, each row measured in turns (best of
//! [`ROUNDS`]) so that load from elsewhere affects every column alike:
//! * Arbor: treelets/s and MB/s for 1 and 4 KiB treelets (lion) with 1, 8 and 64 concurrent
//!   clients, each asking for the same number of treelets, all channels;
//! * nginx over HTTP/2 + TLS (`nginx`, `h2load`; the peers' static tile server): the same 4 KiB
//!   scene's treelet messages as files, byte for byte, the same number per connection, the same
//!   streams in flight. Skipped, loudly, when nginx or h2load is not installed (`apt-get install
//!   nginx nghttp2-client`);
//! * raw quinn, measured the same way: one server-opened unidirectional stream per message of the
//!   scene's mean message size, the same number per connection, the same in-flight window; its
//!   client counts the chunks quinn hands over without copying them, as Arbor's client reads;
//!   with Arbor's transport settings (initial window, ACK-frequency request, the client's
//!   windows and UDP socket), so that only what is served and how differs;
//! * one client fetching the whole 4 KiB scene against raw quinn's bulk rate on one stream of the
//!   same bytes (best runs, medians, and the median of the ratios of runs taken turn by turn),
//!   with the CPU the process spent in each timed window (server and client share the cores,
//!   so the share of them a fetch keeps busy says whether CPU or waiting decides its time);
//! * the same with each end on a CPU of its own, as on two machines (their own runtimes,
//!   pinned; see [`split_ends`]): sharing the cores, the two ends mostly take turns on one;
//! * over the link emulator (25 ms each way, 100 Mbit/s): time until the top 1,000 of a list
//!   (random priorities over all treelets of the 4 KiB scene) have arrived, and all of them,
//!   against raw quinn sending the same bytes on one stream over the same link (each a first
//!   connection, slow start included).
//!
//! `cargo bench -p arbor-tests --bench serve` (ARBOR_BENCH_QUICK=1: fewer treelets per client;
//! ARBOR_BENCH_WHOLE=N: only the whole-scene row, N runs in turns, for experiments, followed by
//! two rows that split the gap: raw quinn sending the same bytes on as many streams as Arbor
//! uses, and Arbor's server sending to a client that only counts bytes, then the row with each
//! end on a CPU of its own; with ARBOR_BENCH_TREELET_BYTES=B as well (what the builder takes:
//! 1024..=16384, a multiple of 8), those rows fetch lion built with B-byte treelets instead of
//! 4 KiB ones: Arbor's share of a fetch is per treelet, so larger treelets, fewer and larger
//! messages, bring it closer to one raw stream;
//! ARBOR_BENCH_PROFILE=N / ARBOR_BENCH_PROFILE_RAW=N / ARBOR_BENCH_PROFILE_COUNTING=N: N
//! whole-scene fetches by Arbor's client / by one raw quinn stream of the same size / by the
//! counting client, nothing else, for a profiler or `/usr/bin/time`, served with the
//! whole-scene row's adaptive window; `WMIN` / `WMAX` change its bounds;
//! ARBOR_BENCH_PROFILE_SPLIT=N / ARBOR_BENCH_PROFILE_SPLIT_RAW=N: the same with each end on a
//! CPU of its own, in threads named `server-end` and `client-end` for `perf report --sort comm`;
//! ARBOR_BENCH_LINK=N: only the link row, N times, the first on a new path, the others returning
//! on it, which Arbor's server remembers and raw quinn does not; ARBOR_BENCH_MESSAGE_CACHE=B with
//! any of these: the server's message cache in bytes, 0 for none, so that every treelet is built
//! from the pool as for a scan many times the cache).
//! Never run in CI.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_net::{ClientConfig, ClientEvent, ServerUrl, TreeletClient, Trust};
use arbor_proto::{SceneDescription, TreeletId};
use arbor_server::daemon::start;
use arbor_server::import::{ImportOptions, import_file};
use arbor_server::octree::BuildOptions;
use arbor_server::pipeline::{SourceImport, build_into_pool};
use arbor_server::pool::Pool;
use arbor_server::service::ServeConfig;
use arbor_server::service::config::AdminTokenSource;
use arbor_tests::link::{LinkConfig, LinkEmulator};
use arbor_tests::support::data;

/// The server's per-connection window bounds used for Arbor, and the streams in flight per
/// connection of raw quinn and nginx.
const WINDOW: usize = 64;
/// Runs per row, in turns; the best counts.
const ROUNDS: usize = 3;
/// Runs of the whole-scene row, taken in turns (best of them, medians, and the median of the
/// ratios of the runs taken side by side).
const WHOLE_ROUNDS: usize = 20;

/// Lion with 1 KiB treelets and with `treelet_bytes`-byte ones (4 KiB but for the experiments of
/// `ARBOR_BENCH_TREELET_BYTES`).
fn build_pool(dir: &std::path::Path, treelet_bytes: u32) -> Vec<SceneDescription> {
    let pool = Pool::open(dir).unwrap();
    let scratch = tempfile::tempdir().unwrap();
    let source = import_file(
        &data("points/lion_takanawa.copc.laz"),
        &ImportOptions::default(),
        scratch.path(),
    )
    .unwrap();
    let mut out: Vec<SceneDescription> = Vec::new();
    for tb in [1024, treelet_bytes] {
        if let Some(same) = out.iter().find(|d| d.build.treelet_bytes == tb) {
            out.push(same.clone());
            continue;
        }
        let name = match tb % 1024 {
            0 => format!("lion-{}k", tb / 1024),
            _ => format!("lion-{tb}b"),
        };
        let opts = BuildOptions {
            treelet_bytes: tb,
            ..BuildOptions::default()
        };
        let job = SourceImport {
            source: &source,
            name: &name,
            label: "lion",
            build: &opts,
            scratch: scratch.path(),
            replace: false,
        };
        out.push(build_into_pool(&pool, &job, None).unwrap());
    }
    out
}

/// Every treelet message of `scene` with all its channels, exactly as the service sends it.
fn messages(dir: &std::path::Path, scene: &str) -> Vec<Vec<u8>> {
    let pool = Pool::open(dir).unwrap();
    let served = arbor_server::service::treelets::ServedScene::new(pool.scene(scene).unwrap());
    let channels = served.stored.description.layout.channels().to_vec();
    (0..served.treelet_count())
        .map(|i| served.message(TreeletId(i), &channels).unwrap().to_vec())
        .collect()
}

/// A client asking for every channel of the scene.
fn client(addr: SocketAddr, scene: &SceneDescription, fingerprint: &str) -> TreeletClient {
    let url = ServerUrl {
        host: addr.ip().to_string(),
        port: addr.port(),
        scene: scene.name.clone(),
    };
    let config = ClientConfig::new(url, Trust::Fingerprint(fingerprint.into()))
        .with_channels(scene.layout.channels().iter().copied());
    TreeletClient::start(config).unwrap()
}

fn serve_config(
    pool: &std::path::Path,
    data: &std::path::Path,
    window: (usize, usize),
) -> ServeConfig {
    let mut cfg = ServeConfig::new(pool);
    cfg.listen = "127.0.0.1:0".parse().unwrap();
    cfg.admin_listen = None;
    cfg.data_dir = Some(data.to_owned());
    cfg.admin_token = AdminTokenSource::Inline("bench".into());
    cfg.default_access = arbor_server::service::config::Access::Public;
    (cfg.window_min, cfg.window_max) = window;
    if let Some(bytes) = std::env::var("ARBOR_BENCH_MESSAGE_CACHE")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        cfg.message_cache_bytes = bytes;
    }
    cfg
}

async fn wait_connected(c: &mut TreeletClient) {
    loop {
        match tokio::time::timeout(Duration::from_secs(30), c.next_event()).await {
            Ok(Some(ClientEvent::Connected(_))) => return,
            Ok(Some(ClientEvent::Disconnected { reason, .. })) => panic!("disconnected: {reason}"),
            Ok(Some(_)) => {}
            Ok(None) | Err(_) => panic!("no connection"),
        }
    }
}

/// Receives `n` treelets; returns wire bytes and when the first treelet came. One deadline for
/// the whole run, not a timer per event, and the queued events taken as a viewer's session
/// takes them (`try_next_event` until none is left, waiting only then): the loop stands for a
/// consumer, and its own overhead should be small.
async fn receive(c: &mut TreeletClient, n: usize) -> (u64, Option<Instant>) {
    let mut got = 0;
    let mut bytes = 0u64;
    let mut first = None;
    let deadline = tokio::time::sleep(Duration::from_secs(120));
    tokio::pin!(deadline);
    while got < n {
        let event = match c.try_next_event() {
            Some(e) => Some(e),
            None => tokio::select! {
                biased;
                e = c.next_event() => e,
                () = &mut deadline => None,
            },
        };
        match event {
            Some(ClientEvent::Treelet(t)) => {
                got += 1;
                bytes += t.wire_bytes as u64;
                first.get_or_insert_with(Instant::now);
            }
            Some(ClientEvent::Disconnected { reason, .. }) => panic!("disconnected: {reason}"),
            Some(_) => {}
            None => panic!("stalled after {got} of {n}"),
        }
    }
    (bytes, first)
}

/// What one timed run took: from the lists (or request) to the last byte, the bytes received,
/// and the CPU the whole process (both ends: server and client share it) spent in that window.
#[derive(Clone, Copy, Debug)]
struct Timed {
    secs: f64,
    bytes: u64,
    cpu: Duration,
    /// From the lists (or request) to the first treelet (or byte) of any client, seconds.
    first: f64,
}

/// CPU time of the whole process so far, every thread (`CLOCK_PROCESS_CPUTIME_ID`).
fn process_cpu() -> Duration {
    cpu_clock(libc::CLOCK_PROCESS_CPUTIME_ID)
}

/// CPU time of the calling thread so far (`CLOCK_THREAD_CPUTIME_ID`).
fn thread_cpu() -> Duration {
    cpu_clock(libc::CLOCK_THREAD_CPUTIME_ID)
}

/// Through libc rather than rustix: rustix reads the vDSO itself, which valgrind does not map,
/// so `scripts/serve-instructions` (callgrind) crashed in the first timed fetch (rustix issue
/// 1559); glibc's `clock_gettime` works under valgrind.
fn cpu_clock(clock: libc::clockid_t) -> Duration {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid, writable timespec; the clock ids are Linux's CPU-time clocks,
    // which always exist (on failure `t` stays zero).
    unsafe { libc::clock_gettime(clock, &mut t) };
    Duration::new(
        t.tv_sec.max(0) as u64,
        t.tv_nsec.clamp(0, 999_999_999) as u32,
    )
}

/// Whole-scene fetches taken in turns: Arbor's, each followed by raw quinn's one stream of the
/// same bytes.
#[derive(Default)]
struct WholeTurns {
    /// (treelets/s, MB/s) per fetch.
    arbor: Vec<(f64, f64)>,
    /// (fetches/s, MB/s) per fetch.
    raw: Vec<(f64, f64)>,
    /// CPU of the whole process in each fetch's timed window, milliseconds.
    arbor_cpu_ms: Vec<f64>,
    raw_cpu_ms: Vec<f64>,
    /// From the list (or request) to the first treelet (or byte), milliseconds.
    arbor_first_ms: Vec<f64>,
    raw_first_ms: Vec<f64>,
    /// Bytes of one fetch.
    bytes: u64,
}

impl WholeTurns {
    fn add(&mut self, treelets: usize, arbor: &Timed, raw: &Timed) {
        self.bytes = arbor.bytes;
        self.arbor.push((
            treelets as f64 / arbor.secs,
            arbor.bytes as f64 / arbor.secs / 1e6,
        ));
        self.raw
            .push((1.0 / raw.secs, raw.bytes as f64 / raw.secs / 1e6));
        self.arbor_cpu_ms.push(arbor.cpu.as_secs_f64() * 1e3);
        self.raw_cpu_ms.push(raw.cpu.as_secs_f64() * 1e3);
        self.arbor_first_ms.push(arbor.first * 1e3);
        self.raw_first_ms.push(raw.first * 1e3);
    }

    /// Prints the medians, the ratios turn by turn, and the CPU per fetch against its wall
    /// time, as a share of the `cpus` both ends ran on (about one of them busy: the ends take
    /// turns; all of them: CPU is what a faster fetch has to save).
    fn print(&self, cpus: usize) {
        let (a_median, r_median) = (median(&self.arbor), median(&self.raw));
        let (turns, low, high) = paired(&self.arbor, &self.raw);
        println!(
            "  medians: Arbor {a_median:.1} MB/s, raw quinn one stream {r_median:.1} MB/s: {:.2}x",
            a_median / r_median
        );
        println!(
            "  turn by turn (Arbor's run over raw quinn's right after it): median {turns:.2}x \
             ({low:.2}–{high:.2}x over {} turns)",
            self.arbor.len()
        );
        let wall_ms = |mb_per_s: f64| 1e3 * self.bytes as f64 / (mb_per_s * 1e6);
        let (a_cpu, r_cpu) = (
            median_of(self.arbor_cpu_ms.clone()),
            median_of(self.raw_cpu_ms.clone()),
        );
        let (a_wall, r_wall) = (wall_ms(a_median), wall_ms(r_median));
        let share = |cpu: f64, wall: f64| 100.0 * cpu / (cpus as f64 * wall);
        println!(
            "  CPU of both ends per fetch, medians: Arbor {a_cpu:.2} ms in {a_wall:.2} ms of wall \
             time ({:.0} % of {cpus} CPUs), raw quinn one stream {r_cpu:.2} ms in {r_wall:.2} ms \
             ({:.0} %)",
            share(a_cpu, a_wall),
            share(r_cpu, r_wall),
        );
        println!(
            "  first arrival, medians: Arbor's first treelet {:.2} ms after the list, raw quinn's \
             first bytes {:.2} ms after the request",
            median_of(self.arbor_first_ms.clone()),
            median_of(self.raw_first_ms.clone()),
        );
    }
}

/// `clients` concurrent clients each fetching the first `per_client` treelets.
async fn arbor_run(
    addr: SocketAddr,
    fp: &str,
    scene: &SceneDescription,
    clients: usize,
    per_client: usize,
) -> Timed {
    let mut cs = Vec::new();
    for _ in 0..clients {
        let mut c = client(addr, scene, fp);
        wait_connected(&mut c).await;
        cs.push(c);
    }
    let list: Vec<(TreeletId, f32)> = (0..per_client as u32)
        .map(|i| (TreeletId(i), (per_client as u32 - i) as f32))
        .collect();
    // The clock runs from the lists to the last treelet; connecting and closing are outside
    // it, for every row alike.
    let t = Instant::now();
    let cpu = process_cpu();
    let mut tasks = Vec::new();
    for mut c in cs {
        c.request(list.clone()).unwrap();
        tasks.push(tokio::spawn(async move {
            let (b, first) = receive(&mut c, per_client).await;
            (b, first, Instant::now(), c)
        }));
    }
    let (mut bytes, mut last, mut done) = (0, t, Vec::new());
    let mut first: Option<Instant> = None;
    for task in tasks {
        let (b, f, at, c) = task.await.unwrap();
        bytes += b;
        last = last.max(at);
        first = earliest(first, f);
        done.push(c);
    }
    let cpu = process_cpu().saturating_sub(cpu);
    for c in done {
        c.close().await;
    }
    Timed {
        secs: (last - t).as_secs_f64(),
        bytes,
        cpu,
        first: since(t, first),
    }
}

/// The earlier of two arrivals, either of which may not have happened.
fn earliest(a: Option<Instant>, b: Option<Instant>) -> Option<Instant> {
    a.into_iter().chain(b).min()
}

/// Seconds from `t` to `first` (0 if nothing came).
fn since(t: Instant, first: Option<Instant>) -> f64 {
    first.map_or(0.0, |f| (f - t).as_secs_f64())
}

/// The first arrival among a fetch's stream readers, each of which sets it if it is still unset.
type FirstArrival = Arc<std::sync::OnceLock<Instant>>;

mod raw {
    //! A raw quinn server and client: per message one server-opened unidirectional stream.
    use super::*;
    use quinn::crypto::rustls::{QuicClientConfig, QuicServerConfig};

    pub struct Raw {
        pub addr: SocketAddr,
        pub client_config: quinn::ClientConfig,
        _endpoint: quinn::Endpoint,
    }

    /// Starts a server that, per connection, reads one request `(count u32, size u32, window u32)`
    /// on a bidi stream and answers with `count` uni streams of `size` bytes, `window` at a time.
    pub fn start() -> Raw {
        let _ = rustls::crypto::ring::default_provider().install_default();
        let cert = rcgen::generate_simple_self_signed(vec!["localhost".into()]).unwrap();
        let der = cert.cert.der().clone();
        let key = rustls::pki_types::PrivatePkcs8KeyDer::from(cert.signing_key.serialize_der());
        let mut tls = rustls::ServerConfig::builder()
            .with_no_client_auth()
            .with_single_cert(vec![der.clone()], key.into())
            .unwrap();
        tls.alpn_protocols = vec![b"raw".to_vec()];
        let mut sc =
            quinn::ServerConfig::with_crypto(Arc::new(QuicServerConfig::try_from(tls).unwrap()));
        // Arbor's transport settings, so that the rows compare what is served and how, not
        // the tuning: the server's initial window and ACK-frequency request, the client's
        // windows (below).
        let mut tc = quinn::TransportConfig::default();
        tc.max_concurrent_uni_streams(1024u32.into());
        let mut cubic = quinn::congestion::CubicConfig::default();
        cubic.initial_window(arbor_server::service::config::DEFAULT_INITIAL_WINDOW);
        tc.congestion_controller_factory(Arc::new(cubic));
        let mut acks = quinn::AckFrequencyConfig::default();
        acks.max_ack_delay(Some(arbor_server::service::server::ACK_DELAY));
        tc.ack_frequency_config(Some(acks));
        sc.transport_config(Arc::new(tc));
        let endpoint = quinn::Endpoint::server(sc, "127.0.0.1:0".parse().unwrap()).unwrap();
        let addr = endpoint.local_addr().unwrap();
        let ep = endpoint.clone();
        // Each size's payload made once and kept, as Arbor keeps its built messages: a fetch
        // sends bytes already in memory, without filling a new buffer in its timed window.
        let payloads: Arc<std::sync::Mutex<std::collections::HashMap<usize, bytes::Bytes>>> =
            Arc::default();
        tokio::spawn(async move {
            while let Some(inc) = ep.accept().await {
                let payloads = payloads.clone();
                tokio::spawn(async move {
                    let Ok(conn) = inc.await else { return };
                    let Ok((_s, mut r)) = conn.accept_bi().await else {
                        return;
                    };
                    let mut req = [0u8; 12];
                    if r.read_exact(&mut req).await.is_err() {
                        return;
                    }
                    let count = u32::from_le_bytes(req[0..4].try_into().unwrap());
                    let size = u32::from_le_bytes(req[4..8].try_into().unwrap()) as usize;
                    let window = u32::from_le_bytes(req[8..12].try_into().unwrap()) as usize;
                    let payload = payloads
                        .lock()
                        .unwrap()
                        .entry(size)
                        .or_insert_with(|| bytes::Bytes::from(vec![7u8; size]))
                        .clone();
                    let sem = Arc::new(tokio::sync::Semaphore::new(window));
                    for _ in 0..count {
                        let permit = sem.clone().acquire_owned().await.unwrap();
                        let (conn, payload) = (conn.clone(), payload.clone());
                        tokio::spawn(async move {
                            if let Ok(mut s) = conn.open_uni().await {
                                // Handed over as it is, without a copy (Arbor writes its
                                // batches the same way).
                                let _ = s.write_chunk(payload).await;
                                let _ = s.finish();
                                let _ = s.stopped().await;
                            }
                            drop(permit);
                        });
                    }
                    conn.closed().await;
                });
            }
        });
        let mut roots = rustls::RootCertStore::empty();
        roots.add(der).unwrap();
        let mut ctls = rustls::ClientConfig::builder()
            .with_root_certificates(roots)
            .with_no_client_auth();
        ctls.alpn_protocols = vec![b"raw".to_vec()];
        let mut cc = quinn::ClientConfig::new(Arc::new(QuicClientConfig::try_from(ctls).unwrap()));
        let mut tc = arbor_client_net::transport::transport_config(
            arbor_client_net::transport::IDLE_TIMEOUT,
        );
        tc.max_concurrent_uni_streams(1024u32.into());
        cc.transport_config(Arc::new(tc));
        Raw {
            addr,
            client_config: cc,
            _endpoint: endpoint,
        }
    }

    /// A connected raw client: its endpoint and connection.
    type Connected = (quinn::Endpoint, quinn::Connection);

    async fn connect(raw_addr: SocketAddr, cc: quinn::ClientConfig) -> Connected {
        // The same UDP socket as Arbor's client (its larger receive buffer included).
        let mut ep =
            arbor_client_net::transport::client_endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
        ep.set_default_client_config(cc);
        let conn = ep.connect(raw_addr, "localhost").unwrap().await.unwrap();
        (ep, conn)
    }

    /// One connected client fetching `count` messages of `size` bytes; returns bytes received,
    /// when the first bytes arrived and when the last did.
    async fn fetch(
        conn: quinn::Connection,
        count: u32,
        size: u32,
        window: u32,
    ) -> (u64, Option<Instant>, Instant) {
        let (mut s, _r) = conn.open_bi().await.unwrap();
        let mut req = Vec::new();
        for v in [count, size, window] {
            req.extend_from_slice(&v.to_le_bytes());
        }
        s.write_all(&req).await.unwrap();
        let mut bytes = 0u64;
        let mut readers = tokio::task::JoinSet::new();
        let first = FirstArrival::default();
        for _ in 0..count {
            let mut r = conn.accept_uni().await.unwrap();
            let first = first.clone();
            // Chunks as quinn received them, counted and dropped: no copy, no growing buffer
            // (a 64 MiB `read_to_end` spent its time in reallocation and fresh pages).
            readers.spawn(async move {
                let mut n = 0u64;
                while let Some(c) = r.read_chunk(usize::MAX, true).await.unwrap() {
                    first.get_or_init(Instant::now);
                    n += c.bytes.len() as u64;
                }
                n
            });
            while let Some(Ok(b)) = readers.try_join_next() {
                bytes += b;
            }
        }
        while let Some(b) = readers.join_next().await {
            bytes += b.unwrap();
        }
        (bytes, first.get().copied(), Instant::now())
    }

    /// `clients` concurrent clients, connected before the clock starts and closed after it
    /// stops (like Arbor's rows).
    pub async fn run(raw: &Raw, clients: usize, count: u32, size: u32, window: u32) -> Timed {
        run_via(raw, raw.addr, clients, count, size, window).await
    }

    /// [`run`] with the clients connecting to `addr`, a link emulator in front of the server.
    pub async fn run_via(
        raw: &Raw,
        addr: SocketAddr,
        clients: usize,
        count: u32,
        size: u32,
        window: u32,
    ) -> Timed {
        let mut connected = Vec::new();
        for _ in 0..clients {
            connected.push(connect(addr, raw.client_config.clone()).await);
        }
        let t = Instant::now();
        let cpu = process_cpu();
        let tasks: Vec<_> = connected
            .iter()
            .map(|(_, conn)| tokio::spawn(fetch(conn.clone(), count, size, window)))
            .collect();
        let (mut bytes, mut last) = (0, t);
        let mut first: Option<Instant> = None;
        for task in tasks {
            let (b, f, at) = task.await.unwrap();
            bytes += b;
            last = last.max(at);
            first = earliest(first, f);
        }
        let cpu = process_cpu().saturating_sub(cpu);
        for (ep, conn) in connected {
            conn.close(0u32.into(), b"done");
            ep.wait_idle().await;
        }
        Timed {
            secs: (last - t).as_secs_f64(),
            bytes,
            cpu,
            first: since(t, first),
        }
    }
}

mod counting {
    //! The least client Arbor's protocol allows, to tell the server's share of a whole-scene
    //! fetch from the client's: `Hello` and one list on the control stream, then every treelet
    //! stream's chunks counted and dropped (no parsing, no events, no budget).
    use super::*;
    use arbor_proto::frame::encode;
    use arbor_proto::wire::{Frame, PROTOCOL_VERSION};

    /// Fetches the first `count` treelets of `scene` until `bytes` have arrived on treelet
    /// streams, timed from the list to the last byte.
    pub async fn run(
        addr: SocketAddr,
        fingerprint: &str,
        scene: &SceneDescription,
        count: u32,
        bytes: u64,
    ) -> Timed {
        let trust = Trust::Fingerprint(fingerprint.into());
        // One list, sent whole at once, as the client's list window lets a list of any size out.
        let config = arbor_client_net::transport::quinn_client_config(
            &trust,
            Duration::from_secs(30),
            16 << 20,
        )
        .unwrap();
        let ep =
            arbor_client_net::transport::client_endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
        let conn = ep
            .connect_with(config, addr, &addr.ip().to_string())
            .unwrap()
            .await
            .unwrap();
        let (mut send, mut recv) = conn.open_bi().await.unwrap();
        let hello = encode(&Frame::Hello {
            version: PROTOCOL_VERSION,
            scene: scene.name.clone(),
            channels: scene.layout.channels().to_vec(),
            token: String::new(),
            flags: 0,
            view: None,
        })
        .unwrap();
        send.write_all(&hello).await.unwrap();
        // SceneInfo (and whatever follows) is read and dropped; the root arrives on a treelet
        // stream like the rest.
        tokio::spawn(
            async move { while let Ok(Some(_)) = recv.read_chunk(usize::MAX, true).await {} },
        );
        let list = encode(&Frame::RequestList {
            seq: 1,
            items: (0..count)
                .map(|i| (TreeletId(i), (count - i) as f32))
                .collect(),
        })
        .unwrap();
        let t = Instant::now();
        let cpu = process_cpu();
        send.write_all(&list).await.unwrap();
        // One shared counter; the last byte wakes the caller.
        let got = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let done = Arc::new(tokio::sync::Notify::new());
        let first = FirstArrival::default();
        let accept = {
            let (conn, got, done, first) = (conn.clone(), got.clone(), done.clone(), first.clone());
            tokio::spawn(async move {
                while let Ok(mut r) = conn.accept_uni().await {
                    let (got, done, first) = (got.clone(), done.clone(), first.clone());
                    tokio::spawn(async move {
                        while let Ok(Some(c)) = r.read_chunk(usize::MAX, false).await {
                            first.get_or_init(Instant::now);
                            let n = c.bytes.len() as u64;
                            let before = got.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
                            if before < bytes && before + n >= bytes {
                                done.notify_one();
                            }
                        }
                    });
                }
            })
        };
        if tokio::time::timeout(Duration::from_secs(30), done.notified())
            .await
            .is_err()
        {
            panic!(
                "stalled after {} of {bytes} bytes",
                got.load(std::sync::atomic::Ordering::Relaxed)
            );
        }
        let got = got.load(std::sync::atomic::Ordering::Relaxed);
        let secs = t.elapsed().as_secs_f64();
        let cpu = process_cpu().saturating_sub(cpu);
        accept.abort();
        conn.close(0u32.into(), b"done");
        ep.wait_idle().await;
        Timed {
            secs,
            bytes: got,
            cpu,
            first: since(t, first.get().copied()),
        }
    }
}

mod nginx {
    //! nginx over HTTP/2 + TLS as the peers' static tile server, loaded by h2load.
    use std::io::Write as _;
    use std::process::{Child, Command, Stdio};

    pub struct Nginx {
        child: Child,
        port: u16,
        dir: tempfile::TempDir,
        /// Bytes of each file, in URI order.
        sizes: Vec<u64>,
    }

    impl Drop for Nginx {
        /// SIGTERM to the master, which stops its workers (SIGKILL would leave them running,
        /// orphaned); SIGKILL only if it has not exited within two seconds.
        fn drop(&mut self) {
            arbor_tests::support::terminate(&mut self.child, std::time::Duration::from_secs(2));
        }
    }

    fn installed(tool: &str) -> bool {
        Command::new(tool)
            .arg("-v")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok()
    }

    /// Serves `files` as `/t/{index}` over HTTP/2 + TLS on a free loopback port; `None` (after
    /// saying so loudly) when nginx or h2load is missing or nginx does not come up.
    pub fn start(files: &[Vec<u8>]) -> Option<Nginx> {
        if !installed("nginx") || !installed("h2load") {
            eprintln!(
                "\n*** nginx HTTP/2 row SKIPPED: nginx or h2load is not installed \
                 (apt-get install nginx nghttp2-client) ***\n"
            );
            return None;
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path();
        for sub in ["www/t", "logs", "tmp"] {
            std::fs::create_dir_all(p.join(sub)).unwrap();
        }
        for (i, f) in files.iter().enumerate() {
            std::fs::write(p.join(format!("www/t/{i}")), f).unwrap();
        }
        // nginx's workers drop to an unprivileged user when started as root: let it read.
        let _ = Command::new("chmod").args(["-R", "a+rX"]).arg(p).status();
        let cert = rcgen::generate_simple_self_signed(vec!["localhost".into()]).unwrap();
        std::fs::write(p.join("cert.pem"), cert.cert.pem()).unwrap();
        std::fs::write(p.join("key.pem"), cert.signing_key.serialize_pem()).unwrap();
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        // The peers' configuration (../shared/peers/nginx-h2.conf), TLS server only.
        let prefix = p.display();
        let conf = format!(
            "daemon off; master_process on; worker_processes 1; pid {prefix}/nginx.pid;\n\
             error_log {prefix}/logs/error.log warn;\n\
             events {{ worker_connections 1024; }}\n\
             http {{ access_log off; client_body_temp_path {prefix}/tmp/body; \
             proxy_temp_path {prefix}/tmp/proxy; fastcgi_temp_path {prefix}/tmp/fastcgi; \
             uwsgi_temp_path {prefix}/tmp/uwsgi; scgi_temp_path {prefix}/tmp/scgi;\n\
             sendfile on; tcp_nopush on; tcp_nodelay on; keepalive_requests 1000000; \
             keepalive_timeout 65; open_file_cache max=20000 inactive=60s; \
             default_type application/octet-stream;\n\
             server {{ listen 127.0.0.1:{port} ssl http2; ssl_certificate {prefix}/cert.pem; \
             ssl_certificate_key {prefix}/key.pem; root {prefix}/www; }} }}\n"
        );
        std::fs::File::create(p.join("nginx.conf"))
            .unwrap()
            .write_all(conf.as_bytes())
            .unwrap();
        let child = Command::new("nginx")
            .arg("-c")
            .arg(p.join("nginx.conf"))
            .arg("-p")
            .arg(p)
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let nginx = Nginx {
            child,
            port,
            sizes: files.iter().map(|f| f.len() as u64).collect(),
            dir,
        };
        for _ in 0..100 {
            if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
                return Some(nginx);
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        eprintln!("\n*** nginx HTTP/2 row SKIPPED: nginx did not start on port {port} ***\n");
        None
    }

    /// h2load with `clients` connections, `streams` requests in flight on each, for 2 s after
    /// a 0.3 s warm-up (handshakes left out, like Arbor's rows), every connection fetching files
    /// `0..per_client` in order, round and round; (files/s, MB/s) or `None` if a request failed.
    pub fn run(
        nginx: &Nginx,
        clients: usize,
        per_client: usize,
        streams: usize,
    ) -> Option<(f64, f64)> {
        let uris = nginx.dir.path().join(format!("uris-{per_client}"));
        let mut text = String::new();
        for i in 0..per_client {
            if i == 0 {
                text.push_str(&format!("https://127.0.0.1:{}/t/0\n", nginx.port));
            } else {
                text.push_str(&format!("/t/{i}\n"));
            }
        }
        std::fs::write(&uris, text).unwrap();
        let out = Command::new("h2load")
            .args(["-c", &clients.to_string(), "-m", &streams.to_string()])
            .args(["-D", "2s", "--warm-up-time", "300ms", "-i"])
            .arg(&uris)
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        let rate = stdout
            .lines()
            .find_map(|l| l.strip_prefix("finished in "))
            .and_then(|l| l.split(", ").nth(1))
            .and_then(|r| r.trim_end_matches(" req/s").parse::<f64>().ok());
        let failed = stdout
            .lines()
            .find(|l| l.starts_with("requests:"))
            .is_none_or(|l| !l.contains(" 0 failed, 0 errored"));
        match rate {
            Some(r) if !failed => {
                let mean = nginx.sizes[..per_client].iter().sum::<u64>() as f64 / per_client as f64;
                Some((r, r * mean / 1e6))
            }
            _ => {
                eprintln!(
                    "*** h2load failed:\n{stdout}{}",
                    String::from_utf8_lossy(&out.stderr)
                );
                None
            }
        }
    }
}

/// Where a treelet's time goes, each part measured alone on this machine: the pool read and
/// message assembly (a cache miss), a cached message, the scheduler's work for one treelet
/// (list, transmit, sent, delivered), against the whole per-treelet time of the rows above.
fn cost_breakdown(dir: &std::path::Path, scene: &str) {
    use arbor_server::service::schedule::{
        ConnectionConfig, ConnectionId, Scheduler, SchedulerConfig,
    };
    // The server just stopped: sled's flusher lets go of the directory lock a moment later.
    let t0 = Instant::now();
    let pool = loop {
        match Pool::open(dir) {
            Ok(p) => break p,
            Err(e) if t0.elapsed() < Duration::from_secs(10) => {
                let _ = e;
                std::thread::sleep(Duration::from_millis(50));
            }
            Err(e) => panic!("opening the pool: {e}"),
        }
    };
    let stored = pool.scene(scene).unwrap();
    let count = stored.description.treelet_count;
    let channels = stored.description.layout.channels().to_vec();
    let cold = arbor_server::service::state::ServiceCaches {
        messages: Arc::new(arbor_server::service::treelets::MessageCache::new(0)),
        shapes: Arc::new(arbor_server::service::shapes::ShapeCache::for_shapes(0)),
        cut_nodes: Arc::new(arbor_server::service::visibility::NodeCache::for_nodes(0)),
        fine_cuts: Arc::default(),
    };
    let served = arbor_server::service::treelets::ServedScene::with_caches(stored.clone(), &cold);
    let t = Instant::now();
    for i in 0..count {
        std::hint::black_box(served.message(TreeletId(i), &channels).unwrap());
    }
    let miss = t.elapsed().as_secs_f64() / f64::from(count);
    let warm = arbor_server::service::treelets::ServedScene::new(stored);
    for i in 0..count {
        warm.message(TreeletId(i), &channels).unwrap();
    }
    let t = Instant::now();
    for i in 0..count {
        std::hint::black_box(warm.message(TreeletId(i), &channels).unwrap());
    }
    let hit = t.elapsed().as_secs_f64() / f64::from(count);
    let mut sched = Scheduler::new(SchedulerConfig {
        max_in_flight: 1 << 20,
    });
    let c = ConnectionId(1);
    sched
        .add_connection(
            c,
            ConnectionConfig {
                window: WINDOW,
                max_queue: 1 << 16,
                redelivery_guard: Duration::ZERO,
                ..ConnectionConfig::default()
            },
        )
        .unwrap();
    let list: Vec<(TreeletId, f32)> = (0..count).map(|i| (TreeletId(i), i as f32)).collect();
    let t = Instant::now();
    let now = Instant::now();
    sched.handle_request_list(c, 1, list, now).unwrap();
    // As the service does: a batch per stream, sent and delivered together.
    let mut done = 0u32;
    let mut batch = Vec::new();
    while done < count {
        let mut started = Vec::new();
        while sched.poll_batch(now, &mut batch).is_some() {
            started.push(std::mem::take(&mut batch));
        }
        for batch in started {
            for &t in &batch {
                sched.handle_sent(c, t, now);
            }
            done += sched.handle_delivered_all(c, &batch, now) as u32;
        }
    }
    let scheduling = t.elapsed().as_secs_f64() / f64::from(count);
    println!(
        "per treelet ({scene}, alone): pool read + assembly (cache miss) {:.2} µs, cached message \
         {:.2} µs, scheduler (list, transmit, sent, delivered) {:.2} µs",
        miss * 1e6,
        hit * 1e6,
        scheduling * 1e6
    );
}

/// The daemon's adaptive window bounds (`WMIN` / `WMAX` override them, for experiments): what
/// the whole-scene row and the link row serve with.
fn adaptive_window() -> (usize, usize) {
    let defaults = ServeConfig::new(std::path::Path::new("."));
    let var = |name: &str, default: usize| {
        std::env::var(name)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    (
        var("WMIN", defaults.window_min),
        var("WMAX", defaults.window_max),
    )
}

/// The median MB/s of some runs.
fn median(runs: &[(f64, f64)]) -> f64 {
    median_of(runs.iter().map(|r| r.1).collect())
}

fn median_of(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// The median, lowest and highest ratio of MB/s of runs `a[i]` and `b[i]`, taken one right after
/// the other: a slow spell of the machine slows both runs of a turn, so the ratios of turns
/// spread less than the ratio of two medians.
fn paired(a: &[(f64, f64)], b: &[(f64, f64)]) -> (f64, f64, f64) {
    let ratios: Vec<f64> = a.iter().zip(b).map(|(a, b)| a.1 / b.1).collect();
    let low = ratios.iter().copied().fold(f64::INFINITY, f64::min);
    let high = ratios.iter().copied().fold(0.0, f64::max);
    (median_of(ratios), low, high)
}

/// The best of `ROUNDS` (rate, MB/s) pairs by rate.
fn best(runs: &[(f64, f64)]) -> (f64, f64) {
    runs.iter()
        .copied()
        .fold((0.0, 0.0), |a, b| if b.0 > a.0 { b } else { a })
}

#[tokio::main(flavor = "multi_thread")]
async fn main() {
    let quick = std::env::var("ARBOR_BENCH_QUICK").is_ok();
    let whole_only: Option<usize> = std::env::var("ARBOR_BENCH_WHOLE")
        .ok()
        .and_then(|n| n.parse().ok());
    let pool_dir = tempfile::tempdir().unwrap();
    let data_dir = tempfile::tempdir().unwrap();
    // Only the whole-scene rows take another treelet size: the others compare lion-4k with
    // nginx serving the same bytes as files.
    let treelet_bytes = match std::env::var("ARBOR_BENCH_TREELET_BYTES") {
        Ok(b) if whole_only.is_some() => b
            .parse()
            .expect("ARBOR_BENCH_TREELET_BYTES is a number of bytes"),
        Ok(_) => {
            panic!("ARBOR_BENCH_TREELET_BYTES is for the whole-scene rows: set ARBOR_BENCH_WHOLE")
        }
        Err(_) => 4096,
    };
    let dir = pool_dir.path().to_owned();
    let (scenes, files) = tokio::task::spawn_blocking(move || {
        let scenes = build_pool(&dir, treelet_bytes);
        let files = messages(&dir, &scenes[1].name);
        (scenes, files)
    })
    .await
    .unwrap();
    // Each end on a CPU of its own, for a profiler: before any other server holds the pool.
    let split_profile = [
        ("ARBOR_BENCH_PROFILE_SPLIT", SplitProfile::Arbor),
        (
            "ARBOR_BENCH_PROFILE_SPLIT_RAW",
            SplitProfile::Raw(files.iter().map(|f| f.len() as u32).sum()),
        ),
    ]
    .into_iter()
    .find_map(|(var, p)| Some((std::env::var(var).ok()?, p)));
    if let Some((runs, p)) = split_profile {
        let runs = runs.parse().unwrap_or(300);
        split_ends(pool_dir.path(), data_dir.path(), &scenes[1], runs, Some(p)).await;
        return;
    }
    // Loopback comparison: Arbor's window fixed to raw quinn's.
    // ARBOR_BENCH_WINDOW=MIN,MAX: other window bounds for Arbor (experiments).
    let window = std::env::var("ARBOR_BENCH_WINDOW")
        .ok()
        .and_then(|w| {
            let (a, b) = w.split_once(',')?;
            Some((a.parse().ok()?, b.parse().ok()?))
        })
        .unwrap_or((WINDOW, WINDOW));
    // The profiling modes stand for the whole-scene row: the daemon's adaptive window, not the
    // fixed one of the loopback comparison (with a window of 64 a whole-scene fetch makes
    // about 1.6× the sendmsg and 5× the recvmmsg calls of the same fetch with the row's window).
    let profiling = [
        "ARBOR_BENCH_PROFILE",
        "ARBOR_BENCH_PROFILE_COUNTING",
        "ARBOR_BENCH_PROFILE_RAW",
        "ARBOR_BENCH_LINK",
    ]
    .iter()
    .any(|v| std::env::var_os(v).is_some());
    let window = if profiling { adaptive_window() } else { window };
    let server = start(serve_config(pool_dir.path(), data_dir.path(), window))
        .await
        .unwrap();
    let fp = server.fingerprint.clone();
    let addr = server.quic_addr;
    if let Ok(runs) = std::env::var("ARBOR_BENCH_PROFILE") {
        // One client fetching lion-4k again and again, for a profiler.
        let n = scenes[1].treelet_count as usize;
        for _ in 0..runs.parse().unwrap_or(300) {
            let run = arbor_run(addr, &fp, &scenes[1], 1, n).await;
            println!("{:.0} treelets/s", n as f64 / run.secs);
        }
        return;
    }
    if let Ok(runs) = std::env::var("ARBOR_BENCH_PROFILE_COUNTING") {
        // The same fetches by a client that only counts bytes: the server's share.
        let n = scenes[1].treelet_count;
        let bytes: u64 = files.iter().map(|f| f.len() as u64).sum();
        for _ in 0..runs.parse().unwrap_or(300) {
            let run = counting::run(addr, &fp, &scenes[1], n, bytes).await;
            println!("{:.1} MB/s", run.bytes as f64 / run.secs / 1e6);
        }
        return;
    }
    let raw = raw::start();
    if let Ok(runs) = std::env::var("ARBOR_BENCH_PROFILE_RAW") {
        // One raw stream of lion-4k's bytes again and again: the profiler's reference.
        for _ in 0..runs.parse().unwrap_or(300) {
            let run = raw::run(&raw, 1, 1, 2_600_000, 1).await;
            println!("{:.0} MB/s", run.bytes as f64 / run.secs / 1e6);
        }
        return;
    }
    if let Ok(turns) = std::env::var("ARBOR_BENCH_LINK") {
        // The first turn is a new path to the server; the later ones return on it, and
        // Arbor's server remembers it (careful resume, `path_memory`), raw quinn does not.
        for _ in 0..turns.parse().unwrap_or(5) {
            link_row(addr, &fp, &scenes[1], &raw).await;
        }
        return;
    }
    let nginx = whole_only.is_none().then(|| nginx::start(&files)).flatten();

    println!(
        "Arbor serving benchmark (loopback, release, {} cores; all channels; {} streams or \
         treelets in flight per connection for Arbor, nginx and raw quinn; best of {ROUNDS} runs \
         in turns)",
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        WINDOW
    );
    println!(
        "{:<8} {:>7} {:>9} {:>7} | {:>10} {:>7} | {:>11} {:>7} | {:>11} {:>7} | {:>7} {:>7}",
        "scene",
        "clients",
        "treelets",
        "mean B",
        "Arbor /s",
        "MB/s",
        "nginx h2 /s",
        "MB/s",
        "raw quic /s",
        "MB/s",
        "÷nginx",
        "÷raw"
    );
    for d in scenes.iter().filter(|_| whole_only.is_none()) {
        for clients in [1usize, 8, 64] {
            let per_client = if quick {
                200
            } else if clients == 64 {
                500
            } else {
                2000
            }
            .min(d.treelet_count as usize);
            let n = (clients * per_client) as f64;
            let (mut a, mut g, mut r) = (Vec::new(), Vec::new(), Vec::new());
            let mut mean = 0;
            for _ in 0..ROUNDS {
                let Timed { secs, bytes, .. } = arbor_run(addr, &fp, d, clients, per_client).await;
                mean = (bytes as f64 / n).round() as u32;
                a.push((n / secs, bytes as f64 / secs / 1e6));
                if let Some(ng) = nginx.as_ref().filter(|_| d.name == "lion-4k") {
                    let (clients, per_client) = (clients, per_client);
                    if let Some(x) =
                        tokio::task::block_in_place(|| nginx::run(ng, clients, per_client, WINDOW))
                    {
                        g.push(x);
                    }
                }
                let Timed {
                    secs: rsecs,
                    bytes: rbytes,
                    ..
                } = raw::run(&raw, clients, per_client as u32, mean, WINDOW as u32).await;
                r.push((n / rsecs, rbytes as f64 / rsecs / 1e6));
            }
            let (a, r) = (best(&a), best(&r));
            let (ng, ng_ratio) = if g.is_empty() {
                ("-".to_owned(), "-".to_owned())
            } else {
                let g = best(&g);
                (
                    format!("{:>11.0} {:>7.1}", g.0, g.1),
                    format!("{:.2}", a.0 / g.0),
                )
            };
            println!(
                "{:<8} {:>7} {:>9} {:>7} | {:>10.0} {:>7.1} | {:>19} | {:>11.0} {:>7.1} | {:>7} {:>7.2}",
                d.name,
                clients,
                clients * per_client,
                mean,
                a.0,
                a.1,
                ng,
                r.0,
                r.1,
                ng_ratio,
                a.0 / r.0
            );
        }
    }
    let Timed {
        secs: bsecs,
        bytes: bbytes,
        ..
    } = raw::run(&raw, 1, 1, 64 << 20, 1).await;
    let bulk = bbytes as f64 / bsecs / 1e6;
    println!("raw quinn bulk, one 64 MiB stream: {bulk:.1} MB/s");
    drop(nginx);
    server.shutdown().await;

    // Over the emulated WAN: the top 1,000 of a list of all treelets, random priorities; the
    // window adapts to RTT × bandwidth within the daemon's bounds ([`adaptive_window`]).
    let server = start(serve_config(
        pool_dir.path(),
        data_dir.path(),
        adaptive_window(),
    ))
    .await
    .unwrap();
    let addr = server.quic_addr;
    // One client fetching the whole 4 KiB scene from a server with the default window against one
    // raw quinn stream of the same bytes.
    let d = &scenes[1];
    let whole = d.treelet_count as usize;
    let mut turns = WholeTurns::default();
    // CPU of the whole process per fetch of the counting client, and its first bytes after the
    // list, milliseconds.
    let (mut c_cpu, mut c_first) = (Vec::new(), Vec::new());
    // With ARBOR_BENCH_WHOLE, in the same turns: raw quinn on as many streams as Arbor's
    // batches, and Arbor's server sending to a client that only counts bytes.
    let (mut split, mut counted) = (Vec::new(), Vec::new());
    // Streams Arbor's server wrote per fetch (its batches), for the raw row of as many.
    let mut arbor_streams = Vec::new();
    let streams_written = || {
        server
            .state
            .metrics
            .treelet_streams
            .load(std::sync::atomic::Ordering::Relaxed)
    };
    // A whole scene is a few megabytes, tens of milliseconds: more runs than the rows above.
    for _ in 0..whole_only.unwrap_or(WHOLE_ROUNDS) {
        let before = streams_written();
        let run = arbor_run(addr, &fp, d, 1, whole).await;
        let streams = (streams_written() - before).max(1) as u32;
        let bytes = run.bytes;
        let raw_run = raw::run(&raw, 1, 1, bytes as u32, 1).await;
        turns.add(whole, &run, &raw_run);
        if whole_only.is_some() {
            arbor_streams.push(f64::from(streams));
            let size = (bytes / u64::from(streams)) as u32;
            let s = raw::run(&raw, 1, streams, size, streams).await;
            split.push((1.0 / s.secs, s.bytes as f64 / s.secs / 1e6));
            let c = counting::run(addr, &fp, d, whole as u32, bytes).await;
            counted.push((1.0 / c.secs, c.bytes as f64 / c.secs / 1e6));
            c_cpu.push(c.cpu.as_secs_f64() * 1e3);
            c_first.push(c.first * 1e3);
        }
    }
    let rounds = turns.arbor.len();
    let (a_best, r_best) = (best(&turns.arbor), best(&turns.raw));
    // No ratio of the best runs: now and then one of raw quinn's runs has both ends running at
    // once (up to 1.6 times its median), and a ratio against it says nothing of Arbor.
    println!(
        "whole {} by one client ({} treelets, {:.1} MB), both ends sharing the CPUs: best runs \
         Arbor {:.1}, raw quinn one stream of the same bytes {:.1} MB/s; Arbor's median over raw \
         quinn's bulk rate above: {:.2}x",
        d.name,
        whole,
        turns.bytes as f64 / 1e6,
        a_best.1,
        r_best.1,
        median(&turns.arbor) / bulk
    );
    // Server and client share the cores here.
    turns.print(std::thread::available_parallelism().map_or(1, |n| n.get()));
    if whole_only.is_some() {
        println!(
            "  medians: raw quinn, the same bytes on as many streams at once as Arbor's server \
             wrote ({:.0}): {:.1} MB/s",
            median_of(arbor_streams),
            median(&split)
        );
        println!(
            "  medians: Arbor's server to a client that only counts bytes {:.1} MB/s: {:.2}x of \
             raw quinn's one stream",
            median(&counted),
            median(&counted) / median(&turns.raw)
        );
        println!(
            "  turn by turn, the counting client over raw quinn: median {:.2}x; its CPU of both \
             ends per fetch {:.2} ms, its first bytes {:.2} ms after the list (medians)",
            paired(&counted, &turns.raw).0,
            median_of(c_cpu),
            median_of(c_first)
        );
        server.shutdown().await;
        split_ends(pool_dir.path(), data_dir.path(), d, rounds, None).await;
        return;
    }
    link_row(addr, &fp, d, &raw).await;
    server.shutdown().await;
    split_ends(pool_dir.path(), data_dir.path(), d, rounds, None).await;
    cost_breakdown(pool_dir.path(), "lion-4k");
    cost_breakdown(pool_dir.path(), "lion-1k");
}

/// Over the link emulator (25 ms each way, 100 Mbit/s): one new client's list of every treelet
/// of `d` (random priorities) until its top 1,000 and all have arrived, then raw quinn's one
/// stream of the same bytes over an emulator of the same link.
async fn link_row(addr: SocketAddr, fp: &str, d: &SceneDescription, raw: &raw::Raw) {
    let link = LinkEmulator::start(
        addr,
        LinkConfig::wan(Duration::from_millis(25), 100_000_000 / 8),
    )
    .await
    .unwrap();
    let mut c = client(link.local_addr(), d, fp);
    let t_connect = Instant::now();
    wait_connected(&mut c).await;
    let connect = t_connect.elapsed();
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut list: Vec<(TreeletId, f32)> = (0..d.treelet_count)
        .map(|i| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (TreeletId(i), (state % 1_000_000) as f32)
        })
        .collect();
    list.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let top: std::collections::HashSet<TreeletId> = list.iter().take(1000).map(|x| x.0).collect();
    let t = Instant::now();
    c.request(list.clone()).unwrap();
    let (mut first, mut top_done, mut got, mut bytes) = (None, None, 0usize, 0u64);
    let mut top_left = top.len();
    while got < list.len() {
        match tokio::time::timeout(Duration::from_secs(120), c.next_event()).await {
            Ok(Some(ClientEvent::Treelet(tr))) => {
                got += 1;
                bytes += tr.wire_bytes as u64;
                first.get_or_insert(t.elapsed());
                if top.contains(&tr.id) {
                    top_left -= 1;
                    if top_left == 0 {
                        top_done = Some(t.elapsed());
                    }
                }
            }
            Ok(Some(_)) => {}
            _ => panic!("stalled over the link after {got}"),
        }
    }
    let all = t.elapsed();
    println!(
        "link 25 ms each way, 100 Mbit/s, window 8..1024, {} ({} treelets, all channels, {:.1} MB): connect {:.0} ms, first treelet {:.0} ms, top 1000 in {:.0} ms, all in {:.0} ms ({:.1} MB/s)",
        d.name,
        list.len(),
        bytes as f64 / 1e6,
        connect.as_secs_f64() * 1e3,
        first.unwrap_or_default().as_secs_f64() * 1e3,
        top_done.unwrap_or_default().as_secs_f64() * 1e3,
        all.as_secs_f64() * 1e3,
        bytes as f64 / all.as_secs_f64() / 1e6
    );
    c.close().await;
    link.shutdown().await;
    // The same bytes from raw quinn on one stream over an emulator of the same link, its first
    // connection too: how far the link, slow start included, lets any QUIC sender go.
    let raw_link = LinkEmulator::start(
        raw.addr,
        LinkConfig::wan(Duration::from_millis(25), 100_000_000 / 8),
    )
    .await
    .unwrap();
    let r = raw::run_via(raw, raw_link.local_addr(), 1, 1, bytes as u32, 1).await;
    println!(
        "  raw quinn, one stream of the same bytes over the same link: first bytes {:.0} ms, all \
         in {:.0} ms ({:.1} MB/s); Arbor's whole list took {:.2}x its time",
        r.first * 1e3,
        r.secs * 1e3,
        r.bytes as f64 / r.secs / 1e6,
        all.as_secs_f64() / r.secs
    );
    raw_link.shutdown().await;
}

/// A runtime of one worker whose threads (the worker and any blocking ones) run on CPU `cpu`
/// only.
fn pinned_runtime(cpu: usize, name: &str) -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name(name)
        .enable_all()
        .on_thread_start(move || {
            let mut set = rustix::thread::CpuSet::new();
            set.set(cpu);
            rustix::thread::sched_setaffinity(None, &set).expect("pin a thread to its CPU");
        })
        .build()
        .unwrap()
}

/// What [`split_ends`] fetches for a profiler, instead of the row.
#[derive(Clone, Copy)]
enum SplitProfile {
    /// Arbor's whole-scene fetches only.
    Arbor,
    /// Raw quinn's one stream of this many bytes only.
    Raw(u32),
}

/// The whole-scene row again with the server's end and the client's end each on a CPU of its
/// own, as when they run on two machines: each has its own runtime of one worker, pinned.
/// Arbor against raw quinn's one stream of the same bytes, `runs` turns (or, with `profile`,
/// only one of the two, `runs` times, and nothing printed).
///
/// Why a row of its own: in the row above both ends share the cores, and the two ends mostly
/// take turns on one CPU (the row's CPU share: about one of two cores busy). Separate runtimes
/// left unpinned measure the same as that row, so it is where the kernel runs the threads, not
/// the runtime; pinned, both ends work at once, as on two machines.
async fn split_ends(
    pool: &std::path::Path,
    data: &std::path::Path,
    d: &SceneDescription,
    runs: usize,
    profile: Option<SplitProfile>,
) {
    let allowed = rustix::thread::sched_getaffinity(None).expect("the CPUs this process may use");
    let cpus: Vec<usize> = (0..rustix::thread::CpuSet::MAX_CPU)
        .filter(|&c| allowed.is_set(c))
        .take(2)
        .collect();
    let [server_cpu, client_cpu] = cpus[..] else {
        println!(
            "whole {} with each end on a CPU of its own: SKIPPED, this process may run on {} \
             CPU(s), the row needs two",
            d.name,
            cpus.len()
        );
        return;
    };
    // Named for profilers (`perf report --sort comm`).
    let server_rt = pinned_runtime(server_cpu, "server-end");
    let client_rt = pinned_runtime(client_cpu, "client-end");
    let config = serve_config(pool, data, adaptive_window());
    let server = server_rt
        .spawn(async move { start(config).await.unwrap() })
        .await
        .unwrap();
    let raw = Arc::new(server_rt.spawn(async { raw::start() }).await.unwrap());
    let (addr, fp) = (server.quic_addr, server.fingerprint.clone());
    let whole = d.treelet_count as usize;
    let arbor_fetch = || {
        let (fp, scene) = (fp.clone(), d.clone());
        client_rt.spawn(async move { arbor_run(addr, &fp, &scene, 1, whole).await })
    };
    let raw_fetch = |bytes: u32| {
        let raw = raw.clone();
        client_rt.spawn(async move { raw::run(&raw, 1, 1, bytes, 1).await })
    };
    // CPU of each end's worker thread so far, read on that thread: (server, client).
    let ends_cpu = async || {
        let server = server_rt.spawn(async { thread_cpu() }).await.unwrap();
        let client = client_rt.spawn(async { thread_cpu() }).await.unwrap();
        (server, client)
    };
    let mut turns = WholeTurns::default();
    // Each end's worker CPU per fetch with its connection and close, milliseconds:
    // [server, client] for Arbor, then for raw quinn.
    let mut ends_ms: [Vec<f64>; 4] = Default::default();
    for _ in 0..runs {
        match profile {
            Some(SplitProfile::Arbor) => {
                arbor_fetch().await.unwrap();
            }
            Some(SplitProfile::Raw(bytes)) => {
                raw_fetch(bytes).await.unwrap();
            }
            None => {
                let t0 = ends_cpu().await;
                let run = arbor_fetch().await.unwrap();
                let t1 = ends_cpu().await;
                let raw_run = raw_fetch(run.bytes as u32).await.unwrap();
                let t2 = ends_cpu().await;
                let ms = |a: Duration, b: Duration| (b - a).as_secs_f64() * 1e3;
                for (v, x) in ends_ms.iter_mut().zip([
                    ms(t0.0, t1.0),
                    ms(t0.1, t1.1),
                    ms(t1.0, t2.0),
                    ms(t1.1, t2.1),
                ]) {
                    v.push(x);
                }
                turns.add(whole, &run, &raw_run);
            }
        }
    }
    if profile.is_none() {
        println!(
            "whole {} with each end on a CPU of its own (server on CPU {server_cpu}, client on \
             CPU {client_cpu}, as on two machines): best runs Arbor {:.1}, raw quinn {:.1} MB/s",
            d.name,
            best(&turns.arbor).1,
            best(&turns.raw).1
        );
        turns.print(2);
        let [a_server, a_client, r_server, r_client] = ends_ms.map(median_of);
        println!(
            "  each end's worker per fetch with its handshake and close, medians: Arbor server \
             {a_server:.2} ms, client {a_client:.2} ms; raw quinn server {r_server:.2} ms, client \
             {r_client:.2} ms"
        );
    }
    server_rt
        .spawn(async move { server.shutdown().await })
        .await
        .unwrap();
    server_rt.shutdown_background();
    client_rt.shutdown_background();
}
