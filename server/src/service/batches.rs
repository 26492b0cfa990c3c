//! Which stream carries which treelets, and which streams a new request list makes obsolete.
//!
//! A connection sends a few treelets adjacent in rank per stream (`streams.rs`). A new list may
//! stop wanting treelets already in flight; their stream is reset only when the list wants
//! *none* of its treelets, since a reset also throws away whatever of the stream was still to
//! come and the scheduler then re-queues every treelet of it the list does want. The decision is
//! made per list: the scheduler names every in-flight treelet the latest list does not want, and
//! a batch is obsolete exactly when all of its treelets are named. (Counting unwanted treelets
//! across lists counted a treelet twice when two lists in a row left it out, reset batches whose
//! other treelets were still wanted and sent those again although most had already arrived: over
//! the link emulator a quarter of the engine's treelets were received twice.)
//!
//! The record is per batch, not per treelet: a batch keeps its treelets, and only a list that
//! leaves something in flight out looks at them. A map from each treelet to its batch cost two
//! hash-map operations per treelet sent whether or not a list ever asked (0.6 million
//! instructions of a whole-scene fetch of lion-4k, 1 % of it); most lists, and every
//! whole-scene fetch, leave nothing in flight out.
//!
//! Plain data, no I/O: the handler keeps one per connection with the stream's cancel handle as
//! `C`; tests use any value.

use arbor_proto::TreeletId;
use rustc_hash::FxHashSet;
use std::collections::BTreeMap;

/// The batches of one connection still in flight.
#[derive(Debug)]
pub(super) struct Batches<C> {
    /// Per batch, by number (the order they started in): its treelets and its cancel handle.
    live: BTreeMap<u64, (Vec<TreeletId>, C)>,
    next: u64,
}

impl<C> Default for Batches<C> {
    fn default() -> Self {
        Self {
            live: BTreeMap::new(),
            next: 0,
        }
    }
}

impl<C> Batches<C> {
    /// A batch of `treelets` starts; returns its number.
    pub(super) fn start(&mut self, treelets: &[TreeletId], cancel: C) -> u64 {
        let id = self.next;
        self.next += 1;
        self.live.insert(id, (treelets.to_vec(), cancel));
        id
    }

    /// Batch `id` ended (delivered, reset or failed); a batch cancelled before is forgotten
    /// already.
    pub(super) fn end(&mut self, id: u64) {
        self.live.remove(&id);
    }

    /// The latest list does not want `unwanted` (every treelet in flight it leaves out): the
    /// cancel handles of the batches it wants nothing of, in the order they started, which are
    /// forgotten. A treelet sent again while its first batch is still in flight is in both:
    /// each batch is judged by all of its own treelets.
    pub(super) fn obsolete(&mut self, unwanted: &[TreeletId]) -> Vec<C> {
        if unwanted.is_empty() {
            return Vec::new();
        }
        let unwanted: FxHashSet<TreeletId> = unwanted.iter().copied().collect();
        let obsolete: Vec<u64> = self
            .live
            .iter()
            .filter(|(_, (treelets, _))| treelets.iter().all(|t| unwanted.contains(t)))
            .map(|(&id, _)| id)
            .collect();
        obsolete
            .into_iter()
            .filter_map(|id| self.live.remove(&id).map(|(_, cancel)| cancel))
            .collect()
    }

    /// Every batch's cancel handle, for a connection that ends.
    pub(super) fn drain(&mut self) -> impl Iterator<Item = C> + '_ {
        std::mem::take(&mut self.live)
            .into_values()
            .map(|(_, cancel)| cancel)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ids(v: &[u32]) -> Vec<TreeletId> {
        v.iter().map(|&i| TreeletId(i)).collect()
    }

    #[test]
    fn a_batch_goes_on_while_any_of_it_is_wanted_however_many_lists_leave_the_rest_out() {
        let mut b = Batches::default();
        b.start(&ids(&[1, 2, 3]), "first");
        // Three lists in a row leave treelet 1 out and still want 2 and 3.
        for _ in 0..3 {
            assert!(b.obsolete(&ids(&[1])).is_empty());
        }
        // Two lists leave 1 and 2 out.
        for _ in 0..2 {
            assert!(b.obsolete(&ids(&[1, 2])).is_empty());
        }
        // Now nothing of it is wanted.
        assert_eq!(b.obsolete(&ids(&[1, 2, 3])), vec!["first"]);
        // Forgotten: a later list cannot cancel it twice.
        assert!(b.obsolete(&ids(&[1, 2, 3])).is_empty());
    }

    #[test]
    fn only_wholly_unwanted_batches_are_cancelled_in_batch_order() {
        let mut b = Batches::default();
        b.start(&ids(&[1, 2]), 'a');
        b.start(&ids(&[3]), 'b');
        b.start(&ids(&[4, 5]), 'c');
        b.start(&ids(&[6]), 'd');
        assert_eq!(b.obsolete(&ids(&[6, 5, 3, 1, 99])), vec!['b', 'd']);
        assert_eq!(b.obsolete(&ids(&[2, 1, 4, 5])), vec!['a', 'c']);
        assert_eq!(b.drain().count(), 0);
    }

    #[test]
    fn a_batch_goes_on_while_a_treelet_sent_again_is_still_wanted_in_it() {
        let mut b = Batches::default();
        let old = b.start(&ids(&[7, 8]), "old");
        // 8 was cancelled with the old batch's end still to come, and sent again alone.
        b.start(&ids(&[8]), "new");
        // The old batch still carries 7, which the list wants.
        assert_eq!(b.obsolete(&ids(&[8])), vec!["new"]);
        b.end(old);
        let again = b.start(&ids(&[9]), "third");
        b.end(again);
        assert!(b.obsolete(&ids(&[7, 8, 9])).is_empty());
    }

    #[test]
    fn a_batch_whose_treelets_were_all_sent_again_is_judged_by_all_of_its_own() {
        let mut b = Batches::default();
        b.start(&ids(&[7, 8]), "old");
        b.start(&ids(&[8]), "new");
        // Neither 7 nor 8 is wanted: both streams go, oldest first.
        assert_eq!(b.obsolete(&ids(&[8, 7])), vec!["old", "new"]);
        assert_eq!(b.drain().count(), 0);
    }

    #[test]
    fn draining_hands_back_every_handle() {
        let mut b = Batches::default();
        b.start(&ids(&[1]), 1);
        b.start(&ids(&[2, 3]), 2);
        let mut all: Vec<i32> = b.drain().collect();
        all.sort_unstable();
        assert_eq!(all, vec![1, 2]);
        assert!(b.obsolete(&ids(&[1, 2, 3])).is_empty());
    }
}
