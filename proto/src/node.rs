//! The 64-bit octree node record shared by Rust and WGSL.

use bytemuck::{Pod, Zeroable};

/// One octree node (docs/design.md §2). Identical layout in Rust and WGSL: two `u32` words.
///
/// * inner node: `first_child` is the offset of its first child *relative to the node's own
///   index*; children are contiguous, ordered by child index among the set bits of `valid_mask`.
/// * leaf: `first_child` is the [`TreeletId`](crate::TreeletId) refining it, or [`Node::NONE`]
///   when the data has no more detail; `valid_mask` and `leaf_mask` are zero.
///
/// `leaf_mask` bit `i` says child `i` is a leaf *in this buffer*. `spare` is unused and zero.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Pod, Zeroable)]
pub struct Node {
    /// Inner node: offset of the first child from this node's own index. Leaf: the refining
    /// treelet's id, or [`Node::NONE`].
    pub first_child: u32,
    /// Bit `i`: child `i` exists.
    pub valid_mask: u8,
    /// Bit `i`: child `i` is a leaf in this buffer.
    pub leaf_mask: u8,
    /// Must be zero.
    pub spare: u16,
}

const _: () = assert!(std::mem::size_of::<Node>() == 8);

impl Node {
    /// "No treelet": a final leaf's `first_child`, a root treelet's parent.
    pub const NONE: u32 = u32::MAX;

    /// A final leaf or, with `subtreelet != NONE`, a refinable leaf.
    pub const fn leaf(subtreelet: u32) -> Self {
        Self {
            first_child: subtreelet,
            valid_mask: 0,
            leaf_mask: 0,
            spare: 0,
        }
    }

    /// Whether this record has no children stored with it.
    pub const fn is_leaf(&self) -> bool {
        self.valid_mask == 0
    }

    /// Number of existing children.
    pub const fn child_count(&self) -> u32 {
        self.valid_mask.count_ones()
    }

    /// Position of child `child_index` among the stored children, if it exists.
    pub fn child_slot(&self, child_index: u8) -> Option<u32> {
        debug_assert!(child_index < 8);
        if self.valid_mask & (1 << child_index) == 0 {
            return None;
        }
        Some((self.valid_mask & ((1u8 << child_index) - 1)).count_ones())
    }

    /// Iterates `(child_index, position among children)` of the existing children.
    pub fn children(&self) -> impl Iterator<Item = (u8, u32)> + '_ {
        let mask = self.valid_mask;
        (0u8..8)
            .filter(move |i| mask & (1 << i) != 0)
            .enumerate()
            .map(|(k, i)| (i, k as u32))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn child_slots_follow_set_bits() {
        let n = Node {
            first_child: 1,
            valid_mask: 0b1010_0101,
            leaf_mask: 0,
            spare: 0,
        };
        assert_eq!(n.child_slot(0), Some(0));
        assert_eq!(n.child_slot(1), None);
        assert_eq!(n.child_slot(2), Some(1));
        assert_eq!(n.child_slot(5), Some(2));
        assert_eq!(n.child_slot(7), Some(3));
        let v: Vec<_> = n.children().collect();
        assert_eq!(v, vec![(0, 0), (2, 1), (5, 2), (7, 3)]);
        assert_eq!(n.child_count(), 4);
    }

    #[test]
    fn node_is_two_words() {
        let n = Node {
            first_child: 0x0102_0304,
            valid_mask: 5,
            leaf_mask: 6,
            spare: 0,
        };
        let words: [u32; 2] = bytemuck::cast(n);
        assert_eq!(words[0], 0x0102_0304);
        assert_eq!(words[1], 5 | (6 << 8));
    }
}
