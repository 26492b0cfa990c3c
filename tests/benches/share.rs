//! Two flows through one bottleneck: what share of a link a server with random-loss tolerance
//! (`arbor_server::service::random_loss`) takes from one without it, against two plain Cubic
//! flows and two tolerant ones, with a deep and a shallow buffer, with and without random loss.
//!
//! `cargo bench -p arbor-tests --bench share` (release). Two real servers of lion with 4 KiB
//! treelets, one tolerant (the default), one with `random_loss_tolerance = false`, behind one
//! link emulator (a second route reaches the second server through the same two directions:
//! [`LinkEmulator::add_route`]); two clients start together, each fetching the whole scene on a
//! connection of its own. Per pair: each flow's rate and the first flow's share of both over the
//! time both were running (after the first 2 s, slow start's), the link's use, the
//! packets it lost or dropped at its queue, and each server's loss events by verdict.
//!
//! The link: 20 ms each way, 4 Mbit/s (`ARBOR_SHARE_DELAY_MS`, `ARBOR_SHARE_RATE_MBIT`; the
//! time left out, `ARBOR_SHARE_WARMUP_MS`, should leave several seconds of both flows), loss 0
//! or 1 % each way. Three buffers: [`LinkConfig::wan`]'s (twice the round trip's bandwidth-delay
//! product, propagation included); the packets propagating plus half a round trip of queue; and
//! a shallow one, the packets propagating plus an eighth of a round trip of queue. That is
//! shorter than the quarter of the smallest round trip that the tolerance takes for a queue, so
//! every congestion loss there looks random to it: the case where a tolerant flow is as
//! aggressive as it gets. `ARBOR_SHARE_RUNS=N` turns per case (default 3),
//! each turn with its own loss sequence; medians and ranges. No assertion; never run in CI.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use arbor_client_net::{ClientEvent, TreeletClient};
use arbor_proto::TreeletId;
use arbor_server::service::random_loss::LossCounters;
use arbor_tests::link::{LinkConfig, LinkEmulator};
use arbor_tests::streaming::{Served, serve, serve_tuned};

/// A fetch that takes longer than this ends the bench with a panic (a stall).
const STALL: Duration = Duration::from_secs(60);

/// Which server a flow fetches from.
#[derive(Clone, Copy, PartialEq)]
enum Sender {
    Tolerant,
    Plain,
}

impl Sender {
    fn name(self) -> &'static str {
        match self {
            Sender::Tolerant => "tolerant",
            Sender::Plain => "Cubic",
        }
    }
}

/// One flow's arrivals: when each treelet message arrived and its bytes on the wire.
struct Arrivals {
    at: Vec<(Instant, u64)>,
}

impl Arrivals {
    fn finished(&self) -> Instant {
        self.at.last().expect("a scene has treelets").0
    }

    fn bytes_between(&self, from: Instant, to: Instant) -> u64 {
        self.at
            .iter()
            .filter(|(t, _)| (from..=to).contains(t))
            .map(|&(_, b)| b)
            .sum()
    }
}

/// A verdict count of one server, read before and after a pair.
fn verdicts(counters: &LossCounters) -> [u64; 3] {
    let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
    [
        load(&counters.congestion),
        load(&counters.random_passed),
        load(&counters.random_ignored),
    ]
}

fn env_or(key: &str, default: f64) -> f64 {
    std::env::var(key)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let delay = Duration::from_secs_f64(env_or("ARBOR_SHARE_DELAY_MS", 20.0) / 1e3);
    let rate = (env_or("ARBOR_SHARE_RATE_MBIT", 4.0) * 1e6 / 8.0) as u64;
    let runs = env_or("ARBOR_SHARE_RUNS", 3.0).max(1.0) as usize;
    // The start of each flow left out of the share: slow start's, before the flows meet.
    let warmup = Duration::from_secs_f64(env_or("ARBOR_SHARE_WARMUP_MS", 2000.0) / 1e3);
    let rel = "points/lion_takanawa.copc.laz";
    let tolerant = serve(rel, "lion", 4096).await;
    let plain = serve_tuned(rel, "lion", 4096, |c| {
        c.random_loss_tolerance = false;
    })
    .await;
    let rtt = 2 * delay;
    let propagating = (rate as f64 * delay.as_secs_f64()) as usize;
    let queue_of = |rtts: f64| propagating + (rate as f64 * rtt.as_secs_f64() * rtts) as usize;
    let buffers = [
        ("deep", LinkConfig::wan(delay, rate).queue_bytes),
        ("half a round trip", queue_of(0.5)),
        ("shallow", queue_of(0.125)),
    ];
    println!(
        "# share: two flows, each the whole of lion 4 KiB ({:.2} MB), through one link of {} ms \
         each way and {} Mbit/s; {runs} turns per case (median, range); share over the time both \
         ran, after the first {:.1} s",
        tolerant.wire_bytes.iter().sum::<u64>() as f64 / 1e6,
        delay.as_millis(),
        rate as f64 * 8.0 / 1e6,
        warmup.as_secs_f64(),
    );
    let pairs = [
        (Sender::Plain, Sender::Plain),
        (Sender::Tolerant, Sender::Plain),
        (Sender::Tolerant, Sender::Tolerant),
    ];
    for (buffer, queue_bytes) in buffers {
        for loss in [0.0, 0.01] {
            println!(
                "\n## {buffer} buffer ({:.1} KB: {:.0} ms of queue), {} % loss each way",
                queue_bytes as f64 / 1e3,
                (queue_bytes - propagating) as f64 / rate as f64 * 1e3,
                loss * 100.0
            );
            println!(
                "{:<22} {:>14} {:>11} {:>11} {:>6} {:>6} {:>6} {:>18} {:>18}",
                "first vs second",
                "first's share",
                "first Mb/s",
                "second Mb/s",
                "use",
                "lost",
                "queue",
                "first: cong/pass/ign",
                "second: cong/pass/ign"
            );
            for &(a, b) in &pairs {
                let mut turns: Vec<[f64; 6]> = Vec::new();
                let mut events = [[0u64; 3]; 2];
                for turn in 0..runs {
                    let config = LinkConfig::wan(delay, rate)
                        .with_queue_bytes(queue_bytes)
                        .with_loss(loss)
                        .with_seed(turn as u64 + 1);
                    let served = |s: Sender| match s {
                        Sender::Tolerant => &tolerant,
                        Sender::Plain => &plain,
                    };
                    for s in [&tolerant, &plain] {
                        s.server.state.paths().clear();
                    }
                    let before =
                        [a, b].map(|s| verdicts(&served(s).server.state.metrics.loss_events));
                    let (arrivals, stats) = async {
                        let mut link = LinkEmulator::start(tolerant.server.quic_addr, config)
                            .await
                            .unwrap();
                        let listen = SocketAddr::new(link.local_addr().ip(), 0);
                        let to_plain = link
                            .add_route(listen, plain.server.quic_addr)
                            .await
                            .unwrap();
                        let addr = |s: Sender| match s {
                            Sender::Tolerant => link.local_addr(),
                            Sender::Plain => to_plain,
                        };
                        let (first, second) =
                            tokio::join!(fetch(served(a), addr(a)), fetch(served(b), addr(b)));
                        let stats = link.stats();
                        link.shutdown().await;
                        ([first, second], stats)
                    }
                    .await;
                    let after =
                        [a, b].map(|s| verdicts(&served(s).server.state.metrics.loss_events));
                    // Two flows from one server share its counters; give each half.
                    let same = if a == b { 2 } else { 1 };
                    for f in 0..2 {
                        for v in 0..3 {
                            events[f][v] += (after[f][v] - before[f][v]) / same;
                        }
                    }
                    let start = arrivals[0].at[0].0.min(arrivals[1].at[0].0) + warmup;
                    let end = arrivals[0].finished().min(arrivals[1].finished());
                    let window = end.saturating_duration_since(start).as_secs_f64();
                    let bytes = arrivals
                        .each_ref()
                        .map(|f| f.bytes_between(start, end) as f64);
                    let mbit = |b: f64| {
                        if window > 0.0 {
                            b * 8.0 / window / 1e6
                        } else {
                            0.0
                        }
                    };
                    turns.push([
                        bytes[0] / (bytes[0] + bytes[1]).max(1.0),
                        mbit(bytes[0]),
                        mbit(bytes[1]),
                        (mbit(bytes[0]) + mbit(bytes[1])) / (rate as f64 * 8.0 / 1e6),
                        (stats.downstream.dropped_loss) as f64,
                        (stats.downstream.dropped_queue) as f64,
                    ]);
                }
                let median = |i: usize| {
                    let mut v: Vec<f64> = turns.iter().map(|t| t[i]).collect();
                    v.sort_by(f64::total_cmp);
                    (v[v.len() / 2], v[0], v[v.len() - 1])
                };
                let (share, lo, hi) = median(0);
                // A server without the tolerance does not classify its losses.
                let per = |s: Sender, e: [u64; 3]| match s {
                    Sender::Plain => "—".to_string(),
                    Sender::Tolerant => {
                        let n = runs as u64;
                        format!("{}/{}/{}", e[0] / n, e[1] / n, e[2] / n)
                    }
                };
                println!(
                    "{:<22} {:>14} {:>11.2} {:>11.2} {:>5.0}% {:>6.0} {:>6.0} {:>18} {:>18}",
                    format!("{} vs {}", a.name(), b.name()),
                    format!("{:.2} ({:.2}–{:.2})", share, lo, hi),
                    median(1).0,
                    median(2).0,
                    median(3).0 * 100.0,
                    median(4).0,
                    median(5).0,
                    per(a, events[0]),
                    per(b, events[1]),
                );
            }
        }
    }
}

/// Fetches every treelet of the scene through `addr` on a connection of its own, recording when
/// each arrived; panics on a disconnect or a stall.
async fn fetch(served: &Served, addr: SocketAddr) -> Arrivals {
    let config = served
        .client_config(addr)
        .with_channels(served.scene.layout.channels().iter().copied());
    let mut client = TreeletClient::start(config).unwrap();
    let count = served.treelets.len() as u32;
    client
        .request((0..count).map(|id| (TreeletId(id), -(id as f32))).collect())
        .unwrap();
    let mut at = Vec::with_capacity(count as usize);
    while at.len() < count as usize {
        match tokio::time::timeout(STALL, client.next_event()).await {
            Ok(Some(ClientEvent::Treelet(t))) => at.push((Instant::now(), t.wire_bytes as u64)),
            Ok(Some(ClientEvent::Disconnected { reason, .. })) => panic!("disconnected: {reason}"),
            Ok(Some(_)) => {}
            Ok(None) | Err(_) => panic!("stalled with {} treelets left", count as usize - at.len()),
        }
    }
    client.close().await;
    Arrivals { at }
}
