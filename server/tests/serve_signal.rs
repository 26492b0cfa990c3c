//! The real `arbor-server serve` binary: prints its addresses, fingerprint and admin token file,
//! serves a raw client, and on SIGTERM says goodbye to it (close code ShuttingDown) and exits 0
//! within the grace bound; restarted on the same data dir it keeps its certificate. On SIGHUP it
//! puts the config's scene rules and tokens in force, ending only the sessions they revoke, and
//! presents a renewed certificate to the next handshake.

mod common;

use std::io::{BufRead as _, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use arbor_proto::Channel;
use arbor_proto::wire::{ErrorCode, Frame};
use common::*;

const BIN: &str = env!("CARGO_BIN_EXE_arbor-server");

struct Serving {
    child: Child,
    quic: std::net::SocketAddr,
    admin: String,
    fingerprint: String,
    token_file: String,
}

impl Drop for Serving {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

fn serve(dir: &Path, config: &Path) -> Serving {
    serve_on(dir, config, "127.0.0.1:0")
}

fn serve_on(dir: &Path, config: &Path, listen: &str) -> Serving {
    serve_with(dir, config, listen, &[])
}

/// [`serve_on`] with more flags.
fn serve_with(dir: &Path, config: &Path, listen: &str, flags: &[&str]) -> Serving {
    let mut child = Command::new(BIN)
        .arg("serve")
        .args(flags)
        .arg("--db")
        .arg(dir.join("pool"))
        .args(["--listen", listen, "--admin", "127.0.0.1:0", "--config"])
        .arg(config)
        .arg("--data-dir")
        .arg(dir.join("state"))
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let mut fields = std::collections::HashMap::new();
    while fields.len() < 4 {
        let line = rx
            .recv_timeout(Duration::from_secs(20))
            .expect("serve did not print its four lines");
        let (k, v) = line.split_once(' ').expect("`key value` lines");
        fields.insert(k.to_owned(), v.to_owned());
    }
    Serving {
        child,
        quic: fields["quic"].parse().unwrap(),
        admin: fields["admin"].clone(),
        fingerprint: fields["fingerprint"].clone(),
        token_file: fields["admin-token-file"].clone(),
    }
}

/// `THP_enabled` of a process (`/proc/PID/status`): 0 once it turned transparent huge pages off.
fn thp_enabled(child: &Child) -> Option<u8> {
    std::fs::read_to_string(format!("/proc/{}/status", child.id()))
        .ok()?
        .lines()
        .find_map(|l| l.strip_prefix("THP_enabled:")?.trim().parse().ok())
}

fn signal(child: &Child, sig: &str) {
    let ok = Command::new("kill")
        .args([sig, &child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill {sig}");
}

fn wait_exit(child: &mut Child, within: Duration) -> std::process::ExitStatus {
    let t0 = Instant::now();
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        assert!(t0.elapsed() < within, "still running after {within:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A pool with the bunny (depth 6, 1 KiB treelets) imported by the real binary, and a config
/// protecting it with `TOKEN`.
fn bunny_pool_and_config() -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let status = Command::new(BIN)
        .args([
            "import",
            "--quiet",
            "--depth",
            "6",
            "--treelet-bytes",
            "1024",
            "--scene",
        ])
        .arg(SCENE)
        .arg("--db")
        .arg(dir.path().join("pool"))
        .arg(bunny_path())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    let config = dir.path().join("serve.toml");
    std::fs::write(
        &config,
        format!("shutdown_grace_ms = 1000\n[scenes.{SCENE}]\ntokens = [\"{TOKEN}\"]\n"),
    )
    .unwrap();

    (dir, config)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_closes_clients_with_shutting_down_and_exits_0() {
    let (dir, config) = bunny_pool_and_config();
    let mut s = serve(dir.path(), &config);
    assert_eq!(s.fingerprint.len(), 64);
    assert_eq!(thp_enabled(&s.child), Some(0), "huge pages off by default");
    assert!(s.admin.starts_with("127.0.0.1:"), "{}", s.admin);
    let token_file = Path::new(&s.token_file);
    assert!(token_file.starts_with(dir.path().join("state")));
    {
        use std::os::unix::fs::PermissionsExt as _;
        let mode = std::fs::metadata(token_file).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600);
        let key = dir.path().join("state/key.pem");
        let mode = std::fs::metadata(key).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600);
    }

    let client = connect(s.quic, &s.fingerprint).await;
    let (mut control, info) = hello(&client.conn, SCENE, &[Channel::Normal], TOKEN).await;
    let d = info.unwrap();
    round(&client, &mut control, 1, &all_ids(&d)).await.unwrap();

    let t0 = Instant::now();
    signal(&s.child, "-TERM");
    let goodbye = tokio::time::timeout(Duration::from_secs(5), control.read()).await;
    assert_eq!(
        goodbye.unwrap(),
        Some(Frame::Goodbye {
            code: ErrorCode::ShuttingDown
        })
    );
    assert_eq!(
        close_code(&client.conn, Duration::from_secs(5)).await,
        code(ErrorCode::ShuttingDown)
    );
    let status = wait_exit(
        &mut s.child,
        Duration::from_secs(1) + Duration::from_secs(3),
    );
    assert_eq!(status.code(), Some(0), "{status}");
    eprintln!("SIGTERM → exit 0 in {:?}", t0.elapsed());

    // Same data dir: the certificate and the admin token are reused; SIGINT also ends cleanly.
    let mut again = serve(dir.path(), &config);
    assert_eq!(again.fingerprint, s.fingerprint);
    assert_eq!(again.token_file, s.token_file);
    let client = connect(again.quic, &again.fingerprint).await;
    let (_c, info) = hello(&client.conn, SCENE, &[], TOKEN).await;
    info.unwrap();
    signal(&again.child, "-INT");
    assert_eq!(
        close_code(&client.conn, Duration::from_secs(5)).await,
        code(ErrorCode::ShuttingDown)
    );
    let status = wait_exit(&mut again.child, Duration::from_secs(4));
    assert_eq!(status.code(), Some(0), "{status}");
}

/// SIGHUP reads the config again and puts its scene rules in force: a token taken out of the
/// scene's token files ends the session it let in (close code Unauthorized, the reason naming
/// the scene) and opens nothing more, a token added opens the scene, every other session goes
/// on; a config that no longer loads changes nothing and the server serves on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_puts_new_tokens_in_force_and_ends_only_revoked_sessions() {
    let (dir, config) = bunny_pool_and_config();
    let token_file = |name: &str, token: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, format!("{token}\n")).unwrap();
        path.display().to_string()
    };
    let (alpha, beta, gamma) = (
        token_file("alpha.token", "alpha"),
        token_file("beta.token", "beta"),
        token_file("gamma.token", "gamma"),
    );
    let rules = |files: &[&str]| {
        let files: Vec<String> = files.iter().map(|f| format!("{f:?}")).collect();
        format!(
            "shutdown_grace_ms = 1000\n[scenes.{SCENE}]\ntoken_files = [{}]\n",
            files.join(", ")
        )
    };
    std::fs::write(&config, rules(&[&alpha, &beta])).unwrap();
    let mut s = serve(dir.path(), &config);
    let admin_token = std::fs::read_to_string(&s.token_file).unwrap();
    let unauthorized = || {
        let metrics = http_get(&s.admin, "/metrics", admin_token.trim());
        sample(&metrics, "arbor_errors_total{kind=\"unauthorized\"}")
    };

    let revoked = connect(s.quic, &s.fingerprint).await;
    let (mut revoked_control, info) = hello(&revoked.conn, SCENE, &[], "alpha").await;
    let ids = all_ids(&info.unwrap());
    round(&revoked, &mut revoked_control, 1, &ids)
        .await
        .unwrap();
    let kept = connect(s.quic, &s.fingerprint).await;
    let (mut kept_control, info) = hello(&kept.conn, SCENE, &[], "beta").await;
    info.unwrap();
    round(&kept, &mut kept_control, 1, &ids).await.unwrap();
    let refused_before = unauthorized();

    // alpha's file taken out, gamma's added.
    std::fs::write(&config, rules(&[&beta, &gamma])).unwrap();
    signal(&s.child, "-HUP");
    let (code_, reason) = close_code_and_reason(&revoked.conn, Duration::from_secs(5))
        .await
        .expect("the revoked session is closed");
    assert_eq!(Ok(code_), code(ErrorCode::Unauthorized));
    assert!(
        reason.contains("revoked") && reason.contains(SCENE),
        "{reason}"
    );
    round(&kept, &mut kept_control, 2, &ids)
        .await
        .expect("the session beta let in goes on");
    for (token, opens) in [("alpha", false), ("beta", true), ("gamma", true)] {
        let c = connect(s.quic, &s.fingerprint).await;
        let (_control, info) = hello(&c.conn, SCENE, &[], token).await;
        assert_eq!(info.is_ok(), opens, "{token}: {info:?}");
    }
    assert_eq!(
        unauthorized(),
        refused_before + 2.0,
        "the revoked session and alpha's hello"
    );

    // A config that does not load leaves the rules in force, and the server serving.
    std::fs::write(&config, "no_such_key = 1\n").unwrap();
    signal(&s.child, "-HUP");
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(s.child.try_wait().unwrap().is_none(), "the server ended");
    for (token, opens) in [("alpha", false), ("gamma", true)] {
        let c = connect(s.quic, &s.fingerprint).await;
        let (_control, info) = hello(&c.conn, SCENE, &[], token).await;
        assert_eq!(info.is_ok(), opens, "{token}: {info:?}");
    }
    round(&kept, &mut kept_control, 3, &ids).await.unwrap();
    signal(&s.child, "-TERM");
    let status = wait_exit(&mut s.child, Duration::from_secs(5));
    assert_eq!(status.code(), Some(0), "{status}");
}

/// What clients pin for `der`.
fn pin(der: &rustls::pki_types::CertificateDer<'_>) -> String {
    arbor_server::service::tls::fingerprint(der)
}

/// A session on the bunny (pinning what the server printed) that fetched the whole scene once:
/// the client, its control stream and the scene's treelets.
async fn fetching_session(s: &Serving) -> (Client, Control, Vec<arbor_proto::TreeletId>) {
    let session = connect(s.quic, &s.fingerprint).await;
    let (mut control, info) = hello(&session.conn, SCENE, &[], TOKEN).await;
    let ids = all_ids(&info.unwrap());
    round(&session, &mut control, 1, &ids).await.unwrap();
    (session, control, ids)
}

/// SIGHUP renews the certificate and the admin token the way certbot's deploy hook or a
/// rotated Kubernetes secret does (the files rewritten in place, then `systemctl reload`): the
/// next QUIC handshake presents the new certificate and the admin API wants the new token,
/// while the session begun under the old certificate goes on; a key that is not its
/// certificate's changes nothing and `/metrics` says the reload failed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_renews_the_certificate_and_admin_token_without_a_restart() {
    let (dir, config) = bunny_pool_and_config();
    let tls = dir.path().join("tls");
    std::fs::create_dir_all(&tls).unwrap();
    let token_file = dir.path().join("admin.token");
    let first = write_pair(&tls, 2030);
    std::fs::write(&token_file, "first\n").unwrap();
    let settings = format!(
        "shutdown_grace_ms = 1000\ncert = {:?}\nkey = {:?}\nadmin_token_file = {:?}\n\
         [scenes.{SCENE}]\ntokens = [\"{TOKEN}\"]\n",
        tls.join("cert.pem"),
        tls.join("key.pem"),
        token_file
    );
    std::fs::write(&config, settings).unwrap();
    let mut s = serve(dir.path(), &config);
    assert_eq!(s.fingerprint, pin(&first));
    let (session, mut control, ids) = fetching_session(&s).await;

    let second = write_pair(&tls, 2031);
    std::fs::write(&token_file, "second\n").unwrap();
    signal(&s.child, "-HUP");
    let t0 = Instant::now();
    let renewed = loop {
        match connect_with(s.quic, &pin(&second), ClientOptions::default()).await {
            Ok(c) => break c,
            Err(e) => assert!(
                t0.elapsed() < Duration::from_secs(5),
                "the new certificate not presented 5 s after SIGHUP: {e}"
            ),
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let (_renewed_control, info) = hello(&renewed.conn, SCENE, &[], TOKEN).await;
    info.expect("a client pinning the renewed certificate is served");
    assert!(
        connect_with(s.quic, &pin(&first), ClientOptions::default())
            .await
            .is_err(),
        "the old certificate still presented"
    );
    round(&session, &mut control, 2, &ids)
        .await
        .expect("the session begun under the old certificate goes on");
    let refused = http_answer(&s.admin, "/metrics", "first");
    assert!(refused.starts_with("HTTP/1.1 401"), "{refused}");
    let metrics = http_get(&s.admin, "/metrics", "second");
    assert_eq!(
        sample(
            &metrics,
            "arbor_tls_certificate_expiry_timestamp_seconds{listener=\"quic\"}"
        ),
        new_year(2031)
    );
    assert_eq!(
        sample(&metrics, "arbor_config_reloads_total{outcome=\"applied\"}"),
        1.0
    );

    // A key that is not the certificate's: the reload fails, the renewed pair stays.
    std::fs::write(
        tls.join("key.pem"),
        rcgen::KeyPair::generate().unwrap().serialize_pem(),
    )
    .unwrap();
    signal(&s.child, "-HUP");
    let t0 = Instant::now();
    while sample(
        &http_get(&s.admin, "/metrics", "second"),
        "arbor_config_last_reload_successful",
    ) != 0.0
    {
        assert!(
            t0.elapsed() < Duration::from_secs(5),
            "the failed reload not counted"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    connect(s.quic, &pin(&second)).await;
    round(&session, &mut control, 3, &ids).await.unwrap();
    signal(&s.child, "-TERM");
    let status = wait_exit(&mut s.child, Duration::from_secs(5));
    assert_eq!(status.code(), Some(0), "{status}");
}

/// With `config_watch_secs`, files rewritten by something that cannot signal the process (the
/// kubelet updating a mounted Secret) are reloaded on their own: the renewed certificate is
/// presented and a token added opens its scene, each change reloaded once; a configuration
/// that stops loading is tried once, counted as a failed reload, and not retried until it
/// changes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watched_configuration_is_reloaded_without_a_signal() {
    let (dir, config) = bunny_pool_and_config();
    let tls = dir.path().join("tls");
    std::fs::create_dir_all(&tls).unwrap();
    let first = write_pair(&tls, 2030);
    let tokens = dir.path().join("bunny.token");
    std::fs::write(&tokens, format!("{TOKEN}\n")).unwrap();
    let newcomer = dir.path().join("newcomer.token");
    std::fs::write(&newcomer, "newcomer\n").unwrap();
    let settings = |token_files: &[&Path]| {
        format!(
            "shutdown_grace_ms = 1000\nconfig_watch_secs = 1\ncert = {:?}\nkey = {:?}\n\
             [scenes.{SCENE}]\ntoken_files = {:?}\n",
            tls.join("cert.pem"),
            tls.join("key.pem"),
            token_files
        )
    };
    std::fs::write(&config, settings(&[&tokens])).unwrap();
    let mut s = serve(dir.path(), &config);
    let admin_token = std::fs::read_to_string(&s.token_file).unwrap();
    let metrics = || http_get(&s.admin, "/metrics", admin_token.trim());
    assert_eq!(s.fingerprint, pin(&first));
    let (session, mut control, ids) = fetching_session(&s).await;

    let second = write_pair(&tls, 2031);
    std::fs::write(&config, settings(&[&tokens, &newcomer])).unwrap();
    let t0 = Instant::now();
    while connect_with(s.quic, &pin(&second), ClientOptions::default())
        .await
        .is_err()
    {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "the renewed certificate not presented 10 s after it was written"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let c = connect(s.quic, &pin(&second)).await;
    let (_newcomer, info) = hello(&c.conn, SCENE, &[], "newcomer").await;
    info.expect("the token added to the file opens the scene");
    round(&session, &mut control, 2, &ids)
        .await
        .expect("the session goes on");
    tokio::time::sleep(Duration::from_secs(3)).await;
    let applied = "arbor_config_reloads_total{outcome=\"applied\"}";
    assert_eq!(sample(&metrics(), applied), 1.0, "one change, one reload");

    std::fs::write(&config, "no_such_key = 1\n").unwrap();
    let failed = "arbor_config_reloads_total{outcome=\"failed\"}";
    let t0 = Instant::now();
    while sample(&metrics(), failed) < 1.0 {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "the broken configuration not tried"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(Duration::from_secs(3)).await;
    let now = metrics();
    assert_eq!(sample(&now, failed), 1.0, "retried without a change");
    assert_eq!(sample(&now, "arbor_config_last_reload_successful"), 0.0);
    assert_eq!(sample(&now, applied), 1.0);
    round(&session, &mut control, 3, &ids).await.unwrap();
    signal(&s.child, "-TERM");
    let status = wait_exit(&mut s.child, Duration::from_secs(5));
    assert_eq!(status.code(), Some(0), "{status}");
}

/// A reader that leaves before the serving lines are written (a script that read what it
/// needed, a closed terminal) does not stop the service: the write fails, the server warns and
/// serves on, and still ends cleanly on SIGTERM.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_closed_stdout_does_not_stop_the_service() {
    let (dir, config) = bunny_pool_and_config();
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let log = dir.path().join("serve.log");
    // This server lets its allocator ask for transparent huge pages (the key precedes the
    // scene tables).
    let with_thp = dir.path().join("thp.toml");
    let text = std::fs::read_to_string(&config).unwrap();
    std::fs::write(&with_thp, format!("transparent_huge_pages = true\n{text}")).unwrap();
    let mut child = Command::new(BIN)
        .args(["serve", "--db"])
        .arg(dir.path().join("pool"))
        .args(["--listen", &format!("127.0.0.1:{port}"), "--admin", "off"])
        .arg("--config")
        .arg(&with_thp)
        .arg("--data-dir")
        .arg(dir.path().join("state"))
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let t0 = Instant::now();
    let warned = loop {
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        if text.contains("could not print the serving lines") {
            break text;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "serve exited with its stdout closed: {text}"
        );
        assert!(t0.elapsed() < Duration::from_secs(20), "no warning: {text}");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(warned.contains("Broken pipe"), "{warned}");
    std::thread::sleep(Duration::from_millis(200));
    assert!(child.try_wait().unwrap().is_none(), "still serving");
    assert_eq!(
        thp_enabled(&child),
        Some(1),
        "transparent_huge_pages = true"
    );
    // The fingerprint it could not print: that of the certificate it made in its data dir.
    let fingerprint = arbor_server::service::tls::load_or_create(
        &arbor_server::service::config::TlsSource::SelfSigned,
        &dir.path().join("state"),
    )
    .unwrap()
    .fingerprint;
    let addr: std::net::SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let client = connect(addr, &fingerprint).await;
    let (_control, info) = hello(&client.conn, SCENE, &[Channel::Normal], TOKEN).await;
    info.unwrap();
    signal(&child, "-TERM");
    let status = wait_exit(&mut child, Duration::from_secs(4));
    assert_eq!(status.code(), Some(0), "{status}");
}

#[test]
fn serve_help_has_examples_and_bad_config_is_named() {
    let out = Command::new(BIN)
        .args(["serve", "--help"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    assert!(help.contains("Examples:"), "{help}");
    assert!(help.contains("--admin"), "{help}");
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("bad.toml");
    std::fs::write(&config, "db = \"x\"\nmax_connections = \"lots\"\n").unwrap();
    let out = Command::new(BIN)
        .args(["serve", "--config"])
        .arg(&config)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("max_connections"), "{err}");
    // Serving never creates a pool.
    let missing = dir.path().join("no-pool");
    let out = Command::new(BIN)
        .args(["serve", "--listen", "127.0.0.1:0", "--admin", "off", "--db"])
        .arg(&missing)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no pool"));
    assert!(!missing.exists());
}

/// One `GET` over HTTP/1.1 with a bearer token; the body.
fn http_get(addr: &str, path: &str, token: &str) -> String {
    let reply = http_answer(addr, path, token);
    assert!(reply.starts_with("HTTP/1.1 200"), "{reply}");
    reply.split_once("\r\n\r\n").unwrap().1.to_owned()
}

/// The whole answer to a GET with `token`, whatever its status.
fn http_answer(addr: &str, path: &str, token: &str) -> String {
    use std::io::{Read as _, Write as _};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {token}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut reply = String::new();
    s.read_to_string(&mut reply).unwrap();
    reply
}

/// The value of an unlabelled sample in Prometheus text.
fn sample(metrics: &str, name: &str) -> f64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
        .unwrap_or_else(|| panic!("{name} missing from /metrics"))
}

async fn next(c: &mut arbor_client_net::TreeletClient) -> arbor_client_net::ClientEvent {
    tokio::time::timeout(Duration::from_secs(30), c.next_event())
        .await
        .expect("no client event in time")
        .expect("the client ended")
}

/// Receives `n` distinct treelets.
async fn receive(
    c: &mut arbor_client_net::TreeletClient,
    n: usize,
) -> std::collections::BTreeSet<u32> {
    let mut ids = std::collections::BTreeSet::new();
    while ids.len() < n {
        match next(c).await {
            arbor_client_net::ClientEvent::Treelet(t) => {
                ids.insert(t.id.0);
            }
            other => panic!("expected treelets, got {other:?}"),
        }
    }
    ids
}

/// `pool_prewarm`: with "always" in the config the server reads the whole pool into the page
/// cache at start and `/metrics` says how much and that it is done; stopped, it leaves the list
/// of the pool's pages in the page cache in its data directory, and the next start reads those
/// first; `--pool-prewarm off` overrides the file and nothing is read.
#[test]
fn the_pool_is_prewarmed_at_start_unless_turned_off() {
    let (dir, config) = bunny_pool_and_config();
    let text = std::fs::read_to_string(&config).unwrap();
    std::fs::write(&config, format!("pool_prewarm = \"always\"\n{text}")).unwrap();
    let db_bytes = std::fs::metadata(dir.path().join("pool").join("db"))
        .unwrap()
        .len();
    assert!(db_bytes > 0);
    let done = |server: &Serving| {
        let token = std::fs::read_to_string(&server.token_file).unwrap();
        let t0 = std::time::Instant::now();
        loop {
            let metrics = http_get(&server.admin, "/metrics", token.trim());
            if sample(&metrics, "arbor_pool_prewarm_done") == 1.0 {
                return metrics;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "the prewarm did not end in 30 s: {metrics}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    };
    let mut warmed = serve(dir.path(), &config);
    let metrics = done(&warmed);
    let total = sample(&metrics, "arbor_pool_prewarm_total_bytes");
    assert!(
        total >= db_bytes as f64,
        "{total} < the db file's {db_bytes}"
    );
    assert_eq!(sample(&metrics, "arbor_pool_prewarm_read_bytes"), total);
    assert_eq!(
        sample(&metrics, "arbor_pool_prewarm_hot_bytes"),
        0.0,
        "no earlier run, no hot pages"
    );
    signal(&warmed.child, "-TERM");
    assert_eq!(
        wait_exit(&mut warmed.child, Duration::from_secs(5)).code(),
        Some(0)
    );

    // Stopping, it saved which of the pool's pages were in the page cache (all of them, just
    // read): the next start reads those first, and says how many bytes.
    use arbor_server::service::hot_pages;
    let pool = dir.path().join("pool");
    let list = dir.path().join("state").join(hot_pages::HOT_PAGES_FILE);
    let hot = hot_pages::load(&list, &pool).unwrap();
    let db = hot.iter().find(|f| f.name == "db").expect("db in the list");
    assert!(db.bytes() > 0, "{hot:?}");
    let files = arbor_server::service::prewarm::pool_files(&pool).unwrap();
    let hot_bytes: u64 = hot_pages::reads(&hot, &pool, &files)
        .iter()
        .map(|r| r.len)
        .sum();
    let mut again = serve(dir.path(), &config);
    let metrics = done(&again);
    assert_eq!(
        sample(&metrics, "arbor_pool_prewarm_hot_bytes"),
        hot_bytes as f64
    );
    assert_eq!(
        sample(&metrics, "arbor_pool_prewarm_total_bytes"),
        files.iter().map(|f| f.1).sum::<u64>() as f64,
        "the hot pages, then the rest: every file once"
    );
    signal(&again.child, "-TERM");
    assert_eq!(
        wait_exit(&mut again.child, Duration::from_secs(5)).code(),
        Some(0)
    );

    let off = serve_with(
        dir.path(),
        &config,
        "127.0.0.1:0",
        &["--pool-prewarm", "off"],
    );
    let metrics = done(&off);
    assert_eq!(sample(&metrics, "arbor_pool_prewarm_total_bytes"), 0.0);
    assert_eq!(sample(&metrics, "arbor_pool_prewarm_read_bytes"), 0.0);
}

/// Serves on a free loopback port and starts a client library connection to it: the listen
/// address (to serve on again), the server, the client.
fn serve_and_connect(
    dir: &Path,
    config: &Path,
) -> (String, Serving, arbor_client_net::TreeletClient) {
    use arbor_client_net::{ClientConfig, ServerUrl, TreeletClient, Trust};
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let listen = format!("127.0.0.1:{port}");
    let server = serve_on(dir, config, &listen);
    let url = ServerUrl {
        host: "127.0.0.1".into(),
        port,
        scene: SCENE.into(),
    };
    let client = TreeletClient::start(
        ClientConfig::new(url, Trust::Fingerprint(server.fingerprint.clone()))
            .with_token(TOKEN)
            .with_channels([Channel::Normal]),
    )
    .unwrap();
    (listen, server, client)
}

/// The real client library against the real binary: treelets arrive, `/metrics` counts exactly
/// that traffic, SIGTERM reaches the client as ShuttingDown with a reconnect scheduled, and when
/// the server is back on the same port the client reconnects by itself, re-sends its latest
/// list and receives it again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_reconnects_when_the_server_is_back_and_metrics_count_the_traffic() {
    use arbor_client_net::ClientEvent;
    let (dir, config) = bunny_pool_and_config();
    let (listen, mut first, mut client) = serve_and_connect(dir.path(), &config);
    let scene = match next(&mut client).await {
        ClientEvent::Connected(d) => d,
        other => panic!("expected Connected, got {other:?}"),
    };
    let n = 40.min(scene.treelet_count) as usize;
    let list: Vec<_> = (0..n as u32)
        .map(|i| (arbor_proto::TreeletId(i), (n as u32 - i) as f32))
        .collect();
    client.request(list).unwrap();
    assert_eq!(receive(&mut client, n).await.len(), n);

    let token = std::fs::read_to_string(&first.token_file).unwrap();
    let metrics = http_get(&first.admin, "/metrics", token.trim());
    assert_eq!(
        sample(&metrics, "arbor_treelets_sent_total"),
        n as f64,
        "{metrics}"
    );
    assert_eq!(sample(&metrics, "arbor_request_lists_total"), 1.0);
    assert_eq!(sample(&metrics, "arbor_request_items_total"), n as f64);
    assert_eq!(sample(&metrics, "arbor_connections_accepted_total"), 1.0);
    assert_eq!(sample(&metrics, "arbor_connections_open"), 1.0);
    // The memory bound of the config it runs (defaults but for the grace), one scene.
    let bound = arbor_server::service::config::ServeConfig::new("pool").memory_bound(1);
    for (part, bytes) in bound.parts() {
        let name = format!("arbor_memory_bound_bytes{{part=\"{part}\"}}");
        assert_eq!(sample(&metrics, &name), bytes as f64, "{part}");
    }
    assert!(bound.cut_buffers() > 0 && bound.connections > 0);
    assert_eq!(
        sample(&metrics, "arbor_request_to_send_seconds_count"),
        n as f64
    );

    signal(&first.child, "-TERM");
    match next(&mut client).await {
        ClientEvent::Disconnected {
            code, reconnect_in, ..
        } => {
            assert_eq!(code, Some(ErrorCode::ShuttingDown));
            assert!(reconnect_in.is_some(), "ShuttingDown must not be final");
        }
        other => panic!("expected Disconnected, got {other:?}"),
    }
    assert_eq!(
        wait_exit(&mut first.child, Duration::from_secs(5)).code(),
        Some(0)
    );

    // Back on the same port with the same certificate: the client reconnects on its own and
    // re-sends its latest list.
    let mut second = serve_on(dir.path(), &config, &listen);
    assert_eq!(second.fingerprint, first.fingerprint);
    loop {
        match next(&mut client).await {
            ClientEvent::Connected(_) => break,
            ClientEvent::Disconnected { reconnect_in, .. } => {
                assert!(reconnect_in.is_some(), "gave up reconnecting")
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!(receive(&mut client, n).await.len(), n);
    assert!(client.stats().connects >= 2);
    client.close().await;
    signal(&second.child, "-TERM");
    assert_eq!(
        wait_exit(&mut second.child, Duration::from_secs(5)).code(),
        Some(0)
    );
}

/// A server killed with SIGKILL and started again on the same port and data dir resets the
/// connections of its previous life at once: the stateless-reset key is derived from the TLS
/// key, so the client accepts the new process's reset (`connection reset`) instead of waiting
/// for its 30 s idle timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_server_resets_its_old_connections_at_once() {
    use arbor_client_net::ClientEvent;
    let (dir, config) = bunny_pool_and_config();
    let (listen, mut first, mut client) = serve_and_connect(dir.path(), &config);
    assert!(matches!(next(&mut client).await, ClientEvent::Connected(_)));
    signal(&first.child, "-KILL");
    wait_exit(&mut first.child, Duration::from_secs(5));
    let second = serve_on(dir.path(), &config, &listen);
    assert_eq!(second.fingerprint, first.fingerprint);
    // A list makes the client send at once; the new process answers with a stateless reset.
    client
        .request(vec![(arbor_proto::TreeletId(0), 1.0)])
        .unwrap();
    // Without the shared key the client would only time out (after 30 s), saying so.
    let within = Duration::from_secs(60);
    let reason = match tokio::time::timeout(within, client.next_event()).await {
        Ok(Some(ClientEvent::Disconnected { reason, .. })) => reason,
        other => panic!("expected Disconnected, got {other:?}"),
    };
    assert!(reason.contains("reset by the server"), "{reason}");
    client.close().await;
}
