//! A minimal in-test treelet server: just enough of the protocol to exercise the client.
//!
//! It answers `Hello` with `SceneInfo` (or an `Error` and a close), answers every request list
//! by sending each newly named treelet once, on its own stream, in priority order, and logs
//! everything it saw so tests can assert on it.
#![allow(dead_code)]

use std::collections::HashSet;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use arbor_client_net::{ServerUrl, certificate_fingerprint};
use arbor_proto::frame::{FrameDecoder, encode, encode_treelet_message};
use arbor_proto::wire::{ALPN, ErrorCode, Frame};
use arbor_proto::{
    AttributeLayout, BuildParameters, Channel, SceneDescription, SceneStats, SourceKind, TreeletId,
};
use quinn::{Connection, ConnectionError, Endpoint, RecvStream, VarInt};
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

/// A server certificate and key.
pub struct Identity {
    pub cert: CertificateDer<'static>,
    key: Vec<u8>,
    pub fingerprint: String,
    /// PEM of the certificate that vouches for the server: itself when self-signed, the CA's
    /// otherwise.
    pub trust_pem: String,
}

fn leaf_params() -> rcgen::CertificateParams {
    let mut p = rcgen::CertificateParams::new(vec![
        "localhost".to_owned(),
        "127.0.0.1".to_owned(),
        "::1".to_owned(),
    ])
    .unwrap();
    p.distinguished_name
        .push(rcgen::DnType::CommonName, "arbor test server");
    p
}

impl Identity {
    pub fn self_signed() -> Self {
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = leaf_params().self_signed(&key).unwrap();
        Self {
            fingerprint: certificate_fingerprint(cert.der()),
            trust_pem: cert.pem(),
            cert: cert.der().clone(),
            key: key.serialize_der(),
        }
    }

    /// A leaf signed by a fresh CA; `trust_pem` is the CA.
    pub fn ca_signed() -> Self {
        let ca_key = rcgen::KeyPair::generate().unwrap();
        let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
        ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
        ca_params.key_usages = vec![
            rcgen::KeyUsagePurpose::KeyCertSign,
            rcgen::KeyUsagePurpose::CrlSign,
        ];
        ca_params
            .distinguished_name
            .push(rcgen::DnType::CommonName, "arbor test CA");
        let ca = rcgen::CertifiedIssuer::self_signed(ca_params, ca_key).unwrap();
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = leaf_params().signed_by(&key, &ca).unwrap();
        Self {
            fingerprint: certificate_fingerprint(cert.der()),
            trust_pem: ca.pem(),
            cert: cert.der().clone(),
            key: key.serialize_der(),
        }
    }

    fn server_config(&self) -> quinn::ServerConfig {
        let key = PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(self.key.clone()));
        let mut tls = rustls::ServerConfig::builder_with_provider(Arc::new(
            rustls::crypto::ring::default_provider(),
        ))
        .with_protocol_versions(&[&rustls::version::TLS13])
        .unwrap()
        .with_no_client_auth()
        .with_single_cert(vec![self.cert.clone()], key)
        .unwrap();
        tls.alpn_protocols = vec![ALPN.to_vec()];
        let quic = quinn::crypto::rustls::QuicServerConfig::try_from(Arc::new(tls)).unwrap();
        quinn::ServerConfig::with_crypto(Arc::new(quic))
    }
}

/// A small scene: `count` treelets with colour and normals.
pub fn scene(name: &str, count: u32) -> SceneDescription {
    SceneDescription {
        name: name.into(),
        origin: [0.0, 0.0, 0.0],
        edge: 1.0,
        treelet_nodes: 512,
        max_depth: 12,
        layout: AttributeLayout::new([Channel::Color, Channel::Normal]),
        treelet_count: count,
        root_treelet: TreeletId::ROOT,
        source_kind: SourceKind::Points,
        source: "synthetic".into(),
        primitives: 100,
        build: BuildParameters {
            requested_depth: None,
            data_resolution: 0.01,
            treelet_bytes: 4096,
            iso: None,
            zstd_level: 3,
            dictionary: false,
        },
        stats: SceneStats::default(),
        node_dictionary: None,
        channel_dictionaries: vec![None, None],
    }
}

/// The node block the fake server sends for treelet `id`: deterministic, different per id.
pub fn node_block(id: TreeletId, len: usize) -> Vec<u8> {
    (0..len)
        .map(|i| {
            (i as u32)
                .wrapping_mul(31)
                .wrapping_add(id.0.wrapping_mul(7)) as u8
        })
        .collect()
}

/// The block of `channel` for treelet `id`.
pub fn channel_block(id: TreeletId, channel: Channel, len: usize) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u32 ^ id.0).wrapping_add(u32::from(channel.id()) * 101) as u8)
        .collect()
}

/// Used nodes announced for treelet `id`.
pub fn used_nodes(id: TreeletId) -> u16 {
    (id.0 % 500 + 1) as u16
}

/// How the fake server behaves.
#[derive(Clone, Debug)]
pub struct Behaviour {
    pub token: String,
    pub scene: SceneDescription,
    /// Refuse every `Hello` with this code (an `Error` frame, then a close with the code).
    pub refuse: Option<ErrorCode>,
    /// After answering this many request lists on a connection (and seeing its treelets
    /// delivered), say `Goodbye` and close with this code.
    pub close_after_lists: Option<(usize, ErrorCode)>,
    /// Send every channel of the scene, asked for or not.
    pub all_channels: bool,
    /// Bytes of each treelet's node block; channel blocks are half of it.
    pub node_bytes: usize,
    /// Send all treelets newly named by a list on one stream, written in pieces of this many
    /// bytes a moment apart (so the client reads them in chunks that split messages anywhere).
    pub one_stream_pieces: Option<usize>,
    /// Bytes cut off the end of that one stream (a message cut short).
    pub cut_last: usize,
}

impl Behaviour {
    pub fn new(token: &str) -> Self {
        Self {
            token: token.into(),
            scene: scene("lion", 1000),
            refuse: None,
            close_after_lists: None,
            all_channels: false,
            node_bytes: 600,
            one_stream_pieces: None,
            cut_last: 0,
        }
    }

    /// The message this server sends for `id` to a client that asked for `channels`.
    pub fn message(&self, id: TreeletId, channels: &[Channel]) -> Vec<u8> {
        let nodes = node_block(id, self.node_bytes);
        let blocks: Vec<(Channel, Vec<u8>)> = Channel::ALL
            .iter()
            .filter(|c| self.scene.layout.contains(**c))
            .filter(|c| self.all_channels || channels.contains(c))
            .map(|&c| (c, channel_block(id, c, self.node_bytes / 2)))
            .collect();
        let refs: Vec<(Channel, &[u8])> = blocks.iter().map(|(c, b)| (*c, &b[..])).collect();
        encode_treelet_message(id, used_nodes(id), &nodes, &refs).unwrap()
    }
}

/// `(connection number from 0, seq, items)` of a request list.
pub type LoggedList = (usize, u64, Vec<(TreeletId, f32)>);

/// What the fake server saw.
#[derive(Debug, Default)]
pub struct Log {
    pub connections: usize,
    /// `(channels, token)` of every `Hello`.
    pub hellos: Vec<(Vec<Channel>, String)>,
    /// `(connection number from 0, seq, items)` of every request list.
    pub lists: Vec<LoggedList>,
    /// The prefetch start of every deep request list, in order.
    pub prefetch_starts: Vec<u32>,
    /// Treelets sent, in order.
    pub sent: Vec<TreeletId>,
    pub goodbyes: usize,
    /// Application close codes the clients closed with.
    pub client_close_codes: Vec<u64>,
}

pub struct FakeServer {
    pub addr: SocketAddr,
    endpoint: Endpoint,
    log: Arc<Mutex<Log>>,
    task: tokio::task::JoinHandle<()>,
}

impl FakeServer {
    /// Listens on `addr` (port 0 for any), retrying briefly while the port is still taken.
    pub async fn start(identity: &Identity, addr: SocketAddr, behaviour: Behaviour) -> Self {
        let mut tries = 0;
        let endpoint = loop {
            match Endpoint::server(identity.server_config(), addr) {
                Ok(ep) => break ep,
                Err(e) if tries < 50 => {
                    tries += 1;
                    eprintln!("bind {addr}: {e}; retrying");
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
                Err(e) => panic!("bind {addr}: {e}"),
            }
        };
        let addr = endpoint.local_addr().unwrap();
        let log = Arc::new(Mutex::new(Log::default()));
        let task = tokio::spawn({
            let endpoint = endpoint.clone();
            let log = log.clone();
            async move {
                while let Some(incoming) = endpoint.accept().await {
                    let index = {
                        let mut l = log.lock().unwrap();
                        l.connections += 1;
                        l.connections - 1
                    };
                    let (b, log) = (behaviour.clone(), log.clone());
                    tokio::spawn(async move {
                        if let Ok(conn) = incoming.await {
                            serve(conn, b, log, index).await;
                        }
                    });
                }
            }
        });
        Self {
            addr,
            endpoint,
            log,
            task,
        }
    }

    pub fn log(&self) -> MutexGuard<'_, Log> {
        self.log.lock().unwrap()
    }

    /// Closes every connection with `code` and frees the port.
    pub async fn stop(self, code: ErrorCode) {
        self.endpoint
            .close(VarInt::from_u32(code.to_u32()), b"fake server stopping");
        let _ = tokio::time::timeout(Duration::from_secs(3), self.endpoint.wait_idle()).await;
        self.task.abort();
    }

    pub fn url(&self, scene: &str) -> ServerUrl {
        ServerUrl {
            host: self.addr.ip().to_string(),
            port: self.addr.port(),
            scene: scene.into(),
        }
    }
}

async fn next_frame(recv: &mut RecvStream, decoder: &mut FrameDecoder) -> Option<Frame> {
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        if let Some(f) = decoder.next().ok()? {
            return Some(f);
        }
        let n = recv.read(&mut buf).await.ok()??;
        let mut chunk = &buf[..n];
        while !chunk.is_empty() {
            let taken = decoder.push(chunk);
            chunk = &chunk[taken..];
            if taken == 0 {
                // Full: a frame must be complete; the caller takes it first.
                return decoder.next().ok()?;
            }
        }
    }
}

async fn serve(conn: Connection, b: Behaviour, log: Arc<Mutex<Log>>, index: usize) {
    let close_code = |c: ErrorCode| VarInt::from_u32(c.to_u32());
    let Ok((mut send, mut recv)) = conn.accept_bi().await else {
        return;
    };
    let mut decoder = FrameDecoder::for_server();
    let Some(Frame::Hello {
        channels, token, ..
    }) = next_frame(&mut recv, &mut decoder).await
    else {
        conn.close(close_code(ErrorCode::ProtocolViolation), b"expected Hello");
        return;
    };
    log.lock()
        .unwrap()
        .hellos
        .push((channels.clone(), token.clone()));
    let refusal = b
        .refuse
        .or((token != b.token).then_some(ErrorCode::Unauthorized));
    if let Some(code) = refusal {
        let frame = Frame::error(code, format!("refused: {}", code.name()));
        let _ = send.write_all(&encode(&frame).unwrap()).await;
        let _ = send.finish();
        // Give the frame a moment to arrive before the close overtakes it.
        tokio::time::sleep(Duration::from_millis(20)).await;
        conn.close(close_code(code), code.name().as_bytes());
        return;
    }
    let info = Frame::SceneInfo {
        description: Box::new(b.scene.clone()),
    };
    if send.write_all(&encode(&info).unwrap()).await.is_err() {
        return;
    }
    let mut sent = HashSet::new();
    let mut lists = 0usize;
    while let Some(frame) = next_frame(&mut recv, &mut decoder).await {
        match frame {
            Frame::RequestList { seq, items } => {
                log.lock().unwrap().lists.push((index, seq, items.clone()));
                lists += 1;
                let mut order = items.clone();
                order.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
                let mut streams = Vec::new();
                if let Some(piece) = b.one_stream_pieces {
                    let fresh: Vec<TreeletId> = order
                        .iter()
                        .map(|o| o.0)
                        .filter(|&id| sent.insert(id))
                        .collect();
                    let mut bytes: Vec<u8> = fresh
                        .iter()
                        .flat_map(|&id| b.message(id, &channels))
                        .collect();
                    bytes.truncate(bytes.len().saturating_sub(b.cut_last));
                    let Ok(mut s) = conn.open_uni().await else {
                        return;
                    };
                    for part in bytes.chunks(piece.max(1)) {
                        if s.write_all(part).await.is_err() {
                            return;
                        }
                        tokio::time::sleep(Duration::from_millis(1)).await;
                    }
                    let _ = s.finish();
                    log.lock().unwrap().sent.extend(fresh);
                    continue;
                }
                for (id, _) in order {
                    if !sent.insert(id) {
                        continue;
                    }
                    let Ok(mut s) = conn.open_uni().await else {
                        return;
                    };
                    if s.write_all(&b.message(id, &channels)).await.is_err() {
                        return;
                    }
                    let _ = s.finish();
                    log.lock().unwrap().sent.push(id);
                    streams.push(s);
                }
                if let Some((n, code)) = b.close_after_lists
                    && lists == n
                {
                    for s in &mut streams {
                        let _ = s.stopped().await;
                    }
                    let bye = Frame::Goodbye { code };
                    let _ = send.write_all(&encode(&bye).unwrap()).await;
                    tokio::time::sleep(Duration::from_millis(20)).await;
                    conn.close(close_code(code), b"fake server closing");
                    return;
                }
            }
            // Logged (as id and the priority its rank stands for) but not answered: the fake
            // server pushes nothing. The client sends its deep lists in the ranked form.
            Frame::RankedRequestList {
                seq,
                items,
                prefetch_from,
                ..
            } => {
                let mut log = log.lock().unwrap();
                log.lists.push((
                    index,
                    seq,
                    arbor_proto::wire::ranked_as_deep(&items)
                        .into_iter()
                        .map(|(id, p, _)| (id, p))
                        .collect(),
                ));
                log.prefetch_starts.push(prefetch_from);
            }
            Frame::Goodbye { .. } => log.lock().unwrap().goodbyes += 1,
            _ => {}
        }
    }
    if let ConnectionError::ApplicationClosed(c) = conn.closed().await {
        log.lock()
            .unwrap()
            .client_close_codes
            .push(c.error_code.into_inner());
    }
}
