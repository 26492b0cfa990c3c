//! Serving throughput, in one run, on loopback:
//! * Arbor: treelets/s and MB/s for 1 and 4 KiB treelets (lion) with 1, 8 and 64 concurrent
//!   clients, each asking for the same number of treelets, all channels;
//! * raw quinn, measured the same way: one server-opened unidirectional stream per message of the
//!   scene's mean message size, the same number per connection, the same in-flight window, plus
//!   one bulk stream for the link's ceiling;
//! * over the link emulator (25 ms each way, 100 Mbit/s): time until the top 1,000 of a list
//!   (random priorities over all treelets of the 4 KiB scene) have arrived.
//!
//! `cargo bench -p arbor-tests --bench serve` (ARBOR_BENCH_QUICK=1: fewer treelets per client).

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

/// The server's per-connection window bounds used for both Arbor and raw quinn.
const WINDOW: usize = 64;

fn build_pool(dir: &std::path::Path) -> Vec<SceneDescription> {
    let pool = Pool::open(dir).unwrap();
    let scratch = tempfile::tempdir().unwrap();
    let source = import_file(
        &data("points/lion_takanawa.copc.laz"),
        &ImportOptions::default(),
        scratch.path(),
    )
    .unwrap();
    let mut out = Vec::new();
    for tb in [1024u32, 4096] {
        let name = format!("lion-{}k", tb / 1024);
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

/// Receives `n` treelets; returns wire bytes.
async fn receive(c: &mut TreeletClient, n: usize) -> u64 {
    let mut got = 0;
    let mut bytes = 0u64;
    while got < n {
        match tokio::time::timeout(Duration::from_secs(120), c.next_event()).await {
            Ok(Some(ClientEvent::Treelet(t))) => {
                got += 1;
                bytes += t.wire_bytes as u64;
            }
            Ok(Some(ClientEvent::Disconnected { reason, .. })) => panic!("disconnected: {reason}"),
            Ok(Some(_)) => {}
            Ok(None) | Err(_) => panic!("stalled after {got} of {n}"),
        }
    }
    bytes
}

/// `clients` concurrent clients each fetching the first `per_client` treelets; (seconds, bytes).
async fn arbor_run(
    addr: SocketAddr,
    fp: &str,
    scene: &SceneDescription,
    clients: usize,
    per_client: usize,
) -> (f64, u64) {
    let mut cs = Vec::new();
    for _ in 0..clients {
        let mut c = client(addr, scene, fp);
        wait_connected(&mut c).await;
        cs.push(c);
    }
    let list: Vec<(TreeletId, f32)> = (0..per_client as u32)
        .map(|i| (TreeletId(i), (per_client as u32 - i) as f32))
        .collect();
    let t = Instant::now();
    let mut tasks = Vec::new();
    for mut c in cs {
        c.request(list.clone()).unwrap();
        tasks.push(tokio::spawn(async move {
            let b = receive(&mut c, per_client).await;
            c.close().await;
            b
        }));
    }
    let mut bytes = 0;
    for t in tasks {
        bytes += t.await.unwrap();
    }
    (t.elapsed().as_secs_f64(), bytes)
}

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
        let mut tc = quinn::TransportConfig::default();
        tc.max_concurrent_uni_streams(1024u32.into());
        sc.transport_config(Arc::new(tc));
        let endpoint = quinn::Endpoint::server(sc, "127.0.0.1:0".parse().unwrap()).unwrap();
        let addr = endpoint.local_addr().unwrap();
        let ep = endpoint.clone();
        tokio::spawn(async move {
            while let Some(inc) = ep.accept().await {
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
                    let payload = Arc::new(vec![7u8; size]);
                    let sem = Arc::new(tokio::sync::Semaphore::new(window));
                    for _ in 0..count {
                        let permit = sem.clone().acquire_owned().await.unwrap();
                        let (conn, payload) = (conn.clone(), payload.clone());
                        tokio::spawn(async move {
                            if let Ok(mut s) = conn.open_uni().await {
                                let _ = s.write_all(&payload).await;
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
        let mut tc = quinn::TransportConfig::default();
        tc.max_concurrent_uni_streams(1024u32.into());
        cc.transport_config(Arc::new(tc));
        Raw {
            addr,
            client_config: cc,
            _endpoint: endpoint,
        }
    }

    /// One client fetching `count` messages of `size` bytes; returns bytes received.
    async fn one(
        raw_addr: SocketAddr,
        cc: quinn::ClientConfig,
        count: u32,
        size: u32,
        window: u32,
    ) -> u64 {
        let mut ep = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
        ep.set_default_client_config(cc);
        let conn = ep.connect(raw_addr, "localhost").unwrap().await.unwrap();
        let (mut s, _r) = conn.open_bi().await.unwrap();
        let mut req = Vec::new();
        for v in [count, size, window] {
            req.extend_from_slice(&v.to_le_bytes());
        }
        s.write_all(&req).await.unwrap();
        let mut bytes = 0u64;
        let mut readers = tokio::task::JoinSet::new();
        for _ in 0..count {
            let mut r = conn.accept_uni().await.unwrap();
            readers.spawn(async move { r.read_to_end(1 << 28).await.unwrap().len() as u64 });
            while let Some(Ok(b)) = readers.try_join_next() {
                bytes += b;
            }
        }
        while let Some(b) = readers.join_next().await {
            bytes += b.unwrap();
        }
        conn.close(0u32.into(), b"done");
        ep.wait_idle().await;
        bytes
    }

    /// `clients` concurrent clients; (seconds, bytes).
    pub async fn run(raw: &Raw, clients: usize, count: u32, size: u32, window: u32) -> (f64, u64) {
        let t = Instant::now();
        let mut tasks = Vec::new();
        for _ in 0..clients {
            tasks.push(tokio::spawn(one(
                raw.addr,
                raw.client_config.clone(),
                count,
                size,
                window,
            )));
        }
        let mut bytes = 0;
        for t in tasks {
            bytes += t.await.unwrap();
        }
        (t.elapsed().as_secs_f64(), bytes)
    }
}

#[tokio::main(flavor = "multi_thread")]
async fn main() {
    let quick = std::env::var("ARBOR_BENCH_QUICK").is_ok();
    let pool_dir = tempfile::tempdir().unwrap();
    let data_dir = tempfile::tempdir().unwrap();
    let dir = pool_dir.path().to_owned();
    let scenes = tokio::task::spawn_blocking(move || build_pool(&dir))
        .await
        .unwrap();
    // Loopback comparison: Arbor's window fixed to raw quinn's.
    let server = start(serve_config(
        pool_dir.path(),
        data_dir.path(),
        (WINDOW, WINDOW),
    ))
    .await
    .unwrap();
    let fp = server.fingerprint.clone();
    let addr = server.quic_addr;
    let raw = raw::start();

    println!(
        "Arbor serving benchmark (loopback QUIC, release, {} cores; all channels; Arbor window fixed at {} like raw quinn)",
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        WINDOW
    );
    println!(
        "{:<8} {:>7} {:>9} | {:>10} {:>8} {:>8} | {:>14} {:>10} {:>8} | {:>6}",
        "scene",
        "clients",
        "treelets",
        "treelets/s",
        "MB/s",
        "mean B",
        "raw streams/s",
        "raw MB/s",
        "raw s",
        "ratio"
    );
    for d in &scenes {
        for clients in [1usize, 8, 64] {
            let per_client = if quick {
                200
            } else if clients == 64 {
                500
            } else {
                2000
            }
            .min(d.treelet_count as usize);
            let (secs, bytes) = arbor_run(addr, &fp, d, clients, per_client).await;
            let n = (clients * per_client) as f64;
            let mean = (bytes as f64 / n).round() as u32;
            let (rsecs, rbytes) =
                raw::run(&raw, clients, per_client as u32, mean, WINDOW as u32).await;
            println!(
                "{:<8} {:>7} {:>9} | {:>10.0} {:>8.1} {:>8} | {:>14.0} {:>10.1} {:>8.2} | {:>6.2}",
                d.name,
                clients,
                clients * per_client,
                n / secs,
                bytes as f64 / secs / 1e6,
                mean,
                n / rsecs,
                rbytes as f64 / rsecs / 1e6,
                rsecs,
                (n / secs) / (n / rsecs)
            );
        }
    }
    let (bsecs, bbytes) = raw::run(&raw, 1, 1, 64 << 20, 1).await;
    println!(
        "raw quinn bulk, one 64 MiB stream: {:.1} MB/s",
        bbytes as f64 / bsecs / 1e6
    );

    // Over the emulated WAN: the top 1,000 of a list of all treelets, random priorities; the
    // window adapts to RTT × bandwidth between 8 and 1024.
    server.shutdown().await;
    let server = start(serve_config(pool_dir.path(), data_dir.path(), (8, 1024)))
        .await
        .unwrap();
    let addr = server.quic_addr;
    let d = &scenes[1];
    let link = LinkEmulator::start(
        addr,
        LinkConfig::wan(Duration::from_millis(25), 100_000_000 / 8),
    )
    .await
    .unwrap();
    let mut c = client(link.local_addr(), d, &fp);
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
    server.shutdown().await;
}
