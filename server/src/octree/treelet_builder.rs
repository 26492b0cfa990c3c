//! Filling one treelet breadth-first (docs/design.md §3 step 2), shared by every input kind.
//!
//! The input kinds differ only in *which primitives touch which child voxel*; that is the
//! [`TreeletBuilder`] trait. The fill itself — a queue of pending nodes, dropping empty children,
//! looking for a queued split that still fits when fewer than 8 records are free, stopping at the
//! target depth — is [`fill_treelet`].

use std::collections::VecDeque;
use std::ops::Range;

use arbor_proto::{Cell, Node, Treelet, TreeletHeader, TreeletId};

use super::idlist::{IdList, ListWriter, Lists};

/// Leaf attributes of a voxel touched by more primitives than this are computed from the first
/// this many (an unbiased enough sample for a mean, and a bound on memory for degenerate inputs
/// such as millions of identical points).
const MAX_LEAF_SAMPLE: usize = 1 << 20;

/// Most primitives one build can index: primitive ids are `u32` (`0..count`), which keeps the
/// id lists — the bulk of a build's memory — at 4 bytes a primitive.
pub const MAX_PRIMITIVES: u64 = u32::MAX as u64;

/// Classifies primitives against voxels. Implemented per input kind.
pub trait TreeletBuilder: Sync {
    /// Number of primitives; ids are `0..count`. A 64-bit count, so that a source past
    /// [`MAX_PRIMITIVES`] is refused by the build instead of wrapping.
    fn primitive_count(&self) -> u64;
    /// Bit `i` set when primitive `prim`, known to touch `cell`, touches child `i` of `cell`.
    fn child_mask(&self, prim: u32, cell: Cell) -> u8;

    /// For builders whose primitives are sorted so that every cell's primitives are one id range
    /// (points sorted by leaf cell): the ranges of `cell`'s eight children within `range`.
    /// `None` (the default): primitives are partitioned one by one.
    fn split_range(&self, _cell: Cell, _range: Range<u32>) -> Option<[Range<u32>; 8]> {
        None
    }

    /// For builders that split ranges: the exact number of nodes strictly below `cell` down to
    /// `max_depth` for its primitive `range`, `Some(None)` once it exceeds `limit` (what the
    /// packing dry run needs, without partitioning). `None` (the default): not supported.
    fn range_subtree_size(
        &self,
        _cell: Cell,
        _range: Range<u32>,
        _max_depth: u8,
        _limit: u64,
    ) -> Option<Option<u64>> {
        None
    }
}

/// Computes leaf attributes from the primitives touching a leaf voxel. Implemented per input kind.
pub trait AttributeGenerator: Sync {
    /// Bytes per voxel over all channels of the layout, channels concatenated in layout order.
    fn bytes_per_voxel(&self) -> usize;
    /// Writes the attributes of a final leaf voxel.
    fn leaf(&self, cell: Cell, prims: &[u32], out: &mut [u8]);

    /// [`AttributeGenerator::leaf`] for primitives given as an id range (range-splitting
    /// builders); the default lists the ids.
    fn leaf_range(&self, cell: Cell, prims: Range<u32>, out: &mut [u8]) {
        let ids: Vec<u32> = prims.collect();
        self.leaf(cell, &ids, out);
    }
}

/// Exact number of nodes strictly below `cell` down to `max_depth`, or `None` once it exceeds
/// `limit` (the dry run stops there, so its cost is bounded by `limit` node splits).
fn subtree_size(
    builder: &dyn TreeletBuilder,
    cell: Cell,
    prims: &[u32],
    max_depth: u8,
    limit: u64,
) -> Option<u64> {
    let mut count = 0u64;
    let mut stack: Vec<(Cell, Vec<u32>)> = Vec::new();
    let first = partition(builder, cell, prims);
    for (i, list) in first.into_iter().enumerate() {
        if !list.is_empty() {
            stack.push((cell.child(i as u8), list));
        }
    }
    while let Some((c, list)) = stack.pop() {
        count += 1;
        if count > limit {
            return None;
        }
        if c.depth >= max_depth {
            continue;
        }
        for (i, l) in partition(builder, c, &list).into_iter().enumerate() {
            if !l.is_empty() {
                stack.push((c.child(i as u8), l));
            }
        }
    }
    Some(count)
}

/// A job: fill the treelet whose root voxel is `root` with the primitives touching it.
#[derive(Debug)]
pub struct TreeletJob {
    pub id: TreeletId,
    pub parent_id: TreeletId,
    pub parent_leaf_index: u16,
    pub parent_leaf_parent_index: u16,
    pub child_index_in_parent: u8,
    pub root: Cell,
    pub prims: IdList,
}

/// A refinable leaf left for a child treelet; `first_child` is patched once its id is known.
#[derive(Debug)]
pub struct PendingLeaf {
    pub local_index: u16,
    pub parent_local_index: u16,
    pub child_index: u8,
    pub cell: Cell,
    pub prims: IdList,
}

/// A filled treelet: nodes, leaf attributes (inner and refinable leaves still zero) and the
/// refinable leaves that need child treelets.
#[derive(Debug)]
pub struct FilledTreelet {
    pub treelet: Treelet,
    /// `capacity × bytes_per_voxel`, node `k` at `k × bytes_per_voxel`.
    pub attributes: Vec<u8>,
    pub pending: Vec<PendingLeaf>,
    /// Final leaves at the target depth.
    pub leaf_voxels: u64,
}

struct Pending {
    /// Space for this node's whole subtree is reserved in the treelet.
    included: bool,
    local: u32,
    parent: u32,
    child_index: u8,
    cell: Cell,
    prims: IdList,
}

/// Partitions `prims` of `cell` into its 8 children, keeping the lists within the budget.
fn partition_list(
    b: &dyn TreeletBuilder,
    cell: Cell,
    prims: &IdList,
    lists: &Lists,
) -> std::io::Result<[IdList; 8]> {
    if let IdList::Range(r) = prims
        && let Some(children) = b.split_range(cell, r.clone())
    {
        return Ok(children.map(IdList::Range));
    }
    let mut out: [ListWriter; 8] = std::array::from_fn(|_| ListWriter::new(lists));
    prims.for_each_chunk(|chunk| {
        for &p in chunk {
            let mut m = b.child_mask(p, cell);
            while m != 0 {
                let i = m.trailing_zeros() as usize;
                out[i].push(p);
                m &= m - 1;
            }
        }
    })?;
    let mut lists_out = Vec::with_capacity(8);
    for w in out {
        lists_out.push(w.finish()?);
    }
    Ok(lists_out.try_into().expect("eight lists"))
}

/// Partitions an in-memory slice (the bounded dry run of [`subtree_size`]).
fn partition(b: &dyn TreeletBuilder, cell: Cell, prims: &[u32]) -> [Vec<u32>; 8] {
    let mut out: [Vec<u32>; 8] = Default::default();
    for &p in prims {
        let mut m = b.child_mask(p, cell);
        while m != 0 {
            let i = m.trailing_zeros() as usize;
            out[i].push(p);
            m &= m - 1;
        }
    }
    out
}

/// Fills one treelet of `capacity` records from `job`, never deeper than `max_depth`.
pub fn fill_treelet(
    builder: &dyn TreeletBuilder,
    attributes: &dyn AttributeGenerator,
    job: TreeletJob,
    capacity: u32,
    max_depth: u8,
    lists: &Lists,
) -> std::io::Result<FilledTreelet> {
    let bpv = attributes.bytes_per_voxel();
    let mut fill = TreeletFill {
        builder,
        attributes,
        lists,
        capacity,
        max_depth,
        bpv,
        nodes: vec![Node::default(); capacity as usize],
        attrs: vec![0u8; capacity as usize * bpv],
        pending_leaves: Vec::new(),
        leaf_voxels: 0,
        used: 1,
        reserved: 0,
        queue: VecDeque::new(),
    };
    fill.queue.push_back(Pending {
        included: false,
        local: 0,
        parent: u32::MAX,
        child_index: 0,
        cell: job.root,
        prims: job.prims,
    });
    while let Some(p) = fill.queue.pop_front() {
        fill.expand(p)?;
    }
    let treelet = Treelet {
        header: TreeletHeader {
            id: job.id,
            parent_id: job.parent_id,
            parent_leaf_index: job.parent_leaf_index,
            parent_leaf_parent_index: job.parent_leaf_parent_index,
            child_index_in_parent: job.child_index_in_parent,
            root_depth: job.root.depth,
            root_cell: [job.root.x, job.root.y, job.root.z],
            used_nodes: fill.used as u16,
        },
        nodes: fill.nodes,
    };
    Ok(FilledTreelet {
        treelet,
        attributes: fill.attrs,
        pending: fill.pending_leaves,
        leaf_voxels: fill.leaf_voxels,
    })
}

/// One treelet being filled breadth-first.
struct TreeletFill<'a> {
    builder: &'a dyn TreeletBuilder,
    attributes: &'a dyn AttributeGenerator,
    lists: &'a Lists,
    capacity: u32,
    max_depth: u8,
    /// Attribute bytes per voxel.
    bpv: usize,
    nodes: Vec<Node>,
    attrs: Vec<u8>,
    pending_leaves: Vec<PendingLeaf>,
    leaf_voxels: u64,
    /// Records in use.
    used: u32,
    /// Records promised to included subtrees not expanded yet.
    reserved: u32,
    queue: VecDeque<Pending>,
}

impl TreeletFill<'_> {
    /// Decides what node `p` becomes: a final leaf, a refinable leaf, or an inner node whose
    /// children are queued.
    fn expand(&mut self, p: Pending) -> std::io::Result<()> {
        if p.cell.depth >= self.max_depth {
            self.final_leaf(&p)?;
            self.leaf_voxels += 1;
            return Ok(());
        }
        let (included, room) = self.room_for(&p)?;
        // A split needs at least one free record; without any the node is a refinable leaf.
        if room == 0 {
            self.refinable_leaf(p);
            return Ok(());
        }
        let children = partition_list(self.builder, p.cell, &p.prims, self.lists)?;
        let count = children.iter().filter(|l| !l.is_empty()).count() as u32;
        if count == 0 {
            // Rounding left no child touched: the voxel is final at this depth.
            return self.final_leaf(&p);
        }
        if count > room {
            // Does not fit: a refinable leaf, refined by a child treelet.
            self.refinable_leaf(p);
            return Ok(());
        }
        if included {
            self.reserved = self.reserved.saturating_sub(count);
        }
        self.split(p, children, included);
        Ok(())
    }

    /// Packing (measured in ARCHITECTURE.md): a node whose whole subtree fits the unreserved
    /// space is kept entirely in this treelet and its space reserved, so small subtrees do not
    /// each become a nearly empty treelet of their own. A node whose subtree is smaller than a
    /// treelet but does not fit here is cut whole rather than split into small pieces. Returns
    /// whether `p`'s subtree is included and how many records its children may take.
    fn room_for(&mut self, p: &Pending) -> std::io::Result<(bool, u32)> {
        let free = self.capacity - self.used;
        let mut included = p.included;
        let mut cut = false;
        let limit = u64::from(self.capacity);
        let dry_run = !included && p.prims.len() <= 64 * limit;
        let by_range = match &p.prims {
            IdList::Range(r) if dry_run => {
                self.builder
                    .range_subtree_size(p.cell, r.clone(), self.max_depth, limit)
            }
            _ => None,
        };
        // Only lists of up to 64·N ids get the dry run (bounded work); a spilled one is read back
        // for it, so the result never depends on the memory budget.
        let small = if dry_run && by_range.is_none() {
            Some(match p.prims.as_slice() {
                Some(s) => std::borrow::Cow::Borrowed(s),
                None => std::borrow::Cow::Owned(p.prims.prefix(p.prims.len() as usize)?),
            })
        } else {
            None
        };
        let size = match (by_range, small) {
            (Some(s), _) => Some(s),
            (None, Some(prims)) => Some(subtree_size(
                self.builder,
                p.cell,
                &prims,
                self.max_depth,
                limit,
            )),
            (None, None) => None,
        };
        if let Some(size) = size {
            match size {
                Some(s) if s <= u64::from(free.saturating_sub(self.reserved)) => {
                    included = true;
                    self.reserved += s as u32;
                }
                Some(_) if p.local != 0 => cut = true,
                _ => {}
            }
        }
        let room = if cut {
            0
        } else if included {
            free
        } else {
            free.saturating_sub(self.reserved)
        };
        Ok((included, room))
    }

    /// Marks node `p.local` as a leaf in its parent's leaf_mask (the root has no parent; its
    /// leafness is its zero valid_mask).
    fn mark_leaf(&mut self, p: &Pending) {
        if p.parent != u32::MAX {
            self.nodes[p.parent as usize].leaf_mask |= 1 << p.child_index;
        }
    }

    /// A leaf with no more detail: its attributes come from the generator.
    fn final_leaf(&mut self, p: &Pending) -> std::io::Result<()> {
        self.nodes[p.local as usize] = Node::leaf(Node::NONE);
        self.mark_leaf(p);
        let k = p.local as usize * self.bpv;
        let out = &mut self.attrs[k..k + self.bpv];
        match (&p.prims, p.prims.as_slice()) {
            (IdList::Range(r), _) => {
                let end = r.end.min(r.start.saturating_add(MAX_LEAF_SAMPLE as u32));
                self.attributes.leaf_range(p.cell, r.start..end, out);
            }
            (_, Some(s)) => self
                .attributes
                .leaf(p.cell, &s[..s.len().min(MAX_LEAF_SAMPLE)], out),
            (_, None) => self
                .attributes
                .leaf(p.cell, &p.prims.prefix(MAX_LEAF_SAMPLE)?, out),
        }
        Ok(())
    }

    /// A leaf refined by a child treelet, built later from its primitives.
    fn refinable_leaf(&mut self, p: Pending) {
        self.nodes[p.local as usize] = Node::leaf(Node::NONE);
        self.mark_leaf(&p);
        self.pending_leaves.push(PendingLeaf {
            local_index: p.local as u16,
            parent_local_index: if p.parent == u32::MAX {
                0
            } else {
                p.parent as u16
            },
            child_index: p.child_index,
            cell: p.cell,
            prims: p.prims,
        });
    }

    /// An inner node: its touched children get consecutive records and are queued.
    fn split(&mut self, p: Pending, children: [IdList; 8], included: bool) {
        let mut valid = 0u8;
        let first = self.used;
        for (i, list) in children.into_iter().enumerate() {
            if list.is_empty() {
                continue;
            }
            valid |= 1 << i;
            self.queue.push_back(Pending {
                included,
                local: self.used,
                parent: p.local,
                child_index: i as u8,
                cell: p.cell.child(i as u8),
                prims: list,
            });
            self.used += 1;
        }
        self.nodes[p.local as usize] = Node {
            first_child: first - p.local,
            valid_mask: valid,
            leaf_mask: 0,
            spare: 0,
        };
    }
}
