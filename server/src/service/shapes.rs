//! Treelet shapes for deep-request pushes ([`super::push::TreeletShape`]: a treelet's root voxel
//! and its refinable leaves), decoded from the stored node blocks on first use and kept in one
//! server-wide [`ShapeCache`] bounded in bytes (`shape_cache_bytes`).
//!
//! Why bounded in bytes: a shape holds one entry per child treelet, so its size follows the
//! scene (a few children in a statue's treelet, 64 in a city terrain's, about 1.3 KB). A bound
//! by count (262,144 shapes per scene before) let a city-scale scene hold about 360 MB, and
//! every scene its own.
//!
//! Why two generations rather than a full LRU: the push plan looks shapes up by the thousand
//! per list, and a lookup must stay one hash probe under one short lock. New shapes go into the
//! young map; when it holds half the budget it becomes the old map and the previous old map is
//! dropped. A hit in the old map moves the shape back into the young one, so the shapes a view
//! keeps walking (the treelets near the root, the current frontier) survive every turn, and
//! what no plan touched for a whole generation goes.

use std::sync::{Arc, Mutex};

use arbor_proto::codec::{self, PreparedDictionaries};
use arbor_proto::{Cell, Node, TreeletId};
use rustc_hash::FxHashMap;

use super::push::TreeletShape;
use crate::pool::StoredScene;

/// Which shape: the scene's generation (unique in a pool, new on every re-import) and the
/// treelet.
type ShapeKey = (u64, TreeletId);

/// The bytes one cached shape costs: its children, the shape and its `Arc`, and the map entry
/// with the slack of a hash table at its usual load.
pub fn shape_bytes(shape: &TreeletShape) -> usize {
    const ENTRY: usize = 2 * (size_of::<ShapeKey>() + size_of::<Arc<TreeletShape>>());
    const ARC_COUNTS: usize = 2 * size_of::<usize>();
    ENTRY
        + ARC_COUNTS
        + size_of::<TreeletShape>()
        + shape.children.capacity() * size_of::<(TreeletId, Cell)>()
}

/// Decoded treelet shapes of every served scene, at most `capacity` bytes by [`shape_bytes`].
#[derive(Debug)]
pub struct ShapeCache {
    capacity: usize,
    inner: Mutex<Generations>,
}

#[derive(Debug, Default)]
struct Generations {
    young: FxHashMap<ShapeKey, Arc<TreeletShape>>,
    young_bytes: usize,
    old: FxHashMap<ShapeKey, Arc<TreeletShape>>,
    old_bytes: usize,
    hits: u64,
    misses: u64,
}

/// What a [`ShapeCache`] holds and how it served, for metrics and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ShapeCacheFigures {
    /// Bytes held, by [`shape_bytes`].
    pub bytes: usize,
    /// Shapes held.
    pub shapes: usize,
    /// Lookups answered from the cache.
    pub hits: u64,
    /// Lookups that decoded the shape.
    pub misses: u64,
}

impl ShapeCache {
    /// A cache of at most `capacity` bytes (0: nothing is kept, every lookup decodes).
    pub fn new(capacity: usize) -> ShapeCache {
        ShapeCache {
            capacity,
            inner: Mutex::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Generations> {
        // Every critical section below leaves the maps and their byte counts consistent.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The shape of treelet `id` of `scene`; `None` if it is not stored or does not decode (the
    /// push is then simply not made).
    pub fn shape(
        &self,
        scene: &StoredScene,
        dictionaries: &PreparedDictionaries,
        id: TreeletId,
    ) -> Option<Arc<TreeletShape>> {
        self.get_or_decode(scene.generation, id, || {
            decode_shape(scene, dictionaries, id)
        })
    }

    /// The shape of treelet `id` of the scene generation `generation`, or `decode`'s, kept if
    /// it fits ([`ShapeCache::shape`] decodes from the pool; benchmarks bring their own). The
    /// lock is not held while decoding: two lookups of the same missing shape may both decode
    /// it.
    pub fn get_or_decode(
        &self,
        generation: u64,
        id: TreeletId,
        decode: impl FnOnce() -> Option<TreeletShape>,
    ) -> Option<Arc<TreeletShape>> {
        let key = (generation, id);
        {
            let mut g = self.lock();
            if let Some(s) = g.young.get(&key) {
                let s = s.clone();
                g.hits += 1;
                return Some(s);
            }
            if let Some(s) = g.old.remove(&key) {
                g.hits += 1;
                g.old_bytes -= shape_bytes(&s);
                self.keep(&mut g, key, s.clone());
                return Some(s);
            }
            g.misses += 1;
        }
        let shape = Arc::new(decode()?);
        let mut g = self.lock();
        if !g.young.contains_key(&key) && !g.old.contains_key(&key) {
            self.keep(&mut g, key, shape.clone());
        }
        Some(shape)
    }

    /// Puts `shape` in the young map, turning the generations first when it would pass half
    /// the budget; a shape larger than half the budget is not kept.
    fn keep(&self, g: &mut Generations, key: ShapeKey, shape: Arc<TreeletShape>) {
        let bytes = shape_bytes(&shape);
        let half = self.capacity / 2;
        if bytes > half {
            return;
        }
        if g.young_bytes + bytes > half {
            g.old = std::mem::take(&mut g.young);
            g.old_bytes = std::mem::take(&mut g.young_bytes);
        }
        g.young_bytes += bytes;
        g.young.insert(key, shape);
    }

    /// What the cache holds and how it served.
    pub fn figures(&self) -> ShapeCacheFigures {
        let g = self.lock();
        ShapeCacheFigures {
            bytes: g.young_bytes + g.old_bytes,
            shapes: g.young.len() + g.old.len(),
            hits: g.hits,
            misses: g.misses,
        }
    }
}

/// The shape of treelet `id`, decoded from its stored node block.
fn decode_shape(
    scene: &StoredScene,
    dictionaries: &PreparedDictionaries,
    id: TreeletId,
) -> Option<TreeletShape> {
    let d = &scene.description;
    let bytes = scene.nodes(id).ok()??;
    let (treelet, places) = codec::decode_compressed_treelet_with_places_using(
        &bytes,
        d.max_depth,
        dictionaries.nodes(),
    )
    .ok()?;
    let mut children: Vec<(TreeletId, Cell)> = places
        .iter()
        .zip(&treelet.nodes)
        .filter(|(p, n)| p.is_leaf && n.first_child != Node::NONE)
        .map(|(p, n)| (TreeletId(n.first_child), p.cell))
        .collect();
    children.shrink_to_fit();
    Some(TreeletShape {
        root: treelet.header.root_cell(),
        children,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn shape_with(children: usize) -> TreeletShape {
        let root = Cell {
            depth: 0,
            x: 0,
            y: 0,
            z: 0,
        };
        let mut children: Vec<(TreeletId, Cell)> =
            (0..children as u32).map(|i| (TreeletId(i), root)).collect();
        children.shrink_to_fit();
        TreeletShape { root, children }
    }

    /// Looks `id` of generation 1 up, decoding a shape of `children` children on a miss;
    /// returns whether it decoded.
    fn look_up(cache: &ShapeCache, id: u32, children: usize) -> bool {
        let mut decoded = false;
        let s = cache.get_or_decode(1, TreeletId(id), || {
            decoded = true;
            Some(shape_with(children))
        });
        assert_eq!(s.unwrap().children.len(), children);
        decoded
    }

    #[test]
    fn a_second_lookup_is_a_hit_and_generations_do_not_mix() {
        let cache = ShapeCache::new(1 << 20);
        assert!(look_up(&cache, 7, 3));
        assert!(!look_up(&cache, 7, 3));
        let other = cache.get_or_decode(2, TreeletId(7), || Some(shape_with(5)));
        assert_eq!(
            other.unwrap().children.len(),
            5,
            "another scene's treelet 7"
        );
        let f = cache.figures();
        assert_eq!((f.shapes, f.hits, f.misses), (2, 1, 2));
        assert_eq!(
            f.bytes,
            shape_bytes(&shape_with(3)) + shape_bytes(&shape_with(5))
        );
    }

    #[test]
    fn a_shape_that_does_not_decode_is_not_kept() {
        let cache = ShapeCache::new(1 << 20);
        assert!(cache.get_or_decode(1, TreeletId(3), || None).is_none());
        assert_eq!(cache.figures().shapes, 0);
        assert!(look_up(&cache, 3, 2), "decoded again on the next lookup");
    }

    #[test]
    fn nothing_is_kept_in_a_cache_of_no_bytes_or_larger_than_half_of_it() {
        let none = ShapeCache::new(0);
        assert!(look_up(&none, 1, 1));
        assert!(look_up(&none, 1, 1));
        assert_eq!(none.figures().bytes, 0);
        let small = ShapeCache::new(2 * shape_bytes(&shape_with(10)) - 1);
        assert!(look_up(&small, 1, 10));
        assert!(look_up(&small, 1, 10));
        assert!(look_up(&small, 2, 1));
        assert!(!look_up(&small, 2, 1));
    }

    #[test]
    fn a_shape_walked_in_every_generation_survives_the_turns() {
        let per = shape_bytes(&shape_with(8));
        let cache = ShapeCache::new(per * 20);
        assert!(look_up(&cache, 0, 8));
        // Many more distinct shapes than fit, with the root looked up between every few.
        for id in 1..500 {
            look_up(&cache, id, 8);
            if id % 5 == 0 {
                assert!(
                    !look_up(&cache, 0, 8),
                    "the root was dropped before shape {id}"
                );
            }
        }
        assert!(look_up(&cache, 1, 8), "the first shapes are long gone");
    }

    proptest! {
        /// Whatever the sizes and the order of lookups: the bytes held never exceed the
        /// capacity, the figures count what the maps hold, and a lookup returns the shape its
        /// key was decoded to.
        #[test]
        fn never_more_than_the_capacity(
            capacity in 0usize..20_000,
            lookups in proptest::collection::vec((0u32..64, 0usize..40), 1..400),
        ) {
            let cache = ShapeCache::new(capacity);
            // A key's shape size is fixed by the key, so hits can be checked.
            let size_of_id = |id: u32| (id as usize * 7) % 40;
            for (id, _) in lookups {
                look_up(&cache, id, size_of_id(id));
                let f = cache.figures();
                prop_assert!(f.bytes <= capacity, "{} > {capacity}", f.bytes);
                let g = cache.lock();
                let counted: usize = g.young.values().chain(g.old.values())
                    .map(|s| shape_bytes(s)).sum();
                prop_assert_eq!(counted, f.bytes);
                prop_assert!(g.young.keys().all(|k| !g.old.contains_key(k)));
            }
        }
    }
}
