//! Fixed-size treelets: `N` node records in breadth-first order, root at 0 (docs/design.md §2).

use std::fmt;

use serde::{Deserialize, Serialize};

use crate::cell::Cell;
use crate::error::ProtoError;
use crate::limits::{MAX_DEPTH, MAX_TREELET_BYTES, MIN_TREELET_BYTES, NODE_BYTES};
use crate::node::Node;

/// Global id of a treelet within its scene. The root treelet is 0; every child has a higher id
/// than its parent.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TreeletId(pub u32);

impl TreeletId {
    /// The root treelet of every scene.
    pub const ROOT: TreeletId = TreeletId(0);
    /// "No treelet" (a root's parent, a final leaf's subtreelet).
    pub const NONE: TreeletId = TreeletId(Node::NONE);

    /// This is [`TreeletId::NONE`].
    pub fn is_none(self) -> bool {
        self == Self::NONE
    }
}

impl fmt::Display for TreeletId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.is_none() {
            f.write_str("NONE")
        } else {
            write!(f, "{}", self.0)
        }
    }
}

/// Where a treelet sits: its own id, the leaf it refines, and its root voxel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TreeletHeader {
    /// The treelet's own id.
    pub id: TreeletId,
    /// [`TreeletId::NONE`] for the root treelet.
    pub parent_id: TreeletId,
    /// Local index of the refinable leaf in the parent treelet that this treelet replaces.
    pub parent_leaf_index: u16,
    /// Local index of that leaf's parent node in the parent treelet.
    pub parent_leaf_parent_index: u16,
    /// Child index (0..8) of the refined leaf within its parent node.
    pub child_index_in_parent: u8,
    /// Depth of the root voxel.
    pub root_depth: u8,
    /// Exact integer cell of the root voxel at `root_depth`.
    pub root_cell: [u32; 3],
    /// Node records in use (1..=N); records from here on are zero.
    pub used_nodes: u16,
}

impl TreeletHeader {
    /// The root voxel's cell.
    pub fn root_cell(&self) -> Cell {
        Cell {
            depth: self.root_depth,
            x: self.root_cell[0],
            y: self.root_cell[1],
            z: self.root_cell[2],
        }
    }
}

/// Node count `N` for a treelet size in bytes, checked against the limits.
pub fn nodes_for_bytes(treelet_bytes: u32) -> Result<u32, ProtoError> {
    if !(MIN_TREELET_BYTES..=MAX_TREELET_BYTES).contains(&treelet_bytes)
        || !treelet_bytes.is_multiple_of(NODE_BYTES)
    {
        return Err(ProtoError::OutOfRange {
            what: "treelet size",
            detail: format!(
                "{treelet_bytes} bytes; must be a multiple of {NODE_BYTES} in {MIN_TREELET_BYTES}..={MAX_TREELET_BYTES}"
            ),
        });
    }
    Ok(treelet_bytes / NODE_BYTES)
}

/// One treelet: header plus exactly `N` node records.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Treelet {
    /// Where the treelet sits.
    pub header: TreeletHeader,
    /// Exactly `N` records, breadth-first, root at 0.
    pub nodes: Vec<Node>,
}

/// One node's place, as found by walking a treelet from its root.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NodePlace {
    /// The node's voxel.
    pub cell: Cell,
    /// Local index of the parent node; `u32::MAX` for the root.
    pub parent: u32,
    /// Child index within the parent (0 for the root).
    pub child_index: u8,
    /// Whether the parent's `leaf_mask` marks this node as a leaf (the root: `valid_mask == 0`).
    pub is_leaf: bool,
}

impl Treelet {
    /// Capacity `N`.
    pub fn capacity(&self) -> u32 {
        self.nodes.len() as u32
    }

    /// The used node records.
    pub fn used(&self) -> &[Node] {
        &self.nodes[..usize::from(self.header.used_nodes)]
    }

    /// Checks that the node records form a well-formed tree: masks consistent, offsets in range,
    /// children contiguous in child-index order and in breadth-first order, every used node
    /// reached exactly once, unused records zero, no voxel deeper than `max_depth`, final-depth
    /// voxels are final leaves. Returns every node's place, indexed by local index.
    pub fn validate(&self, max_depth: u8) -> Result<Vec<NodePlace>, ProtoError> {
        let id = self.header.id;
        let bad = |node: u32, detail: String| ProtoError::MalformedTreelet { id, node, detail };
        let used = u32::from(self.header.used_nodes);
        if used == 0 || used > self.capacity() {
            return Err(bad(
                0,
                format!("used_nodes {used} not in 1..={}", self.capacity()),
            ));
        }
        if let Some(k) = self.nodes[used as usize..]
            .iter()
            .position(|n| *n != Node::default())
        {
            return Err(bad(used + k as u32, "unused record is not zero".into()));
        }
        let root = self.header.root_cell();
        if !root.is_valid() || root.depth > max_depth || max_depth > MAX_DEPTH {
            return Err(bad(
                0,
                format!("root cell {root:?} invalid for depth {max_depth}"),
            ));
        }
        // Breadth-first order: children are allocated in the order parents are expanded, so the
        // next expected child block starts right after the previous one, and `places` (pushed
        // in that order) always holds exactly the records reached so far: a record at or past
        // its end is not reachable from the root.
        let mut places = Vec::with_capacity(used as usize);
        places.push(NodePlace {
            cell: root,
            parent: u32::MAX,
            child_index: 0,
            is_leaf: self.nodes[0].valid_mask == 0,
        });
        for i in 0..used {
            let Some(&place) = places.get(i as usize) else {
                return Err(bad(i, "not reachable from the root".into()));
            };
            let n = self.nodes[i as usize];
            if n.spare != 0 {
                return Err(bad(i, "spare bits set".into()));
            }
            if place.is_leaf {
                if n.valid_mask != 0 || n.leaf_mask != 0 {
                    return Err(bad(i, "leaf with child masks".into()));
                }
                if n.first_child != Node::NONE && place.cell.depth >= max_depth {
                    return Err(bad(i, "refinable leaf at the target depth".into()));
                }
                continue;
            }
            if n.valid_mask == 0 {
                return Err(bad(i, "inner node without children".into()));
            }
            if n.leaf_mask & !n.valid_mask != 0 {
                return Err(bad(i, "leaf_mask not a subset of valid_mask".into()));
            }
            if place.cell.depth >= max_depth {
                return Err(bad(
                    i,
                    format!("inner node at depth {} ≥ target", place.cell.depth),
                ));
            }
            let next_free = places.len() as u64;
            let start = u64::from(i) + u64::from(n.first_child);
            let count = n.child_count();
            if start != next_free || start + u64::from(count) > u64::from(used) {
                return Err(bad(
                    i,
                    format!(
                        "children at {start}..{} but expected block at {next_free} within {used}",
                        start + u64::from(count)
                    ),
                ));
            }
            // The set bits of the valid mask, lowest first: child index order.
            let mut mask = n.valid_mask;
            while mask != 0 {
                let ci = mask.trailing_zeros() as u8;
                mask &= mask - 1;
                let c = places.len() as u32;
                let is_leaf = n.leaf_mask & (1 << ci) != 0;
                if !is_leaf && self.nodes[c as usize].valid_mask == 0 {
                    return Err(bad(c, "inner child without children".into()));
                }
                places.push(NodePlace {
                    cell: place.cell.child(ci),
                    parent: i,
                    child_index: ci,
                    is_leaf,
                });
            }
        }
        if places.len() as u32 != used {
            return Err(bad(
                places.len() as u32,
                format!("{} records used but only {} reachable", used, places.len()),
            ));
        }
        Ok(places)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The validation walk written the plain way, as a reference: a slot per record, filled as
    /// parents are expanded, every rule checked in the same order as [`Treelet::validate`].
    fn reference_places(t: &Treelet, max_depth: u8) -> Result<Vec<NodePlace>, ProtoError> {
        let id = t.header.id;
        let bad = |node: u32, detail: String| ProtoError::MalformedTreelet { id, node, detail };
        let used = u32::from(t.header.used_nodes);
        if used == 0 || used > t.capacity() {
            return Err(bad(
                0,
                format!("used_nodes {used} not in 1..={}", t.capacity()),
            ));
        }
        if let Some(k) = (used..t.capacity()).find(|&k| t.nodes[k as usize] != Node::default()) {
            return Err(bad(k, "unused record is not zero".into()));
        }
        let root = t.header.root_cell();
        if !root.is_valid() || root.depth > max_depth || max_depth > MAX_DEPTH {
            return Err(bad(
                0,
                format!("root cell {root:?} invalid for depth {max_depth}"),
            ));
        }
        let mut places = vec![None::<NodePlace>; used as usize];
        places[0] = Some(NodePlace {
            cell: root,
            parent: u32::MAX,
            child_index: 0,
            is_leaf: t.nodes[0].valid_mask == 0,
        });
        let mut next_free = 1u32;
        for i in 0..used {
            let Some(place) = places[i as usize] else {
                return Err(bad(i, "not reachable from the root".into()));
            };
            let n = t.nodes[i as usize];
            if n.spare != 0 {
                return Err(bad(i, "spare bits set".into()));
            }
            if place.is_leaf {
                if n.valid_mask != 0 || n.leaf_mask != 0 {
                    return Err(bad(i, "leaf with child masks".into()));
                }
                if n.first_child != Node::NONE && place.cell.depth >= max_depth {
                    return Err(bad(i, "refinable leaf at the target depth".into()));
                }
                continue;
            }
            if n.valid_mask == 0 {
                return Err(bad(i, "inner node without children".into()));
            }
            if n.leaf_mask & !n.valid_mask != 0 {
                return Err(bad(i, "leaf_mask not a subset of valid_mask".into()));
            }
            if place.cell.depth >= max_depth {
                return Err(bad(
                    i,
                    format!("inner node at depth {} ≥ target", place.cell.depth),
                ));
            }
            let start = u64::from(i) + u64::from(n.first_child);
            let count = u64::from(n.child_count());
            if start != u64::from(next_free) || start + count > u64::from(used) {
                return Err(bad(
                    i,
                    format!(
                        "children at {start}..{} but expected block at {next_free} within {used}",
                        start + count
                    ),
                ));
            }
            for (k, ci) in (0u8..8)
                .filter(|ci| n.valid_mask & (1 << ci) != 0)
                .enumerate()
            {
                let c = start as u32 + k as u32;
                let is_leaf = n.leaf_mask & (1 << ci) != 0;
                if !is_leaf && t.nodes[c as usize].valid_mask == 0 {
                    return Err(bad(c, "inner child without children".into()));
                }
                places[c as usize] = Some(NodePlace {
                    cell: place.cell.child(ci),
                    parent: i,
                    child_index: ci,
                    is_leaf,
                });
            }
            next_free += count as u32;
        }
        if next_free != used {
            return Err(bad(
                next_free,
                format!("{used} records used but only {next_free} reachable"),
            ));
        }
        Ok(places.into_iter().map(Option::unwrap).collect())
    }

    /// A well-formed treelet of `capacity` records grown breadth-first from `bytes`: each inner
    /// node takes its masks from the next bytes, while records and depth last.
    fn grown(bytes: &[u8], capacity: usize, root_depth: u8, max_depth: u8) -> Treelet {
        let mut nodes = vec![Node::default(); capacity];
        let mut take = bytes.iter().copied().cycle();
        // (index, depth, is_leaf, parent and child index)
        let mut queue =
            std::collections::VecDeque::from([(0usize, root_depth, false, None::<(usize, u8)>)]);
        let mut used = 1usize;
        while let Some((i, depth, is_leaf, parent)) = queue.pop_front() {
            let valid = take.next().unwrap_or(1) | 1;
            if is_leaf || depth >= max_depth || used + valid.count_ones() as usize > capacity {
                // Planned as an inner node but out of records or depth: its parent says leaf.
                if let Some((p, ci)) = parent {
                    nodes[p].leaf_mask |= 1u8 << ci;
                }
                let refines = take.next().unwrap_or(0) % 3 == 0 && depth < max_depth;
                nodes[i] = Node::leaf(if refines { 100 + i as u32 } else { Node::NONE });
                continue;
            }
            let leaves = take.next().unwrap_or(0) & valid;
            nodes[i] = Node {
                first_child: (used - i) as u32,
                valid_mask: valid,
                leaf_mask: leaves,
                spare: 0,
            };
            for ci in (0u8..8).filter(|ci| valid & (1 << ci) != 0) {
                queue.push_back((used, depth + 1, leaves & (1 << ci) != 0, Some((i, ci))));
                used += 1;
            }
        }
        Treelet {
            header: TreeletHeader {
                id: TreeletId(9),
                parent_id: TreeletId(1),
                parent_leaf_index: 0,
                parent_leaf_parent_index: 0,
                child_index_in_parent: 0,
                root_depth,
                root_cell: [1, 0, (1u32 << root_depth) - 1],
                used_nodes: used as u16,
            },
            nodes,
        }
    }

    #[test]
    fn grown_treelets_are_well_formed() {
        for seed in 0..200u8 {
            let bytes: Vec<u8> = (0..64u8)
                .map(|k| seed.wrapping_mul(37) ^ k.wrapping_mul(11))
                .collect();
            let t = grown(&bytes, 64, 2, 9);
            let places = t.validate(9).unwrap();
            assert_eq!(places.len(), usize::from(t.header.used_nodes));
            assert_eq!(places, reference_places(&t, 9).unwrap());
        }
    }

    proptest! {
        /// Any record or count of a well-formed treelet changed: the walk accepts and rejects
        /// exactly as the reference does, with the same places or the same error.
        #[test]
        fn validation_agrees_with_the_reference_walk(
            bytes in proptest::collection::vec(any::<u8>(), 1..64),
            capacity in 1usize..96,
            root_depth in 1u8..6,
            extra_depth in 0u8..6,
            edits in proptest::collection::vec((any::<u16>(), 0u8..5, any::<u32>()), 0..4),
            used_delta in prop_oneof![6 => Just(0i32), 1 => -2i32..0, 1 => 1i32..3],
            max_depth_delta in prop_oneof![4 => Just(0i32), 1 => -2i32..2],
        ) {
            let max_depth = root_depth + extra_depth;
            let mut t = grown(&bytes, capacity, root_depth, max_depth);
            // Mostly used records, and now and then the first unused one.
            let editable = (usize::from(t.header.used_nodes) + 1).min(capacity);
            for (at, field, value) in edits {
                let n = &mut t.nodes[usize::from(at) % editable];
                match field {
                    0 => n.first_child = value,
                    1 => n.first_child = n.first_child.wrapping_add(value % 3).wrapping_sub(1),
                    2 => n.valid_mask ^= value as u8,
                    3 => n.leaf_mask ^= value as u8,
                    _ => n.spare = value as u16 & 1,
                }
            }
            t.header.used_nodes =
                (i32::from(t.header.used_nodes) + used_delta).clamp(0, capacity as i32) as u16;
            let max_depth = (i32::from(max_depth) + max_depth_delta).clamp(0, 63) as u8;
            prop_assert_eq!(t.validate(max_depth), reference_places(&t, max_depth));
        }
    }
}
