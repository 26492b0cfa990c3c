//! The shipped Prometheus files (`deploy/prometheus/`) against the real tools and a real daemon:
//! the alerting rules through `promtool check rules` and their unit tests through `promtool test
//! rules`; every metric the rules name declared by a daemon's `/metrics`, and that page clean
//! under `promtool check metrics`; and a real Prometheus, started on the shipped
//! `prometheus.yml` pointed at a daemon serving a damaged pool, that scrapes it, evaluates every
//! rule without an error and fires `ArborSceneDamaged` for the damaged scenes and no others.
//! `promtool` and `prometheus` come from Debian's `prometheus` package, which `scripts/test`
//! installs; without them these tests fail and say so.

mod common;

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use arbor_server::daemon::{DaemonOptions, RunningServer};
use arbor_server::service::config::AdminTokenSource;
use common::{TestPool, damaged_pool};
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

const ADMIN: &str = "admin-secret";

fn shipped(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deploy/prometheus")
        .join(file)
}

/// A tool of Debian's `prometheus` package, found on `PATH`; a missing one fails the test.
fn prometheus_tool(name: &str) -> PathBuf {
    std::env::var_os("PATH")
        .iter()
        .flat_map(std::env::split_paths)
        .map(|dir| dir.join(name))
        .find(|p| p.is_file())
        .unwrap_or_else(|| {
            panic!(
                "`{name}` is not installed: these tests need Debian's `prometheus` package \
                 (scripts/test installs it; by hand: apt-get install prometheus)"
            )
        })
}

/// Runs `promtool` with `args` in `dir`; its exit status and what it printed.
fn promtool(dir: &Path, args: &[&str], stdin: Option<&str>) -> (bool, String) {
    let mut child = Command::new(prometheus_tool("promtool"))
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("promtool starts");
    {
        use std::io::Write as _;
        let mut input = child.stdin.take().unwrap();
        input
            .write_all(stdin.unwrap_or_default().as_bytes())
            .unwrap();
    }
    let out = child.wait_with_output().unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// A `GET` over HTTP/1.0 (so the answer is neither chunked nor kept alive): status and body;
/// status 0 when nothing listens yet.
async fn get(addr: SocketAddr, path: &str, token: Option<&str>) -> (u16, String) {
    let Ok(mut s) = tokio::net::TcpStream::connect(addr).await else {
        return (0, String::new());
    };
    let auth = token
        .map(|t| format!("Authorization: Bearer {t}\r\n"))
        .unwrap_or_default();
    s.write_all(format!("GET {path} HTTP/1.0\r\nHost: x\r\n{auth}\r\n").as_bytes())
        .await
        .unwrap();
    let mut raw = String::new();
    s.read_to_string(&mut raw).await.unwrap();
    let (head, body) = raw.split_once("\r\n\r\n").unwrap_or((&raw, ""));
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, body.to_owned())
}

/// The `arbor_*` names the rules' expressions and texts mention.
fn names_in_rules(rules: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut rest = rules;
    while let Some(at) = rest.find("arbor_") {
        let name: String = rest[at..]
            .chars()
            .take_while(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == '_')
            .collect();
        rest = &rest[at + name.len()..];
        names.insert(name);
    }
    names
}

/// The families a metrics page declares (`# TYPE name kind`).
fn families(page: &str) -> BTreeSet<String> {
    page.lines()
        .filter_map(|l| l.strip_prefix("# TYPE "))
        .filter_map(|l| l.split(' ').next())
        .map(str::to_owned)
        .collect()
}

/// A daemon with the admin token [`ADMIN`], checking every scene every 300 ms and copying the
/// pool every 2 s under a scratch root (so every family the rules name has samples).
async fn daemon(pool: &TestPool, copy_root: &Path) -> RunningServer {
    let mut config = pool.config();
    config.admin_token = AdminTokenSource::Inline(ADMIN.into());
    for scene in ["holes", "garbage"] {
        config.scenes.insert(
            scene.into(),
            arbor_server::service::config::SceneAccess::Tokens(vec![common::TOKEN.into()]),
        );
    }
    common::start_with(
        config,
        DaemonOptions {
            check_every: Some(Duration::from_millis(300)),
            copy_root: Some(copy_root.to_owned()),
            copy_every: Some(Duration::from_secs(2)),
            ..DaemonOptions::default()
        },
    )
    .await
}

#[test]
fn the_shipped_rules_pass_promtool_and_their_unit_tests() {
    let dir = shipped("");
    let (ok, out) = promtool(&dir, &["check", "rules", "arbor-alerts.yml"], None);
    assert!(
        ok && out.contains("SUCCESS"),
        "promtool check rules:\n{out}"
    );
    let (ok, out) = promtool(&dir, &["test", "rules", "arbor-alerts.test.yml"], None);
    assert!(ok && out.contains("SUCCESS"), "promtool test rules:\n{out}");
    // Every alert of the rules has a unit test.
    let rules = std::fs::read_to_string(shipped("arbor-alerts.yml")).unwrap();
    let tests = std::fs::read_to_string(shipped("arbor-alerts.test.yml")).unwrap();
    let alerts: Vec<&str> = rules
        .lines()
        .filter_map(|l| l.trim().strip_prefix("- alert: "))
        .collect();
    assert!(alerts.len() >= 10, "{alerts:?}");
    for alert in alerts {
        assert!(
            tests.contains(&format!("alertname: {alert}\n")),
            "{alert} has no unit test in arbor-alerts.test.yml"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_real_prometheus_scrapes_the_daemon_and_fires_the_shipped_alerts() {
    let pool = damaged_pool();
    let copies = tempfile::tempdir().unwrap();
    let server = daemon(&pool, copies.path()).await;
    let admin = server.admin_addr.unwrap();

    // Every metric the rules name is a family the daemon declares, and its page is clean.
    let rules = std::fs::read_to_string(shipped("arbor-alerts.yml")).unwrap();
    let named = names_in_rules(&rules);
    assert!(named.len() >= 15, "{named:?}");
    let t0 = Instant::now();
    let page = loop {
        let (status, page) = get(admin, "/metrics", Some(ADMIN)).await;
        assert_eq!(status, 200, "{page}");
        let all_sampled = [
            "arbor_scene_check_ok{",
            "arbor_scene_check_end_seconds{",
            "arbor_pool_copy_next_scheduled_seconds ",
            "arbor_scene_check_next_scheduled_seconds ",
        ]
        .iter()
        .all(|s| page.contains(s));
        if all_sampled {
            break page;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "{page}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let declared = families(&page);
    for name in &named {
        assert!(
            declared.contains(name),
            "the rules name {name}, which the daemon does not serve"
        );
    }
    let (ok, out) = promtool(Path::new("."), &["check", "metrics"], Some(&page));
    assert!(
        ok && out.trim().is_empty(),
        "promtool check metrics:\n{out}"
    );

    // The shipped configuration, pointed at this daemon, scraped and evaluated every second.
    let token_file = copies.path().join("admin-token");
    std::fs::write(&token_file, ADMIN).unwrap();
    let mut config = std::fs::read_to_string(shipped("prometheus.yml")).unwrap();
    for (from, to) in [
        ("127.0.0.1:9090", admin.to_string()),
        (
            "/var/lib/arbor/admin-token",
            token_file.display().to_string(),
        ),
        (
            "- arbor-alerts.yml",
            format!("- {}", shipped("arbor-alerts.yml").display()),
        ),
        ("scrape_interval: 15s", "scrape_interval: 1s".into()),
        ("evaluation_interval: 15s", "evaluation_interval: 1s".into()),
    ] {
        assert!(config.contains(from), "prometheus.yml no longer has {from}");
        config = config.replace(from, &to);
    }
    let prometheus = Prometheus::start(&config);

    let firing = |alerts: &Value, name: &str| -> BTreeSet<String> {
        alerts["data"]["alerts"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|a| a["labels"]["alertname"] == name && a["state"] == "firing")
            .map(|a| a["labels"]["scene"].as_str().unwrap_or("").to_owned())
            .collect()
    };
    let t0 = Instant::now();
    let alerts = loop {
        let (status, body) = get(prometheus.addr, "/api/v1/alerts", None).await;
        if status == 200 {
            let alerts: Value = serde_json::from_str(&body).unwrap();
            if firing(&alerts, "ArborSceneDamaged").len() >= 2 {
                break alerts;
            }
        }
        assert!(
            t0.elapsed() < Duration::from_secs(90),
            "ArborSceneDamaged did not fire: {status} {body}\n{}",
            prometheus.log()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert_eq!(
        firing(&alerts, "ArborSceneDamaged"),
        BTreeSet::from(["garbage".to_owned(), "holes".to_owned()]),
        "{alerts}"
    );
    // What a healthy daemon must not raise, even as pending.
    for quiet in [
        "ArborDown",
        "ArborNotReady",
        "ArborPoolUnreadable",
        "ArborConnectionsRefused",
        "ArborSceneUnchecked",
        "ArborBackupMissing",
        "ArborScheduleStalled",
    ] {
        assert!(
            !alerts["data"]["alerts"]
                .as_array()
                .unwrap()
                .iter()
                .any(|a| a["labels"]["alertname"] == quiet),
            "{quiet} raised: {alerts}"
        );
    }

    // The daemon is a healthy target, and every rule evaluated on its real series without error.
    let (_, body) = get(prometheus.addr, "/api/v1/query?query=up", None).await;
    let up: Value = serde_json::from_str(&body).unwrap();
    let up = &up["data"]["result"][0];
    assert_eq!(up["metric"]["job"], "arbor", "{up}");
    assert_eq!(up["value"][1], "1", "{up}");
    let (_, body) = get(prometheus.addr, "/api/v1/rules", None).await;
    let groups: Value = serde_json::from_str(&body).unwrap();
    let evaluated: Vec<&Value> = groups["data"]["groups"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|g| g["rules"].as_array().unwrap())
        .collect();
    assert_eq!(
        evaluated.len(),
        rules.matches("- alert: ").count(),
        "{groups}"
    );
    for rule in evaluated {
        assert_eq!(rule["health"], "ok", "{rule}");
        assert!(
            !rule["lastEvaluation"]
                .as_str()
                .unwrap()
                .starts_with("0001-"),
            "never evaluated: {rule}"
        );
    }
    drop(prometheus);
    server.shutdown().await;
    drop(pool);
}

/// A Prometheus server on a free loopback port with its own scratch storage, stopped on drop.
struct Prometheus {
    child: Child,
    addr: SocketAddr,
    dir: tempfile::TempDir,
}

impl Prometheus {
    fn start(config: &str) -> Prometheus {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("prometheus.yml"), config).unwrap();
        let addr = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap();
        let log = std::fs::File::create(dir.path().join("log")).unwrap();
        let child = Command::new(prometheus_tool("prometheus"))
            .arg(format!(
                "--config.file={}",
                dir.path().join("prometheus.yml").display()
            ))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.path().join("data").display()
            ))
            .arg(format!("--web.listen-address={addr}"))
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .expect("prometheus starts");
        Prometheus { child, addr, dir }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("log")).unwrap_or_default()
    }
}

impl Drop for Prometheus {
    /// SIGTERM, so that it closes its storage, then SIGKILL after 5 s.
    fn drop(&mut self) {
        let pid = rustix::process::Pid::from_child(&self.child);
        let _ = rustix::process::kill_process(pid, rustix::process::Signal::TERM);
        let t0 = Instant::now();
        while matches!(self.child.try_wait(), Ok(None)) && t0.elapsed() < Duration::from_secs(5) {
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
