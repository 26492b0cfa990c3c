//! What a request list costs the scheduler against the deliveries within its connection's
//! redelivery guard: the scheduler leaves out of a list what it delivered less than the guard
//! before, so applying a list looks at those deliveries. A viewer lists every frame (60 a
//! second, a list every 16 ms) while the server delivers up to hundreds of thousands of
//! treelets a second over loopback: tens of thousands within the default 100 ms guard.
//!
//! For each count of deliveries within the guard (0 first: the list alone), one connection
//! gets a list every 16 ms of simulated time and is sent and acknowledged, between two lists,
//! a sixth of that count (as the service reports them: `poll_batch`, `handle_sent_all`,
//! `handle_delivered_all`; its window set to them). Each list has `ARBOR_SCHEDULE_LIST` items
//! (default 4,096; more where the treelets to deliver are more): the treelets to deliver before
//! the next list, up to half of the list among those delivered within the guard (the client's
//! lists name what it has just received until it sees it), and treelets never sent. The lists
//! after the first seven (the guard then holds its full count) are timed,
//! `ARBOR_SCHEDULE_LISTS` of them (default 30); the median is printed, with the deliveries' own
//! cost per treelet. The service applies lists under the lock every connection's scheduling
//! takes, so what one list costs delays every client's next batch.
//!
//! `cargo bench -p arbor-server --bench schedule`; run it at two commits to compare them.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use arbor_proto::treelet::TreeletId;
use arbor_server::service::schedule::{
    ConnectionConfig, ConnectionId, ListOutcome, Scheduler, SchedulerConfig,
};

const CONN: ConnectionId = ConnectionId(1);
/// Between two lists, a viewer's frame.
const FRAME: Duration = Duration::from_millis(16);
/// Lists before the timed ones: the default 100 ms guard spans six frames.
const WARM_LISTS: usize = 7;
/// Ids from here on are never delivered.
const NEVER_SENT: u32 = 1 << 30;

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.replace('_', "").parse().ok())
        .unwrap_or(default)
}

/// The median list, its items, and the time per delivery, for `per_frame` deliveries between
/// lists.
fn run(per_frame: usize, list_len: usize, timed: usize) -> (Duration, usize, Option<Duration>) {
    let mut sched = Scheduler::new(SchedulerConfig::default());
    sched
        .add_connection(CONN, ConnectionConfig::default())
        .expect("a new connection");
    let guard = ConnectionConfig::default().redelivery_guard;
    let start = Instant::now();
    let mut next_id = 0u32;
    let mut filler = NEVER_SENT;
    // Deliveries, oldest first, pruned to the guard.
    let mut recent: VecDeque<(Instant, TreeletId)> = VecDeque::new();
    let (mut list_times, mut delivery_time, mut deliveries) = (Vec::new(), Duration::ZERO, 0);
    let mut batch = Vec::new();
    let mut latencies = Vec::new();
    let mut items_listed = 0;
    for frame in 0..WARM_LISTS + timed {
        let now = start + FRAME * frame as u32;
        while recent.front().is_some_and(|&(at, _)| at + guard <= now) {
            recent.pop_front();
        }
        let fresh = per_frame;
        let again = (list_len / 2)
            .min(recent.len())
            .min(list_len.saturating_sub(fresh));
        let items: Vec<(TreeletId, f32)> = (next_id..next_id + fresh as u32)
            .map(|i| (TreeletId(i), 2.0))
            // Spread over the guard's deliveries, newest first.
            .chain((0..again).map(|k| {
                (
                    recent[recent.len() - 1 - k * recent.len() / again.max(1)].1,
                    1.0,
                )
            }))
            .chain(
                (0..list_len.saturating_sub(fresh + again))
                    .map(|k| (TreeletId(filler + k as u32), 0.5)),
            )
            .collect();
        filler += list_len.saturating_sub(fresh + again) as u32;
        items_listed = items.len();
        let clock = Instant::now();
        let applied = sched.handle_request_list(CONN, frame as u64 + 1, items, now);
        let took = clock.elapsed();
        let Ok(ListOutcome::Applied { .. }) = applied else {
            panic!("list {frame} was not applied: {applied:?}");
        };
        if frame >= WARM_LISTS {
            list_times.push(took);
        }
        // The fresh treelets, sent and acknowledged over the frame: the window is set to
        // them, so that the list's other items wait.
        let clock = Instant::now();
        let mut done = 0;
        if fresh > 0 {
            sched.set_window(CONN, fresh).expect("the connection");
            let mut in_flight = Vec::new();
            while sched.poll_batch(now, &mut batch).is_some() {
                latencies.clear();
                sched.handle_sent_all(CONN, &batch, now, &mut latencies);
                in_flight.push(std::mem::take(&mut batch));
            }
            let batches = in_flight.len();
            for (k, acked) in in_flight.into_iter().enumerate() {
                let at = now + FRAME.mul_f64((k + 1) as f64 / batches as f64);
                for &t in &acked {
                    assert!(
                        t.0 < NEVER_SENT,
                        "a treelet ranked below the fresh ones was started"
                    );
                    recent.push_back((at, t));
                }
                done += sched.handle_delivered_all(CONN, &acked, at);
            }
        }
        assert_eq!(done, fresh, "frame {frame}: every fresh treelet delivered");
        next_id += fresh as u32;
        if frame >= WARM_LISTS {
            delivery_time += clock.elapsed();
            deliveries += done;
        }
    }
    list_times.sort_unstable();
    let per_delivery = (deliveries > 0).then(|| delivery_time / deliveries as u32);
    (list_times[list_times.len() / 2], items_listed, per_delivery)
}

fn main() {
    let list_len = env_usize("ARBOR_SCHEDULE_LIST", 4096).max(2);
    let timed = env_usize("ARBOR_SCHEDULE_LISTS", 30).max(1);
    println!(
        "A list every {} ms of {list_len} items (or the treelets to deliver) against the \
         deliveries within the 100 ms redelivery guard; one connection; median of {timed} lists",
        FRAME.as_millis()
    );
    println!(
        "{:>22} | {:>10} | {:>13} | {:>12}",
        "delivered within guard", "list items", "list applied", "per delivery"
    );
    for within_guard in [0usize, 1_000, 8_000, 32_000, 64_000] {
        // The guard spans 100 ms: six frames and a quarter.
        let per_frame = within_guard * FRAME.as_millis() as usize / 100;
        let (list, items, per_delivery) = run(per_frame, list_len, timed);
        let per_delivery = per_delivery.map_or("-".into(), |d| format!("{} ns", d.as_nanos()));
        println!(
            "{within_guard:>22} | {items:>10} | {:>10.1} µs | {per_delivery:>12}",
            list.as_secs_f64() * 1e6,
        );
    }
}
