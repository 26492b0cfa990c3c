//! A returning client's connection resumes the congestion window its path reached last time
//! (the server's careful resume, `arbor_server::service::path_memory`), and only on the same
//! path: a real server, real clients, the link emulator at 60 ms each way and 100 Mbit/s, then
//! plain loopback. What it saves in time is the refine bench's (`ARBOR_REFINE_RETURNING`).

use std::net::{IpAddr, Ipv4Addr};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use arbor_server::prometheus::PromText;
use arbor_server::service::config::DEFAULT_INITIAL_WINDOW;
use arbor_server::service::path_memory::PathRecord;
use arbor_tests::link::{LinkConfig, LinkEmulator};
use arbor_tests::streaming::{Served, fetch_scene, serve};

const LOOPBACK: IpAddr = IpAddr::V4(Ipv4Addr::LOCALHOST);

/// The server's record of the loopback address once it differs from `before` (the server
/// records a path when it has finished with the connection, a moment after the client closed).
async fn record_after(served: &Served, before: Option<PathRecord>) -> PathRecord {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let now = served.server.state.paths().get(LOOPBACK).copied();
        if let Some(r) = now
            && Some(r) != before
        {
            return r;
        }
        assert!(
            Instant::now() < deadline,
            "the server recorded no path for {LOOPBACK} within 10 s"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_returning_client_resumes_its_path_and_another_path_does_not() {
    let served = serve("points/lion_takanawa.copc.laz", "lion", 4096).await;
    let resumes = served.server.state.metrics.path_resumes.clone();
    let counts = || {
        (
            resumes.jumped.load(Ordering::Relaxed),
            resumes.refused.load(Ordering::Relaxed),
        )
    };
    // 60 ms each way: a loopback connection's first round trip stays far below half the saved
    // 120 ms even on a loaded machine, so the refusal below is the path's, not the load's.
    let wan = LinkConfig::wan(Duration::from_millis(60), 100_000_000 / 8);

    // First contact over the link: an ordinary slow start, and the path is recorded.
    let link = LinkEmulator::start(served.server.quic_addr, wan.clone())
        .await
        .unwrap();
    fetch_scene(&served, link.local_addr()).await;
    link.shutdown().await;
    let first = record_after(&served, None).await;
    assert_eq!(counts(), (0, 0), "nothing to resume on first contact");
    assert!(
        (Duration::from_millis(120)..Duration::from_millis(240)).contains(&first.rtt),
        "the link's smallest round trip was recorded, not one inflated by its queue: {:?}",
        first.rtt
    );
    assert!(
        first.window / 2 > DEFAULT_INITIAL_WINDOW,
        "slow start carried the window past twice the initial one over the whole scene: {} B",
        first.window
    );

    // The same path again: the window jumps once the first round trip confirms it.
    let link = LinkEmulator::start(served.server.quic_addr, wan.clone())
        .await
        .unwrap();
    fetch_scene(&served, link.local_addr()).await;
    link.shutdown().await;
    let second = record_after(&served, Some(first)).await;
    assert_eq!(counts(), (1, 0), "the returning client resumed its path");
    assert!(second.rtt >= Duration::from_millis(45), "{:?}", second.rtt);

    // Another path from the same address (loopback, well under half the saved round trip):
    // refused, an ordinary start.
    fetch_scene(&served, served.server.quic_addr).await;
    record_after(&served, Some(second)).await;
    assert_eq!(counts(), (1, 1), "a path of another RTT is not resumed");

    // What /metrics says.
    let mut text = PromText::default();
    served.server.state.write_prometheus(&mut text);
    let text = text.finish();
    for line in [
        "arbor_path_resumes_total 1",
        "arbor_path_resumes_refused_total 1",
        "arbor_paths_remembered 1",
    ] {
        assert!(
            text.lines().any(|l| l == line),
            "/metrics has `{line}`:\n{text}"
        );
    }

    // Forgotten on request (benchmarks measure first contacts so): the next start is ordinary.
    served.server.state.paths().clear();
    let link = LinkEmulator::start(served.server.quic_addr, wan.clone())
        .await
        .unwrap();
    fetch_scene(&served, link.local_addr()).await;
    link.shutdown().await;
    record_after(&served, None).await;
    assert_eq!(counts(), (1, 1), "a forgotten path starts afresh");
}
