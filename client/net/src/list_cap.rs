//! How many items a request list may carry on one connection: all of them while the uplink
//! keeps up with the lists, fewer while lists wait for it.
//!
//! A list names the treelets the view wants, up to the core's `max_requests` (4,096), and the
//! client writes one every cycle the view changes; the list window
//! ([`crate::transport::LIST_SEND_WINDOW`]) makes a list wait while those before it are
//! unacknowledged, and sends only the latest. Over a thin uplink that also loses packets (a
//! home line on Wi-Fi: 2 Mbit/s up, 1 % loss), long lists waited there for several round trips:
//! lion-1k at 512² through `arbor-link --delay-ms 40 --rate-mbit 10 --uplink-mbit 2 --loss 0.01`
//! took 5.7–14.4 s to converge with 600–3,650 treelets received twice (lists that reached the
//! server after the treelets they named had been delivered), against 2.9 s without the loss;
//! lists of at most 1,024 items took 7.1–7.3 s with 0–41 (docs/measurements.md, stop 63).
//! The server serves the head of a list until the next one replaces it, so a shorter list loses
//! nothing while lists come often; a fresh one matters more.
//!
//! The rule, a multiplicative decrease and a slower increase of the length, each at most once a
//! round trip: after each list is written, how long the write waited for the list window says
//! whether the lists before it had been acknowledged. A wait of at least half a round trip means
//! the uplink carries the lists more slowly than the view changes them, and the next lists get
//! at most three quarters of this one's items (never fewer than [`MIN_LIST_ITEMS`]; a wait under
//! [`MIN_WAIT`] never counts). A write that waited less than a quarter of a round trip (or half
//! of [`MIN_WAIT`]) lets the cap grow by an eighth, and the cap
//! goes once a whole list fits under it. Once a round trip, since the writes right after a long
//! wait find the window just emptied and wait for nothing, whatever the uplink carries (growing
//! at every such write held the cap between 1,500 and 3,000 items, where it had to shrink). A
//! connection starts uncapped: over an uplink that keeps up, nothing changes.
//!
//! [`ListCap`] is plain data with the wait and the round trip passed in, tested without a
//! connection; `send_lists` in `connection.rs` applies it to the ranked lists it writes.

use std::time::{Duration, Instant};

/// A cap never goes below this many items: at the link rates Arbor is used over, enough for the
/// server to stay busy for a round trip on a list alone.
pub const MIN_LIST_ITEMS: usize = 256;
/// A write that waited less than this never lowers the cap, however short the round trip: a list
/// a few milliseconds old is fresh (on loopback or a LAN, half a round trip is a fraction of a
/// millisecond, and a busy machine delays acknowledgements by more).
pub const MIN_WAIT: Duration = Duration::from_millis(10);

/// The item cap of one connection's request lists.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ListCap {
    /// `None`: uncapped.
    cap: Option<usize>,
    /// When the cap last changed.
    changed_at: Option<Instant>,
}

impl ListCap {
    /// The cap now; `None` while lists go out whole.
    pub fn cap(&self) -> Option<usize> {
        self.cap
    }

    /// How many of a list's `len` items (in the order the server serves them) to send.
    pub fn apply(&self, len: usize) -> usize {
        self.cap.map_or(len, |c| len.min(c))
    }

    /// A list of `full` items was written at `now` with `sent` of them, after waiting `waited`
    /// for the list window, on a connection whose round trip is `rtt`.
    pub fn handle_written(
        &mut self,
        now: Instant,
        full: usize,
        sent: usize,
        waited: Duration,
        rtt: Duration,
    ) {
        if self.changed_at.is_some_and(|at| now < at + rtt) {
            return;
        }
        if waited >= (rtt / 2).max(MIN_WAIT) {
            let lower = (sent * 3 / 4).max(MIN_LIST_ITEMS);
            if lower < sent {
                self.cap = Some(self.cap.map_or(lower, |c| c.min(lower)));
                self.changed_at = Some(now);
            }
        } else if waited < (rtt / 4).max(MIN_WAIT / 2)
            && let Some(c) = self.cap
        {
            let grown = c + (c / 8).max(1);
            self.cap = (grown < full).then_some(grown);
            self.changed_at = Some(now);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const RTT: Duration = Duration::from_millis(80);
    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn an_uplink_that_keeps_up_leaves_lists_whole() {
        let t0 = Instant::now();
        let mut c = ListCap::default();
        for (i, waited) in [Duration::ZERO, 5 * MS, 39 * MS].into_iter().enumerate() {
            c.handle_written(t0 + RTT * i as u32, 4096, 4096, waited, RTT);
            assert_eq!((c.cap(), c.apply(4096)), (None, 4096));
        }
    }

    #[test]
    fn lists_that_wait_shrink_to_the_floor_and_grow_back_when_they_stop_waiting() {
        let t0 = Instant::now();
        let mut c = ListCap::default();
        let mut caps = Vec::new();
        for i in 0..12 {
            let sent = c.apply(4096);
            c.handle_written(t0 + RTT * i, 4096, sent, 200 * MS, RTT);
            caps.push(c.cap().unwrap());
        }
        assert_eq!(&caps[..4], [3072, 2304, 1728, 1296]);
        assert_eq!(*caps.last().unwrap(), MIN_LIST_ITEMS, "{caps:?}");
        let mut now = t0 + RTT * 12;
        // A short list that waited does not lower the cap below its floor either.
        c.handle_written(now, 100, 100, 200 * MS, RTT);
        assert_eq!(c.cap(), Some(MIN_LIST_ITEMS));
        // Between a quarter and half a round trip: hold.
        c.handle_written(now, 4096, 256, 30 * MS, RTT);
        assert_eq!(c.cap(), Some(MIN_LIST_ITEMS));
        let mut round_trips = 0;
        while c.cap().is_some() {
            // Several writes a round trip; the cap grows once.
            for k in 0..4 {
                let sent = c.apply(4096);
                c.handle_written(now + 10 * MS * k, 4096, sent, MS, RTT);
            }
            now += RTT;
            round_trips += 1;
        }
        assert_eq!(
            round_trips, 24,
            "an eighth more per round trip until a whole list fits"
        );
        assert_eq!(c.apply(4096), 4096);
    }

    #[test]
    fn a_short_wait_on_a_short_path_does_not_cap() {
        let t0 = Instant::now();
        let lan = Duration::from_micros(200);
        let mut c = ListCap::default();
        c.handle_written(t0, 4096, 4096, 3 * MS, lan);
        assert_eq!(
            c.cap(),
            None,
            "3 ms is many round trips here, but a fresh list"
        );
        c.handle_written(t0 + MS, 4096, 4096, 12 * MS, lan);
        assert_eq!(c.cap(), Some(3072));
        c.handle_written(t0 + 2 * MS, 4096, 3072, 4 * MS, lan);
        assert_eq!(c.cap(), Some(3456), "under half the floor: grows");
    }

    #[test]
    fn one_backlog_cuts_once_a_round_trip() {
        let t0 = Instant::now();
        let mut c = ListCap::default();
        c.handle_written(t0, 4096, 4096, RTT, RTT);
        assert_eq!(c.cap(), Some(3072));
        // The writes right after a long wait find the window empty: no growth within the round
        // trip, nor another cut.
        c.handle_written(t0 + MS, 4096, 3072, Duration::ZERO, RTT);
        c.handle_written(t0 + 2 * MS, 4096, 3072, RTT, RTT);
        assert_eq!(c.cap(), Some(3072));
        c.handle_written(t0 + RTT, 4096, 3072, RTT, RTT);
        assert_eq!(c.cap(), Some(2304));
    }

    #[test]
    fn a_short_list_lifts_the_cap_once_it_fits_whole() {
        let t0 = Instant::now();
        let mut c = ListCap::default();
        c.handle_written(t0, 4096, 4096, RTT, RTT);
        assert_eq!(c.cap(), Some(3072));
        c.handle_written(t0 + RTT, 3000, 3000, Duration::ZERO, RTT);
        assert_eq!(c.cap(), None, "3,456 would hold all 3,000");
    }
}
