//! The admin listener's transport: HTTPS with the daemon's certificate (or a given one) when it
//! binds anything other than loopback or when asked to; cleartext on loopback, or anywhere with
//! an explicit `admin_tls = "off"`. Real daemons on real ports; requests go to 127.0.0.1 only.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use arbor_server::daemon::RunningServer;
use arbor_server::pool::Pool;
use arbor_server::service::ServeConfig;
use arbor_server::service::config::{AdminTls, TlsSource};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName};
use tokio::io::{AsyncRead, AsyncReadExt as _, AsyncWrite, AsyncWriteExt as _};
use tokio::net::TcpStream;

/// A daemon over an empty pool with the admin listener on `admin` in `mode`.
async fn daemon(dir: &Path, admin: &str, mode: AdminTls) -> RunningServer {
    drop(Pool::open(&dir.join("pool")).unwrap());
    let mut config = ServeConfig::new(dir.join("pool"));
    config.data_dir = Some(dir.join("state"));
    config.listen = "127.0.0.1:0".parse().unwrap();
    config.admin_listen = Some(admin.parse().unwrap());
    config.admin_token = arbor_server::service::config::AdminTokenSource::Inline("t0ken".into());
    config.admin_tls = mode;
    with_identity(config, dir, TlsSource::SelfSigned).await
}

async fn with_identity(mut config: ServeConfig, _dir: &Path, identity: TlsSource) -> RunningServer {
    config.admin_identity = identity;
    arbor_server::daemon::start(config).await.unwrap()
}

/// The admin port on 127.0.0.1, whatever address the listener bound.
fn loopback(server: &RunningServer) -> SocketAddr {
    let port = server.admin_addr.expect("admin listener").port();
    SocketAddr::from(([127, 0, 0, 1], port))
}

/// One HTTP/1.1 GET with the bearer token over `stream`; the whole answer.
async fn get(mut stream: impl AsyncRead + AsyncWrite + Unpin, path: &str) -> String {
    let request = format!(
        "GET {path} HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer t0ken\r\nConnection: close\r\n\r\n"
    );
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut raw = Vec::new();
    let read = tokio::time::timeout(Duration::from_secs(30), stream.read_to_end(&mut raw)).await;
    // A TLS peer may end without close_notify after a complete answer.
    if let Ok(Err(e)) = read {
        assert!(!raw.is_empty(), "reading the answer: {e}");
    }
    String::from_utf8_lossy(&raw).into_owned()
}

/// GET over TLS, trusting only `roots`; also returns the certificate the server presented.
async fn get_https(
    addr: SocketAddr,
    roots: &[CertificateDer<'static>],
    path: &str,
) -> (String, CertificateDer<'static>) {
    let mut store = rustls::RootCertStore::empty();
    for c in roots {
        store.add(c.clone()).unwrap();
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(store)
        .with_no_client_auth();
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    let connector = tokio_rustls::TlsConnector::from(Arc::new(config));
    let tcp = TcpStream::connect(addr).await.unwrap();
    let tls = connector
        .connect(ServerName::try_from("localhost").unwrap(), tcp)
        .await
        .expect("TLS handshake with the admin listener");
    let presented = tls.get_ref().1.peer_certificates().unwrap()[0].clone();
    (get(tls, path).await, presented)
}

fn certs(path: &Path) -> Vec<CertificateDer<'static>> {
    CertificateDer::pem_file_iter(path)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap()
}

fn status_ok(answer: &str) -> bool {
    answer.starts_with("HTTP/1.1 200")
}

#[tokio::test]
async fn off_loopback_the_admin_api_is_https_with_the_daemon_certificate() {
    let dir = tempfile::tempdir().unwrap();
    let server = daemon(dir.path(), "0.0.0.0:0", AdminTls::Auto).await;
    assert!(server.admin_https);
    let addr = loopback(&server);
    let daemon_cert = certs(&dir.path().join("state/cert.pem"));
    let (answer, presented) = get_https(addr, &daemon_cert, "/healthz").await;
    assert!(status_ok(&answer), "{answer}");
    assert_eq!(presented, daemon_cert[0], "not the daemon's certificate");
    assert_eq!(
        arbor_server::service::tls::fingerprint(&presented),
        server.fingerprint
    );
    let (metrics, _) = get_https(addr, &daemon_cert, "/metrics").await;
    assert!(status_ok(&metrics), "{metrics}");
    // Cleartext HTTP to the same port gets no HTTP answer.
    let plain = get(TcpStream::connect(addr).await.unwrap(), "/healthz").await;
    assert!(!plain.starts_with("HTTP/"), "cleartext answered: {plain}");
    server.shutdown().await;
}

/// `/healthz` answers in cleartext on the admin port.
async fn assert_cleartext_health(server: &RunningServer) {
    let answer = get(
        TcpStream::connect(loopback(server)).await.unwrap(),
        "/healthz",
    )
    .await;
    assert!(status_ok(&answer), "{answer}");
}

#[tokio::test]
async fn on_loopback_the_admin_api_is_cleartext_unless_asked() {
    let dir = tempfile::tempdir().unwrap();
    let server = daemon(dir.path(), "127.0.0.1:0", AdminTls::Auto).await;
    assert!(!server.admin_https);
    assert_cleartext_health(&server).await;
    server.shutdown().await;

    let dir = tempfile::tempdir().unwrap();
    let server = daemon(dir.path(), "127.0.0.1:0", AdminTls::On).await;
    assert!(server.admin_https);
    let daemon_cert = certs(&dir.path().join("state/cert.pem"));
    let (answer, _) = get_https(loopback(&server), &daemon_cert, "/readyz").await;
    assert!(status_ok(&answer), "{answer}");
    server.shutdown().await;
}

#[tokio::test]
async fn an_explicit_flag_allows_cleartext_off_loopback() {
    let dir = tempfile::tempdir().unwrap();
    let server = daemon(dir.path(), "0.0.0.0:0", AdminTls::Off).await;
    assert!(!server.admin_https);
    assert_cleartext_health(&server).await;
    server.shutdown().await;
}

#[tokio::test]
async fn a_given_admin_certificate_is_presented_instead() {
    let dir = tempfile::tempdir().unwrap();
    let other = rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).unwrap();
    let (cert, key) = (
        dir.path().join("admin.pem"),
        dir.path().join("admin-key.pem"),
    );
    std::fs::write(&cert, other.cert.pem()).unwrap();
    std::fs::write(&key, other.signing_key.serialize_pem()).unwrap();
    drop(Pool::open(&dir.path().join("pool")).unwrap());
    let mut config = ServeConfig::new(dir.path().join("pool"));
    config.data_dir = Some(dir.path().join("state"));
    config.listen = "127.0.0.1:0".parse().unwrap();
    config.admin_listen = Some("0.0.0.0:0".parse().unwrap());
    let server = with_identity(
        config,
        dir.path(),
        TlsSource::Files {
            cert: cert.clone(),
            key,
        },
    )
    .await;
    let given = certs(&cert);
    let (answer, presented) = get_https(loopback(&server), &given, "/healthz").await;
    assert!(status_ok(&answer), "{answer}");
    assert_eq!(presented, given[0]);
    assert_ne!(
        arbor_server::service::tls::fingerprint(&presented),
        server.fingerprint,
        "the QUIC certificate was presented"
    );
    server.shutdown().await;
}

#[test]
fn the_config_file_and_the_flag_choose_the_mode() {
    use arbor_server::service::ConfigOverrides;
    let path = Path::new("arbor.toml");
    let parse = |text: &str, flag: Option<AdminTls>| {
        let overrides = ConfigOverrides {
            db: Some("pool".into()),
            admin_tls: flag,
            ..ConfigOverrides::default()
        };
        ServeConfig::from_toml(text, path, &overrides)
    };
    assert_eq!(parse("", None).unwrap().admin_tls, AdminTls::Auto);
    assert_eq!(
        parse("admin_tls = \"off\"", None).unwrap().admin_tls,
        AdminTls::Off
    );
    assert_eq!(
        parse("admin_tls = \"off\"", Some(AdminTls::On))
            .unwrap()
            .admin_tls,
        AdminTls::On
    );
    let c = parse("admin_cert = \"a.pem\"\nadmin_key = \"k.pem\"", None).unwrap();
    assert_eq!(
        c.admin_identity,
        TlsSource::Files {
            cert: "a.pem".into(),
            key: "k.pem".into()
        }
    );
    let e = parse("admin_cert = \"a.pem\"", None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("admin_key"), "{e}");
    let e = parse("admin_tls = \"maybe\"", None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("admin_tls"), "{e}");
}
