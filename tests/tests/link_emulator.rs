//! The loopback link emulator (`arbor_tests::link`): delay, rate, loss, per-client routing, a
//! second route through the same link and the drop-tail buffer, checked with plain tokio UDP sockets.
//!
//! Timed assertions are lower bounds ("not faster than the link allows") or very generous upper
//! bounds: the machine is small and shared with other tests.

use std::collections::HashSet;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use arbor_tests::link::{LinkConfig, LinkEmulator, LinkStats};
use arbor_tests::support;
use tokio::net::UdpSocket;
use tokio::task::JoinHandle;

/// One datagram a [`Server`] received.
#[derive(Debug, Clone)]
struct Received {
    at: Instant,
    peer: SocketAddr,
    payload: Vec<u8>,
}

/// A UDP server on loopback that records every datagram and optionally echoes it back unchanged.
#[derive(Debug)]
struct Server {
    addr: SocketAddr,
    log: Arc<Mutex<Vec<Received>>>,
    task: JoinHandle<()>,
}

impl Server {
    async fn start(echo: bool) -> Self {
        let sock = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let addr = sock.local_addr().unwrap();
        let log = Arc::new(Mutex::new(Vec::new()));
        let task_log = Arc::clone(&log);
        let task = tokio::spawn(async move {
            let mut buf = vec![0u8; 65_536];
            loop {
                let Ok((n, peer)) = sock.recv_from(&mut buf).await else {
                    continue;
                };
                task_log.lock().unwrap().push(Received {
                    at: Instant::now(),
                    peer,
                    payload: buf[..n].to_vec(),
                });
                if echo {
                    let _ = sock.send_to(&buf[..n], peer).await;
                }
            }
        });
        Self { addr, log, task }
    }

    fn received(&self) -> Vec<Received> {
        self.log.lock().unwrap().clone()
    }

    fn count(&self) -> usize {
        self.log.lock().unwrap().len()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.task.abort();
    }
}

async fn client() -> UdpSocket {
    UdpSocket::bind("127.0.0.1:0").await.unwrap()
}

/// Polls `cond` until it holds, or panics after `limit` with `what` and the last stats.
async fn wait_until<F, Fut>(limit: Duration, what: &str, link: &LinkEmulator, mut cond: F)
where
    F: FnMut() -> Fut,
    Fut: Future<Output = bool>,
{
    let deadline = Instant::now() + limit;
    while !cond().await {
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}; stats: {:#?}",
            link.stats()
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Sends one small datagram through the link and waits for its echo; returns the round trip.
async fn ping(sock: &UdpSocket, link: SocketAddr, tag: u32) -> Duration {
    let mut buf = [0u8; 64];
    let start = Instant::now();
    sock.send_to(&tag.to_le_bytes(), link).await.unwrap();
    loop {
        let (n, from) = tokio::time::timeout(Duration::from_secs(10), sock.recv_from(&mut buf))
            .await
            .expect("echo did not come back within 10 s")
            .unwrap();
        assert_eq!(from, link, "replies come from the emulator's address");
        if buf[..n] == tag.to_le_bytes() {
            return start.elapsed();
        }
    }
}

/// Sends `count` datagrams of `size` bytes (the first 4 bytes are the index), yielding to the
/// runtime every few packets so the kernel's receive buffer of the emulator never overflows
/// (losses must come from the emulator only).
async fn send_numbered(sock: &UdpSocket, to: SocketAddr, count: u32, size: usize) {
    let mut payload = vec![0xA5u8; size.max(4)];
    for i in 0..count {
        payload[..4].copy_from_slice(&i.to_le_bytes());
        sock.send_to(&payload, to).await.unwrap();
        if i % 16 == 15 {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    }
}

fn index(payload: &[u8]) -> u32 {
    u32::from_le_bytes(payload[..4].try_into().unwrap())
}

fn total_in(s: &LinkStats) -> u64 {
    s.upstream.packets_in
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delay_applies_in_each_direction() {
    let echo = Server::start(true).await;
    let config = LinkConfig::default().with_delay(Duration::from_millis(25));
    let link = LinkEmulator::start(echo.addr, config).await.unwrap();
    let sock = client().await;
    let mut rtts = Vec::new();
    for tag in 0..5 {
        rtts.push(ping(&sock, link.local_addr(), tag).await);
    }
    eprintln!("RTTs through a 25 ms one-way link: {rtts:?}");
    for rtt in &rtts {
        assert!(
            *rtt >= Duration::from_millis(50),
            "faster than the link: {rtts:?}"
        );
    }
    let best = rtts.iter().min().unwrap();
    assert!(
        *best < Duration::from_millis(90),
        "far slower than the link: {rtts:?}"
    );
    let s = link.stats();
    assert_eq!(
        (s.upstream.packets_forwarded, s.downstream.packets_forwarded),
        (5, 5)
    );
    assert_eq!(s.clients, 1);
    link.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rate_limit_serializes_packets() {
    const RATE: u64 = 1_000_000;
    const SIZE: usize = 1200;
    const COUNT: u32 = 417; // 500,400 bytes
    let sink = Server::start(false).await;
    let config = LinkConfig::default().with_rate(Some(RATE));
    let link = LinkEmulator::start(sink.addr, config).await.unwrap();
    let sock = client().await;
    let start = Instant::now();
    send_numbered(&sock, link.local_addr(), COUNT, SIZE).await;
    wait_until(
        Duration::from_secs(20),
        "all packets at the sink",
        &link,
        || async { sink.count() == COUNT as usize },
    )
    .await;
    let received = sink.received();
    let elapsed = received.last().unwrap().at - start;
    let bytes: usize = received.iter().map(|r| r.payload.len()).sum();
    eprintln!("{bytes} bytes through a {RATE} B/s link in {elapsed:?}");
    assert_eq!(bytes, COUNT as usize * SIZE);
    assert!(
        elapsed >= Duration::from_millis(450),
        "faster than the link: {elapsed:?}"
    );
    assert!(
        elapsed < Duration::from_secs(10),
        "far slower than the link: {elapsed:?}"
    );
    // Arrival order is kept.
    let order: Vec<u32> = received.iter().map(|r| index(&r.payload)).collect();
    assert!(order.windows(2).all(|w| w[0] < w[1]), "reordered");
    let s = link.stats();
    assert_eq!(s.upstream.packets_forwarded, u64::from(COUNT));
    assert_eq!(s.upstream.bytes_forwarded, bytes as u64);
    assert_eq!((s.upstream.dropped_loss, s.upstream.dropped_queue), (0, 0));
    assert_eq!(s.upstream.queued_bytes, 0);
    link.shutdown().await;
}

/// An asymmetric link: the uplink unlimited, the downlink at 1 MB/s. A burst goes up at once
/// and its echoes come down at the downlink's rate.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_upstream_rate_can_differ_from_the_downstream_rate() {
    const RATE: u64 = 1_000_000;
    const SIZE: usize = 1200;
    const COUNT: u32 = 417; // 500,400 bytes
    let echo = Server::start(true).await;
    let config = LinkConfig::default().with_rate(Some(RATE));
    let link = LinkEmulator::start(echo.addr, config).await.unwrap();
    link.set_upstream_rate(None).unwrap();
    assert_eq!(link.config().rate_bytes_per_s, Some(RATE), "the downlink's");
    assert!(
        link.set_upstream_rate(Some(0)).is_err(),
        "a zero rate is refused"
    );

    let sock = Arc::new(client().await);
    let reader = {
        let sock = Arc::clone(&sock);
        tokio::spawn(async move {
            let mut buf = vec![0u8; 65_536];
            let mut last = None;
            for _ in 0..COUNT {
                let Ok(Ok((n, _))) =
                    tokio::time::timeout(Duration::from_secs(10), sock.recv_from(&mut buf)).await
                else {
                    break;
                };
                assert_eq!(n, SIZE);
                last = Some(Instant::now());
            }
            last
        })
    };
    let start = Instant::now();
    send_numbered(&sock, link.local_addr(), COUNT, SIZE).await;
    wait_until(
        Duration::from_secs(20),
        "all packets at the echo server",
        &link,
        || async { echo.count() == COUNT as usize },
    )
    .await;
    let up = echo.received().last().unwrap().at - start;
    let down = reader.await.unwrap().expect("every echo came back") - start;
    eprintln!("up in {up:?}, echoes down in {down:?}");
    assert!(
        up < Duration::from_millis(300),
        "the uplink is not limited: {up:?}"
    );
    assert!(
        down >= Duration::from_millis(450),
        "the downlink is: {down:?}"
    );
    let s = link.stats();
    assert_eq!(s.upstream.packets_forwarded, u64::from(COUNT));
    assert_eq!(s.downstream.packets_forwarded, u64::from(COUNT));
    link.shutdown().await;
}

/// Runs 2000 numbered packets through a lossy link to an echo server; returns the indices the
/// server saw, the indices echoed back, and the stats.
async fn lossy_run(seed: u64) -> (Vec<u32>, Vec<u32>, LinkStats) {
    const COUNT: u32 = 2000;
    let echo = Server::start(true).await;
    let config = LinkConfig::default().with_loss(0.3).with_seed(seed);
    let link = LinkEmulator::start(echo.addr, config).await.unwrap();
    let sock = Arc::new(client().await);
    let back = Arc::new(Mutex::new(Vec::new()));
    let rx = {
        let (sock, back) = (Arc::clone(&sock), Arc::clone(&back));
        tokio::spawn(async move {
            let mut buf = [0u8; 256];
            while let Ok((n, _)) = sock.recv_from(&mut buf).await {
                back.lock().unwrap().push(index(&buf[..n]));
            }
        })
    };
    send_numbered(&sock, link.local_addr(), COUNT, 100).await;
    wait_until(
        Duration::from_secs(20),
        "all packets through",
        &link,
        || async {
            let s = link.stats();
            // Every packet that came in is accounted for, in both directions.
            let settled = |d: &arbor_tests::link::DirectionStats| {
                d.queued_bytes == 0
                    && d.packets_forwarded + d.dropped_queue + d.dropped_loss + d.send_errors
                        == d.packets_in
            };
            total_in(&s) == u64::from(COUNT)
                && settled(&s.upstream)
                && settled(&s.downstream)
                && s.downstream.packets_in == s.upstream.packets_forwarded
                && back.lock().unwrap().len() as u64 == s.downstream.packets_forwarded
        },
    )
    .await;
    rx.abort();
    let seen: Vec<u32> = echo.received().iter().map(|r| index(&r.payload)).collect();
    let back = back.lock().unwrap().clone();
    let stats = link.stats();
    link.shutdown().await;
    (seen, back, stats)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn loss_is_counted_and_deterministic() {
    let (seen, back, s) = lossy_run(7).await;
    eprintln!("loss 0.3, seed 7: {s:#?}");
    let up = &s.upstream;
    assert_eq!(up.packets_in, 2000);
    assert!(
        (400..=800).contains(&up.dropped_loss),
        "upstream lost {}",
        up.dropped_loss
    );
    assert_eq!(up.dropped_queue, 0);
    assert_eq!(up.packets_forwarded + up.dropped_loss, 2000);
    assert_eq!(seen.len() as u64, up.packets_forwarded);
    let down = &s.downstream;
    assert_eq!(down.packets_in, up.packets_forwarded);
    let frac = down.dropped_loss as f64 / down.packets_in as f64;
    assert!((0.2..=0.4).contains(&frac), "downstream lost {frac}");
    assert_eq!(down.packets_forwarded + down.dropped_loss, down.packets_in);
    assert_eq!(back.len() as u64, down.packets_forwarded);
    // Everything that came back was seen by the server.
    let seen_set: HashSet<u32> = seen.iter().copied().collect();
    assert!(back.iter().all(|i| seen_set.contains(i)));

    // The same seed and the same packets lose the same packets; another seed does not.
    let (seen_again, back_again, _) = lossy_run(7).await;
    assert_eq!(seen, seen_again);
    assert_eq!(back, back_again);
    let (seen_other, _, _) = lossy_run(8).await;
    assert_ne!(seen, seen_other);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_client_gets_its_own_upstream_socket() {
    let echo = Server::start(true).await;
    let config = LinkConfig::default().with_delay(Duration::from_millis(5));
    let link = LinkEmulator::start(echo.addr, config).await.unwrap();
    let (a, b) = (client().await, client().await);
    for round in 0..3u8 {
        for (sock, name) in [(&a, b'A'), (&b, b'B')] {
            sock.send_to(&[name, round], link.local_addr())
                .await
                .unwrap();
        }
        for (sock, name) in [(&a, b'A'), (&b, b'B')] {
            let mut buf = [0u8; 16];
            let (n, from) = tokio::time::timeout(Duration::from_secs(10), sock.recv_from(&mut buf))
                .await
                .expect("reply within 10 s")
                .unwrap();
            assert_eq!(from, link.local_addr());
            assert_eq!(
                &buf[..n],
                &[name, round],
                "a reply went to the wrong client"
            );
        }
    }
    let received = echo.received();
    assert_eq!(received.len(), 6);
    let peers_of = |name: u8| -> HashSet<SocketAddr> {
        received
            .iter()
            .filter(|r| r.payload[0] == name)
            .map(|r| r.peer)
            .collect()
    };
    let (pa, pb) = (peers_of(b'A'), peers_of(b'B'));
    assert_eq!(
        pa.len(),
        1,
        "client A must keep one upstream peer address: {pa:?}"
    );
    assert_eq!(
        pb.len(),
        1,
        "client B must keep one upstream peer address: {pb:?}"
    );
    assert_ne!(pa, pb, "two clients must look like two peers to the server");
    assert!(!pa.contains(&link.local_addr()) && !pb.contains(&link.local_addr()));
    let s = link.stats();
    assert_eq!(s.clients, 2);
    assert_eq!(s.unroutable_packets, 0);
    assert_eq!(
        (s.upstream.packets_forwarded, s.downstream.packets_forwarded),
        (6, 6)
    );
    link.shutdown().await;
}

/// A second route (`LinkEmulator::add_route`) reaches another server through the same link: each
/// server gets only its own clients' packets, replies come back from the address the client
/// sent to, and the two flows share one rate.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_route_shares_the_link() {
    const RATE: u64 = 1_000_000;
    const SIZE: usize = 1200;
    const COUNT: u32 = 209; // 250,800 bytes per route
    let (first, second) = (Server::start(true).await, Server::start(true).await);
    let config = LinkConfig::default().with_rate(Some(RATE));
    let mut link = LinkEmulator::start(first.addr, config).await.unwrap();
    let route = link
        .add_route("127.0.0.1:0".parse().unwrap(), second.addr)
        .await
        .unwrap();
    assert_ne!(route, link.local_addr());
    let (a, b) = (client().await, client().await);
    let start = Instant::now();
    tokio::join!(
        send_numbered(&a, link.local_addr(), COUNT, SIZE),
        send_numbered(&b, route, COUNT, SIZE)
    );
    wait_until(
        Duration::from_secs(20),
        "all packets at both servers",
        &link,
        || async { first.count() == COUNT as usize && second.count() == COUNT as usize },
    )
    .await;
    let last = first
        .received()
        .last()
        .unwrap()
        .at
        .max(second.received().last().unwrap().at);
    let elapsed = last - start;
    eprintln!("2 × {COUNT} packets through one {RATE} B/s link in {elapsed:?}");
    assert!(
        elapsed >= Duration::from_millis(450),
        "both routes together were faster than the one link: {elapsed:?}"
    );
    for (server, name) in [(&first, "first"), (&second, "second")] {
        let peers: HashSet<SocketAddr> = server.received().iter().map(|r| r.peer).collect();
        assert_eq!(peers.len(), 1, "the {name} server saw one peer: {peers:?}");
        assert!(
            !peers.contains(&a.local_addr().unwrap()) && !peers.contains(&b.local_addr().unwrap())
        );
    }
    for (sock, from) in [(&a, link.local_addr()), (&b, route)] {
        let mut buf = [0u8; 2048];
        let (_, at) = tokio::time::timeout(Duration::from_secs(10), sock.recv_from(&mut buf))
            .await
            .expect("echo within 10 s")
            .unwrap();
        assert_eq!(
            at, from,
            "the echo comes from the address the client sent to"
        );
    }
    let s = link.stats();
    assert_eq!(s.clients, 2);
    assert_eq!(s.upstream.packets_forwarded, 2 * u64::from(COUNT));
    assert_eq!((s.upstream.dropped_loss, s.upstream.dropped_queue), (0, 0));
    link.shutdown().await;
}

/// The `arbor-link` binary: `--route` reaches a second server through the same link and
/// `--uplink-mbit` limits only the clients' direction; bad values are refused by name.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_routes_a_second_server_and_limits_the_uplink() {
    const COUNT: u32 = 100; // 120,000 bytes at 1 Mbit/s: 0.96 s
    const SIZE: usize = 1200;
    let exe = env!("CARGO_BIN_EXE_arbor-link");
    for (args, named) in [
        (vec!["--route", "nonsense"], "LISTEN=UPSTREAM"),
        (vec!["--uplink-mbit=-3"], "--uplink-mbit"),
    ] {
        let out = std::process::Command::new(exe)
            .args(["--upstream", "127.0.0.1:9"])
            .args(&args)
            .env("RUST_BACKTRACE", "0")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(named),
            "{args:?}: {err}"
        );
    }
    let (first, second) = (Server::start(true).await, Server::start(true).await);
    // Ports of its own choosing, read back from its stdout: none taken from under it.
    let mut child = std::process::Command::new(exe)
        .args(["--listen", "127.0.0.1:0", "--upstream"])
        .arg(first.addr.to_string())
        .arg("--route")
        .arg(format!("127.0.0.1:0={}", second.addr))
        .args(["--uplink-mbit", "1", "--stats-every-s", "0"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // Its first two lines, read off the runtime and waited for at most 20 s: a child that
    // neither prints nor exits fails the test instead of hanging it.
    let stdout = child.stdout.take().unwrap();
    let first_lines = tokio::task::spawn_blocking(move || {
        std::io::BufRead::lines(std::io::BufReader::new(stdout))
            .take(2)
            .collect::<std::io::Result<Vec<String>>>()
    });
    let printed = tokio::time::timeout(Duration::from_secs(20), first_lines)
        .await
        .expect("arbor-link printed its addresses within 20 s")
        .unwrap()
        .unwrap();
    let field = |i: usize, prefix: &str| -> String {
        let l = printed
            .get(i)
            .unwrap_or_else(|| panic!("arbor-link ended before printing `{prefix}`: {printed:?}"));
        l.strip_prefix(prefix)
            .unwrap_or_else(|| panic!("expected `{prefix}…`, got {l:?}"))
            .to_owned()
    };
    let listen: SocketAddr = field(0, "listen ").parse().unwrap();
    let route_line = field(1, "route ");
    let (route, upstream) = route_line.split_once('=').unwrap();
    let route: SocketAddr = route.parse().unwrap();
    assert_eq!(upstream, second.addr.to_string(), "the route's upstream");
    assert!(
        listen.port() != 0 && route.port() != 0 && listen != route,
        "bound ports: {listen}, {route}"
    );
    let (a, b) = (client().await, client().await);
    // Up once the route answers.
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut buf = [0u8; 2048];
    'up: loop {
        assert!(Instant::now() < deadline, "arbor-link did not come up");
        b.send_to(b"ping", route).await.unwrap();
        while let Ok(Ok((n, from))) =
            tokio::time::timeout(Duration::from_millis(200), b.recv_from(&mut buf)).await
        {
            if from == route && &buf[..n] == b"ping" {
                break 'up;
            }
        }
    }
    let start = Instant::now();
    send_numbered(&b, route, COUNT, SIZE).await;
    while second.count() < COUNT as usize + 1 {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "{} of {COUNT} packets at the second server",
            second.count() - 1
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let elapsed = second.received().last().unwrap().at - start;
    eprintln!("{COUNT} packets up through a 1 Mbit/s uplink in {elapsed:?}");
    assert!(
        elapsed >= Duration::from_millis(850),
        "faster than the uplink: {elapsed:?}"
    );
    assert_eq!(
        first.count(),
        0,
        "the route's packets went to the second server only"
    );
    ping(&a, listen, 7).await;
    assert_eq!(
        first.count(),
        1,
        "the first address reaches the first server"
    );
    support::terminate(&mut child, Duration::from_secs(2));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queue_overflow_drops_at_the_tail() {
    const QUEUE: usize = 5_000;
    const SIZE: usize = 1000;
    const COUNT: u32 = 50;
    let sink = Server::start(false).await;
    let config = LinkConfig::default()
        .with_rate(Some(20_000))
        .with_queue_bytes(QUEUE);
    let link = LinkEmulator::start(sink.addr, config).await.unwrap();
    let sock = client().await;
    // 50 kB in a burst into a 5 kB buffer draining at 20 kB/s.
    send_numbered(&sock, link.local_addr(), COUNT, SIZE).await;
    wait_until(
        Duration::from_secs(20),
        "the burst to drain",
        &link,
        || async {
            let s = link.stats();
            let up = &s.upstream;
            // Every packet that came in is accounted for (a packet just taken off the queue is
            // neither queued nor counted as forwarded yet).
            total_in(&s) == u64::from(COUNT)
                && up.queued_bytes == 0
                && up.packets_forwarded + up.dropped_queue + up.dropped_loss + up.send_errors
                    == u64::from(COUNT)
                && sink.count() as u64 == up.packets_forwarded
        },
    )
    .await;
    let s = link.stats();
    eprintln!(
        "burst of {COUNT} x {SIZE} B into a {QUEUE} B buffer: {:#?}",
        s.upstream
    );
    let up = &s.upstream;
    assert!(
        up.dropped_queue >= 30,
        "only {} tail drops",
        up.dropped_queue
    );
    assert_eq!(up.packets_forwarded + up.dropped_queue, u64::from(COUNT));
    assert_eq!(up.dropped_loss, 0);
    assert_eq!(up.send_errors, 0);
    assert!(
        up.peak_queued_bytes <= QUEUE as u64,
        "buffer exceeded: {up:?}"
    );
    assert!(
        up.peak_queued_bytes >= (QUEUE - SIZE) as u64,
        "buffer never filled: {up:?}"
    );
    // Drop-tail: the first packets got through.
    let got: Vec<u32> = sink.received().iter().map(|r| index(&r.payload)).collect();
    assert_eq!(&got[..4], &[0, 1, 2, 3]);
    link.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn config_changes_on_the_fly() {
    let echo = Server::start(true).await;
    let link = LinkEmulator::start(echo.addr, LinkConfig::default())
        .await
        .unwrap();
    let sock = client().await;
    let fast = ping(&sock, link.local_addr(), 1).await;
    let slow_config = LinkConfig::default().with_delay(Duration::from_millis(30));
    link.set_config(slow_config.clone()).unwrap();
    assert_eq!(link.config(), slow_config);
    let slow = ping(&sock, link.local_addr(), 2).await;
    eprintln!("RTT without delay {fast:?}, with 30 ms one way {slow:?}");
    assert!(slow >= Duration::from_millis(60), "{slow:?}");
    // Invalid parameters are refused and leave the link as it was.
    let err = link
        .set_config(LinkConfig::default().with_loss(2.0))
        .unwrap_err();
    assert_eq!(err.kind(), std::io::ErrorKind::InvalidInput);
    assert_eq!(link.config(), slow_config);
    // Full loss: nothing gets through any more.
    link.set_config(LinkConfig::default().with_loss(1.0))
        .unwrap();
    sock.send_to(b"lost", link.local_addr()).await.unwrap();
    wait_until(
        Duration::from_secs(10),
        "the loss to be counted",
        &link,
        || async { link.stats().upstream.dropped_loss == 1 },
    )
    .await;
    assert_eq!(echo.count(), 2);
    link.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_closes_the_listen_socket() {
    let echo = Server::start(true).await;
    let link = LinkEmulator::start(echo.addr, LinkConfig::default())
        .await
        .unwrap();
    let addr = link.local_addr();
    link.shutdown().await;
    // The port is free again once shutdown returns.
    UdpSocket::bind(addr)
        .await
        .expect("the emulator's port is released");
}
