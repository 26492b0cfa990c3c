//! An import into the serving daemon while a client streams another scene: the client's view
//! still converges exactly to the fully resident reference (RMSE 0), the imports complete, and
//! the new scenes are served. Real sled pool, real QUIC service and headless client, admin API
//! on a real port.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_core::backend::CpuBackend;
use arbor_server::daemon::DaemonOptions;
use arbor_tests::streaming::{admin_request, converge, serve_with};
use serde_json::json;

fn shared(rel: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(rel)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_of_another_scene_converges_exactly_while_scenes_are_imported() {
    let root = tempfile::tempdir().unwrap();
    std::fs::copy(
        shared("points/lion_takanawa.copc.laz"),
        root.path().join("lion.laz"),
    )
    .unwrap();
    std::fs::copy(
        shared("points/autzen_trim.las"),
        root.path().join("autzen.las"),
    )
    .unwrap();
    let options = DaemonOptions {
        import_root: Some(root.path().to_owned()),
        ..DaemonOptions::default()
    };
    let served = Arc::new(serve_with("points/lion_takanawa.copc.laz", "lion", 1024, options).await);
    let admin = served.server.admin_addr.unwrap();
    let mut ids = Vec::new();
    for (scene, input) in [("lion2", "lion.laz"), ("autzen", "autzen.las")] {
        let (s, r) = admin_request(
            admin,
            "POST",
            "/v1/scenes",
            &json!({"scene": scene, "inputs": [input]}).to_string(),
        )
        .await;
        assert_eq!(s, 202, "{r}");
        ids.push(r["id"].as_u64().unwrap());
    }
    let started = Instant::now();
    let addr = served.server.quic_addr;
    let run = converge(
        &served,
        addr,
        "lion while importing",
        &mut CpuBackend,
        || Box::new(CpuBackend),
    )
    .await;
    let streamed = started.elapsed();
    assert!(run.converged_at.is_some());
    // Both imports finish and their scenes are served next to lion.
    for id in ids {
        let t0 = Instant::now();
        loop {
            let (s, st) = admin_request(admin, "GET", &format!("/v1/imports/{id}"), "").await;
            assert_eq!(s, 200, "{st}");
            if st["phase"] == "done" {
                eprintln!(
                    "import {id} ({}) took {:.2} s; the lion view converged in {:.2} s",
                    st["scene"],
                    st["seconds"].as_f64().unwrap(),
                    streamed.as_secs_f64()
                );
                break;
            }
            assert_ne!(st["phase"], "failed", "{st}");
            assert!(
                t0.elapsed() < Duration::from_secs(120),
                "import {id} stuck: {st}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
    let mut names: Vec<String> = served
        .server
        .pool()
        .scenes()
        .unwrap()
        .into_iter()
        .map(|d| d.name)
        .collect();
    names.sort();
    assert_eq!(names, ["autzen", "lion", "lion2"]);
}
