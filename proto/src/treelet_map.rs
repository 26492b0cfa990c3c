//! Hashing treelet ids so that consecutive ids stay close in memory.
//!
//! Ids are numbered breadth-first (a child after its parent), request lists go coarse to fine
//! and the server sends in rank order, so some maps are filled and read in nearly ascending id
//! order: the client's request times (filled by each list, emptied by arrivals) and the
//! server's message cache (read a stream's batch at a time). With a scattering hash every such
//! access is a cache miss; [`RunHasher`] keeps each run of 64 consecutive ids in consecutive
//! buckets and scatters the runs, so those accesses walk the table. On a whole-scene fetch of
//! lion-4k over loopback the client's request-time map took 2.6× fewer samples with it than
//! with FxHash (perf, docs/measurements.md). Ids that are not consecutive (random, strided, a
//! few per run) cost about what they cost with FxHash, within about 10 % per insertion and removal
//! from 4,000 to 1,000,000 ids. The server's window and delivery maps were tried with it too and
//! got slower: they hold a sliding window of a few hundred ids, where a handful of runs collide
//! in a small table.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use crate::treelet::TreeletId;

/// A map keyed by treelet id, hashed with [`RunHasher`].
pub type TreeletMap<V> = HashMap<TreeletId, V, BuildHasherDefault<RunHasher>>;

/// The hash of [`TreeletMap`]. The position bits are the high half of a multiplicative hash of
/// the id's run (`id / 64`) and the salt, plus the id's offset in its run: a run's ids take
/// consecutive buckets, runs start anywhere, and ids in a strided pattern do not pile up in one
/// bucket. (Runs starting only at multiples of 64 made partly filled runs crowd into the first
/// buckets of each block: a third slower than FxHash with seven ids per run.) The top seven bits,
/// the table's tag, come from a multiplicative hash of the whole id, so neighbours in one group
/// rarely share a tag.
///
/// A key hashes its id with one [`Hasher::write_u32`], after an optional [`Hasher::write_u64`]
/// of what else tells keys apart (a scene generation, a channel set): the salt. Not meant for
/// keys an adversary picks: the maps hold ids the program chose or validated against the scene.
#[derive(Clone, Copy, Debug, Default)]
pub struct RunHasher {
    hash: u64,
    /// Set by [`Hasher::write_u64`]: places the runs of another key space elsewhere.
    salt: u64,
}

impl RunHasher {
    /// An odd constant with well-spread bits (2⁶⁴ / φ).
    const MIX: u64 = 0x9E37_79B9_7F4A_7C15;
    /// The bits the table takes its tag from.
    const TAG: u64 = 0xFE00_0000_0000_0000;
}

impl Hasher for RunHasher {
    fn write_u32(&mut self, id: u32) {
        let run = (u64::from(id >> 6) ^ self.salt).wrapping_mul(Self::MIX) >> 32;
        let tag = (u64::from(id) ^ self.salt).wrapping_mul(Self::MIX) & Self::TAG;
        self.hash = tag | (run + u64::from(id & 63));
    }

    fn write_u64(&mut self, salt: u64) {
        self.salt = (self.salt ^ salt).wrapping_mul(Self::MIX).rotate_left(29);
    }

    /// Not used by the keys here; folds bytes into the salt for completeness.
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.salt = (self.salt.rotate_left(8) ^ u64::from(b)).wrapping_mul(Self::MIX);
        }
        self.hash = self.salt;
    }

    fn finish(&self) -> u64 {
        self.hash
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;
    use std::hash::BuildHasher;

    fn hash(id: u32) -> u64 {
        BuildHasherDefault::<RunHasher>::default().hash_one(TreeletId(id))
    }

    fn salted(salt: u64, id: u32) -> u64 {
        let mut h = RunHasher::default();
        h.write_u64(salt);
        h.write_u32(id);
        h.finish()
    }

    #[test]
    fn consecutive_ids_take_consecutive_positions_within_a_run() {
        let mask = (1u64 << 20) - 1;
        for id in [0u32, 64, 6400, u32::MAX - 63] {
            for k in 1..64 {
                assert_eq!(hash(id + k).wrapping_sub(hash(id)) & mask, u64::from(k));
            }
        }
    }

    #[test]
    fn strided_ids_spread_over_a_table_and_its_tags() {
        // Ids 2¹³ apart (a stride a table of 8,192 buckets would pile into one bucket if the
        // position were the id itself): they take many distinct positions and tags.
        let mask = 8191u64;
        let ids: Vec<u32> = (0..1000).map(|i| i << 13).collect();
        let positions: HashSet<u64> = ids.iter().map(|&id| hash(id) & mask).collect();
        let tags: HashSet<u64> = ids.iter().map(|&id| hash(id) >> 57).collect();
        assert!(positions.len() > 100, "{} positions", positions.len());
        assert!(tags.len() > 100, "{} tags", tags.len());
        // Neighbours rarely share a tag.
        let same = (0..1000u32)
            .filter(|&i| hash(i) >> 57 == hash(i + 1) >> 57)
            .count();
        assert!(same < 50, "{same} neighbours share a tag");
    }

    #[test]
    fn runs_start_anywhere_so_partly_filled_runs_do_not_crowd() {
        // The first id of 1,000 runs: where they start within a block of 64 buckets varies.
        let starts: HashSet<u64> = (0..1000u32).map(|r| hash(r << 6) & 63).collect();
        assert!(
            starts.len() > 48,
            "runs start at only {} offsets",
            starts.len()
        );
    }

    #[test]
    fn a_salt_moves_the_runs_and_keeps_them_whole() {
        let mask = (1u64 << 20) - 1;
        let (a, b) = (salted(1, 640), salted(2, 640));
        assert_ne!(a & mask, b & mask);
        for k in 1..64 {
            assert_eq!(salted(1, 640 + k).wrapping_sub(a) & mask, u64::from(k));
            assert_eq!(salted(2, 640 + k).wrapping_sub(b) & mask, u64::from(k));
        }
        // A zero salt places the runs as no salt does.
        assert_eq!(salted(0, 77) & mask, hash(77) & mask);
    }

    #[test]
    fn a_map_behaves_as_a_map() {
        let mut m: TreeletMap<u32> = TreeletMap::default();
        for id in (0..10_000u32).chain((0..1000).map(|i| i << 20)) {
            m.insert(TreeletId(id), id);
        }
        assert_eq!(m.len(), 10_999);
        assert_eq!(m.get(&TreeletId(5 << 20)), Some(&(5 << 20)));
        assert_eq!(m.remove(&TreeletId(9_999)), Some(9_999));
        assert_eq!(m.get(&TreeletId(9_999)), None);
        assert_eq!(m.get(&TreeletId(10_000)), None);
    }
}
