//! The path memory outlives a graceful restart: the service writes it to the data directory as
//! it stops and reads it back as it starts, and a damaged file costs the memory, never the
//! start. Real services on loopback with a raw quinn client.

mod common;

use std::net::{IpAddr, Ipv4Addr};
use std::time::{Duration, Instant};

use arbor_proto::wire::Frame;
use arbor_proto::{Channel, TreeletId};
use arbor_server::service::path_memory::{PATHS_FILE, PathRecord};
use common::*;

const LOOPBACK: IpAddr = IpAddr::V4(Ipv4Addr::LOCALHOST);

/// Connects, fetches a few treelets and closes; returns the server's record of loopback once
/// the server has finished with the connection.
async fn visit(server: &arbor_server::daemon::RunningServer) -> PathRecord {
    let client = connect(server.quic_addr, &server.fingerprint).await;
    let (mut control, info) = hello(&client.conn, SCENE, &[Channel::Normal], TOKEN).await;
    let n = (info.unwrap().treelet_count as usize).min(20);
    let items = (0..n as u32).map(|i| (TreeletId(i), -(i as f32))).collect();
    control.send(&Frame::RequestList { seq: 1, items }).await;
    receive(&client.conn, n, Duration::from_secs(10))
        .await
        .unwrap();
    client.conn.close(0u32.into(), b"done");
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        if let Some(r) = server.state.paths().get(LOOPBACK).copied() {
            return r;
        }
        assert!(Instant::now() < deadline, "no path recorded within 10 s");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_path_memory_survives_a_graceful_restart() {
    let tp = TestPool::new();
    let server = start(tp.config()).await;
    let before = visit(&server).await;
    assert!(before.window > 0 && before.rtt > Duration::ZERO);
    server.shutdown().await;
    let file = tp.data_dir().join(PATHS_FILE);
    assert!(file.is_file(), "{} written at shutdown", file.display());

    let server = start(tp.config()).await;
    let after = server
        .state
        .paths()
        .get(LOOPBACK)
        .copied()
        .expect("the record came back");
    assert_eq!((after.window, after.rtt), (before.window, before.rtt));
    assert!(
        after.at.elapsed() < Duration::from_secs(60),
        "its age carried over (seconds, not a fresh or an ancient record)"
    );
    server.shutdown().await;

    // Off: nothing read, nothing written.
    std::fs::remove_file(&file).unwrap();
    let mut off = tp.config();
    off.path_memory_secs = 0;
    let server = start(off).await;
    visit_without_memory(&server).await;
    server.shutdown().await;
    assert!(!file.exists(), "nothing written with the memory off");
}

/// A visit to a server whose memory is off: served as always, nothing recorded.
async fn visit_without_memory(server: &arbor_server::daemon::RunningServer) {
    let client = connect(server.quic_addr, &server.fingerprint).await;
    let (mut control, info) = hello(&client.conn, SCENE, &[Channel::Normal], TOKEN).await;
    assert!(info.is_ok());
    control
        .send(&Frame::RequestList {
            seq: 1,
            items: vec![(TreeletId(0), 1.0)],
        })
        .await;
    receive(&client.conn, 1, Duration::from_secs(10))
        .await
        .unwrap();
    client.conn.close(0u32.into(), b"done");
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(server.state.paths().is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_paths_file_costs_the_memory_not_the_start() {
    let tp = TestPool::new();
    std::fs::create_dir_all(tp.data_dir()).unwrap();
    let file = tp.data_dir().join(PATHS_FILE);
    std::fs::write(&file, b"{\"version\":1,\"records\":[{\"addr\":").unwrap();
    let server = start(tp.config()).await;
    assert!(server.state.paths().is_empty(), "nothing loaded");
    // It serves, and its shutdown replaces the damaged file with a good one.
    visit(&server).await;
    server.shutdown().await;
    let text = std::fs::read_to_string(&file).unwrap();
    assert!(
        text.contains("\"records\":[{\"addr\":\"127.0.0.1\""),
        "{text}"
    );
}
