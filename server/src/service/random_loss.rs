//! Telling a packet lost on the wire from one dropped by a full queue, so that random loss (a
//! radio link, a lossy peering) does not cut the congestion window as congestion does.
//!
//! Cubic answers every loss as congestion: it cuts its window to 0.7× and regrows it. With
//! random loss of a share `p` of the packets a loss-based controller averages about
//! `MSS / RTT × 1.22 / √p`: at 1 % loss and 80 ms round trips, 1.5 Mbit/s, whatever the link
//! carries (the 10⁸-point city over a 10 Mbit/s link with 1 % loss got 1.4 of them,
//! docs/measurements.md, stop 61). A full queue, though, delays every packet behind it before
//! it drops one, while a packet lost on the wire leaves the round trips at the path's minimum.
//! TCP Veno (Fu & Liew, 2003) told the two apart by that backlog; so does this filter:
//!
//! * a loss detected while the latest round trip lies within a [`QUEUE_SHARE`]th of the path's
//!   smallest above it (at least [`QUEUE_FLOOR`]) found no queue: it is taken as random and
//!   does not reach Cubic, except every [`PASS_EVERY`]th such event in a row, so that a
//!   bottleneck whose buffer is too shallow to show a queue still gets a multiplicative
//!   decrease (a flow cut at an eighth of its loss events holds √8 ≈ 2.8 times the window, as
//!   about three Cubic flows would together);
//! * a loss with a queue behind it, persistent congestion and ECN marks always reach Cubic, and
//!   so does every loss on a path whose smallest round trip is under [`SHORT_PATH`]: there the
//!   threshold is the floor, and a queue shorter than it (a LAN's or a data centre's switch
//!   buffer, well under a millisecond) would pass for none, so congestion losses would look
//!   random. Such paths rarely lose packets at random, and on them Cubic's loss-limited rate is
//!   high anyway (it grows as the round trip shrinks: at 1 % loss and 3 ms, about 40 Mbit/s).
//!
//! Once random loss is ignored the window grows past what the path holds, a queue forms, and
//! the next loss counts: the window settles about the path's bandwidth-delay product instead
//! of a seventh of it. Lion over a 10 Mbit/s, 80 ms link with 1 % loss, with the client's
//! lists paced too: converged in 2.6 s against 7.2 s with plain Cubic (2.4 s without loss;
//! the refine bench's lossy-link table, stop 62). Beside a plain Cubic flow on one bottleneck it
//! takes an even share where the buffer holds half a round trip or more, and three quarters
//! where it holds an eighth (the share bench, stop 63). Operators turn it off with
//! `random_loss_tolerance = false`.
//!
//! Like Cubic's recovery period, losses of packets sent before the last event counted (passed
//! or ignored) belong to that event, so [`PASS_EVERY`] counts events of about one round trip
//! each, not packets.
//!
//! [`RandomLossFilter`] is the decision as plain data, tested without quinn; the controller in
//! [`super::path_memory`] feeds it.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// A loss counts as congestion when the latest round trip exceeds the smallest by at least a
/// `QUEUE_SHARE`th of the smallest (a queue of a quarter of the path's own delay).
pub const QUEUE_SHARE: u32 = 4;
/// The queue threshold is at least this: round trips of a fast path jitter by more than a
/// quarter of their length (quinn's timer granularity is 1 ms).
pub const QUEUE_FLOOR: Duration = Duration::from_millis(1);
/// On a path whose smallest round trip is shorter than this, every loss is congestion: the
/// queue threshold would be [`QUEUE_FLOOR`], and a shorter queue would pass for none.
pub const SHORT_PATH: Duration = QUEUE_FLOOR.saturating_mul(QUEUE_SHARE);
/// One in this many random-looking loss events still reaches Cubic.
pub const PASS_EVERY: u32 = 8;

/// What [`RandomLossFilter::handle_congestion`] made of one congestion event.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LossVerdict {
    /// Congestion (a queue, persistent congestion or an ECN mark): Cubic cuts its window.
    Congestion,
    /// Random-looking, and the [`PASS_EVERY`]th in a row: Cubic cuts its window.
    RandomPassed,
    /// Random-looking: the window is kept.
    RandomIgnored,
    /// A loss of a packet sent before the last event counted: part of that event, and reaches
    /// the controller if that event did (Cubic too ignores it then, as its recovery began).
    SameEvent {
        /// Whether the event it belongs to reached the controller.
        reached: bool,
    },
}

impl LossVerdict {
    /// Whether the event reaches the congestion controller.
    pub fn reaches_controller(self) -> bool {
        match self {
            LossVerdict::Congestion | LossVerdict::RandomPassed => true,
            LossVerdict::RandomIgnored => false,
            LossVerdict::SameEvent { reached } => reached,
        }
    }
}

/// The round trips seen and the events counted, for one connection.
#[derive(Clone, Debug, Default)]
pub struct RandomLossFilter {
    /// The smallest round trip of any acknowledged packet.
    min_rtt: Option<Duration>,
    /// The smallest round trip of the latest acknowledgement's packets (the first packet of a
    /// batch acknowledged together waited for the last).
    latest_rtt: Option<Duration>,
    /// The same for the acknowledgement being read.
    batch_rtt: Option<Duration>,
    /// When the last event counted, and whether it reached the controller; losses of packets
    /// sent before belong to it.
    last_event: Option<(Instant, bool)>,
    /// Random-looking events ignored since the last that reached the controller.
    ignored_in_a_row: u32,
}

impl RandomLossFilter {
    /// A packet of the acknowledgement being read took `rtt` from sending to its ACK.
    pub fn handle_ack(&mut self, rtt: Duration) {
        self.min_rtt = Some(self.min_rtt.map_or(rtt, |m| m.min(rtt)));
        self.batch_rtt = Some(self.batch_rtt.map_or(rtt, |b| b.min(rtt)));
    }

    /// The acknowledgement has been read.
    pub fn handle_end_acks(&mut self) {
        if let Some(b) = self.batch_rtt.take() {
            self.latest_rtt = Some(b);
        }
    }

    /// The queue the latest round trip shows above the smallest; `None` before any ACK.
    pub fn queue_delay(&self) -> Option<Duration> {
        Some(self.latest_rtt?.saturating_sub(self.min_rtt?))
    }

    /// The queue delay at and above which a loss counts as congestion.
    pub fn queue_threshold(&self) -> Option<Duration> {
        Some((self.min_rtt? / QUEUE_SHARE).max(QUEUE_FLOOR))
    }

    /// A congestion event at `now`: `lost_bytes` of packets lost, the latest sent at `sent`
    /// (0 bytes: an ECN mark), or persistent congestion.
    pub fn handle_congestion(
        &mut self,
        now: Instant,
        sent: Instant,
        persistent: bool,
        lost_bytes: u64,
    ) -> LossVerdict {
        if persistent || lost_bytes == 0 {
            return self.counted(now, LossVerdict::Congestion);
        }
        if let Some((at, reached)) = self.last_event
            && sent <= at
        {
            return LossVerdict::SameEvent { reached };
        }
        let short_path = self.min_rtt.is_some_and(|m| m < SHORT_PATH);
        let queued = short_path
            || match (self.queue_delay(), self.queue_threshold()) {
                (Some(delay), Some(threshold)) => delay >= threshold,
                // Nothing acknowledged yet: nothing to tell a queue by.
                _ => true,
            };
        if queued {
            return self.counted(now, LossVerdict::Congestion);
        }
        if self.ignored_in_a_row + 1 >= PASS_EVERY {
            return self.counted(now, LossVerdict::RandomPassed);
        }
        self.ignored_in_a_row += 1;
        self.last_event = Some((now, false));
        LossVerdict::RandomIgnored
    }

    fn counted(&mut self, now: Instant, verdict: LossVerdict) -> LossVerdict {
        self.last_event = Some((now, true));
        self.ignored_in_a_row = 0;
        verdict
    }
}

/// Loss events by verdict, over every connection (the service's metrics hold one); losses that
/// belong to an event already counted are not counted again.
#[derive(Debug, Default)]
pub struct LossCounters {
    /// [`LossVerdict::Congestion`].
    pub congestion: AtomicU64,
    /// [`LossVerdict::RandomPassed`].
    pub random_passed: AtomicU64,
    /// [`LossVerdict::RandomIgnored`].
    pub random_ignored: AtomicU64,
}

impl LossCounters {
    /// Counts one verdict.
    pub fn count(&self, verdict: LossVerdict) {
        let counter = match verdict {
            LossVerdict::Congestion => &self.congestion,
            LossVerdict::RandomPassed => &self.random_passed,
            LossVerdict::RandomIgnored => &self.random_ignored,
            LossVerdict::SameEvent { .. } => return,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    /// A filter that has seen one acknowledgement with round trips `rtts` (ms).
    fn seen(rtts: &[u32]) -> RandomLossFilter {
        let mut f = RandomLossFilter::default();
        for &r in rtts {
            f.handle_ack(MS * r);
        }
        f.handle_end_acks();
        f
    }

    #[test]
    fn a_loss_without_a_queue_is_random_and_one_in_pass_every_still_cuts() {
        let mut f = seen(&[82, 80, 81]);
        let t0 = Instant::now();
        let mut verdicts = Vec::new();
        for i in 1..=2 * PASS_EVERY {
            let now = t0 + MS * (100 * i);
            verdicts.push(f.handle_congestion(now, now - 10 * MS, false, 1200));
        }
        let passed: Vec<usize> = (0..verdicts.len())
            .filter(|&i| verdicts[i] == LossVerdict::RandomPassed)
            .collect();
        assert_eq!(
            passed,
            vec![PASS_EVERY as usize - 1, 2 * PASS_EVERY as usize - 1],
            "{verdicts:?}"
        );
        assert!(
            verdicts
                .iter()
                .all(|v| matches!(v, LossVerdict::RandomIgnored | LossVerdict::RandomPassed))
        );
        assert!(!LossVerdict::RandomIgnored.reaches_controller());
        assert!(LossVerdict::RandomPassed.reaches_controller());
    }

    #[test]
    fn a_loss_behind_a_queue_is_congestion_and_restarts_the_count() {
        // Smallest 80 ms: a quarter of it, 20 ms, is the threshold.
        let mut f = seen(&[80]);
        assert_eq!(f.queue_threshold(), Some(20 * MS));
        let t0 = Instant::now();
        let at = |i: u32| t0 + MS * (100 * i);
        for i in 1..PASS_EVERY {
            let now = at(i);
            assert_eq!(
                f.handle_congestion(now, now - MS, false, 1200),
                LossVerdict::RandomIgnored
            );
        }
        f.handle_ack(100 * MS);
        f.handle_end_acks();
        assert_eq!(f.queue_delay(), Some(20 * MS));
        let now = at(10);
        assert_eq!(
            f.handle_congestion(now, now - MS, false, 1200),
            LossVerdict::Congestion,
            "a queue of a quarter of the path's delay"
        );
        f.handle_ack(95 * MS);
        f.handle_end_acks();
        let now = at(11);
        assert_eq!(
            f.handle_congestion(now, now - MS, false, 1200),
            LossVerdict::RandomIgnored,
            "just under the threshold; the congestion restarted the count"
        );
    }

    #[test]
    fn persistent_congestion_ecn_and_a_first_loss_before_any_ack_always_cut() {
        let t0 = Instant::now();
        let mut blind = RandomLossFilter::default();
        assert_eq!(
            blind.handle_congestion(t0, t0, false, 1200),
            LossVerdict::Congestion,
            "no round trip seen: nothing to tell a queue by"
        );
        let mut f = seen(&[50]);
        let now = t0 + 100 * MS;
        assert_eq!(
            f.handle_congestion(now, now, true, 1200),
            LossVerdict::Congestion
        );
        let now = t0 + 200 * MS;
        assert_eq!(
            f.handle_congestion(now, now, false, 0),
            LossVerdict::Congestion,
            "an ECN mark"
        );
    }

    #[test]
    fn losses_sent_before_an_event_belong_to_it() {
        let mut f = seen(&[40]);
        let t0 = Instant::now();
        let first = t0 + 100 * MS;
        assert_eq!(
            f.handle_congestion(first, first - 5 * MS, false, 1200),
            LossVerdict::RandomIgnored
        );
        for _ in 0..2 * PASS_EVERY {
            assert_eq!(
                f.handle_congestion(first + 10 * MS, first - MS, false, 1200),
                LossVerdict::SameEvent { reached: false },
                "sent before the ignored event: ignored with it, and not counted"
            );
        }
        f.handle_ack(70 * MS);
        f.handle_end_acks();
        let second = t0 + 200 * MS;
        assert_eq!(
            f.handle_congestion(second, second - MS, false, 1200),
            LossVerdict::Congestion
        );
        let v = f.handle_congestion(second + MS, second - 2 * MS, false, 1200);
        assert_eq!(v, LossVerdict::SameEvent { reached: true });
        assert!(v.reaches_controller(), "Cubic ignores it itself");
    }

    #[test]
    fn the_threshold_has_a_floor_for_fast_paths_and_the_batch_minimum_is_the_latest() {
        let mut f = seen(&[2]);
        assert_eq!(f.queue_threshold(), Some(QUEUE_FLOOR));
        // The first packet of a batch acknowledged together waited for the last: the batch's
        // smallest round trip is the path's latest.
        f.handle_ack(9 * MS);
        f.handle_ack(3 * MS);
        f.handle_ack(7 * MS);
        f.handle_end_acks();
        assert_eq!(f.queue_delay(), Some(MS));
    }

    #[test]
    fn every_loss_on_a_short_path_is_congestion() {
        let t0 = Instant::now();
        for (rtt, verdict) in [
            (3, LossVerdict::Congestion),
            (4, LossVerdict::RandomIgnored),
        ] {
            let mut f = seen(&[rtt]);
            assert_eq!(
                f.handle_congestion(t0 + MS * 100, t0 + MS * 99, false, 1200),
                verdict,
                "{rtt} ms round trips, no queue"
            );
        }
    }

    #[test]
    fn counters_count_events_not_losses() {
        let c = LossCounters::default();
        for v in [
            LossVerdict::Congestion,
            LossVerdict::RandomIgnored,
            LossVerdict::RandomIgnored,
            LossVerdict::RandomPassed,
            LossVerdict::SameEvent { reached: true },
        ] {
            c.count(v);
        }
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        assert_eq!(
            (
                load(&c.congestion),
                load(&c.random_passed),
                load(&c.random_ignored)
            ),
            (1, 1, 2)
        );
    }
}
