//! The admin listener's transport: HTTPS with the daemon's certificate (or a given one) when it
//! binds anything other than loopback or when asked to; cleartext on loopback, or anywhere with
//! an explicit `admin_tls = "off"`. Real daemons on real ports; requests go to 127.0.0.1 only.
//! A reload renews both listeners' certificates and the admin token for the next handshake and
//! request, and changes nothing when a file does not load.

mod common;

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
async fn get(stream: impl AsyncRead + AsyncWrite + Unpin, path: &str) -> String {
    get_as(stream, path, "t0ken").await
}

/// [`get`] with `token`.
async fn get_as(
    mut stream: impl AsyncRead + AsyncWrite + Unpin,
    path: &str,
    token: &str,
) -> String {
    let request = format!(
        "GET {path} HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer {token}\r\nConnection: close\r\n\r\n"
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
    get_https_as(addr, roots, path, "t0ken").await
}

/// [`get_https`] with `token`.
async fn get_https_as(
    addr: SocketAddr,
    roots: &[CertificateDer<'static>],
    path: &str,
    token: &str,
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
    (get_as(tls, path, token).await, presented)
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

/// One sample of `/metrics`.
fn sample(metrics: &str, series: &str) -> Option<f64> {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
}

/// A reload renews what both listeners present and the admin token, for the next handshake
/// and the next request, while an open QUIC session goes on; a pair whose key is not its
/// certificate's changes nothing at all, and `/metrics` counts both.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reload_renews_the_certificates_and_the_admin_token_without_ending_sessions() {
    use common::*;
    let pool = TestPool::new();
    let tls_dir = pool.dir.path().join("tls");
    std::fs::create_dir_all(&tls_dir).unwrap();
    let first = write_pair(&tls_dir, 2030);
    let mut config = pool.config();
    config.tls = TlsSource::Files {
        cert: tls_dir.join("cert.pem"),
        key: tls_dir.join("key.pem"),
    };
    config.admin_listen = Some("0.0.0.0:0".parse().unwrap());
    config.admin_token = arbor_server::service::config::AdminTokenSource::Inline("t0ken".into());
    let server = start(config.clone()).await;
    let admin = loopback(&server);
    let pinned = |der: &CertificateDer<'_>| arbor_server::service::tls::fingerprint(der);
    assert_eq!(server.fingerprint, pinned(&first));

    let session = connect(server.quic_addr, &pinned(&first)).await;
    let (mut control, info) = hello(&session.conn, SCENE, &[], TOKEN).await;
    let ids = all_ids(&info.unwrap());
    round(&session, &mut control, 1, &ids).await.unwrap();
    let (metrics, presented) = get_https(admin, std::slice::from_ref(&first), "/metrics").await;
    assert_eq!(presented, first);
    for listener in ["quic", "admin"] {
        let series =
            format!("arbor_tls_certificate_expiry_timestamp_seconds{{listener=\"{listener}\"}}");
        assert_eq!(sample(&metrics, &series), Some(new_year(2030)), "{metrics}");
    }
    assert_eq!(
        sample(&metrics, "arbor_config_last_reload_successful"),
        Some(1.0)
    );

    // The pair renewed in place and a new admin token, as certbot and a secret rotation do.
    let second = write_pair(&tls_dir, 2031);
    config.admin_token = arbor_server::service::config::AdminTokenSource::Inline("n3w".into());
    let done = server.reloader().reload(&config).unwrap();
    assert!(done.certificate_changed && done.admin_certificate_changed && done.admin_token_changed);
    assert_eq!(done.fingerprint, pinned(&second));
    assert_eq!(done.sessions.shut_out, 0);

    round(&session, &mut control, 2, &ids)
        .await
        .expect("the session begun under the old certificate goes on");
    let refused = connect_with(server.quic_addr, &pinned(&first), ClientOptions::default()).await;
    assert!(refused.is_err(), "the old certificate was presented");
    let renewed = connect(server.quic_addr, &pinned(&second)).await;
    let (_control, info) = hello(&renewed.conn, SCENE, &[], TOKEN).await;
    info.expect("a client pinning the new certificate is served");
    let (answer, presented) = get_https(admin, std::slice::from_ref(&second), "/healthz").await;
    assert!(status_ok(&answer), "{answer}");
    assert_eq!(presented, second, "the admin listener renewed too");
    let (answer, _) = get_https(admin, std::slice::from_ref(&second), "/metrics").await;
    assert!(
        answer.starts_with("HTTP/1.1 401"),
        "the old admin token: {answer}"
    );
    let (metrics, _) = get_https_as(admin, std::slice::from_ref(&second), "/metrics", "n3w").await;
    assert!(status_ok(&metrics), "{metrics}");
    let (server_view, _) =
        get_https_as(admin, std::slice::from_ref(&second), "/v1/server", "n3w").await;
    assert!(server_view.contains(&pinned(&second)), "{server_view}");
    for listener in ["quic", "admin"] {
        let series =
            format!("arbor_tls_certificate_expiry_timestamp_seconds{{listener=\"{listener}\"}}");
        assert_eq!(sample(&metrics, &series), Some(new_year(2031)), "{metrics}");
    }
    let applied = "arbor_config_reloads_total{outcome=\"applied\"}";
    assert_eq!(sample(&metrics, applied), Some(1.0), "{metrics}");

    // A key that is not the certificate's: nothing changes, the token included.
    let third_key = rcgen::KeyPair::generate().unwrap();
    std::fs::write(tls_dir.join("key.pem"), third_key.serialize_pem()).unwrap();
    config.admin_token = arbor_server::service::config::AdminTokenSource::Inline("l4st".into());
    let e = server.reloader().reload(&config).unwrap_err().to_string();
    assert!(e.contains("key.pem") && e.contains("not the key"), "{e}");
    let again = connect(server.quic_addr, &pinned(&second)).await;
    drop(again);
    let (metrics, presented) =
        get_https_as(admin, std::slice::from_ref(&second), "/metrics", "n3w").await;
    assert!(status_ok(&metrics), "the admin token stayed: {metrics}");
    assert_eq!(presented, second);
    assert_eq!(
        sample(&metrics, "arbor_config_last_reload_successful"),
        Some(0.0)
    );
    let failed = "arbor_config_reloads_total{outcome=\"failed\"}";
    assert_eq!(sample(&metrics, failed), Some(1.0), "{metrics}");
    let (page, _) = get_https_as(admin, std::slice::from_ref(&second), "/", "n3w").await;
    assert!(page.contains("the last reload failed"), "{page}");
    assert!(page.contains("1 reloads applied, 1 failed"), "{page}");
    assert!(
        page.contains("quic 2031-01-01 00:00:00 UTC · admin 2031-01-01 00:00:00 UTC"),
        "{page}"
    );
    round(&session, &mut control, 3, &ids).await.unwrap();
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
