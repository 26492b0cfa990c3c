//! Scene management in a live daemon, end to end: real sled pool, real QUIC service, admin API on
//! a real port. Imports with and without the token, paths outside the import root, a bad file
//! (clear error, pool untouched, serving goes on), a replacement while a session reads the old
//! generation (it finishes on it; newcomers get the new one; the old trees go when it ends),
//! removal, and the `arbor-server import --server` CLI. Checks of scenes while the daemon serves
//! (`POST /v1/scenes/{name}/verify`): a sound scene, a damaged one, an unreadable one, by the
//! API and by `arbor-server verify --server`. Copies of the served pool (`POST /v1/copies`): the
//! copy against the served scenes, refusals, metrics, and `arbor-server copy --server`.

mod common;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use arbor_proto::wire::Frame;
use arbor_proto::{Channel, TreeletId};
use arbor_server::daemon::{DaemonOptions, RunningServer};
use arbor_server::service::ServeConfig;
use arbor_server::service::config::SceneAccess;
use common::{TestPool, connect, damaged_pool, hello, receive};
use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

const ADMIN: &str = "admin-secret";
const SCAN_TOKEN: &str = "scan-token";

fn points(name: &str) -> PathBuf {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/points")
        .join(name);
    assert!(p.exists(), "the real scans in ../shared/data are required");
    p
}

/// An HTTP/1.1 request on its own connection; status and JSON body.
async fn http(addr: SocketAddr, method: &str, path: &str, token: &str, body: &str) -> (u16, Value) {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let auth = if token.is_empty() {
        String::new()
    } else {
        format!("Authorization: Bearer {token}\r\n")
    };
    let req = format!(
        "{method} {path} HTTP/1.1\r\nHost: x\r\n{auth}Content-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(req.as_bytes()).await.unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).await.unwrap();
    let raw = String::from_utf8(raw).unwrap();
    let (head, body) = raw.split_once("\r\n\r\n").unwrap();
    let status = head.split(' ').nth(1).unwrap().parse().unwrap();
    (status, serde_json::from_str(body).unwrap_or(Value::Null))
}

/// A `GET` of a text route, with the admin token: the whole answer, head and body.
async fn text(addr: SocketAddr, path: &str) -> String {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(
        format!(
            "GET {path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {ADMIN}\r\n\
             Connection: close\r\n\r\n"
        )
        .as_bytes(),
    )
    .await
    .unwrap();
    let mut page = String::new();
    s.read_to_string(&mut page).await.unwrap();
    page
}

struct Daemon {
    server: RunningServer,
    admin: SocketAddr,
    root: tempfile::TempDir,
    pool: TestPool,
}

impl Daemon {
    async fn start(with_root: bool) -> Daemon {
        Self::start_on(TestPool::new(), with_root, None).await
    }

    async fn start_on(pool: TestPool, with_root: bool, check_every: Option<Duration>) -> Daemon {
        Self::start_with(pool, |root| DaemonOptions {
            import_root: with_root.then(|| root.to_owned()),
            check_every,
            ..DaemonOptions::default()
        })
        .await
    }

    /// A daemon on `pool` with the options `options` makes for its scratch root.
    async fn start_with(pool: TestPool, options: impl FnOnce(&Path) -> DaemonOptions) -> Daemon {
        let root = tempfile::tempdir().unwrap();
        let mut config: ServeConfig = pool.config();
        config.admin_token = arbor_server::service::config::AdminTokenSource::Inline(ADMIN.into());
        for scene in ["autzen", "lion", "bad"] {
            config
                .scenes
                .insert(scene.into(), SceneAccess::Tokens(vec![SCAN_TOKEN.into()]));
        }
        let options = options(root.path());
        let server = common::start_with(config, options).await;
        let admin = server.admin_addr.unwrap();
        Daemon {
            server,
            admin,
            root,
            pool,
        }
    }

    async fn post(&self, job: Value, token: &str) -> (u16, Value) {
        http(self.admin, "POST", "/v1/scenes", token, &job.to_string()).await
    }

    /// Polls an import until it is done or failed.
    async fn wait(&self, id: u64) -> Value {
        let t0 = Instant::now();
        loop {
            let (status, s) =
                http(self.admin, "GET", &format!("/v1/imports/{id}"), ADMIN, "").await;
            assert_eq!(status, 200, "{s}");
            if s["phase"] == "done" || s["phase"] == "failed" {
                return s;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(120),
                "import {id} stuck: {s}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    async fn import(&self, job: Value) -> Value {
        let (status, answer) = self.post(job, ADMIN).await;
        assert_eq!(status, 202, "{answer}");
        self.wait(answer["id"].as_u64().unwrap()).await
    }

    fn scenes(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .server
            .pool()
            .scenes()
            .unwrap()
            .into_iter()
            .map(|d| d.name)
            .collect();
        v.sort();
        v
    }
}

/// The bunny's root still streams: serving went on.
async fn bunny_streams(d: &Daemon) {
    let client = connect(d.server.quic_addr, &d.server.fingerprint).await;
    let (mut control, desc) = hello(&client.conn, common::SCENE, &[], common::TOKEN).await;
    desc.expect("bunny SceneInfo");
    control
        .send(&Frame::RequestList {
            seq: 1,
            items: vec![(TreeletId::ROOT, 1.0)],
        })
        .await;
    receive(&client.conn, 1, Duration::from_secs(10))
        .await
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn imports_need_the_token_and_stay_inside_the_root() {
    let d = Daemon::start(true).await;
    std::fs::copy(points("autzen_trim.las"), d.root.path().join("autzen.las")).unwrap();
    let outside = tempfile::tempdir().unwrap();
    std::fs::copy(points("autzen_trim.las"), outside.path().join("x.las")).unwrap();
    std::os::unix::fs::symlink(outside.path().join("x.las"), d.root.path().join("link.las"))
        .unwrap();
    let job = json!({"scene": "autzen", "inputs": ["autzen.las"]});
    assert_eq!(d.post(job.clone(), "").await.0, 401);
    assert_eq!(d.post(job.clone(), "wrong").await.0, 401);
    for (input, status, want) in [
        ("../x.las", 403, "'..' is not allowed"),
        ("link.las", 403, "outside the import root"),
        (
            outside.path().join("x.las").to_str().unwrap(),
            403,
            "outside the import root",
        ),
        ("missing.las", 400, "No such file"),
    ] {
        let (s, e) = d
            .post(json!({"scene": "autzen", "inputs": [input]}), ADMIN)
            .await;
        assert_eq!(s, status, "{input}: {e}");
        assert!(e["error"].as_str().unwrap().contains(want), "{input}: {e}");
    }
    let (s, e) = d
        .post(
            json!({"scene": "autzen", "inputs": ["autzen.las"], "depth": 40}),
            ADMIN,
        )
        .await;
    assert_eq!(s, 400, "{e}");
    let (s, e) = d
        .post(json!({"scene": "bunny", "inputs": ["autzen.las"]}), ADMIN)
        .await;
    assert_eq!(s, 409, "{e}");
    assert_eq!(d.scenes(), ["bunny"]);

    let done = d.import(job).await;
    assert_eq!(done["phase"], "done", "{done}");
    assert_eq!(done["primitives"], 110_000);
    assert_eq!(d.scenes(), ["autzen", "bunny"]);
    let (s, listed) = http(d.admin, "GET", "/v1/scenes/autzen", ADMIN, "").await;
    assert_eq!(s, 200, "{listed}");
    assert_eq!(listed["treelets"], done["treelets"]);
    let (s, all) = http(d.admin, "GET", "/v1/imports", ADMIN, "").await;
    assert_eq!(s, 200);
    assert_eq!(all.as_array().unwrap().len(), 1);
    bunny_streams(&d).await;
    d.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_file_fails_cleanly_and_serving_goes_on() {
    let d = Daemon::start(true).await;
    let bytes = std::fs::read(points("autzen_trim.las")).unwrap();
    std::fs::write(d.root.path().join("bad.las"), &bytes[..bytes.len() - 3_000]).unwrap();
    let generations = d.server.pool().stored_generations();
    let failed = d
        .import(json!({"scene": "bad", "inputs": ["bad.las"]}))
        .await;
    assert_eq!(failed["phase"], "failed", "{failed}");
    let e = failed["error"].as_str().unwrap();
    assert!(
        e.contains("bad.las") && e.contains("truncated LAS point data"),
        "{e}"
    );
    assert_eq!(d.scenes(), ["bunny"]);
    assert_eq!(d.server.pool().stored_generations(), generations);
    bunny_streams(&d).await;
    // The status page shows the import and its error.
    let page = text(d.admin, "/").await;
    assert!(page.contains("<h2>Imports</h2>"), "{page}");
    assert!(page.contains("truncated LAS point data"), "{page}");
    d.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_an_import_root_imports_are_refused() {
    let d = Daemon::start(false).await;
    let (s, e) = d
        .post(json!({"scene": "x", "inputs": ["a.las"]}), ADMIN)
        .await;
    assert_eq!(s, 403, "{e}");
    assert!(
        e["error"].as_str().unwrap().contains("--import-root"),
        "{e}"
    );
    d.server.shutdown().await;
}

/// Every treelet of the session's scene, received and compared with what `stored` holds.
async fn fetch_all_and_compare(
    client: &common::Client,
    control: &mut common::Control,
    seq: u64,
    stored: &arbor_server::pool::StoredScene,
) {
    let ids = common::all_ids(&stored.description);
    let items = ids.iter().map(|&t| (t, 1.0)).collect();
    control.send(&Frame::RequestList { seq, items }).await;
    let got = receive(&client.conn, ids.len(), Duration::from_secs(30))
        .await
        .unwrap();
    for (id, bytes) in got {
        let m = arbor_proto::frame::decode_treelet_message(&bytes).unwrap();
        assert_eq!(
            m.nodes,
            stored.nodes(id).unwrap().unwrap().as_ref(),
            "treelet {} from another generation",
            id.0
        );
    }
}

/// Waits (at most 10 s) until the pool no longer stores `generation`'s trees.
async fn dropped(d: &Daemon, generation: u64) {
    let t0 = Instant::now();
    while d.server.pool().stored_generations().contains(&generation) {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "generation {generation} kept"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replacing_a_scene_lets_sessions_finish_on_their_generation() {
    let d = Daemon::start(true).await;
    std::fs::copy(points("autzen_trim.las"), d.root.path().join("autzen.las")).unwrap();
    let first = d
        .import(json!({"scene": "autzen", "inputs": ["autzen.las"], "depth": 8}))
        .await;
    assert_eq!(first["phase"], "done", "{first}");
    let old = d.server.pool().scene("autzen").unwrap();
    let old_client = connect(d.server.quic_addr, &d.server.fingerprint).await;
    let (mut old_control, desc) =
        hello(&old_client.conn, "autzen", &[Channel::Color], SCAN_TOKEN).await;
    assert_eq!(desc.unwrap().treelet_count, old.description.treelet_count);

    let second = d
        .import(json!({"scene": "autzen", "inputs": ["autzen.las"], "replace": true, "treelet_bytes": 1024}))
        .await;
    assert_eq!(second["phase"], "done", "{second}");
    let new = d.server.pool().scene("autzen").unwrap();
    assert_ne!(new.generation, old.generation);
    assert_ne!(new.description.treelet_count, old.description.treelet_count);
    assert_eq!(d.server.imports.retired_generations(), [old.generation]);

    // The old session reads the old generation, all of it; a new one gets the new generation.
    fetch_all_and_compare(&old_client, &mut old_control, 1, &old).await;
    let new_client = connect(d.server.quic_addr, &d.server.fingerprint).await;
    let (mut new_control, desc) = hello(&new_client.conn, "autzen", &[], SCAN_TOKEN).await;
    assert_eq!(desc.unwrap().treelet_count, new.description.treelet_count);
    fetch_all_and_compare(&new_client, &mut new_control, 1, &new).await;

    // The old generation goes once its last session ended.
    old_client.conn.close(0u32.into(), b"done");
    dropped(&d, old.generation).await;
    assert!(d.server.imports.retired_generations().is_empty());

    // Removal: unpublished at once; the live session still finishes on it.
    let (s, r) = http(d.admin, "DELETE", "/v1/scenes/autzen", ADMIN, "").await;
    assert_eq!(s, 200, "{r}");
    let (s, _) = http(d.admin, "GET", "/v1/scenes/autzen", ADMIN, "").await;
    assert_eq!(s, 404);
    assert_eq!(d.scenes(), ["bunny"]);
    fetch_all_and_compare(&new_client, &mut new_control, 2, &new).await;
    let (s, _) = http(d.admin, "DELETE", "/v1/scenes/autzen", ADMIN, "").await;
    assert_eq!(s, 404);
    new_client.conn.close(0u32.into(), b"done");
    d.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_cli_drives_a_daemon_import() {
    let d = Daemon::start(true).await;
    let tiles = d.root.path().join("tiles");
    std::fs::create_dir(&tiles).unwrap();
    std::fs::copy(points("autzen_trim.las"), tiles.join("a.las")).unwrap();
    let token_file = d.root.path().join("token");
    std::fs::write(&token_file, ADMIN).unwrap();
    let run = |scene: &'static str, input: &'static str| {
        let admin = format!("http://{}", d.admin);
        let token_file = token_file.clone();
        tokio::task::spawn_blocking(move || {
            std::process::Command::new(env!("CARGO_BIN_EXE_arbor-server"))
                .args(["import", "--server", &admin, "--token-file"])
                .arg(&token_file)
                .args(["--scene", scene, "--depth", "8", input])
                .output()
                .unwrap()
        })
    };
    let out = run("autzen", "tiles").await.unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("imported autzen"), "{stdout}");
    assert_eq!(d.scenes(), ["autzen", "bunny"]);
    let out = run("lion", "../etc").await.unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("refused the import (403)") && stderr.contains("'..'"),
        "{stderr}"
    );
    d.server.shutdown().await;
    drop(d.pool);
}

/// Asks for a check of `scene` and polls it until it ends.
async fn check(d: &Daemon, scene: &str) -> Value {
    let (status, answer) = http(
        d.admin,
        "POST",
        &format!("/v1/scenes/{scene}/verify"),
        ADMIN,
        "",
    )
    .await;
    assert_eq!(status, 202, "{answer}");
    follow(d, answer["status"].as_str().unwrap()).await
}

/// Polls a background job's status (a check, a copy) until it ends.
async fn follow(d: &Daemon, path: &str) -> Value {
    let t0 = Instant::now();
    loop {
        let (status, s) = http(d.admin, "GET", path, ADMIN, "").await;
        assert_eq!(status, 200, "{s}");
        if !["queued", "running"].contains(&s["phase"].as_str().unwrap()) {
            return s;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "{path} stuck: {s}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The count of pool reads the serving histogram holds.
async fn serving_reads(d: &Daemon) -> u64 {
    let page = text(d.admin, "/metrics").await;
    page.lines()
        .find_map(|l| l.strip_prefix("arbor_pool_read_seconds_count "))
        .unwrap_or_else(|| panic!("no read count in {page}"))
        .trim()
        .parse()
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scenes_are_checked_while_the_daemon_serves() {
    let d = Daemon::start_on(damaged_pool(), false, None).await;
    let verify = |scene: &str| format!("/v1/scenes/{scene}/verify");
    assert_eq!(http(d.admin, "POST", &verify("bunny"), "", "").await.0, 401);
    for scene in ["nope", "..", "a%20b"] {
        let (s, e) = http(d.admin, "POST", &verify(scene), ADMIN, "").await;
        assert_eq!(s, 404, "{scene}: {e}");
    }
    let reads = serving_reads(&d).await;

    // A sound scene: the report the stand-alone check gives, and serving goes on.
    let sound = check(&d, "bunny").await;
    assert_eq!(sound["phase"], "ok", "{sound}");
    assert_eq!(
        serving_reads(&d).await,
        reads,
        "the check's reads were counted as serving"
    );
    let stored = d.server.pool().scene("bunny").unwrap();
    let expected = arbor_server::verify::verify_scene(&stored).unwrap();
    assert_eq!(sound["report"], serde_json::to_value(&expected).unwrap());
    assert_eq!(sound["generation"], stored.generation);
    assert_eq!(sound["treelets_checked"], expected.treelets);
    assert_eq!(
        sound["treelets_planned"],
        u64::from(stored.description.treelet_count)
    );
    bunny_streams(&d).await;

    // A damaged scene: its problems, as the stand-alone check finds them.
    let damaged = check(&d, "holes").await;
    assert_eq!(damaged["phase"], "problems", "{damaged}");
    let expected =
        arbor_server::verify::verify_scene(&d.server.pool().scene("holes").unwrap()).unwrap();
    assert!(!expected.is_ok());
    assert_eq!(damaged["report"], serde_json::to_value(&expected).unwrap());

    // An unreadable one: failed, naming the entry; the daemon serves on.
    let unreadable = check(&d, "garbage").await;
    assert_eq!(unreadable["phase"], "failed", "{unreadable}");
    let e = unreadable["error"].as_str().unwrap();
    assert!(e.contains("pool entry nodes pack"), "{e}");
    bunny_streams(&d).await;

    let (s, all) = http(d.admin, "GET", "/v1/verifications", ADMIN, "").await;
    assert_eq!(s, 200);
    let phases: Vec<&str> = all
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["phase"].as_str().unwrap())
        .collect();
    assert_eq!(phases, ["ok", "problems", "failed"]);
    let page = text(d.admin, "/").await;
    assert!(page.contains("<h2>Checks</h2>"), "{page}");
    assert!(
        page.contains("every invariant holds") && page.contains("problems</span>"),
        "{page}"
    );
    // Cancelling a finished check leaves it as it ended; unknown ids are 404.
    let id = sound["id"].as_u64().unwrap();
    let (s, after) = http(
        d.admin,
        "DELETE",
        &format!("/v1/verifications/{id}"),
        ADMIN,
        "",
    )
    .await;
    assert_eq!((s, after["phase"].as_str()), (200, Some("ok")), "{after}");
    for path in ["/v1/verifications/999", "/v1/verifications/x"] {
        assert_eq!(http(d.admin, "GET", path, ADMIN, "").await.0, 404, "{path}");
        assert_eq!(
            http(d.admin, "DELETE", path, ADMIN, "").await.0,
            404,
            "{path}"
        );
    }
    d.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_cli_asks_a_serving_daemon_to_check_a_scene() {
    let d = Daemon::start_on(damaged_pool(), false, None).await;
    let token_file = d.root.path().join("token");
    std::fs::write(&token_file, ADMIN).unwrap();
    let run = |args: Vec<String>| {
        tokio::task::spawn_blocking(move || {
            std::process::Command::new(env!("CARGO_BIN_EXE_arbor-server"))
                .args(args)
                .output()
                .unwrap()
        })
    };
    let remote = |scene: &str| {
        vec![
            "verify".into(),
            "--server".into(),
            format!("http://{}", d.admin),
            "--token-file".into(),
            token_file.display().to_string(),
            "--scene".into(),
            scene.into(),
            "--quiet".into(),
        ]
    };
    let text = |o: &std::process::Output| {
        format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        )
    };
    let out = run(remote("bunny")).await.unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", text(&out));
    assert!(
        text(&out).contains("ok: every invariant holds"),
        "{}",
        text(&out)
    );
    let out = run(remote("holes")).await.unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", text(&out));
    assert!(text(&out).contains("problem: "), "{}", text(&out));
    let out = run(remote("garbage")).await.unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", text(&out));
    assert!(
        text(&out).contains("failed on the server"),
        "{}",
        text(&out)
    );
    let out = run(remote("nope")).await.unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", text(&out));
    assert!(
        text(&out).contains("refused to check nope (404)"),
        "{}",
        text(&out)
    );
    // A name no scene can have is refused before any request is made.
    let out = run(remote("a b/../c")).await.unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", text(&out));
    assert!(
        text(&out).contains("scene name") && !text(&out).contains("refused"),
        "{}",
        text(&out)
    );
    // The stand-alone check cannot open the served pool, and says what to do instead.
    let out = run(vec![
        "verify".into(),
        "--db".into(),
        d.pool.db().display().to_string(),
        "--scene".into(),
        "bunny".into(),
        "--quiet".into(),
    ])
    .await
    .unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", text(&out));
    assert!(text(&out).contains("verify --server"), "{}", text(&out));
    d.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_scene_is_checked_each_period_and_metrics_say_how_it_went() {
    let d = Daemon::start_on(damaged_pool(), false, Some(Duration::from_millis(300))).await;
    let metrics = text(d.admin, "/metrics").await;
    assert!(
        !metrics.contains("arbor_scene_check_ok{"),
        "a scene reported checked before any check: {metrics}"
    );
    // Nobody asks: each scene is checked within a few periods, and again after.
    let t0 = Instant::now();
    let checks = loop {
        let (s, all) = http(d.admin, "GET", "/v1/verifications", ADMIN, "").await;
        assert_eq!(s, 200);
        let ended: Vec<(String, String)> = all
            .as_array()
            .unwrap()
            .iter()
            .filter(|c| !["queued", "running"].contains(&c["phase"].as_str().unwrap()))
            .map(|c| {
                (
                    c["scene"].as_str().unwrap().to_owned(),
                    c["phase"].as_str().unwrap().to_owned(),
                )
            })
            .collect();
        if ended.len() >= 6 {
            break ended;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "periodic checks missing: {all}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    for (scene, phase) in [
        ("bunny", "ok"),
        ("holes", "problems"),
        ("garbage", "failed"),
    ] {
        let n = checks.iter().filter(|c| c.0 == scene).count();
        assert!(n >= 2, "{scene} checked {n} times: {checks:?}");
        assert!(
            checks.iter().filter(|c| c.0 == scene).all(|c| c.1 == phase),
            "{scene}: {checks:?}"
        );
    }
    let metrics = text(d.admin, "/metrics").await;
    for line in [
        "arbor_scene_check_ok{scene=\"bunny\"} 1\n",
        "arbor_scene_check_ok{scene=\"holes\"} 0\n",
        "arbor_scene_check_ok{scene=\"garbage\"} 0\n",
        "arbor_scene_check_problems{scene=\"bunny\"} 0\n",
    ] {
        assert!(metrics.contains(line), "no {line} in {metrics}");
    }
    let sample = |name: &str| -> f64 {
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .unwrap_or_else(|| panic!("no {name} in {metrics}"))
            .trim()
            .parse()
            .unwrap()
    };
    assert!(sample("arbor_scene_check_problems{scene=\"holes\"}") > 0.0);
    assert!(sample("arbor_scene_checks_total{outcome=\"failed\"}") >= 2.0);
    assert!(sample("arbor_scene_checks_total{outcome=\"ok\"}") >= 2.0);
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    let ended = sample("arbor_scene_check_end_seconds{scene=\"bunny\"}");
    assert!(
        (now - 60.0..=now + 1.0).contains(&ended),
        "{ended} against {now}"
    );

    // A removed scene's checks no longer report on it.
    let (s, _) = http(d.admin, "DELETE", "/v1/scenes/holes", ADMIN, "").await;
    assert_eq!(s, 200);
    let metrics = text(d.admin, "/metrics").await;
    assert!(!metrics.contains("scene=\"holes\""), "{metrics}");
    bunny_streams(&d).await;
    d.server.shutdown().await;
}

/// The daemon's pool copied while it serves: refusals first (token, names, unknown scene,
/// disabled), then a copy of every scene, compared pack for pack with what the daemon serves,
/// carrying its certificate, not counted as serving reads, in `/metrics` and on the page; the
/// destination taken afterwards; and the CLI's copy of one scene.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_served_pool_is_copied_while_the_daemon_serves() {
    let without = Daemon::start_on(TestPool::new(), false, None).await;
    let (s, e) = http(without.admin, "POST", "/v1/copies", ADMIN, r#"{"to":"a"}"#).await;
    assert_eq!(s, 403, "{e}");
    assert!(e["error"].as_str().unwrap().contains("--copy-root"), "{e}");
    without.server.shutdown().await;

    let d = Daemon::start_with(TestPool::with_copies(&["second"]), |root| {
        std::fs::create_dir(root.join("copies")).unwrap();
        DaemonOptions {
            copy_root: Some(root.join("copies")),
            ..DaemonOptions::default()
        }
    })
    .await;
    let copies = d.root.path().join("copies");
    let post = |body: &'static str, token: &'static str| {
        let admin = d.admin;
        async move { http(admin, "POST", "/v1/copies", token, body).await }
    };
    assert_eq!(post(r#"{"to":"a"}"#, "").await.0, 401);
    for (body, status) in [
        (r#"{"to":"../a"}"#, 400),
        (r#"{"to":".a"}"#, 400),
        (r#"{"to":"a/b"}"#, 400),
        (r#"{"to":""}"#, 400),
        (r#"{"to":"a","extra":1}"#, 400),
        (r#"{"scenes":["bunny"]}"#, 400),
        ("not json", 400),
        (r#"{"to":"a","scenes":["nope"]}"#, 404),
        (r#"{"to":"scheduled-2026-12-02T030000Z"}"#, 400),
    ] {
        let (s, e) = post(body, ADMIN).await;
        assert_eq!(s, status, "{body}: {e}");
        assert!(e["error"].is_string(), "{body}: {e}");
    }
    assert_eq!(std::fs::read_dir(&copies).unwrap().count(), 0);
    let reads = serving_reads(&d).await;

    let (s, answer) = post(r#"{"to":"backup"}"#, ADMIN).await;
    assert_eq!(s, 202, "{answer}");
    let done = follow(&d, answer["status"].as_str().unwrap()).await;
    assert_eq!(done["phase"], "done", "{done}");
    assert_eq!(done["bytes_copied"], done["bytes_planned"], "{done}");
    let names: Vec<&str> = done["scenes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, [common::SCENE, "second"]);
    let carried = &done["report"]["carried"];
    assert_eq!(carried, &json!(["cert.pem", "key.pem"]), "{done}");
    assert_eq!(
        serving_reads(&d).await,
        reads,
        "the copy's reads were counted as serving"
    );
    let backup = copies.join("backup");
    assert!(!copies.join(".backup.copy-partial").exists());
    assert_eq!(
        std::fs::read(backup.join("cert.pem")).unwrap(),
        std::fs::read(d.pool.data_dir().join("cert.pem")).unwrap()
    );
    {
        let copied = arbor_server::pool::Pool::open(&backup).unwrap();
        for name in names {
            let served = d.server.pool().scene(name).unwrap();
            let scene = copied.scene(name).unwrap();
            arbor_server::pool::copy::compare_scene(&served, &scene).unwrap();
            assert!(arbor_server::verify::verify_scene(&scene).unwrap().is_ok());
        }
    }
    bunny_streams(&d).await;
    let (s, e) = post(r#"{"to":"backup"}"#, ADMIN).await;
    assert_eq!(s, 409, "{e}");

    let metrics = text(d.admin, "/metrics").await;
    assert!(
        metrics.contains("arbor_pool_copies_total{outcome=\"done\"} 1\n"),
        "{metrics}"
    );
    let ended: f64 = metrics
        .lines()
        .find_map(|l| l.strip_prefix("arbor_pool_copy_last_done_seconds "))
        .unwrap_or_else(|| panic!("no copy's end in {metrics}"))
        .parse()
        .unwrap();
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    assert!(
        (now - 60.0..=now + 1.0).contains(&ended),
        "{ended} against {now}"
    );
    let page = text(d.admin, "/").await;
    assert!(page.contains("<h2>Copies</h2>") && page.contains("compared with the source"));
    let (s, all) = http(d.admin, "GET", "/v1/copies", ADMIN, "").await;
    assert_eq!((s, all.as_array().unwrap().len()), (200, 1), "{all}");
    for path in ["/v1/copies/999", "/v1/copies/x"] {
        assert_eq!(http(d.admin, "GET", path, ADMIN, "").await.0, 404, "{path}");
        assert_eq!(http(d.admin, "DELETE", path, ADMIN, "").await.0, 404);
    }

    // The CLI: one scene; a name that is not a plain directory name refused before asking.
    let token_file = d.root.path().join("token");
    std::fs::write(&token_file, ADMIN).unwrap();
    let cli = |to: &str| {
        let args: Vec<String> = [
            "copy",
            "--server",
            &format!("http://{}", d.admin),
            "--token-file",
            &token_file.display().to_string(),
            "--to",
            to,
            "--scene",
            "second",
            "--quiet",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        tokio::task::spawn_blocking(move || {
            let o = std::process::Command::new(env!("CARGO_BIN_EXE_arbor-server"))
                .args(args)
                .output()
                .unwrap();
            let text = format!(
                "{}{}",
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            );
            (o.status.code(), text)
        })
    };
    let (code, out) = cli("second-only").await.unwrap();
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains("copied second:"), "{out}");
    let copied = arbor_server::pool::Pool::open(&copies.join("second-only")).unwrap();
    let names: Vec<String> = copied
        .scenes()
        .unwrap()
        .into_iter()
        .map(|d| d.name)
        .collect();
    assert_eq!(names, ["second"]);
    let (code, out) = cli("../escape").await.unwrap();
    assert_eq!(code, Some(1), "{out}");
    assert!(
        out.contains("a directory name under the daemon's --copy-root"),
        "{out}"
    );
    let (code, out) = cli("backup").await.unwrap();
    assert_eq!(code, Some(1), "{out}");
    assert!(
        out.contains("409") && out.contains("already exists"),
        "{out}"
    );
    d.server.shutdown().await;
}

/// Every pack of a scene's trees, by tree name and key.
fn packs_of(scene: &arbor_server::pool::StoredScene) -> Vec<(&'static str, Vec<u8>, Vec<u8>)> {
    scene
        .trees()
        .into_iter()
        .flat_map(|(name, tree)| {
            tree.iter()
                .map(move |e| {
                    let (k, v) = e.unwrap();
                    (name, k.to_vec(), v.to_vec())
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

/// A sample of the text metrics, by its line's prefix.
fn sample(metrics: &str, prefix: &str) -> Option<f64> {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(prefix))
        .map(|v| v.trim().parse().unwrap())
}

/// Polls a job's status until `ready` holds of it.
async fn until(d: &Daemon, path: &str, ready: impl Fn(&Value) -> bool) -> Value {
    let t0 = Instant::now();
    loop {
        let (status, s) = http(d.admin, "GET", path, ADMIN, "").await;
        assert_eq!(status, 200, "{s}");
        if ready(&s) {
            return s;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "{path}: {s}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Checks and copies read at the daemon's background read rate, which the admin API changes
/// while they run. A check and a copy slowed to it are running when the bunny is replaced: the
/// reaper keeps the old generation while they read it, both end on it once the rate is lifted
/// (the copy pack for pack the old generation), and the old generation goes after them. A
/// copy at the slowest rate stops at once when cancelled (its reader waits no more).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn background_jobs_keep_the_read_rate_and_the_generation_they_read() {
    let d = Daemon::start_with(TestPool::new(), |root| {
        std::fs::create_dir(root.join("copies")).unwrap();
        DaemonOptions {
            import_root: Some(root.to_owned()),
            copy_root: Some(root.join("copies")),
            background_read_rate: Some(1_000),
            ..DaemonOptions::default()
        }
    })
    .await;
    let put = |body: &'static str, token: &'static str| {
        let admin = d.admin;
        async move { http(admin, "PUT", "/v1/background-reads", token, body).await }
    };
    let (s, f) = http(d.admin, "GET", "/v1/background-reads", ADMIN, "").await;
    assert_eq!(s, 200, "{f}");
    assert_eq!(f["read_bytes_per_second"], 1_000, "{f}");
    assert_eq!(put(r#"{"read_bytes_per_second":null}"#, "").await.0, 401);
    for body in [
        r#"{"read_bytes_per_second":5}"#,
        r#"{"read_bytes_per_second":"fast"}"#,
        r#"{"read_bytes_per_second":-1}"#,
        r#"{"read_bytes_per_second":"2000TB"}"#,
        r#"{"rate":1}"#,
        "not json",
    ] {
        let (s, e) = put(body, ADMIN).await;
        assert_eq!(s, 400, "{body}: {e}");
        assert!(e["error"].is_string(), "{body}: {e}");
    }
    let (_, f) = http(d.admin, "GET", "/v1/background-reads", ADMIN, "").await;
    assert_eq!(
        f["read_bytes_per_second"], 1_000,
        "a refused rate was set: {f}"
    );

    let old = d.server.pool().scene(common::SCENE).unwrap();
    let old_packs = packs_of(&old);
    let old_bytes: usize = old_packs.iter().map(|(_, _, v)| v.len()).sum();
    assert!(
        old_bytes > 80 * 1024,
        "{old_bytes} bytes: the bunny's copy fits in the pace's burst"
    );
    let (s, copy) = http(d.admin, "POST", "/v1/copies", ADMIN, r#"{"to":"held"}"#).await;
    assert_eq!(s, 202, "{copy}");
    let copy = copy["status"].as_str().unwrap().to_owned();
    let (s, check) = http(d.admin, "POST", "/v1/scenes/bunny/verify", ADMIN, "").await;
    assert_eq!(s, 202, "{check}");
    let check = check["status"].as_str().unwrap().to_owned();
    until(&d, &copy, |s| {
        s["phase"] == "running" && s["bytes_copied"].as_u64() > Some(0)
    })
    .await;
    until(&d, &check, |s| s["phase"] == "running").await;

    // The bunny replaced (2 KiB treelets: another treelet count) while both read it.
    std::fs::copy(common::bunny_path(), d.root.path().join("bunny.obj")).unwrap();
    let replaced = d
        .import(
            json!({"scene": "bunny", "inputs": ["bunny.obj"], "replace": true,
                       "depth": 6, "treelet_bytes": 2048}),
        )
        .await;
    assert_eq!(replaced["phase"], "done", "{replaced}");
    let new = d.server.pool().scene(common::SCENE).unwrap();
    assert_ne!(new.description.treelet_count, old.description.treelet_count);
    tokio::time::sleep(Duration::from_millis(1_000)).await;
    assert_eq!(d.server.imports.retired_generations(), [old.generation]);
    assert!(
        d.server
            .pool()
            .stored_generations()
            .contains(&old.generation)
    );
    let (_, running) = http(d.admin, "GET", &copy, ADMIN, "").await;
    assert_eq!(
        running["phase"], "running",
        "the copy outran the pace: {running}"
    );
    let metrics = text(d.admin, "/metrics").await;
    assert_eq!(
        sample(&metrics, "arbor_pool_background_read_rate_bytes "),
        Some(1_000.0),
        "{metrics}"
    );
    assert!(
        sample(&metrics, "arbor_pool_background_wait_seconds_total ") > Some(0.0),
        "{metrics}"
    );

    // The rate lifted: both end on the old generation, which then goes.
    let (s, f) = put(r#"{"read_bytes_per_second":null}"#, ADMIN).await;
    assert_eq!((s, &f["read_bytes_per_second"]), (200, &Value::Null), "{f}");
    let copied = follow(&d, &copy).await;
    assert_eq!(copied["phase"], "done", "{copied}");
    let checked = follow(&d, &check).await;
    assert_eq!(checked["phase"], "ok", "{checked}");
    assert_eq!(checked["generation"], old.generation, "{checked}");
    dropped(&d, old.generation).await;
    assert!(d.server.imports.retired_generations().is_empty());
    {
        let held = arbor_server::pool::Pool::open(&d.root.path().join("copies/held")).unwrap();
        let scene = held.scene(common::SCENE).unwrap();
        assert_eq!(scene.description, old.description);
        assert!(
            packs_of(&scene) == old_packs,
            "the copy is not the old generation"
        );
    }
    let metrics = text(d.admin, "/metrics").await;
    assert_eq!(
        sample(&metrics, "arbor_pool_background_read_rate_bytes "),
        None
    );
    let read = sample(&metrics, "arbor_pool_background_read_bytes_total ").unwrap();
    // The copy read every pack twice (copied, then compared); the check read each at least once.
    assert!(read >= 3.0 * old_bytes as f64, "{read} of {old_bytes}");

    // At the slowest rate, a cancelled copy stops at once.
    let (s, f) = put(r#"{"read_bytes_per_second":"1kB/s"}"#, ADMIN).await;
    assert_eq!(
        (s, &f["read_bytes_per_second"]),
        (200, &json!(1_000)),
        "{f}"
    );
    let (s, slow) = http(d.admin, "POST", "/v1/copies", ADMIN, r#"{"to":"slow"}"#).await;
    assert_eq!(s, 202, "{slow}");
    let slow = slow["status"].as_str().unwrap().to_owned();
    until(&d, &slow, |s| {
        s["phase"] == "running" && s["bytes_copied"].as_u64() > Some(0)
    })
    .await;
    let t0 = Instant::now();
    let (s, _) = http(d.admin, "DELETE", &slow, ADMIN, "").await;
    assert_eq!(s, 200);
    let stopped = follow(&d, &slow).await;
    assert_eq!(stopped["phase"], "cancelled", "{stopped}");
    // What was left to read would take minutes at 1 kB/s.
    assert!(t0.elapsed() < Duration::from_secs(10), "{:?}", t0.elapsed());
    assert!(!d.root.path().join("copies/slow").exists());
    let page = text(d.admin, "/").await;
    assert!(page.contains("Background reads (checks, copies): at most 1.0 kB/s"));
    d.server.shutdown().await;
}

/// `serve --copy-every` copies the pool on its own, names each copy by its time, and keeps the
/// newest `--copy-keep`; directories it did not make are left alone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_pool_is_copied_each_period_and_old_scheduled_copies_go() {
    let pool = TestPool::new();
    let refused = arbor_server::daemon::start_with(
        pool.config(),
        DaemonOptions {
            copy_every: Some(Duration::from_secs(1)),
            ..DaemonOptions::default()
        },
    )
    .await
    .unwrap_err();
    assert!(
        refused
            .to_string()
            .contains("--copy-every and --copy-at need --copy-root"),
        "{refused}"
    );
    drop(pool);
    let d = Daemon::start_with(TestPool::new(), |root| {
        std::fs::create_dir_all(root.join("copies/manual")).unwrap();
        DaemonOptions {
            copy_root: Some(root.join("copies")),
            copy_every: Some(Duration::from_secs(1)),
            copy_keep: std::num::NonZeroUsize::new(2),
            ..DaemonOptions::default()
        }
    })
    .await;
    let copies = d.root.path().join("copies");
    let t0 = Instant::now();
    loop {
        let metrics = text(d.admin, "/metrics").await;
        let done = sample(&metrics, "arbor_pool_copies_total{outcome=\"done\"} ").unwrap_or(0.0);
        if done >= 3.0 {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "{metrics}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let (s, all) = http(d.admin, "GET", "/v1/copies", ADMIN, "").await;
    assert_eq!(s, 200);
    let all = all.as_array().unwrap();
    assert!(all.len() >= 3, "{all:?}");
    assert!(all.iter().all(|c| c["scheduled"] == true), "{all:?}");
    d.server.shutdown().await;
    // The copy in hand, if any, sees the cancel within a pack.
    tokio::time::sleep(Duration::from_millis(500)).await;
    // Each copy done pruned the ones before it to two (a third appears between a copy's rename
    // and its pruning).
    let mut scheduled: Vec<String> = std::fs::read_dir(&copies)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("scheduled-"))
        .collect();
    scheduled.sort();
    assert!(
        (2..=3).contains(&scheduled.len()),
        "{scheduled:?} after at least three copies"
    );
    assert!(
        copies.join("manual").is_dir(),
        "a directory it did not make was removed"
    );
    // Each one left is a whole pool with the bunny.
    for name in scheduled {
        let copy = copies.join(&name);
        let pool = arbor_server::pool::Pool::open(&copy).unwrap();
        assert_eq!(pool.scenes().unwrap()[0].name, common::SCENE, "{name}");
    }
}

/// `serve --copy-at`/`--check-at` pin the schedules to the wall clock: copies every 2 s at odd
/// seconds are named by the odd second they were due, whatever second the daemon started in;
/// `/metrics` and the page say when each schedule is next due; a schedule that would drift
/// from its clock time, or scheduled copies without a root, are refused before serving.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clock_time_schedules_name_copies_by_the_time_they_were_due() {
    use arbor_server::periodic::parse_clock_time;
    for (options, expected) in [
        (
            DaemonOptions {
                copy_at: Some(parse_clock_time("03:00").unwrap()),
                ..DaemonOptions::default()
            },
            "--copy-every and --copy-at need --copy-root",
        ),
        (
            DaemonOptions {
                check_at: Some(parse_clock_time("Sun 04:00").unwrap()),
                check_every: Some(Duration::from_secs(86_400)),
                ..DaemonOptions::default()
            },
            "whole weeks",
        ),
    ] {
        let pool = TestPool::new();
        let refused = arbor_server::daemon::start_with(pool.config(), options)
            .await
            .unwrap_err();
        assert!(refused.to_string().contains(expected), "{refused}");
    }
    let d = Daemon::start_with(TestPool::new(), |root| {
        std::fs::create_dir_all(root.join("copies")).unwrap();
        DaemonOptions {
            copy_root: Some(root.join("copies")),
            copy_every: Some(Duration::from_secs(2)),
            copy_at: Some(parse_clock_time("00:00:01").unwrap()),
            check_every: Some(Duration::from_secs(3)),
            check_at: Some(parse_clock_time("00:00:02Z").unwrap()),
            ..DaemonOptions::default()
        }
    })
    .await;
    let t0 = Instant::now();
    let metrics = loop {
        let metrics = text(d.admin, "/metrics").await;
        let done = sample(&metrics, "arbor_pool_copies_total{outcome=\"done\"} ").unwrap_or(0.0);
        if done >= 2.0 {
            break metrics;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "{metrics}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    let next_copy = sample(&metrics, "arbor_pool_copy_next_scheduled_seconds ").unwrap();
    let next_check = sample(&metrics, "arbor_scene_check_next_scheduled_seconds ").unwrap();
    assert_eq!(next_copy % 2.0, 1.0, "{metrics}");
    assert_eq!(next_check % 3.0, 2.0, "{metrics}");
    for next in [next_copy, next_check] {
        assert!(next > now - 1.5 && next < now + 3.5, "{next} at {now}");
    }
    assert!(sample(&metrics, "arbor_pool_copies_skipped_total ").is_some());
    assert_eq!(
        sample(&metrics, "arbor_pool_copy_period_seconds "),
        Some(2.0)
    );
    assert_eq!(
        sample(&metrics, "arbor_scene_check_period_seconds "),
        Some(3.0)
    );
    let (s, all) = http(d.admin, "GET", "/v1/copies", ADMIN, "").await;
    assert_eq!(s, 200);
    let names: Vec<&str> = all
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["to"].as_str().unwrap())
        .collect();
    assert!(names.len() >= 2, "{all}");
    for name in &names {
        // scheduled-YYYY-MM-DDTHHMMSSZ: the seconds are the two digits before the Z.
        let second: u32 = name[name.len() - 3..name.len() - 1].parse().unwrap();
        assert_eq!(
            second % 2,
            1,
            "{name} was not due at an odd second: {names:?}"
        );
    }
    let page = text(d.admin, "/").await;
    for part in [
        "Scheduled: checks of every scene every 3s at 00:00:02 UTC, next 20",
        "copies of the pool every 2s at 00:00:01 UTC, next 20",
    ] {
        assert!(page.contains(part), "{part} not in the page:\n{page}");
    }
    d.server.shutdown().await;
}

/// A daemon started after the time its nightly copy was due, with the last scheduled copy
/// older than that (it was down, or a restart cut the copy short), makes the missed one at
/// once, named by the time it was due.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nightly_copy_missed_while_down_is_made_at_start() {
    use arbor_server::live_copy::{scheduled_name, scheduled_time};
    // Midnight in UTC, and in Kolkata (UTC+05:30 all year): named by its UTC time, 18:30.
    for (clock, offset) in [("00:00", 0), ("00:00 Asia/Kolkata", 19_800)] {
        let d = Daemon::start_with(TestPool::new(), |root| {
            std::fs::create_dir_all(root.join("copies/scheduled-2020-01-01T000000Z")).unwrap();
            DaemonOptions {
                copy_root: Some(root.join("copies")),
                copy_at: Some(arbor_server::periodic::parse_clock_time(clock).unwrap()),
                ..DaemonOptions::default()
            }
        })
        .await;
        let t0 = Instant::now();
        let all = loop {
            let (s, all) = http(d.admin, "GET", "/v1/copies", ADMIN, "").await;
            assert_eq!(s, 200);
            if all.as_array().unwrap().iter().any(|c| c["phase"] == "done") {
                break all;
            }
            assert!(t0.elapsed() < Duration::from_secs(60), "{clock}: {all}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        let all = all.as_array().unwrap();
        assert_eq!(all.len(), 1, "{clock}: one missed time, one copy: {all:?}");
        let name = all[0]["to"].as_str().unwrap();
        let due = scheduled_time(name).unwrap();
        let now = std::time::SystemTime::now();
        let local = now.duration_since(std::time::UNIX_EPOCH).unwrap().as_secs() + offset;
        let midnight =
            std::time::UNIX_EPOCH + Duration::from_secs(local / 86_400 * 86_400 - offset);
        // Today's midnight there (yesterday's if the test straddles one).
        assert!(
            name == scheduled_name(midnight)
                || name == scheduled_name(midnight - Duration::from_secs(86_400)),
            "{clock}: {name}"
        );
        assert!(due <= now);
        let page = text(d.admin, "/").await;
        assert!(
            page.contains(&format!("copies of the pool every 1d at {clock}")),
            "{page}"
        );
        d.server.shutdown().await;
    }
}

/// The scheduled checks keep the time the last one was due in the data directory; a daemon
/// started after a check time it missed checks every scene at once and records that time.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scheduled_check_missed_while_down_runs_at_start() {
    use arbor_server::live_import::LAST_SCHEDULED_CHECK_FILE;
    let pool = TestPool::new();
    let record = pool.data_dir().join(LAST_SCHEDULED_CHECK_FILE);
    std::fs::create_dir_all(pool.data_dir()).unwrap();
    std::fs::write(&record, "1577836800\n").unwrap();
    let d = Daemon::start_with(pool, |_| DaemonOptions {
        check_at: Some(arbor_server::periodic::parse_clock_time("00:00").unwrap()),
        ..DaemonOptions::default()
    })
    .await;
    let done = until(&d, "/v1/verifications", |all| {
        all.as_array()
            .is_some_and(|a| a.iter().any(|c| c["phase"] == "ok"))
    })
    .await;
    assert_eq!(done.as_array().unwrap().len(), 1, "{done}");
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs();
    let recorded: u64 = std::fs::read_to_string(&record)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert_eq!(recorded % 86_400, 0, "not a midnight: {recorded}");
    assert!(
        recorded <= now && now - recorded < 2 * 86_400,
        "{recorded} at {now}"
    );
    d.server.shutdown().await;
}
