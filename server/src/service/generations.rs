//! A server-wide cache of what is decoded from a scene's stored treelets, keyed by the scene's
//! generation (unique in a pool, new on every re-import) and the treelet, bounded in bytes:
//! the push plans' treelet shapes ([`super::shapes::ShapeCache`]) and the node records the
//! visible cuts are cast through ([`super::visibility::NodeCache`]).
//!
//! Why two generations rather than a full LRU: the push plan looks shapes up by the thousand
//! per list and a cut reads thousands of treelets, so a lookup must stay one hash probe under
//! one short lock. New values go into the young map; when it holds half the budget it becomes
//! the old map and the previous old map is dropped. A hit in the old map moves the value back
//! into the young one, so what every view keeps walking (the treelets near the root, the
//! current frontier) survives every turn, and what nothing touched for a whole generation
//! goes.

use std::sync::{Arc, Mutex};

use arbor_proto::TreeletId;
use rustc_hash::FxHashMap;

/// Which value: the scene's generation and the treelet.
type Key = (u64, TreeletId);

/// What a map entry costs beyond the value's own bytes: the key and the `Arc` in the map (with
/// the slack of a hash table at its usual load) and the `Arc`'s counts.
pub const ENTRY_BYTES: usize =
    2 * (size_of::<Key>() + size_of::<Arc<()>>()) + 2 * size_of::<usize>();

/// Decoded values of every served scene, at most `capacity` bytes: each value's own bytes
/// (`bytes_of`) plus [`ENTRY_BYTES`].
#[derive(Debug)]
pub struct GenerationCache<V> {
    capacity: usize,
    bytes_of: fn(&V) -> usize,
    inner: Mutex<Generations<V>>,
}

#[derive(Debug)]
struct Generations<V> {
    young: FxHashMap<Key, Arc<V>>,
    young_bytes: usize,
    old: FxHashMap<Key, Arc<V>>,
    old_bytes: usize,
    hits: u64,
    misses: u64,
}

impl<V> Default for Generations<V> {
    fn default() -> Self {
        Self {
            young: FxHashMap::default(),
            young_bytes: 0,
            old: FxHashMap::default(),
            old_bytes: 0,
            hits: 0,
            misses: 0,
        }
    }
}

/// What a [`GenerationCache`] holds and how it served, for metrics and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheFigures {
    /// Bytes held, each value's own bytes and its entry.
    pub bytes: usize,
    /// Values held.
    pub entries: usize,
    /// Lookups answered from the cache.
    pub hits: u64,
    /// Lookups that decoded the value.
    pub misses: u64,
}

impl<V> GenerationCache<V> {
    /// A cache of at most `capacity` bytes (0: nothing is kept, every lookup decodes), a value
    /// costing `bytes_of` its own bytes (heap and inline) and its entry.
    pub fn new(capacity: usize, bytes_of: fn(&V) -> usize) -> Self {
        Self {
            capacity,
            bytes_of,
            inner: Mutex::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Generations<V>> {
        // Every critical section below leaves the maps and their byte counts consistent.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// What a value costs the cache.
    pub fn cost(&self, value: &V) -> usize {
        (self.bytes_of)(value) + ENTRY_BYTES
    }

    /// The value of treelet `id` of the scene generation `generation`, or `decode`'s, kept if
    /// it fits. The lock is not held while decoding: two lookups of the same missing value may
    /// both decode it.
    pub fn get_or_decode(
        &self,
        generation: u64,
        id: TreeletId,
        decode: impl FnOnce() -> Option<V>,
    ) -> Option<Arc<V>> {
        let key = (generation, id);
        {
            let mut g = self.lock();
            if let Some(v) = self.held(&mut g, key) {
                g.hits += 1;
                return Some(v);
            }
            g.misses += 1;
        }
        let value = Arc::new(decode()?);
        let mut g = self.lock();
        if !g.young.contains_key(&key) && !g.old.contains_key(&key) {
            self.keep(&mut g, key, value.clone());
        }
        Some(value)
    }

    /// The value of treelet `id` of the scene generation `generation` if the cache holds it;
    /// never decodes. Counts nothing: a caller that uses what it found counts it with
    /// [`Self::count_hits`], and one that gives up at a missing value and looks everything up
    /// again with [`Self::get_or_decode`] (on a thread that may wait for the disk) is counted
    /// there, once.
    pub fn get(&self, generation: u64, id: TreeletId) -> Option<Arc<V>> {
        self.held(&mut self.lock(), (generation, id))
    }

    /// Counts `n` lookups answered by [`Self::get`] as hits.
    pub fn count_hits(&self, n: u64) {
        self.lock().hits += n;
    }

    /// The value held under `key`, moved into the young map if it was in the old one.
    fn held(&self, g: &mut Generations<V>, key: Key) -> Option<Arc<V>> {
        if let Some(v) = g.young.get(&key) {
            return Some(v.clone());
        }
        let v = g.old.remove(&key)?;
        g.old_bytes -= self.cost(&v);
        self.keep(g, key, v.clone());
        Some(v)
    }

    /// Puts `value` in the young map, turning the generations first when it would pass half
    /// the budget; a value larger than half the budget is not kept.
    fn keep(&self, g: &mut Generations<V>, key: Key, value: Arc<V>) {
        let bytes = self.cost(&value);
        let half = self.capacity / 2;
        if bytes > half {
            return;
        }
        if g.young_bytes + bytes > half {
            g.old = std::mem::take(&mut g.young);
            g.old_bytes = std::mem::take(&mut g.young_bytes);
        }
        g.young_bytes += bytes;
        g.young.insert(key, value);
    }

    /// What the cache holds and how it served.
    pub fn figures(&self) -> CacheFigures {
        let g = self.lock();
        CacheFigures {
            bytes: g.young_bytes + g.old_bytes,
            entries: g.young.len() + g.old.len(),
            hits: g.hits,
            misses: g.misses,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A value of `n` bytes.
    fn value(n: usize) -> Vec<u8> {
        vec![1; n]
    }

    fn cache(capacity: usize) -> GenerationCache<Vec<u8>> {
        GenerationCache::new(capacity, Vec::len)
    }

    /// Looks `id` of generation 1 up, decoding a value of `n` bytes on a miss; returns whether
    /// it decoded.
    fn look_up(cache: &GenerationCache<Vec<u8>>, id: u32, n: usize) -> bool {
        let mut decoded = false;
        let v = cache.get_or_decode(1, TreeletId(id), || {
            decoded = true;
            Some(value(n))
        });
        assert_eq!(v.unwrap().len(), n);
        decoded
    }

    #[test]
    fn a_second_lookup_is_a_hit_and_generations_do_not_mix() {
        let cache = cache(1 << 20);
        assert!(look_up(&cache, 7, 3));
        assert!(!look_up(&cache, 7, 3));
        let other = cache.get_or_decode(2, TreeletId(7), || Some(value(5)));
        assert_eq!(other.unwrap().len(), 5, "another scene's treelet 7");
        let f = cache.figures();
        assert_eq!((f.entries, f.hits, f.misses), (2, 1, 2));
        assert_eq!(f.bytes, 3 + 5 + 2 * ENTRY_BYTES);
    }

    #[test]
    fn get_finds_only_what_is_held_and_counts_only_what_it_is_told() {
        let cache = cache(4 * (8 + ENTRY_BYTES));
        assert!(cache.get(1, TreeletId(5)).is_none());
        assert!(look_up(&cache, 5, 8));
        assert_eq!(cache.get(1, TreeletId(5)).unwrap().len(), 8);
        assert!(
            cache.get(2, TreeletId(5)).is_none(),
            "another scene's treelet 5"
        );
        let f = cache.figures();
        assert_eq!((f.hits, f.misses), (0, 1), "get counts nothing itself");
        cache.count_hits(3);
        assert_eq!(cache.figures().hits, 3);
        // Two more values turn the generations; a `get` of the old one keeps it young, so it
        // survives the next turn.
        look_up(&cache, 6, 8);
        look_up(&cache, 7, 8);
        assert!(cache.get(1, TreeletId(5)).is_some());
        look_up(&cache, 8, 8);
        look_up(&cache, 9, 8);
        assert!(
            cache.get(1, TreeletId(5)).is_some(),
            "5 was dropped with its generation"
        );
        assert!(
            cache.get(1, TreeletId(6)).is_none(),
            "6 was not touched and went"
        );
    }

    #[test]
    fn a_value_that_does_not_decode_is_not_kept() {
        let cache = cache(1 << 20);
        assert!(cache.get_or_decode(1, TreeletId(3), || None).is_none());
        assert_eq!(cache.figures().entries, 0);
        assert!(look_up(&cache, 3, 2), "decoded again on the next lookup");
    }

    #[test]
    fn nothing_is_kept_in_a_cache_of_no_bytes_or_larger_than_half_of_it() {
        let none = cache(0);
        assert!(look_up(&none, 1, 1));
        assert!(look_up(&none, 1, 1));
        assert_eq!(none.figures().bytes, 0);
        let small = cache(2 * (100 + ENTRY_BYTES) - 1);
        assert!(look_up(&small, 1, 100));
        assert!(look_up(&small, 1, 100));
        assert!(look_up(&small, 2, 1));
        assert!(!look_up(&small, 2, 1));
    }

    #[test]
    fn a_value_walked_in_every_generation_survives_the_turns() {
        let cache = cache(20 * (8 + ENTRY_BYTES));
        assert!(look_up(&cache, 0, 8));
        // Many more distinct values than fit, with the root looked up between every few.
        for id in 1..500 {
            look_up(&cache, id, 8);
            if id % 5 == 0 {
                assert!(
                    !look_up(&cache, 0, 8),
                    "the root was dropped before value {id}"
                );
            }
        }
        assert!(look_up(&cache, 1, 8), "the first values are long gone");
    }

    proptest! {
        /// Whatever the sizes and the order of lookups: the bytes held never exceed the
        /// capacity, the figures count what the maps hold, and a lookup returns the value its
        /// key was decoded to.
        #[test]
        fn never_more_than_the_capacity(
            capacity in 0usize..20_000,
            lookups in proptest::collection::vec((0u32..64, 0usize..40), 1..400),
        ) {
            let cache = cache(capacity);
            // A key's value size is fixed by the key, so hits can be checked.
            let size_of_id = |id: u32| (id as usize * 7) % 40 * 16;
            for (id, _) in lookups {
                look_up(&cache, id, size_of_id(id));
                let f = cache.figures();
                prop_assert!(f.bytes <= capacity, "{} > {capacity}", f.bytes);
                let g = cache.lock();
                let counted: usize = g.young.values().chain(g.old.values())
                    .map(|v| cache.cost(v)).sum();
                prop_assert_eq!(counted, f.bytes);
                prop_assert!(g.young.keys().all(|k| !g.old.contains_key(k)));
            }
        }
    }
}
