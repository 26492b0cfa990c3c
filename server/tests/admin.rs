//! The admin HTTP API served for real: `axum::serve` on a TCP port of 127.0.0.1, a sled pool in a
//! tempdir holding the real bunny, a `ServiceState` filled with known counters and sessions, and a
//! tiny hand-written HTTP/1.1 client (below) so that nothing between the test and the socket
//! interprets the answers. Every route is asked without a token, with a wrong one and with the
//! right one; `/metrics` goes through a strict Prometheus text parser (also below).

use std::collections::{BTreeMap, BTreeSet};
use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use arbor_proto::wire::ErrorCode;
use arbor_proto::{Channel, SceneDescription, TreeletId};
use arbor_server::admin::{AdminContext, AdminCredentials, router};
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_server::pipeline::{SceneImport, import_scene};
use arbor_server::pool::{Pool, PoolReadBuckets, pack};
use arbor_server::prometheus::Buckets;
use arbor_server::scratch::ScratchDir;
use arbor_server::service::state::{LATENCY_BUCKETS, ServiceState, SessionInfo};
use serde_json::Value;
use tempfile::TempDir;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

const TOKEN: &str = "Zx9-test-token_4f1c/+=";
/// The low-privilege readiness-probe token.
const PROBE: &str = "probe-only-token";
const FINGERPRINT: &str = "3f2a9c0d5e6b7a8190fedcba98765432100123456789abcdef0011223344556677";
/// A session's scene shown in HTML must come out escaped.
const HOSTILE: &str = "<img src=x onerror=alert(1)>";

// ---------------------------------------------------------------------------------------------
// Fixture: a real pool, a known state, a real server.

struct Fixture {
    addr: SocketAddr,
    state: Arc<ServiceState>,
    pool: Pool,
    description: Option<SceneDescription>,
    _dirs: Dirs,
}

/// The pool's directory and the import's scratch files, removed on drop.
struct Dirs {
    _pool: TempDir,
    _scratch: Option<ScratchDir>,
}

/// A pool in a tempdir; with `bunny`, holding the real bunny built at depth 5.
fn pool(bunny: bool) -> (Pool, Option<SceneDescription>, Dirs) {
    let dir = tempfile::tempdir().unwrap();
    let pool = Pool::open(dir.path()).unwrap();
    if !bunny {
        return (
            pool,
            None,
            Dirs {
                _pool: dir,
                _scratch: None,
            },
        );
    }
    let path = Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/meshes/stanford-bunny.obj"
    ));
    assert!(
        path.exists(),
        "the real scans in ../shared/data are required"
    );
    let request = SceneImport {
        name: "bunny".into(),
        input: path.to_path_buf(),
        build: BuildOptions {
            depth: DepthChoice::Fixed(5),
            treelet_bytes: 1024,
            ..BuildOptions::default()
        },
        ..SceneImport::default()
    };
    let imported = import_scene(&pool, &request).unwrap();
    (
        pool,
        Some(imported.description),
        Dirs {
            _pool: dir,
            _scratch: Some(imported.scratch),
        },
    )
}

/// Known counters: what `/metrics` must report.
fn fill(state: &ServiceState) {
    let m = &state.metrics;
    m.connections_accepted.store(11, Ordering::Relaxed);
    m.connections_rejected.store(2, Ordering::Relaxed);
    m.connections_open.store(3, Ordering::Relaxed);
    m.request_lists.store(40, Ordering::Relaxed);
    m.request_items.store(12_345, Ordering::Relaxed);
    m.treelets_sent.store(500, Ordering::Relaxed);
    m.treelet_bytes_sent.store(987_654, Ordering::Relaxed);
    m.treelet_streams.store(31, Ordering::Relaxed);
    m.treelets_cancelled.store(7, Ordering::Relaxed);
    m.pool_prewarm.total.store(3 << 20, Ordering::Relaxed);
    m.pool_prewarm.read.store(1 << 20, Ordering::Relaxed);
    m.pool_prewarm.hot.store(2 << 20, Ordering::Relaxed);
    m.error(ErrorCode::FrameTooLarge);
    m.error(ErrorCode::FrameTooLarge);
    m.error(ErrorCode::Unauthorized);
    for micros in [300, 3_000, 3_000, 40_000, 20_000_000] {
        m.request_to_send.observe(Duration::from_micros(micros));
    }
    let mut s = SessionInfo::new(1, "127.0.0.1:4433".parse().unwrap());
    s.scene = "bunny".into();
    s.set_channels(&[Channel::Normal]);
    s.request_lists = 4;
    s.treelets_sent = 100;
    s.bytes_sent = 4096;
    s.queue_depth = 5;
    s.in_flight = 4;
    state.add_session(s);
    let mut s = SessionInfo::new(2, "[::1]:5000".parse().unwrap());
    s.scene = HOSTILE.into();
    s.queue_depth = 2;
    s.in_flight = 1;
    state.add_session(s);
}

async fn start(bunny: bool, token: &str) -> Fixture {
    let (pool, description, dirs) = pool(bunny);
    let state = Arc::new(ServiceState::new(FINGERPRINT.into()));
    let app = router(AdminContext {
        state: state.clone(),
        pool: pool.clone(),
        credentials: AdminCredentials::new(token, Some(PROBE)),
    });
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    Fixture {
        addr,
        state,
        pool,
        description,
        _dirs: dirs,
    }
}

// ---------------------------------------------------------------------------------------------
// A tiny HTTP/1.1 client: one request per connection (`Connection: close`), read to the end.

#[derive(Debug)]
struct Reply {
    status: u16,
    /// Names lowercased, in order.
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Reply {
    fn header(&self, name: &str) -> Option<&str> {
        let mut it = self.headers.iter().filter(|(k, _)| k == name);
        let v = it.next().map(|(_, v)| v.as_str());
        assert!(it.next().is_none(), "header {name} twice: {self:?}");
        v
    }

    fn text(&self) -> &str {
        std::str::from_utf8(&self.body).expect("UTF-8 body")
    }

    fn json(&self) -> Value {
        assert!(
            self.header("content-type")
                .is_some_and(|c| c.starts_with("application/json")),
            "not JSON: {self:?}"
        );
        serde_json::from_slice(&self.body).expect("JSON body")
    }

    /// A JSON error `{"error": "..."}` with nothing else.
    fn error(&self) -> String {
        let v = self.json();
        let o = v.as_object().expect("error object");
        assert_eq!(o.len(), 1, "{v}");
        o["error"].as_str().expect("error string").to_owned()
    }
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack.windows(needle.len()).position(|w| w == needle)
}

/// Parses a whole HTTP/1.1 response: status line, headers, body (by length or chunked).
fn parse_reply(raw: &[u8]) -> Reply {
    let end = find(raw, b"\r\n\r\n").expect("end of headers");
    let head = std::str::from_utf8(&raw[..end]).expect("ASCII head");
    let mut lines = head.split("\r\n");
    let status_line = lines.next().unwrap();
    let mut parts = status_line.splitn(3, ' ');
    assert_eq!(parts.next(), Some("HTTP/1.1"), "{status_line}");
    let code = parts.next().expect("status code");
    assert!(
        code.len() == 3 && code.bytes().all(|b| b.is_ascii_digit()),
        "{status_line}"
    );
    let status = code.parse().unwrap();
    let headers: Vec<(String, String)> = lines
        .map(|l| {
            let (k, v) = l.split_once(':').expect("header line");
            assert!(!k.is_empty() && !k.contains(' '), "header name {k:?}");
            (k.to_ascii_lowercase(), v.trim().to_owned())
        })
        .collect();
    let mut body = raw[end + 4..].to_vec();
    let get = |n: &str| headers.iter().find(|(k, _)| k == n).map(|(_, v)| v.clone());
    if get("transfer-encoding").is_some_and(|t| t.eq_ignore_ascii_case("chunked")) {
        let mut out = Vec::new();
        let mut rest = &body[..];
        loop {
            let nl = find(rest, b"\r\n").expect("chunk size line");
            let size_str = std::str::from_utf8(&rest[..nl]).unwrap();
            let size = usize::from_str_radix(size_str.split(';').next().unwrap().trim(), 16)
                .expect("chunk size");
            rest = &rest[nl + 2..];
            if size == 0 {
                break;
            }
            out.extend_from_slice(&rest[..size]);
            assert_eq!(&rest[size..size + 2], b"\r\n");
            rest = &rest[size + 2..];
        }
        body = out;
    } else if let Some(len) = get("content-length") {
        assert_eq!(body.len(), len.parse::<usize>().unwrap(), "content-length");
    }
    Reply {
        status,
        headers,
        body,
    }
}

async fn http(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> Reply {
    let mut s = TcpStream::connect(addr).await.unwrap();
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    if method == "POST" || !body.is_empty() {
        req.push_str(&format!("Content-Length: {}\r\n", body.len()));
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).await.unwrap();
    s.write_all(body).await.unwrap();
    let mut raw = Vec::new();
    tokio::time::timeout(Duration::from_secs(30), s.read_to_end(&mut raw))
        .await
        .expect("answer within 30 s")
        .unwrap();
    parse_reply(&raw)
}

async fn get(addr: SocketAddr, path: &str, headers: &[(&str, &str)]) -> Reply {
    http(addr, "GET", path, headers, b"").await
}

fn bearer(token: &str) -> String {
    format!("Bearer {token}")
}

/// `application/x-www-form-urlencoded` value.
fn form_value(s: &str) -> String {
    let mut out = String::new();
    for b in s.bytes() {
        if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
            out.push(char::from(b));
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

async fn login(addr: SocketAddr, token: &str) -> Reply {
    let body = format!("token={}", form_value(token));
    http(
        addr,
        "POST",
        "/login",
        &[("Content-Type", "application/x-www-form-urlencoded")],
        body.as_bytes(),
    )
    .await
}

/// `name=value` of a `Set-Cookie` header, for sending back in `Cookie`.
fn cookie_pair(set_cookie: &str) -> String {
    set_cookie.split(';').next().unwrap().trim().to_owned()
}

// ---------------------------------------------------------------------------------------------
// A strict parser of the Prometheus text exposition format 0.0.4.

#[derive(Debug, Default)]
struct Family {
    help: Option<String>,
    kind: Option<String>,
    samples: Vec<Sample>,
}

#[derive(Debug, Clone)]
struct Sample {
    name: String,
    labels: BTreeMap<String, String>,
    value: f64,
}

fn is_metric_name(s: &str) -> bool {
    let mut b = s.bytes();
    b.next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == b'_' || c == b':')
        && b.all(|c| c.is_ascii_alphanumeric() || c == b'_' || c == b':')
}

fn is_label_name(s: &str) -> bool {
    let mut b = s.bytes();
    b.next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == b'_')
        && b.all(|c| c.is_ascii_alphanumeric() || c == b'_')
}

fn parse_float(s: &str) -> f64 {
    match s {
        "+Inf" => f64::INFINITY,
        "-Inf" => f64::NEG_INFINITY,
        "NaN" => f64::NAN,
        _ => {
            assert!(
                !s.is_empty()
                    && s.bytes()
                        .all(|b| b.is_ascii_digit() || b"+-.eE".contains(&b)),
                "not a float: {s:?}"
            );
            s.parse().unwrap_or_else(|_| panic!("not a float: {s:?}"))
        }
    }
}

/// `name{a="x",b="y"} value [timestamp]`
fn parse_sample(line: &str) -> Sample {
    let name_end = line.find(['{', ' ']).expect("sample without value");
    let name = &line[..name_end];
    assert!(is_metric_name(name), "metric name {name:?} in {line:?}");
    let mut rest = &line[name_end..];
    let mut labels = BTreeMap::new();
    if let Some(r) = rest.strip_prefix('{') {
        rest = r;
        loop {
            if let Some(r) = rest.strip_prefix('}') {
                rest = r;
                break;
            }
            let eq = rest.find('=').expect("label without =");
            let lname = &rest[..eq];
            assert!(is_label_name(lname), "label name {lname:?} in {line:?}");
            rest = rest[eq + 1..]
                .strip_prefix('"')
                .expect("label value must be quoted");
            let mut value = String::new();
            let mut chars = rest.char_indices();
            let close = loop {
                match chars.next().expect("unterminated label value") {
                    (i, '"') => break i,
                    (_, '\\') => match chars.next().expect("dangling escape").1 {
                        '\\' => value.push('\\'),
                        '"' => value.push('"'),
                        'n' => value.push('\n'),
                        c => panic!("bad escape \\{c} in {line:?}"),
                    },
                    (_, '\n') => panic!("raw newline in label"),
                    (_, c) => value.push(c),
                }
            };
            rest = &rest[close + 1..];
            assert!(
                labels.insert(lname.to_owned(), value).is_none(),
                "label {lname} twice in {line:?}"
            );
            if let Some(r) = rest.strip_prefix(',') {
                rest = r;
            } else {
                assert!(rest.starts_with('}'), "expected , or }} in {line:?}");
            }
        }
    }
    let rest = rest
        .strip_prefix(' ')
        .unwrap_or_else(|| panic!("one space before the value in {line:?}"));
    let mut fields = rest.split(' ');
    let value = parse_float(fields.next().unwrap());
    if let Some(ts) = fields.next() {
        ts.parse::<i64>()
            .unwrap_or_else(|_| panic!("timestamp {ts:?}"));
    }
    assert!(fields.next().is_none(), "trailing fields in {line:?}");
    Sample {
        name: name.to_owned(),
        labels,
        value,
    }
}

/// The family a sample belongs to (histogram and summary samples carry suffixes).
fn family_of(name: &str, families: &BTreeMap<String, Family>) -> String {
    let kind = |n: &str| families.get(n).and_then(|f| f.kind.as_deref());
    if let Some(k) = kind(name) {
        assert!(
            !matches!(k, "histogram" | "summary"),
            "{name}: bare sample of a {k}"
        );
        return name.to_owned();
    }
    for (suffix, kinds) in [
        ("_bucket", &["histogram"][..]),
        ("_sum", &["histogram", "summary"][..]),
        ("_count", &["histogram", "summary"][..]),
    ] {
        if let Some(base) = name.strip_suffix(suffix)
            && kind(base).is_some_and(|k| kinds.contains(&k))
        {
            return base.to_owned();
        }
    }
    panic!("sample {name} of no declared family (HELP and TYPE must come first)")
}

/// Parses and checks: every line is HELP, TYPE or a sample; every family is declared exactly once
/// with HELP and TYPE before its samples, which are contiguous and unique; histogram buckets are
/// ascending in `le`, monotone in count, end with `+Inf` equal to `_count`, and have a `_sum`.
fn parse_prometheus(text: &str) -> BTreeMap<String, Family> {
    assert!(text.ends_with('\n'), "text must end with a newline");
    let mut families: BTreeMap<String, Family> = BTreeMap::new();
    let mut current: Option<String> = None;
    let mut closed: BTreeSet<String> = BTreeSet::new();
    let mut seen: BTreeSet<(String, BTreeMap<String, String>)> = BTreeSet::new();
    for line in text.lines() {
        assert!(!line.is_empty(), "blank line");
        if let Some(rest) = line.strip_prefix('#') {
            let rest = rest
                .strip_prefix(' ')
                .expect("comment: '# HELP' or '# TYPE'");
            let mut parts = rest.splitn(3, ' ');
            let what = parts.next().unwrap();
            let name = parts.next().expect("metric name");
            assert!(is_metric_name(name), "{line:?}");
            let f = families.entry(name.to_owned()).or_default();
            assert!(f.samples.is_empty(), "{line:?} after samples of {name}");
            match what {
                "HELP" => {
                    let help = parts.next().unwrap_or("");
                    assert!(!help.trim().is_empty(), "empty HELP for {name}");
                    assert!(
                        f.help.replace(help.to_owned()).is_none(),
                        "HELP {name} twice"
                    );
                }
                "TYPE" => {
                    let kind = parts.next().expect("type");
                    assert!(
                        ["counter", "gauge", "histogram", "summary", "untyped"].contains(&kind),
                        "{line:?}"
                    );
                    assert!(
                        f.kind.replace(kind.to_owned()).is_none(),
                        "TYPE {name} twice"
                    );
                }
                _ => panic!("unexpected comment {line:?}"),
            }
            continue;
        }
        let sample = parse_sample(line);
        let family = family_of(&sample.name, &families);
        if current.as_deref() != Some(&family) {
            assert!(
                !closed.contains(&family),
                "samples of {family} are not contiguous"
            );
            if let Some(c) = current.replace(family.clone()) {
                closed.insert(c);
            }
        }
        assert!(
            seen.insert((sample.name.clone(), sample.labels.clone())),
            "duplicate sample {line:?}"
        );
        let f = families.get_mut(&family).unwrap();
        assert!(f.help.is_some(), "{family} has no HELP before its samples");
        if f.kind.as_deref() == Some("counter") {
            assert!(
                sample.value.is_finite() && sample.value >= 0.0,
                "counter {line:?}"
            );
        }
        f.samples.push(sample);
    }
    for (name, f) in &families {
        assert!(
            f.help.is_some() && f.kind.is_some(),
            "{name} lacks HELP or TYPE"
        );
        if f.kind.as_deref() == Some("histogram") {
            check_histogram(name, f);
        }
    }
    families
}

fn check_histogram(name: &str, f: &Family) {
    let mut series: BTreeMap<BTreeMap<String, String>, Vec<(f64, f64)>> = BTreeMap::new();
    for s in f
        .samples
        .iter()
        .filter(|s| s.name == format!("{name}_bucket"))
    {
        let mut labels = s.labels.clone();
        let le = parse_float(&labels.remove("le").expect("bucket without le"));
        series.entry(labels).or_default().push((le, s.value));
    }
    assert!(!series.is_empty(), "histogram {name} without buckets");
    for (labels, buckets) in series {
        for w in buckets.windows(2) {
            assert!(w[0].0 < w[1].0, "{name}: le not ascending {buckets:?}");
            assert!(w[0].1 <= w[1].1, "{name}: counts not monotone {buckets:?}");
        }
        let last = buckets.last().unwrap();
        assert_eq!(last.0, f64::INFINITY, "{name}: last bucket must be +Inf");
        let find = |suffix: &str| {
            f.samples
                .iter()
                .find(|s| s.name == format!("{name}{suffix}") && s.labels == labels)
                .unwrap_or_else(|| panic!("{name}{suffix} missing"))
                .value
        };
        assert_eq!(last.1, find("_count"), "{name}: +Inf bucket != count");
        assert!(find("_sum").is_finite());
    }
}

/// The value of the sample `name{labels}`.
fn value(families: &BTreeMap<String, Family>, name: &str, labels: &[(&str, &str)]) -> f64 {
    let want: BTreeMap<String, String> = labels
        .iter()
        .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
        .collect();
    families
        .values()
        .flat_map(|f| &f.samples)
        .find(|s| s.name == name && s.labels == want)
        .unwrap_or_else(|| panic!("no sample {name}{labels:?}"))
        .value
}

// ---------------------------------------------------------------------------------------------
// Tests.

/// Every authenticated route, as `GET` paths.
const PROTECTED: [&str; 7] = [
    "/",
    "/readyz",
    "/metrics",
    "/v1/scenes",
    "/v1/scenes/bunny",
    "/v1/sessions",
    "/v1/server",
];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_route_needs_the_token_but_healthz() {
    let f = start(true, TOKEN).await;
    fill(&f.state);
    f.state.set_ready(true);
    let right = bearer(TOKEN);
    let wrong_tokens = [
        bearer("Zx9-test-token_4f1c/+"),
        bearer(&format!("{TOKEN}x")),
        bearer(""),
        format!("Basic {TOKEN}"),
        bearer(&TOKEN.to_uppercase()),
    ];
    for path in PROTECTED {
        let r = get(f.addr, path, &[]).await;
        if path == "/" {
            // A browser without credentials is sent to the login form.
            assert_eq!(r.status, 303, "{path}: {r:?}");
            assert_eq!(r.header("location"), Some("/login"));
        } else {
            assert_eq!(r.status, 401, "{path} without token: {r:?}");
            assert!(
                r.header("www-authenticate")
                    .is_some_and(|v| v.starts_with("Bearer")),
                "{path}: {r:?}"
            );
            assert!(!r.error().is_empty());
        }
        for wrong in &wrong_tokens {
            let r = get(f.addr, path, &[("Authorization", wrong)]).await;
            assert_eq!(r.status, 401, "{path} with {wrong:?}: {r:?}");
            assert!(
                r.header("www-authenticate")
                    .is_some_and(|v| v.starts_with("Bearer")),
                "{path}: {r:?}"
            );
            assert!(!r.error().is_empty());
            assert!(
                !r.text().contains(TOKEN),
                "{path}: the answer names the token"
            );
        }
        let r = get(f.addr, path, &[("Cookie", "arbor_admin=wrong")]).await;
        if path == "/" {
            assert_eq!(r.status, 303, "{path} with a wrong cookie: {r:?}");
        } else {
            assert_eq!(r.status, 401, "{path} with a wrong cookie: {r:?}");
        }
        let r = get(f.addr, path, &[("Authorization", &right)]).await;
        assert_eq!(r.status, 200, "{path} with the token: {r:?}");
        assert_eq!(r.header("cache-control"), Some("no-store"), "{path}");
        // The scheme is case-insensitive.
        let r = get(
            f.addr,
            path,
            &[("Authorization", &format!("bearer {TOKEN}"))],
        )
        .await;
        assert_eq!(r.status, 200, "{path} with lowercase scheme: {r:?}");
    }
    for headers in [
        &[][..],
        &[("Authorization", wrong_tokens[0].as_str())][..],
        &[("Authorization", right.as_str())][..],
    ] {
        let r = get(f.addr, "/healthz", headers).await;
        assert_eq!(r.status, 200);
        assert_eq!(r.text(), "ok");
    }
    // Unknown routes and methods: JSON errors, with or without the token.
    for headers in [&[][..], &[("Authorization", right.as_str())][..]] {
        let r = get(f.addr, "/nope", headers).await;
        assert_eq!(r.status, 404, "{r:?}");
        assert!(!r.error().is_empty());
        let r = get(f.addr, "/v1/scenes/bunny/more", headers).await;
        assert_eq!(r.status, 404, "{r:?}");
    }
    let r = http(
        f.addr,
        "POST",
        "/metrics",
        &[("Authorization", &right)],
        b"",
    )
    .await;
    assert_eq!(r.status, 405, "{r:?}");
    assert!(
        r.header("allow").is_some_and(|a| a.contains("GET")),
        "{r:?}"
    );
    assert!(!r.error().is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_report_the_server_wide_caches() {
    use arbor_proto::TreeletId;
    use arbor_server::service::shapes::ShapeCache;
    use arbor_server::service::state::ServiceCaches;
    use arbor_server::service::treelets::{MessageCache, ServedScene};
    use arbor_server::service::visibility::NodeCache;
    let f = start(true, TOKEN).await;
    let bearer = bearer(TOKEN);
    let auth = [("Authorization", bearer.as_str())];
    let names = [
        "arbor_message_cache_bytes",
        "arbor_message_cache_hits_total",
        "arbor_message_cache_misses_total",
        "arbor_shape_cache_bytes",
        "arbor_shape_cache_shapes",
        "arbor_shape_cache_hits_total",
        "arbor_shape_cache_misses_total",
        "arbor_cut_node_cache_bytes",
        "arbor_cut_node_cache_treelets",
        "arbor_cut_node_cache_hits_total",
        "arbor_cut_node_cache_misses_total",
    ];
    let fams = parse_prometheus(get(f.addr, "/metrics", &auth).await.text());
    for name in names {
        assert_eq!(
            value(&fams, name, &[]),
            0.0,
            "{name} before the service set its caches"
        );
    }

    let caches = ServiceCaches {
        messages: Arc::new(MessageCache::new(1 << 20)),
        shapes: Arc::new(ShapeCache::for_shapes(1 << 20)),
        cut_nodes: Arc::new(NodeCache::for_nodes(1 << 20)),
        fine_cuts: Arc::default(),
    };
    f.state.set_caches(caches.clone());
    let d = f.description.as_ref().unwrap();
    let served = ServedScene::with_caches(f.pool.scene("bunny").unwrap(), &caches);
    let channels = d.layout.channels().to_vec();
    let n = d.treelet_count;
    for _ in 0..2 {
        for i in 0..n {
            served.message(TreeletId(i), &channels).unwrap();
            served.shape(TreeletId(i)).unwrap();
        }
    }
    // The same view's cut twice: the second reads every treelet from the cut node cache.
    let view = arbor_proto::wire::ViewHint {
        eye: std::array::from_fn(|i| d.origin[i] + d.edge * [0.5, 0.5, 2.5][i]),
        forward: [0.0, 0.0, -1.0],
        up: [0.0, 1.0, 0.0],
        tan_half_fov_y: 0.6,
        aspect: 1.0,
        footprint: 1.2 / 64.0,
        free_slots: 0,
    };
    let cuts: Vec<_> = (0..2)
        .map(|_| {
            served
                .visible_cut(&view, 32, &[], 1 << 24, |_| true)
                .unwrap()
        })
        .collect();
    assert_eq!(cuts[0].treelets, cuts[1].treelets);
    assert!(
        cuts[0].complete && cuts[0].treelets.len() > 1,
        "{:?}",
        cuts[0]
    );
    let fams = parse_prometheus(get(f.addr, "/metrics", &auth).await.text());
    let v = |name: &str| value(&fams, name, &[]);
    let (message_bytes, ..) = caches.messages.figures();
    let shapes = caches.shapes.figures();
    assert!(message_bytes > 0 && shapes.bytes > 0);
    let nodes = caches.cut_nodes.figures();
    // The root (read once, when the scene's caster is made) and the cut's treelets, each
    // decoded by the first cut and read again by the second.
    let cut = cuts[0].treelets.len() as u64;
    assert_eq!((nodes.misses, nodes.hits), (cut + 1, cut), "{nodes:?}");
    assert_eq!(nodes.entries as u64, cut + 1);
    for (name, want) in [
        ("arbor_cut_node_cache_bytes", nodes.bytes as f64),
        ("arbor_cut_node_cache_treelets", (cut + 1) as f64),
        ("arbor_cut_node_cache_hits_total", cut as f64),
        ("arbor_cut_node_cache_misses_total", (cut + 1) as f64),
    ] {
        assert_eq!(v(name), want, "{name}");
    }
    let n = f64::from(n);
    for (name, want) in [
        ("arbor_message_cache_bytes", message_bytes as f64),
        ("arbor_message_cache_hits_total", n),
        ("arbor_message_cache_misses_total", n),
        ("arbor_shape_cache_bytes", shapes.bytes as f64),
        ("arbor_shape_cache_shapes", n),
        ("arbor_shape_cache_hits_total", n),
        ("arbor_shape_cache_misses_total", n),
    ] {
        assert_eq!(v(name), want, "{name}");
    }
    for (name, kind) in [
        ("arbor_shape_cache_bytes", "gauge"),
        ("arbor_shape_cache_hits_total", "counter"),
    ] {
        assert_eq!(fams[name].kind.as_deref(), Some(kind), "{name}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_parse_and_report_the_state_and_the_pool() {
    let f = start(true, TOKEN).await;
    fill(&f.state);
    f.state.set_ready(true);
    // Recorded at the start with seven scenes; reported for the one the pool holds now.
    let bound = arbor_server::service::config::ServeConfig::new("p").memory_bound(7);
    f.state.set_memory_bound(bound);
    // Every node block read through the pool handle the admin API was given (a clone of it):
    // one read per pack of consecutive ids, then one for a lone block.
    let stored = f.pool.scene("bunny").unwrap();
    let ids: Vec<TreeletId> = (0..stored.description.treelet_count)
        .map(TreeletId)
        .collect();
    assert!(stored.nodes_of(&ids).unwrap().iter().all(Option::is_some));
    assert!(stored.nodes(TreeletId(0)).unwrap().is_some());
    let mut packs: Vec<_> = ids.iter().map(|&id| pack::locate(id).0).collect();
    packs.dedup();
    let reads = packs.len() as f64 + 1.0;
    let r = get(f.addr, "/metrics", &[("Authorization", &bearer(TOKEN))]).await;
    assert_eq!(r.status, 200, "{r:?}");
    let ct = r.header("content-type").unwrap();
    assert!(
        ct.starts_with("text/plain") && ct.contains("version=0.0.4"),
        "{ct}"
    );
    let fams = parse_prometheus(r.text());
    let v = |name: &str| value(&fams, name, &[]);
    for (name, want) in [
        ("arbor_connections_accepted_total", 11.0),
        ("arbor_connections_rejected_total", 2.0),
        ("arbor_connections_open", 3.0),
        ("arbor_request_lists_total", 40.0),
        ("arbor_request_items_total", 12_345.0),
        ("arbor_treelets_sent_total", 500.0),
        ("arbor_treelet_bytes_sent_total", 987_654.0),
        ("arbor_treelet_streams_total", 31.0),
        ("arbor_treelets_cancelled_total", 7.0),
        ("arbor_pool_prewarm_total_bytes", 3_145_728.0),
        ("arbor_pool_prewarm_read_bytes", 1_048_576.0),
        ("arbor_pool_prewarm_hot_bytes", 2_097_152.0),
        ("arbor_pool_prewarm_done", 0.0),
        ("arbor_queue_depth", 7.0),
        ("arbor_in_flight", 5.0),
        ("arbor_ready", 1.0),
        ("arbor_shutting_down", 0.0),
        ("arbor_pool_readable", 1.0),
        ("arbor_pool_scenes", 1.0),
    ] {
        assert_eq!(v(name), want, "{name}");
    }
    let now = bound.with_scenes(1);
    for (part, bytes) in now.parts() {
        let got = value(&fams, "arbor_memory_bound_bytes", &[("part", part)]);
        assert_eq!(got, bytes as f64, "{part}");
    }
    assert_eq!(now.cut_buffers() * 7, bound.cut_buffers());
    for (kind, n) in [("frame_too_large", 2.0), ("unauthorized", 1.0)] {
        assert_eq!(value(&fams, "arbor_errors_total", &[("kind", kind)]), n);
    }
    let errors = &fams["arbor_errors_total"];
    assert_eq!(errors.kind.as_deref(), Some("counter"));
    assert_eq!(errors.samples.len(), ErrorCode::ALL.len());
    assert_eq!(errors.samples.iter().map(|s| s.value).sum::<f64>(), 3.0);

    // Latencies observed: 0.3 ms, 3 ms, 3 ms, 40 ms, 20 s.
    let h = &fams["arbor_request_to_send_seconds"];
    assert_eq!(h.kind.as_deref(), Some("histogram"));
    let bucket = |le: &str| value(&fams, "arbor_request_to_send_seconds_bucket", &[("le", le)]);
    assert_eq!(bucket("0.0005"), 1.0);
    assert_eq!(bucket("0.002"), 1.0);
    assert_eq!(bucket("0.005"), 3.0);
    assert_eq!(bucket("0.05"), 4.0);
    assert_eq!(bucket("10"), 4.0);
    assert_eq!(bucket("+Inf"), 5.0);
    assert_eq!(v("arbor_request_to_send_seconds_count"), 5.0);
    assert!((v("arbor_request_to_send_seconds_sum") - 20.0463).abs() < 1e-9);
    assert_eq!(
        h.samples
            .iter()
            .filter(|s| s.name.ends_with("_bucket"))
            .count(),
        LATENCY_BUCKETS.len() + 1
    );

    // The pool's read times.
    let h = &fams["arbor_pool_read_seconds"];
    assert_eq!(h.kind.as_deref(), Some("histogram"));
    let buckets: Vec<f64> = h
        .samples
        .iter()
        .filter(|s| s.name == "arbor_pool_read_seconds_bucket")
        .map(|s| s.value)
        .collect();
    assert_eq!(buckets.len(), PoolReadBuckets::BOUNDS.len() + 1);
    assert!(buckets.windows(2).all(|w| w[0] <= w[1]), "{buckets:?}");
    assert_eq!(buckets.last(), Some(&reads));
    assert_eq!(v("arbor_pool_read_seconds_count"), reads);
    assert!(v("arbor_pool_read_seconds_sum") > 0.0);

    // The pool's gauges.
    let d = f.description.as_ref().unwrap();
    let scene = [("scene", "bunny")];
    assert_eq!(
        value(&fams, "arbor_scene_treelets", &scene),
        f64::from(d.treelet_count)
    );
    assert_eq!(
        value(&fams, "arbor_scene_voxels", &scene),
        d.stats.voxels as f64
    );
    assert_eq!(
        value(
            &fams,
            "arbor_scene_compressed_bytes",
            &[("scene", "bunny"), ("stream", "nodes")]
        ),
        d.stats.node_bytes as f64
    );
    assert_eq!(
        value(
            &fams,
            "arbor_scene_compressed_bytes",
            &[("scene", "bunny"), ("stream", "normal")]
        ),
        d.stats.channel_bytes[0] as f64
    );
    assert!(v("arbor_pool_disk_bytes") > 0.0);
    for (name, fam) in &fams {
        if name.starts_with("arbor_scene_")
            || (name.starts_with("arbor_pool_") && name != "arbor_pool_read_seconds")
        {
            let kind = if name.ends_with("_total") {
                "counter"
            } else {
                "gauge"
            };
            assert_eq!(fam.kind.as_deref(), Some(kind), "{name}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scenes_sessions_and_server_as_json() {
    let f = start(true, TOKEN).await;
    fill(&f.state);
    let auth = bearer(TOKEN);
    let auth = [("Authorization", auth.as_str())];
    let d = f.description.as_ref().unwrap();
    assert!(
        d.treelet_count > 1,
        "depth 5 with 1 KiB treelets spans several"
    );

    let r = get(f.addr, "/v1/scenes", &auth).await;
    assert_eq!(r.status, 200, "{r:?}");
    assert!(
        !r.text().contains("node_dictionary") && !r.text().contains("channel_dictionaries"),
        "{}",
        r.text()
    );
    let list = r.json();
    let list = list.as_array().unwrap();
    assert_eq!(list.len(), 1);
    let s = &list[0];
    assert_eq!(s["name"], "bunny");
    assert_eq!(s["kind"], "mesh");
    assert_eq!(s["treelets"], u64::from(d.treelet_count));
    assert_eq!(s["depth"], 5);
    assert_eq!(s["treelet_bytes"], 1024);
    assert_eq!(s["voxels"], d.stats.voxels);
    assert_eq!(s["leaf_voxels"], d.stats.leaf_voxels);
    assert_eq!(s["primitives"], d.primitives);
    assert_eq!(s["channels"], serde_json::json!(["normal"]));
    assert_eq!(s["compressed_bytes"]["nodes"], d.stats.node_bytes);
    assert_eq!(
        s["compressed_bytes"]["channels"]["normal"],
        d.stats.channel_bytes[0]
    );
    let total = d.stats.node_bytes + d.stats.channel_bytes[0];
    assert_eq!(s["compressed_bytes"]["total"], total);
    let bpv = s["bytes_per_voxel"].as_f64().unwrap();
    assert!((bpv - total as f64 / d.stats.voxels as f64).abs() < 1e-9);
    assert_eq!(s["build_seconds"].as_f64().unwrap(), d.stats.build_seconds);
    assert_eq!(s["origin"], serde_json::json!(d.origin));
    assert_eq!(s["edge"].as_f64().unwrap(), d.edge);
    assert_eq!(s["source"], d.source.as_str());
    assert!(s["dictionaries"].is_boolean());
    // No byte arrays anywhere: the dictionaries are never sent.
    fn longest_array(v: &Value) -> usize {
        match v {
            Value::Array(a) => a.iter().map(longest_array).max().unwrap_or(0).max(a.len()),
            Value::Object(o) => o.values().map(longest_array).max().unwrap_or(0),
            _ => 0,
        }
    }
    assert!(longest_array(s) <= 3, "{s}");

    let r = get(f.addr, "/v1/scenes/bunny", &auth).await;
    assert_eq!(r.status, 200, "{r:?}");
    assert_eq!(&r.json(), s);
    for missing in ["/v1/scenes/nope", "/v1/scenes/..%2Fetc", "/v1/scenes/%00"] {
        let r = get(f.addr, missing, &auth).await;
        assert_eq!(r.status, 404, "{missing}: {r:?}");
        assert!(!r.error().is_empty());
    }

    let r = get(f.addr, "/v1/sessions", &auth).await;
    assert_eq!(r.status, 200, "{r:?}");
    let sessions = r.json();
    let sessions = sessions.as_array().unwrap();
    assert_eq!(sessions.len(), 2);
    let one = sessions.iter().find(|s| s["id"] == 1).unwrap();
    assert_eq!(one["peer"], "127.0.0.1:4433");
    assert_eq!(one["scene"], "bunny");
    assert_eq!(one["channels"], serde_json::json!(["normal"]));
    assert_eq!(one["request_lists"], 4);
    assert_eq!(one["treelets_sent"], 100);
    assert_eq!(one["bytes_sent"], 4096);
    assert_eq!(one["queue_depth"], 5);
    assert_eq!(one["in_flight"], 4);
    f.state.remove_session(2);
    let r = get(f.addr, "/v1/sessions", &auth).await;
    assert_eq!(r.json().as_array().unwrap().len(), 1);

    let r = get(f.addr, "/v1/server", &auth).await;
    assert_eq!(r.status, 200, "{r:?}");
    let v = r.json();
    assert_eq!(v["fingerprint"], FINGERPRINT);
    assert_eq!(v["ready"], false);
    assert_eq!(v["shutting_down"], false);
    assert_eq!(v["version"], env!("CARGO_PKG_VERSION"));
    assert!(v["uptime_seconds"].as_f64().unwrap() >= 0.0);
    assert_eq!(v["sessions"], 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readiness_follows_the_state() {
    let f = start(false, TOKEN).await;
    let auth = bearer(TOKEN);
    let auth = [("Authorization", auth.as_str())];
    let ready = |r: &Reply| (r.status, r.text().to_owned());
    let r = get(f.addr, "/readyz", &auth).await;
    assert_eq!(ready(&r), (503, "not ready".into()));
    f.state.set_ready(true);
    let r = get(f.addr, "/readyz", &auth).await;
    assert_eq!(ready(&r), (200, "ready".into()));
    assert_eq!(get(f.addr, "/v1/server", &auth).await.json()["ready"], true);
    f.state.begin_shutdown();
    let r = get(f.addr, "/readyz", &auth).await;
    assert_eq!(ready(&r), (503, "not ready".into()));
    let v = get(f.addr, "/v1/server", &auth).await.json();
    assert_eq!(
        (v["ready"].clone(), v["shutting_down"].clone()),
        (false.into(), true.into())
    );
    // Health is not readiness: the process still runs.
    assert_eq!(get(f.addr, "/healthz", &[]).await.status, 200);
    // An empty pool still has its gauges.
    let fams = parse_prometheus(get(f.addr, "/metrics", &auth).await.text());
    assert_eq!(value(&fams, "arbor_pool_scenes", &[]), 0.0);
    assert_eq!(value(&fams, "arbor_ready", &[]), 0.0);
    assert_eq!(value(&fams, "arbor_shutting_down", &[]), 1.0);
    assert!(fams["arbor_scene_treelets"].samples.is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn browser_login_and_status_page() {
    let f = start(true, TOKEN).await;
    fill(&f.state);
    f.state.set_ready(true);

    let r = get(f.addr, "/", &[]).await;
    assert_eq!(r.status, 303, "{r:?}");
    assert_eq!(r.header("location"), Some("/login"));

    let r = get(f.addr, "/login", &[]).await;
    assert_eq!(r.status, 200, "{r:?}");
    assert!(r.header("content-type").unwrap().starts_with("text/html"));
    assert!(r.text().contains("name=\"token\"") && r.text().contains("action=\"/login\""));

    let r = login(f.addr, "not-the-token").await;
    assert_eq!(r.status, 401, "{r:?}");
    assert!(r.header("set-cookie").is_none());
    assert!(r.header("content-type").unwrap().starts_with("text/html"));
    assert!(r.text().contains("Wrong token"));
    let r = http(
        f.addr,
        "POST",
        "/login",
        &[("Content-Type", "application/x-www-form-urlencoded")],
        b"nothing=here",
    )
    .await;
    assert_eq!(r.status, 400, "{r:?}");
    assert!(r.header("set-cookie").is_none());

    let r = login(f.addr, TOKEN).await;
    assert_eq!(r.status, 303, "{r:?}");
    assert_eq!(r.header("location"), Some("/"));
    let set = r.header("set-cookie").unwrap();
    for attr in ["HttpOnly", "SameSite=Strict", "Path=/"] {
        assert!(set.split(';').any(|a| a.trim() == attr), "{attr} in {set}");
    }
    let cookie = cookie_pair(set);
    assert!(cookie.starts_with("arbor_admin="), "{cookie}");

    let r = get(f.addr, "/", &[("Cookie", &cookie)]).await;
    assert_eq!(r.status, 200, "{r:?}");
    assert!(r.header("content-type").unwrap().starts_with("text/html"));
    let csp = r.header("content-security-policy").unwrap();
    assert!(csp.contains("default-src 'none'"), "{csp}");
    let page = r.text();
    assert!(page.starts_with("<!doctype html>"));
    assert!(page.contains(FINGERPRINT), "fingerprint missing");
    assert!(page.contains(">bunny<"), "scene name missing");
    assert!(page.contains("127.0.0.1:4433"), "session missing");
    assert!(!page.contains(HOSTILE), "unescaped session scene");
    assert!(page.contains("&lt;img src=x onerror=alert(1)&gt;"));
    assert!(page.contains("frame_too_large"));
    assert!(
        !page.contains("http://") && !page.contains("https://"),
        "external asset"
    );
    assert!(!page.contains(TOKEN), "the page names the token");
    // The page's own links work with the cookie too.
    let r = get(f.addr, "/v1/server", &[("Cookie", &cookie)]).await;
    assert_eq!(r.json()["fingerprint"], FINGERPRINT);
    // Among other cookies, too.
    let r = get(
        f.addr,
        "/",
        &[("Cookie", &format!("theme=dark; {cookie}; x=1"))],
    )
    .await;
    assert_eq!(r.status, 200);

    let r = http(f.addr, "POST", "/logout", &[("Cookie", &cookie)], b"").await;
    assert_eq!(r.status, 303, "{r:?}");
    assert_eq!(r.header("location"), Some("/login"));
    let cleared = r.header("set-cookie").unwrap();
    assert!(
        cleared.starts_with("arbor_admin=;") && cleared.contains("Max-Age=0"),
        "{cleared}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_with_odd_characters_work_as_bearer_and_cookie() {
    let token = "sp ace;semi,comma%pct\"quote";
    let f = start(false, token).await;
    let r = get(f.addr, "/v1/server", &[("Authorization", &bearer(token))]).await;
    assert_eq!(r.status, 200, "{r:?}");
    let r = login(f.addr, token).await;
    assert_eq!(r.status, 303, "{r:?}");
    let cookie = cookie_pair(r.header("set-cookie").unwrap());
    let r = get(f.addr, "/", &[("Cookie", &cookie)]).await;
    assert_eq!(r.status, 200, "{r:?}");
    assert!(r.text().contains("The pool holds no scene"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_empty_token_admits_nobody() {
    let f = start(false, "").await;
    for auth in ["Bearer ", "Bearer", ""] {
        let r = get(f.addr, "/v1/server", &[("Authorization", auth)]).await;
        assert_eq!(r.status, 401, "{auth:?}: {r:?}");
    }
    assert_eq!(login(f.addr, "").await.status, 401);
    assert_eq!(get(f.addr, "/healthz", &[]).await.status, 200);
}

/// The parser above is strict: each of these malformed texts is rejected, the good one accepted.
#[test]
fn the_prometheus_parser_rejects_malformed_text() {
    let good = "# HELP a_total A.\n# TYPE a_total counter\na_total{k=\"v\\\"x\"} 3\n\
                # HELP h H.\n# TYPE h histogram\nh_bucket{le=\"0.1\"} 1\nh_bucket{le=\"+Inf\"} 2\n\
                h_sum 0.3\nh_count 2\n";
    let fams = parse_prometheus(good);
    assert_eq!(value(&fams, "a_total", &[("k", "v\"x")]), 3.0);
    let bad = [
        ("no final newline", "# HELP a A.\n# TYPE a gauge\na 1"),
        ("no HELP", "# TYPE a gauge\na 1\n"),
        ("no TYPE", "# HELP a A.\na 1\n"),
        (
            "TYPE twice",
            "# HELP a A.\n# TYPE a gauge\n# TYPE a gauge\na 1\n",
        ),
        (
            "HELP after samples",
            "# HELP a A.\n# TYPE a gauge\na 1\n# HELP a A.\n",
        ),
        ("not a float", "# HELP a A.\n# TYPE a gauge\na one\n"),
        ("two spaces", "# HELP a A.\n# TYPE a gauge\na  1\n"),
        ("unquoted label", "# HELP a A.\n# TYPE a gauge\na{k=v} 1\n"),
        ("bad name", "# HELP 1a A.\n# TYPE 1a gauge\n1a 1\n"),
        (
            "duplicate",
            "# HELP a A.\n# TYPE a gauge\na{k=\"1\"} 1\na{k=\"1\"} 2\n",
        ),
        (
            "not contiguous",
            "# HELP a A.\n# TYPE a gauge\n# HELP b B.\n# TYPE b gauge\na 1\nb 1\na{x=\"1\"} 1\n",
        ),
        ("negative counter", "# HELP a A.\n# TYPE a counter\na -1\n"),
        ("blank line", "# HELP a A.\n# TYPE a gauge\n\na 1\n"),
        (
            "buckets not monotone",
            "# HELP h H.\n# TYPE h histogram\nh_bucket{le=\"0.1\"} 3\nh_bucket{le=\"+Inf\"} 2\nh_sum 1\nh_count 2\n",
        ),
        (
            "+Inf is not the count",
            "# HELP h H.\n# TYPE h histogram\nh_bucket{le=\"+Inf\"} 2\nh_sum 1\nh_count 3\n",
        ),
        (
            "no +Inf",
            "# HELP h H.\n# TYPE h histogram\nh_bucket{le=\"1\"} 2\nh_sum 1\nh_count 2\n",
        ),
        (
            "no sum",
            "# HELP h H.\n# TYPE h histogram\nh_bucket{le=\"+Inf\"} 2\nh_count 2\n",
        ),
    ];
    for (what, text) in bad {
        let r = std::panic::catch_unwind(|| parse_prometheus(text));
        assert!(r.is_err(), "accepted: {what}");
    }
}

/// Served the way the daemon serves it (`with_graceful_shutdown`), the API stops promptly and
/// stops accepting when told to.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graceful_shutdown_ends_the_server() {
    let (pool, _, _dirs) = pool(false);
    let state = Arc::new(ServiceState::new(FINGERPRINT.into()));
    let app = router(AdminContext {
        state,
        pool,
        credentials: AdminCredentials::new(TOKEN, None),
    });
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(async move {
        axum::serve(listener, app)
            .with_graceful_shutdown(async move {
                let _ = stopped.await;
            })
            .await
    });
    let auth = bearer(TOKEN);
    let r = get(addr, "/v1/server", &[("Authorization", &auth)]).await;
    assert_eq!(r.status, 200);
    stop.send(()).unwrap();
    tokio::time::timeout(Duration::from_secs(5), server)
        .await
        .expect("server ends within 5 s")
        .unwrap()
        .unwrap();
    assert!(TcpStream::connect(addr).await.is_err(), "still accepting");
}

#[tokio::test]
async fn remembered_paths_are_listed_and_forgotten_through_the_api() {
    let f = start(false, TOKEN).await;
    let auth_value = bearer(TOKEN);
    let auth = [("Authorization", auth_value.as_str())];
    {
        let mut paths = f.state.paths();
        paths.set_lifetime(Duration::from_secs(600));
        paths.set_initial_window(128 << 10);
        let now = std::time::Instant::now();
        paths.handle_close(
            "10.1.2.3".parse().unwrap(),
            now,
            1 << 20,
            Duration::from_millis(50),
        );
        paths.handle_close(
            "::1".parse().unwrap(),
            now,
            200 << 10,
            Duration::from_micros(300),
        );
    }
    let r = get(f.addr, "/v1/paths", &[]).await;
    assert_eq!(r.status, 401, "no token");
    let r = http(f.addr, "DELETE", "/v1/paths", &[], b"").await;
    assert_eq!(r.status, 401, "no token");
    assert_eq!(f.state.paths().len(), 2, "a refused DELETE forgets nothing");

    let r = get(f.addr, "/v1/paths", &auth).await;
    assert_eq!(r.status, 200, "{r:?}");
    let v = r.json();
    let list = v.as_array().unwrap();
    assert_eq!(list.len(), 2, "{v}");
    let far = list.iter().find(|p| p["addr"] == "10.1.2.3").unwrap();
    assert_eq!(far["window_bytes"], 1 << 20);
    assert_eq!(far["jump_bytes"], 512 << 10);
    assert_eq!(far["rtt_ms"], 50.0);
    assert!(far["age_s"].as_f64().unwrap() >= 0.0);
    let near = list.iter().find(|p| p["addr"] == "::1").unwrap();
    assert_eq!(
        near["jump_bytes"], 0,
        "half of 200 KiB is not above the initial window"
    );

    let r = http(f.addr, "DELETE", "/v1/paths", &auth, b"").await;
    assert_eq!(r.status, 200, "{r:?}");
    assert_eq!(r.json()["forgotten"], 2);
    let r = get(f.addr, "/v1/paths", &auth).await;
    assert_eq!(r.json(), serde_json::json!([]));
}

#[tokio::test]
async fn the_probe_token_opens_readiness_only() {
    let f = start(false, TOKEN).await;
    f.state.set_ready(true);
    let probe = bearer(PROBE);
    let r = get(f.addr, "/readyz", &[("Authorization", probe.as_str())]).await;
    assert_eq!(r.status, 200, "probe token on /readyz");
    for path in [
        "/metrics",
        "/v1/scenes",
        "/v1/sessions",
        "/v1/server",
        "/v1/paths",
    ] {
        let r = get(f.addr, path, &[("Authorization", probe.as_str())]).await;
        assert_eq!(r.status, 401, "probe token accepted on {path}");
    }
    let r = get(f.addr, "/readyz", &[]).await;
    assert_eq!(r.status, 401, "/readyz without any token");
    let admin = bearer(TOKEN);
    let r = get(f.addr, "/readyz", &[("Authorization", admin.as_str())]).await;
    assert_eq!(r.status, 200, "admin token on /readyz");
}
