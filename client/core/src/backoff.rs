//! Treelets that arrived and could not be decoded, held off the request lists for a while.
//!
//! A treelet whose bytes the client cannot decode (a damaged or misfiled block in the server's
//! pool) is not resident afterwards, so the next presort would name it again, and the server
//! would send the same bytes again as soon as its redelivery guard lets it: one useless message
//! every tenth of a second for as long as the view lasts. QUIC's integrity checks rule out
//! damage on the way, so a second copy from the same server is as bad as the first. The
//! treelet is therefore held off the lists for a number of cycles that doubles with each
//! failure, up to [`LONGEST_HOLD_CYCLES`]: a replica the client fails over to, or a pool
//! repaired meanwhile, still gets asked, and a view never stops refining for good over one bad
//! block. A copy that decodes clears the record.
//!
//! Cycles are the time here, as everywhere in this crate: a hold of 8 cycles is a few tens of
//! milliseconds on a fast view, and the longest about ten seconds.

use std::collections::HashMap;

use arbor_proto::TreeletId;

/// Cycles the first failure holds a treelet off the lists.
pub const FIRST_HOLD_CYCLES: u64 = 8;

/// The longest hold, however often the treelet failed.
pub const LONGEST_HOLD_CYCLES: u64 = 1024;

/// Most treelets remembered. A view that meets this many undecodable treelets is served from
/// a broken pool; forgetting them only costs a copy of each.
pub const MAX_REMEMBERED: usize = 1 << 16;

/// One undecodable treelet: how often it failed, and until which cycle it is held.
#[derive(Clone, Copy, Debug)]
struct Failure {
    count: u32,
    held_until: u64,
}

/// The undecodable treelets and their holds. Plain data, driven by the caller's cycle count.
#[derive(Clone, Debug, Default)]
pub struct DecodeBackoff {
    failures: HashMap<TreeletId, Failure>,
    /// Changes whenever the set of held treelets changes, for memos that depend on it.
    generation: u64,
    /// The earliest cycle a hold ends, if any hold is running.
    next_release: Option<u64>,
}

impl DecodeBackoff {
    /// The hold after the `count`-th failure: [`FIRST_HOLD_CYCLES`], doubling, at most
    /// [`LONGEST_HOLD_CYCLES`].
    pub fn hold_cycles(count: u32) -> u64 {
        let doublings = count.saturating_sub(1).min(u64::BITS - 1);
        FIRST_HOLD_CYCLES
            .saturating_mul(1 << doublings)
            .min(LONGEST_HOLD_CYCLES)
    }

    /// `id` arrived at `cycle` and could not be decoded: it is held off the lists from now.
    pub fn failed(&mut self, id: TreeletId, cycle: u64) {
        if self.failures.len() >= MAX_REMEMBERED && !self.failures.contains_key(&id) {
            self.failures.clear();
        }
        let failure = self.failures.entry(id).or_insert(Failure {
            count: 0,
            held_until: 0,
        });
        failure.count = failure.count.saturating_add(1);
        failure.held_until = cycle.saturating_add(Self::hold_cycles(failure.count));
        let until = failure.held_until;
        self.next_release = Some(self.next_release.map_or(until, |n| n.min(until)));
        self.generation += 1;
    }

    /// A copy of `id` decoded: it is no longer held, and a later failure starts afresh. Called
    /// for every arrival, so nothing is looked up while no treelet ever failed.
    pub fn decoded(&mut self, id: TreeletId) {
        if !self.failures.is_empty() && self.failures.remove(&id).is_some() {
            self.generation += 1;
        }
    }

    /// Forgets every failure.
    pub fn clear(&mut self) {
        if !self.failures.is_empty() {
            self.failures.clear();
            self.generation += 1;
        }
    }

    /// Whether `id` is held off the lists at `cycle`. Asked for every candidate of every
    /// presort, so nothing is looked up while no treelet ever failed.
    pub fn holds(&self, id: TreeletId, cycle: u64) -> bool {
        !self.failures.is_empty() && self.failures.get(&id).is_some_and(|f| f.held_until > cycle)
    }

    /// How often `id` failed since it last decoded.
    pub fn failures(&self, id: TreeletId) -> u32 {
        self.failures.get(&id).map_or(0, |f| f.count)
    }

    /// A number that changes whenever the treelets held at `cycle` differ from those held at
    /// the last call: a hold began, ended or was cleared. `cycle` must not go back.
    pub fn generation(&mut self, cycle: u64) -> u64 {
        if self.next_release.is_some_and(|n| n <= cycle) {
            self.generation += 1;
            self.next_release = self
                .failures
                .values()
                .map(|f| f.held_until)
                .filter(|&u| u > cycle)
                .min();
        }
        self.generation
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn holds_double_with_each_failure_up_to_the_longest() {
        let holds: Vec<u64> = (1..=9).map(DecodeBackoff::hold_cycles).collect();
        assert_eq!(holds, [8, 16, 32, 64, 128, 256, 512, 1024, 1024]);
        assert_eq!(DecodeBackoff::hold_cycles(u32::MAX), LONGEST_HOLD_CYCLES);
        assert_eq!(DecodeBackoff::hold_cycles(0), FIRST_HOLD_CYCLES);
    }

    #[test]
    fn a_failed_treelet_is_held_for_its_hold_then_released() {
        let mut b = DecodeBackoff::default();
        let id = TreeletId(5);
        let g0 = b.generation(0);
        b.failed(id, 10);
        let g1 = b.generation(10);
        assert_ne!(g0, g1, "a hold began");
        assert!(b.holds(id, 10) && b.holds(id, 17));
        assert!(!b.holds(id, 18) && !b.holds(TreeletId(6), 10));
        assert_eq!(b.generation(17), g1, "nothing changed");
        let g2 = b.generation(18);
        assert_ne!(g1, g2, "the hold ended");
        assert_eq!(b.generation(40), g2);

        // The second failure holds twice as long; a decoded copy clears it at once.
        b.failed(id, 40);
        assert!(b.holds(id, 55) && !b.holds(id, 56));
        assert_eq!(b.failures(id), 2);
        let g3 = b.generation(41);
        b.decoded(id);
        assert_ne!(b.generation(41), g3);
        assert!(!b.holds(id, 41));
        assert_eq!(b.failures(id), 0);
        b.failed(id, 50);
        assert!(b.holds(id, 57) && !b.holds(id, 58), "starts afresh");
    }

    #[test]
    fn releases_are_seen_in_order_among_several_holds() {
        let mut b = DecodeBackoff::default();
        b.failed(TreeletId(1), 0);
        b.failed(TreeletId(2), 0);
        b.failed(TreeletId(2), 0);
        let mut g = b.generation(0);
        let mut changes = Vec::new();
        for cycle in 1..40 {
            let now = b.generation(cycle);
            if now != g {
                changes.push(cycle);
                g = now;
            }
        }
        assert_eq!(changes, [8, 16], "each release seen once, when it happens");
    }

    #[test]
    fn memory_is_bounded() {
        let mut b = DecodeBackoff::default();
        for i in 0..(MAX_REMEMBERED as u32 + 10) {
            b.failed(TreeletId(i), 0);
        }
        assert!(b.failures.len() <= MAX_REMEMBERED);
        assert!(b.holds(TreeletId(MAX_REMEMBERED as u32 + 9), 0));
    }
}
