//! Treelet shapes for deep-request pushes ([`super::push::TreeletShape`]: a treelet's root voxel
//! and its refinable leaves), decoded from the stored node blocks on first use and kept in one
//! server-wide [`ShapeCache`] bounded in bytes (`shape_cache_bytes`; two generations, see
//! [`super::generations`]).
//!
//! Why bounded in bytes: a shape holds one entry per child treelet, so its size follows the
//! scene (a few children in a statue's treelet, 64 in a city terrain's, about 1.3 KB). A bound
//! by count (262,144 shapes per scene before) let a city-scale scene hold about 360 MB, and
//! every scene its own.

use std::sync::Arc;

use arbor_proto::codec::{self, PreparedDictionaries};
use arbor_proto::{Cell, Node, TreeletId};

use super::generations::{ENTRY_BYTES, GenerationCache};
use super::push::TreeletShape;
use crate::pool::StoredScene;

/// Decoded treelet shapes of every served scene, at most `shape_cache_bytes` by
/// [`shape_bytes`].
pub type ShapeCache = GenerationCache<TreeletShape>;

/// A shape's own bytes: the shape and its children.
fn own_bytes(shape: &TreeletShape) -> usize {
    size_of::<TreeletShape>() + shape.children.capacity() * size_of::<(TreeletId, Cell)>()
}

/// The bytes one cached shape costs: its children, the shape and its `Arc`, and the map entry
/// with the slack of a hash table at its usual load.
pub fn shape_bytes(shape: &TreeletShape) -> usize {
    own_bytes(shape) + ENTRY_BYTES
}

impl ShapeCache {
    /// A cache of at most `capacity` bytes by [`shape_bytes`] (0: nothing is kept, every lookup
    /// decodes).
    pub fn for_shapes(capacity: usize) -> ShapeCache {
        GenerationCache::new(capacity, own_bytes)
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

    /// The shape of treelet `id` of `scene` if the cache holds it, never read from the pool
    /// (counts nothing: [`GenerationCache::get`]).
    pub fn cached(&self, scene: &StoredScene, id: TreeletId) -> Option<Arc<TreeletShape>> {
        self.get(scene.generation, id)
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
