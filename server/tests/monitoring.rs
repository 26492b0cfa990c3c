//! The shipped monitoring files against the real tools and a real daemon. The alerting rules
//! (`deploy/prometheus/arbor-alerts.yml`) through `promtool check rules` and their unit tests
//! through `promtool test rules`; every metric they name declared by a daemon's `/metrics`, and
//! that page clean under `promtool check metrics`; a real Prometheus, started on the shipped
//! `prometheus.yml` pointed at a daemon serving a damaged pool, that scrapes it, evaluates every
//! rule without an error and fires `ArborSceneDamaged` for the damaged scenes and no others. The
//! Grafana dashboard (`deploy/grafana/arbor-dashboard.json`): its layout, and every panel's
//! query answered with data by a real Prometheus scraping a daemon a client has fetched from.
//! The Prometheus Operator's `PrometheusRule` (`deploy/kubernetes/prometheusrule.yaml`): the
//! same rules, line for line. Its `ServiceMonitor` (`deploy/kubernetes/servicemonitor.yaml`):
//! what it names found in the other manifests, and its endpoint's settings scraping a real
//! daemon's HTTPS admin API through a real Prometheus, the certificate checked.
//! `promtool` and `prometheus` come from Debian's `prometheus` package, which `scripts/test`
//! installs; without them these tests fail and say so.

mod common;

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use arbor_server::daemon::{DaemonOptions, RunningServer};
use arbor_server::service::config::{AdminTls, AdminTokenSource, TlsSource};
use common::{TestPool, damaged_pool};
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

const ADMIN: &str = "admin-secret";

/// A file of `deploy/prometheus/`.
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
/// status 0 when nothing listens yet, or what listens does not answer whole within 10 s.
async fn get(addr: SocketAddr, path: &str, token: Option<&str>) -> (u16, String) {
    let auth = token
        .map(|t| format!("Authorization: Bearer {t}\r\n"))
        .unwrap_or_default();
    let exchange = async {
        let mut s = tokio::net::TcpStream::connect(addr).await?;
        s.write_all(format!("GET {path} HTTP/1.0\r\nHost: x\r\n{auth}\r\n").as_bytes())
            .await?;
        let mut bytes = Vec::new();
        s.read_to_end(&mut bytes).await?;
        std::io::Result::Ok(bytes)
    };
    let Ok(Ok(bytes)) = tokio::time::timeout(Duration::from_secs(10), exchange).await else {
        return (0, String::new());
    };
    let raw = String::from_utf8_lossy(&bytes);
    let (head, body) = raw.split_once("\r\n\r\n").unwrap_or((&raw, ""));
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, body.to_owned())
}

/// The `arbor_*` names a text mentions.
fn arbor_names(text: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut rest = text;
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

/// Fails unless every `arbor_*` name in `text` (a family, or a histogram's `_bucket`, `_count`
/// or `_sum` series) is a family the metrics page `page` declares.
fn assert_served(text: &str, page: &str, file: &str) {
    let declared = families(page);
    for name in arbor_names(text) {
        let family = ["_bucket", "_count", "_sum"]
            .iter()
            .find_map(|s| name.strip_suffix(s))
            .filter(|f| declared.contains(*f))
            .unwrap_or(&name);
        assert!(
            declared.contains(family),
            "{file} reads {name}, which the daemon does not serve"
        );
    }
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
/// pool every 2 s under a scratch root, its background reads limited to 1 GB/s (so every
/// family the rules and the dashboard name has samples).
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
            background_read_rate: Some(1_000_000_000),
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

#[test]
fn the_operators_prometheusrule_holds_the_same_rules() {
    let rules = std::fs::read_to_string(shipped("arbor-alerts.yml")).unwrap();
    let groups: Vec<&str> = rules[rules.find("groups:\n").unwrap()..].lines().collect();
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/kubernetes/prometheusrule.yaml");
    let manifest = std::fs::read_to_string(path).unwrap();
    let spec = &manifest[manifest.find("\nspec:\n").expect("a spec") + "\nspec:\n".len()..];
    // The same lines, two spaces in.
    let undented: Vec<&str> = spec
        .lines()
        .map(|l| match l.strip_prefix("  ") {
            Some(rest) => rest,
            None => {
                assert!(l.is_empty(), "not under spec: {l:?}");
                l
            }
        })
        .collect();
    assert_eq!(
        undented, groups,
        "prometheusrule.yaml differs from arbor-alerts.yml"
    );
    // And promtool reads them as rules.
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("rules.yml"), undented.join("\n")).unwrap();
    let (ok, out) = promtool(dir.path(), &["check", "rules", "rules.yml"], None);
    let count = rules.matches("- alert: ").count();
    assert!(
        ok && out.contains(&format!("SUCCESS: {count} rules found")),
        "{out}"
    );
}

/// A file of `deploy/kubernetes/`.
fn manifest(file: &str) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deploy/kubernetes")
        .join(file);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The mapping under the one line `key:` of `yaml` (the lines indented deeper), for reading
/// the few fields of a hand-written manifest without a YAML parser.
fn block(yaml: &str, key: &str) -> String {
    let lines: Vec<&str> = yaml
        .lines()
        .filter(|l| !l.trim_start().starts_with('#'))
        .collect();
    let heads: Vec<usize> = (0..lines.len())
        .filter(|&i| lines[i].trim().trim_start_matches("- ") == format!("{key}:"))
        .collect();
    assert_eq!(heads.len(), 1, "one '{key}:' in\n{yaml}");
    let indent = |l: &str| l.len() - l.trim_start().len();
    let own = indent(lines[heads[0]]);
    lines[heads[0] + 1..]
        .iter()
        .take_while(|l| l.trim().is_empty() || indent(l) > own)
        .copied()
        .collect::<Vec<_>>()
        .join("\n")
}

/// The value of the one `key: value` line of `yaml` (a list item's `- key:` too).
fn field<'a>(yaml: &'a str, key: &str) -> &'a str {
    let values: Vec<&str> = yaml
        .lines()
        .filter_map(|l| {
            l.trim()
                .trim_start_matches("- ")
                .strip_prefix(&format!("{key}: "))
        })
        .map(|v| v.trim().trim_matches('"'))
        .collect();
    assert_eq!(values.len(), 1, "one '{key}:' in\n{yaml}");
    values[0]
}

/// The one document of a multi-document manifest whose `metadata` has `name: NAME`.
fn document<'a>(yaml: &'a str, name: &str) -> &'a str {
    let found: Vec<&str> = yaml
        .split("\n---\n")
        .filter(|d| field(&block(d, "metadata"), "name") == name)
        .collect();
    assert_eq!(found.len(), 1, "one document named {name}");
    found[0]
}

/// The labels a `matchLabels:` or `labels:` block lists, as `key=value`.
fn labels(block: &str) -> BTreeSet<String> {
    block
        .lines()
        .filter_map(|l| l.trim().split_once(": "))
        .map(|(k, v)| format!("{k}={v}"))
        .collect()
}

/// The ServiceMonitor (`deploy/kubernetes/servicemonitor.yaml`) names what the other manifests
/// hold: the admin Service (by its labels, not the QUIC one) and its port, the Secrets' token
/// and certificate under the keys the server reads, the namespace, and the job the rules
/// select. Then a real Prometheus scrapes a real daemon's HTTPS admin API with its endpoint's
/// settings as the Operator would write them (scheme, path, the bearer token, the replicas'
/// certificate as CA, `serverName`, the job relabeling): the target is up as job `arbor`,
/// while a job that expects another name in the certificate is refused by the TLS check.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_servicemonitor_scrapes_the_replicas_admin_api_over_verified_tls() {
    let monitor = manifest("servicemonitor.yaml");
    let services = manifest("service.yaml");
    let admin_service = document(&services, "arbor-admin");
    let quic_service = document(&services, "arbor-quic");
    let endpoint = block(&monitor, "endpoints");

    let (metadata, admin_metadata) = (
        block(&monitor, "metadata"),
        block(admin_service, "metadata"),
    );
    assert_eq!(
        field(&metadata, "namespace"),
        field(&admin_metadata, "namespace")
    );
    let wanted = labels(&block(&monitor, "matchLabels"));
    assert!(
        wanted.is_subset(&labels(&block(admin_service, "labels"))),
        "the selector {wanted:?} misses arbor-admin"
    );
    assert!(
        !wanted.is_subset(&labels(&block(quic_service, "labels"))),
        "the selector {wanted:?} also picks arbor-quic"
    );
    let port = field(&endpoint, "port");
    assert_eq!(port, field(&block(admin_service, "ports"), "name"));

    let token = block(&endpoint, "credentials");
    let secrets = manifest("secret.yaml");
    assert_eq!(
        field(&token, "name"),
        field(&block(&secrets, "metadata"), "name")
    );
    let token_key = field(&token, "key");
    assert!(
        block(&secrets, "stringData")
            .lines()
            .any(|l| l.trim().starts_with(&format!("{token_key}:"))),
        "secret.yaml has no key {token_key}"
    );
    let config = manifest("configmap.yaml");
    assert!(
        config.contains(&format!(
            "admin_token_file = \"/etc/arbor/secrets/{token_key}\""
        )),
        "the server does not read the admin token from key {token_key}"
    );
    let ca = block(&endpoint, "secret");
    let deployment = manifest("deployment.yaml");
    assert!(
        deployment.contains(&format!("secretName: {}", field(&ca, "name"))),
        "the replicas do not mount {}",
        field(&ca, "name")
    );
    let ca_key = field(&ca, "key");
    assert!(
        config.contains(&format!("cert = \"/etc/arbor/tls/{ca_key}\"")),
        "the replicas' certificate is not key {ca_key}"
    );
    assert!(
        !config.contains("admin_cert"),
        "the admin listener must present the replicas' certificate"
    );
    let tls = block(&endpoint, "tlsConfig");
    let server_name = field(&tls, "serverName");
    let guide =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/README.md"))
            .unwrap();
    assert!(
        guide.contains(&format!("subjectAltName=DNS:{server_name}")),
        "deploy/README.md's certificate does not carry {server_name}"
    );
    let relabel = block(&endpoint, "relabelings");
    assert_eq!(field(&relabel, "targetLabel"), "job");
    let job = field(&relabel, "replacement");
    let rules = std::fs::read_to_string(shipped("arbor-alerts.yml")).unwrap();
    assert!(
        rules.contains(&format!("up{{job=\"{job}\"}}")),
        "the rules select another job"
    );

    // A replica: the shared certificate names `server_name` only (Prometheus dials the pod's
    // address, 127.0.0.1 here, and checks the name it was given), the admin API on HTTPS.
    let dir = tempfile::tempdir().unwrap();
    let identity = rcgen::generate_simple_self_signed(vec![server_name.to_owned()]).unwrap();
    let (cert, key) = (dir.path().join(ca_key), dir.path().join("tls.key"));
    std::fs::write(&cert, identity.cert.pem()).unwrap();
    std::fs::write(&key, identity.signing_key.serialize_pem()).unwrap();
    let pool = TestPool::new();
    let mut config = pool.config();
    config.admin_token = AdminTokenSource::Inline(ADMIN.into());
    config.tls = TlsSource::Files {
        cert: cert.clone(),
        key,
    };
    config.admin_tls = AdminTls::On;
    let server = common::start(config).await;
    assert!(server.admin_https);
    let admin = server.admin_addr.unwrap();

    let token_file = dir.path().join(token_key);
    std::fs::write(&token_file, ADMIN).unwrap();
    let scrape = |name: &str, tls_name: &str| {
        format!(
            "  - job_name: {name}\n    scrape_interval: 1s\n    scheme: {scheme}\n    metrics_path: {path}\n    \
             authorization: {{ type: {kind}, credentials_file: {token} }}\n    \
             tls_config: {{ ca_file: {ca}, server_name: {tls_name} }}\n    \
             static_configs: [{{ targets: ['{admin}'] }}]\n    \
             relabel_configs: [{{ target_label: job, replacement: {job}-{name} }}]\n",
            scheme = field(&endpoint, "scheme"),
            path = field(&endpoint, "path"),
            kind = field(&block(&endpoint, "authorization"), "type"),
            token = token_file.display(),
            ca = cert.display(),
        )
    };
    let prometheus = Prometheus::start(
        tempfile::tempdir().unwrap(),
        &format!(
            "scrape_configs:\n{}{}",
            scrape("monitor", server_name),
            scrape("other", "other.example.org")
        ),
    )
    .await;
    let targets = prometheus
        .api_until("/api/v1/targets", "both targets scraped", |targets| {
            targets["data"]["activeTargets"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|t| t["health"] != "unknown")
                .count()
                == 2
        })
        .await;
    let target = |name: &str| {
        targets["data"]["activeTargets"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["labels"]["job"] == format!("{job}-{name}"))
            .unwrap_or_else(|| panic!("no target {name}: {targets}"))
            .clone()
    };
    let good = target("monitor");
    assert_eq!(good["health"], "up", "{good}");
    let wrong = target("other");
    assert_eq!(wrong["health"], "down", "{wrong}");
    assert!(
        wrong["lastError"]
            .as_str()
            .is_some_and(|e| e.contains("certificate") && e.contains("other.example.org")),
        "{wrong}"
    );
    let info = query(&prometheus, "arbor_build_info").await;
    let info = &info["data"]["result"];
    assert_eq!(info.as_array().map(Vec::len), Some(1), "{info}");
    assert_eq!(info[0]["metric"]["job"], format!("{job}-monitor"), "{info}");
    drop(prometheus);
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_real_prometheus_scrapes_the_daemon_and_fires_the_shipped_alerts() {
    let pool = damaged_pool();
    let copies = tempfile::tempdir().unwrap();
    let server = daemon(&pool, copies.path()).await;
    let admin = server.admin_addr.unwrap();

    // Every metric the rules name is a family the daemon declares, and its page is clean.
    let rules = std::fs::read_to_string(shipped("arbor-alerts.yml")).unwrap();
    let named = arbor_names(&rules);
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
    assert_served(&rules, &page, "arbor-alerts.yml");
    let (ok, out) = promtool(Path::new("."), &["check", "metrics"], Some(&page));
    assert!(
        ok && out.trim().is_empty(),
        "promtool check metrics:\n{out}"
    );

    let prometheus = Prometheus::watching(admin).await;

    let firing = |alerts: &Value, name: &str| -> BTreeSet<String> {
        alerts["data"]["alerts"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|a| a["labels"]["alertname"] == name && a["state"] == "firing")
            .map(|a| a["labels"]["scene"].as_str().unwrap_or("").to_owned())
            .collect()
    };
    let alerts = prometheus
        .api_until("/api/v1/alerts", "ArborSceneDamaged fired", |alerts| {
            firing(alerts, "ArborSceneDamaged").len() >= 2
        })
        .await;
    assert_eq!(
        firing(&alerts, "ArborSceneDamaged"),
        BTreeSet::from(["garbage".to_owned(), "holes".to_owned()]),
        "{alerts}"
    );
    // Nothing else is raised, even as pending: the copies of a damaged pool may fail (or be
    // skipped while one runs), every other alert is about something this daemon is not.
    for quiet in rules
        .lines()
        .filter_map(|l| l.trim().strip_prefix("- alert: "))
        .filter(|a| {
            ![
                "ArborSceneDamaged",
                "ArborBackupFailed",
                "ArborBackupSkipped",
            ]
            .contains(a)
        })
    {
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
    let up = query(&prometheus, "up").await;
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

/// The Grafana dashboard's panels, those with queries.
fn dashboard_panels() -> Vec<Value> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/grafana/arbor-dashboard.json");
    let dashboard: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    dashboard["panels"].as_array().unwrap().clone()
}

#[test]
fn the_shipped_dashboard_is_laid_out_on_grafanas_grid() {
    let panels = dashboard_panels();
    let mut ids = BTreeSet::new();
    let mut cells = BTreeSet::new();
    for p in &panels {
        let title = p["title"].as_str().unwrap();
        assert!(ids.insert(p["id"].as_u64().unwrap()), "{title}: id taken");
        let g = &p["gridPos"];
        let (x, y, w, h) = [&g["x"], &g["y"], &g["w"], &g["h"]]
            .map(|v| v.as_u64().unwrap())
            .into();
        assert!(w > 0 && h > 0 && x + w <= 24, "{title}: {g}");
        // No two panels overlap.
        for cx in x..x + w {
            for cy in y..y + h {
                assert!(
                    cells.insert((cx, cy)),
                    "{title} overlaps another panel at {cx},{cy}"
                );
            }
        }
        if p["type"] == "row" {
            continue;
        }
        assert!(!p["description"].as_str().unwrap().is_empty(), "{title}");
        assert_eq!(p["datasource"]["uid"], "${datasource}", "{title}");
        let targets = p["targets"].as_array().unwrap();
        assert!(!targets.is_empty(), "{title}: no query");
        let refs: BTreeSet<&str> = targets
            .iter()
            .map(|t| t["refId"].as_str().unwrap())
            .collect();
        assert_eq!(refs.len(), targets.len(), "{title}: refIds repeat");
        for t in targets {
            let expr = t["expr"].as_str().unwrap();
            // Every series the panel reads follows the replica selector.
            assert_eq!(
                expr.matches("arbor_").count(),
                expr.matches("{instance=~\"$instance\"").count(),
                "{title}: {expr}"
            );
        }
    }
}

/// `s` percent-encoded for a URL's query.
fn url_encoded(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// An instant query; the API's answer.
async fn query(prometheus: &Prometheus, expr: &str) -> Value {
    let (status, body) = get(
        prometheus.addr,
        &format!("/api/v1/query?query={}", url_encoded(expr)),
        None,
    )
    .await;
    serde_json::from_str(&body).unwrap_or_else(|_| panic!("{expr}: {status} {body}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_panel_of_the_shipped_dashboard_shows_a_real_daemons_data() {
    let pool = TestPool::new();
    let copies = tempfile::tempdir().unwrap();
    let server = daemon(&pool, copies.path()).await;
    let admin = server.admin_addr.unwrap();
    let prometheus = Prometheus::watching(admin).await;

    // Every name the dashboard reads is a family the daemon declares.
    let panels = dashboard_panels();
    let exprs: Vec<String> = panels
        .iter()
        .flat_map(|p| p["targets"].as_array().cloned().unwrap_or_default())
        .map(|t| t["expr"].as_str().unwrap().to_owned())
        .collect();
    assert!(exprs.len() >= 40, "{exprs:?}");
    let (_, page) = get(admin, "/metrics", Some(ADMIN)).await;
    assert_served(&exprs.join("\n"), &page, "arbor-dashboard.json");
    // The limits the rules and panels compare with, as configured.
    let config = pool.config();
    for line in [
        format!("arbor_connections_max {}\n", config.max_connections),
        format!("arbor_pool_readers {}\n", config.pool_readers),
    ] {
        assert!(page.contains(&line), "no {line} in {page}");
    }

    // A client fetches every treelet a few times while the daemon checks and copies.
    let client = common::connect(server.quic_addr, &server.fingerprint).await;
    let (mut control, info) = common::hello(
        &client.conn,
        common::SCENE,
        &[arbor_proto::Channel::Normal],
        common::TOKEN,
    )
    .await;
    let ids = common::all_ids(&info.unwrap());
    let t0 = Instant::now();
    let mut seq = 0;
    loop {
        seq += 1;
        common::round(&client, &mut control, seq, &ids)
            .await
            .unwrap();
        let copied = query(&prometheus, "arbor_pool_copy_last_done_seconds").await;
        let scraped = query(&prometheus, "count_over_time(arbor_uptime_seconds[1m])").await;
        let samples = scraped["data"]["result"][0]["value"][1]
            .as_str()
            .map_or(0, |v| v.parse::<u32>().unwrap());
        if samples >= 6 && !copied["data"]["result"].as_array().unwrap().is_empty() {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(90),
            "no copy, or no scrapes: {copied} {scraped}\n{}",
            prometheus.log()
        );
        tokio::time::sleep(Duration::from_millis(300)).await;
    }

    // Each query as Grafana sends it for "All" replicas: valid, and with a series to draw.
    for expr in &exprs {
        let sent = expr
            .replace("$instance", ".*")
            .replace("$__rate_interval", "30s");
        let answer = query(&prometheus, &sent).await;
        assert_eq!(answer["status"], "success", "{sent}: {answer}");
        assert!(
            !answer["data"]["result"].as_array().unwrap().is_empty(),
            "{sent}: no data from a daemon that served, checked and copied"
        );
    }
    drop(prometheus);
    server.shutdown().await;
}

/// A Prometheus server on a free loopback port with its own scratch storage, stopped on drop.
struct Prometheus {
    child: Child,
    addr: SocketAddr,
    dir: tempfile::TempDir,
}

impl Prometheus {
    /// Started on the shipped `prometheus.yml`, pointed at the admin API at `admin` (token
    /// [`ADMIN`]), scraping and evaluating every second, and answering `/-/ready`.
    async fn watching(admin: SocketAddr) -> Prometheus {
        let dir = tempfile::tempdir().unwrap();
        let token_file = dir.path().join("admin-token");
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
        Prometheus::start(dir, &config).await
    }

    /// Started on `config` (written into `dir`, which also holds its storage and log), and
    /// answering `/-/ready`. Its port is one the kernel had free a moment before; should
    /// another process take it in between, Prometheus exits naming the address, and it is
    /// started again on another (at most five times).
    async fn start(dir: tempfile::TempDir, config: &str) -> Prometheus {
        std::fs::write(dir.path().join("prometheus.yml"), config).unwrap();
        let log_file = dir.path().join("log");
        for attempt in 1..=5 {
            let addr = std::net::TcpListener::bind("127.0.0.1:0")
                .unwrap()
                .local_addr()
                .unwrap();
            let log = std::fs::File::create(&log_file).unwrap();
            let mut child = Command::new(prometheus_tool("prometheus"))
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
            if answers_ready(&mut child, addr, &log_file).await {
                return Prometheus { child, addr, dir };
            }
            let log = std::fs::read_to_string(&log_file).unwrap_or_default();
            assert!(
                log.contains("address already in use") && attempt < 5,
                "Prometheus did not start (attempt {attempt}):\n{log}"
            );
        }
        unreachable!("the fifth attempt returns or fails above")
    }

    /// The JSON of the API's `path` once `done` holds for it; fails after 90 s, saying
    /// `what` did not happen, with the last answer and the log.
    async fn api_until(&self, path: &str, what: &str, done: impl Fn(&Value) -> bool) -> Value {
        let t0 = Instant::now();
        loop {
            let (status, body) = get(self.addr, path, None).await;
            if status == 200 {
                let answer: Value = serde_json::from_str(&body).unwrap();
                if done(&answer) {
                    return answer;
                }
            }
            assert!(
                t0.elapsed() < Duration::from_secs(90),
                "{what}: not within 90 s; the last answer {status} {body}\n{}",
                self.log()
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("log")).unwrap_or_default()
    }
}

/// Waits until the Prometheus of `child` answers `/-/ready` at `addr` as Prometheus does:
/// `true`. `false`: it exited first (its log says why). Fails after 60 s.
async fn answers_ready(child: &mut Child, addr: SocketAddr, log: &Path) -> bool {
    let t0 = Instant::now();
    loop {
        if matches!(child.try_wait(), Ok(Some(_))) {
            return false;
        }
        let (status, body) = get(addr, "/-/ready", None).await;
        if status == 200 && body.contains("Prometheus") {
            return true;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "Prometheus did not start:\n{}",
            std::fs::read_to_string(log).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
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
