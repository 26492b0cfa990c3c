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
//! Plain data, no I/O: the handler keeps one per connection with the stream's cancel handle as
//! `C`; tests use any value.

use arbor_proto::TreeletId;
use rustc_hash::FxHashMap;
use std::collections::hash_map::Entry;

/// The batches of one connection still in flight.
#[derive(Debug)]
pub(super) struct Batches<C> {
    /// The batch of each treelet in flight (the newest, if a treelet was sent again).
    batch_of: FxHashMap<TreeletId, u64>,
    /// Per batch: its cancel handle and how many treelets it carries.
    batches: FxHashMap<u64, (C, usize)>,
    next: u64,
}

impl<C> Default for Batches<C> {
    fn default() -> Self {
        Self {
            batch_of: FxHashMap::default(),
            batches: FxHashMap::default(),
            next: 0,
        }
    }
}

impl<C> Batches<C> {
    /// A batch of `treelets` starts; returns its number.
    pub(super) fn start(&mut self, treelets: &[TreeletId], cancel: C) -> u64 {
        let id = self.next;
        self.next += 1;
        for &t in treelets {
            self.batch_of.insert(t, id);
        }
        self.batches.insert(id, (cancel, treelets.len()));
        id
    }

    /// Batch `id` ended (delivered, reset or failed). Its treelets may already be in a newer
    /// batch: only entries of this one go.
    pub(super) fn end(&mut self, id: u64, treelets: &[TreeletId]) {
        self.batches.remove(&id);
        for &t in treelets {
            if let Entry::Occupied(e) = self.batch_of.entry(t)
                && *e.get() == id
            {
                e.remove();
            }
        }
    }

    /// The latest list does not want `unwanted` (every treelet in flight it leaves out): the
    /// cancel handles of the batches it wants nothing of, which are forgotten.
    pub(super) fn obsolete(&mut self, unwanted: &[TreeletId]) -> Vec<C> {
        let mut named: FxHashMap<u64, usize> = FxHashMap::default();
        for t in unwanted {
            if let Some(&b) = self.batch_of.get(t) {
                *named.entry(b).or_default() += 1;
            }
        }
        let mut obsolete: Vec<u64> = named
            .into_iter()
            .filter(|&(b, count)| self.batches.get(&b).is_some_and(|&(_, size)| count >= size))
            .map(|(b, _)| b)
            .collect();
        obsolete.sort_unstable();
        obsolete
            .into_iter()
            .filter_map(|b| self.batches.remove(&b).map(|(cancel, _)| cancel))
            .collect()
    }

    /// Every batch's cancel handle, for a connection that ends.
    pub(super) fn drain(&mut self) -> impl Iterator<Item = C> + '_ {
        self.batch_of.clear();
        self.batches.drain().map(|(_, (cancel, _))| cancel)
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
    fn a_treelet_sent_again_belongs_to_its_newest_batch() {
        let mut b = Batches::default();
        let old = b.start(&ids(&[7, 8]), "old");
        // 8 was cancelled with the old batch's end still to come, and sent again alone.
        b.start(&ids(&[8]), "new");
        b.end(old, &ids(&[7, 8]));
        assert_eq!(b.obsolete(&ids(&[8])), vec!["new"]);
        // The old batch's end removed its own entries only.
        let again = b.start(&ids(&[9]), "third");
        b.end(again, &ids(&[9]));
        assert!(b.obsolete(&ids(&[7, 8, 9])).is_empty());
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
