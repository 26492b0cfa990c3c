//! Synthetic octrees with exactly known answers for the traversal and renderer tests: a
//! treelet builder from leaf cells, slot buffers with patched child treelets (including a child
//! in a lower slot than its parent, i.e. a negative wrapping offset), and a brute-force ray
//! query over every voxel that needs no octree at all.
#![allow(dead_code)]

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};

use arbor_client_core::camera::SplitMix64;
use arbor_client_core::incore::{IncoreView, SceneFrame};
use arbor_client_core::traverse::{Lod, Ray};
use arbor_proto::treelet::NodePlace;
use arbor_proto::{Cell, Node, Treelet, TreeletHeader, TreeletId};
use glam::DVec3;

/// Builds one valid treelet of `n` records rooted at `root` whose leaves are `leaves` (cells
/// inside `root`, at any depth; a given cell with another given cell inside it is an inner
/// node). `refinable` maps leaf cells to the id of the treelet refining them. Runs
/// [`Treelet::validate`] and returns the places it found.
pub fn build_treelet(
    id: u32,
    root: Cell,
    leaves: &[Cell],
    refinable: &BTreeMap<Cell, u32>,
    n: u32,
    max_depth: u8,
) -> (Treelet, Vec<NodePlace>) {
    let mut all = BTreeSet::new();
    all.insert(root);
    for c in leaves.iter().chain(refinable.keys()) {
        assert!(root.contains(c), "{c:?} outside the root {root:?}");
        for d in root.depth..=c.depth {
            all.insert(c.ancestor(d));
        }
    }
    let children = |c: &Cell| -> Vec<u8> {
        if c.depth >= 31 {
            return Vec::new();
        }
        (0..8u8).filter(|&i| all.contains(&c.child(i))).collect()
    };
    // Breadth-first: a node's children are appended in child-index order as it is expanded.
    let mut order = vec![root];
    let mut queue = VecDeque::from([root]);
    let mut first = HashMap::new();
    while let Some(c) = queue.pop_front() {
        let ch = children(&c);
        if !ch.is_empty() {
            first.insert(c, order.len() as u32);
        }
        for i in ch {
            order.push(c.child(i));
            queue.push_back(c.child(i));
        }
    }
    assert!(
        order.len() <= n as usize,
        "{} nodes do not fit in {n}",
        order.len()
    );
    let mut nodes = vec![Node::default(); n as usize];
    for (k, c) in order.iter().enumerate() {
        let ch = children(c);
        nodes[k] = if ch.is_empty() {
            Node::leaf(refinable.get(c).copied().unwrap_or(Node::NONE))
        } else {
            let mut valid = 0u8;
            let mut leaf = 0u8;
            for i in ch {
                valid |= 1 << i;
                if children(&c.child(i)).is_empty() {
                    leaf |= 1 << i;
                }
            }
            Node {
                first_child: first[c] - k as u32,
                valid_mask: valid,
                leaf_mask: leaf,
                spare: 0,
            }
        };
    }
    let header = TreeletHeader {
        id: TreeletId(id),
        parent_id: if id == 0 {
            TreeletId::NONE
        } else {
            TreeletId(0)
        },
        parent_leaf_index: 0,
        parent_leaf_parent_index: 0,
        child_index_in_parent: 0,
        root_depth: root.depth,
        root_cell: [root.x, root.y, root.z],
        used_nodes: order.len() as u16,
    };
    let t = Treelet { header, nodes };
    let places = t
        .validate(max_depth)
        .unwrap_or_else(|e| panic!("synthetic treelet invalid: {e}"));
    (t, places)
}

/// A slot buffer: `slots × n` records plus per-node colours.
#[derive(Clone, Debug)]
pub struct Buffer {
    pub n: u32,
    pub nodes: Vec<Node>,
    pub color: Option<Vec<u8>>,
    /// Places of the treelet in each slot (empty for free slots).
    pub places: Vec<Vec<NodePlace>>,
}

impl Buffer {
    pub fn new(n: u32, slots: u32) -> Self {
        Buffer {
            n,
            nodes: vec![Node::default(); (n * slots) as usize],
            color: None,
            places: vec![Vec::new(); slots as usize],
        }
    }

    /// Copies a treelet into `slot` unchanged (relative offsets make it position-independent).
    pub fn put(&mut self, slot: u32, t: &Treelet, places: Vec<NodePlace>) {
        let s = (slot * self.n) as usize;
        self.nodes[s..s + self.n as usize].copy_from_slice(&t.nodes);
        self.places[slot as usize] = places;
    }

    /// Patches the refinable leaf `leaf` of the treelet in `parent_slot` with the root of the
    /// treelet in `child_slot` (docs/design.md §5): the leaf record becomes the child root with
    /// `first_child = (child_slot·N + 1) − leaf_global` (wrapping), and the leaf bit in the
    /// leaf's parent's `leaf_mask` is cleared.
    pub fn patch(&mut self, parent_slot: u32, leaf: Cell, child_slot: u32) {
        let places = &self.places[parent_slot as usize];
        let li = places
            .iter()
            .position(|p| p.cell == leaf)
            .unwrap_or_else(|| panic!("{leaf:?} not in slot {parent_slot}"));
        let p = places[li];
        assert!(p.is_leaf && li > 0);
        let g = parent_slot * self.n + li as u32;
        let root = self.nodes[(child_slot * self.n) as usize];
        assert!(!root.is_leaf());
        self.nodes[g as usize] = Node {
            first_child: (child_slot * self.n + 1).wrapping_sub(g),
            ..root
        };
        let pg = (parent_slot * self.n + p.parent) as usize;
        self.nodes[pg].leaf_mask &= !(1 << p.child_index);
    }

    /// Gives every used record (global index `g`) the colour `f(cell)`.
    pub fn paint(&mut self, f: impl Fn(Cell) -> [u8; 3]) {
        let mut color = vec![0u8; self.nodes.len() * 3];
        for (s, places) in self.places.iter().enumerate() {
            for (k, p) in places.iter().enumerate() {
                let g = s * self.n as usize + k;
                color[g * 3..g * 3 + 3].copy_from_slice(&f(p.cell));
            }
        }
        // A patched leaf record shows the child root's cell, which is the same cell.
        self.color = Some(color);
    }

    pub fn view(&self) -> IncoreView<'_> {
        IncoreView {
            nodes: &self.nodes,
            treelet_nodes: self.n,
            color: self.color.as_deref(),
            normal: None,
            density: None,
        }
    }
}

/// Three treelets in three slots: the root in slot 0 with child A in slot 2, and A's child B in
/// slot 1, *before* its parent's slot, so the offset patched into A wraps (negative).
#[derive(Clone, Debug)]
pub struct LowerSlotChain {
    pub buffer: Buffer,
    /// The root's leaves: A's cell first, then `refinable` refinable leaves naming treelets 10,
    /// 11, … (not resident), then plain leaves.
    pub root_leaves: Vec<Cell>,
    pub a_cell: Cell,
    /// A's leaves: B's cell first, then plain leaves.
    pub a_leaves: Vec<Cell>,
    pub b_cell: Cell,
    pub b_leaves: Vec<Cell>,
}

/// A [`LowerSlotChain`] of `n`-record treelets with random leaves from `rng`: 16 at depth 2
/// for the root, 30 three levels below A's cell for A, 40 three below B's for B.
pub fn lower_slot_chain(rng: &mut Rng, n: u32, max_depth: u8, refinable: usize) -> LowerSlotChain {
    let root_leaves = random_cells(rng, 2, 16);
    let a_cell = root_leaves[0];
    let named: BTreeMap<Cell, u32> = root_leaves[1..=refinable]
        .iter()
        .enumerate()
        .map(|(i, &c)| (c, 10 + i as u32))
        .chain([(a_cell, 1u32)])
        .collect();
    let (t0, p0) = build_treelet(
        0,
        Cell::ROOT,
        &root_leaves[1 + refinable..],
        &named,
        n,
        max_depth,
    );
    let a_leaves: Vec<Cell> = random_cells(rng, 3, 30)
        .into_iter()
        .map(|c| under(a_cell, c))
        .collect();
    let b_cell = a_leaves[0];
    let (ta, pa) = build_treelet(
        1,
        a_cell,
        &a_leaves[1..],
        &BTreeMap::from([(b_cell, 2u32)]),
        n,
        max_depth,
    );
    let b_leaves: Vec<Cell> = random_cells(rng, 3, 40)
        .into_iter()
        .map(|c| under(b_cell, c))
        .collect();
    let (tb, pb) = build_treelet(2, b_cell, &b_leaves, &BTreeMap::new(), n, max_depth);
    let mut buffer = Buffer::new(n, 3);
    buffer.put(0, &t0, p0);
    buffer.put(2, &ta, pa);
    buffer.put(1, &tb, pb);
    buffer.patch(0, a_cell, 2);
    buffer.patch(2, b_cell, 1);
    LowerSlotChain {
        buffer,
        root_leaves,
        a_cell,
        a_leaves,
        b_cell,
        b_leaves,
    }
}

/// The cell `rel` (relative to a unit cube) placed inside `root`.
pub fn under(root: Cell, rel: Cell) -> Cell {
    Cell {
        depth: root.depth + rel.depth,
        x: (root.x << rel.depth) | rel.x,
        y: (root.y << rel.depth) | rel.y,
        z: (root.z << rel.depth) | rel.z,
    }
}

/// A one-treelet scene from leaf cells (all inside the root cube).
pub fn single(leaves: &[Cell], n: u32, max_depth: u8) -> Buffer {
    single_refinable(leaves, &BTreeMap::new(), n, max_depth)
}

pub fn single_refinable(
    leaves: &[Cell],
    refinable: &BTreeMap<Cell, u32>,
    n: u32,
    max_depth: u8,
) -> Buffer {
    let (t, places) = build_treelet(0, Cell::ROOT, leaves, refinable, n, max_depth);
    let mut b = Buffer::new(n, 1);
    b.put(0, &t, places);
    b
}

/// Entry/exit of the closed box of `cell` along `ray`, computed directly in camera-relative
/// f64: `lo = (origin − ray.origin) + c·size`, `hi = (origin − ray.origin) + (c+1)·size`.
/// `None` on a miss.
pub fn box_hit(frame: &SceneFrame, cell: Cell, ray: &Ray) -> Option<(f64, f64)> {
    let size = frame.edge / 2f64.powi(i32::from(cell.depth));
    let o = ray.origin.to_array();
    let d = ray.dir.to_array();
    let c = [cell.x, cell.y, cell.z];
    let mut t0 = f64::NEG_INFINITY;
    let mut t1 = f64::INFINITY;
    for a in 0..3 {
        let rel = frame.origin[a] - o[a];
        let lo = rel + f64::from(c[a]) * size;
        let hi = rel + (f64::from(c[a]) + 1.0) * size;
        if d[a] == 0.0 {
            if lo > 0.0 || hi < 0.0 {
                return None;
            }
        } else {
            let (x, y) = (lo / d[a], hi / d[a]);
            t0 = t0.max(x.min(y));
            t1 = t1.min(x.max(y));
        }
    }
    (t0 <= t1 && t1 >= 0.0).then_some((t0, t1))
}

/// The tree of a set of resident leaves: every leaf and all its ancestors.
#[derive(Clone, Debug)]
pub struct Reference {
    pub nodes: BTreeSet<Cell>,
    pub leaves: BTreeSet<Cell>,
}

impl Reference {
    pub fn new(leaves: impl IntoIterator<Item = Cell>) -> Self {
        let leaves: BTreeSet<Cell> = leaves.into_iter().collect();
        let mut nodes = BTreeSet::new();
        for c in &leaves {
            for d in 0..=c.depth {
                nodes.insert(c.ancestor(d));
            }
        }
        for c in &leaves {
            assert!(
                (0..8).all(|i| c.depth == 31 || !nodes.contains(&c.child(i))),
                "leaf {c:?} has descendants"
            );
        }
        Reference { nodes, leaves }
    }

    /// Brute force: the smallest `max(t_enter, 0)` over every terminal voxel, with all voxels
    /// tied at it. A voxel is terminal when it is hit and stops (leaf, depth limit, or projects
    /// to at most `pixel_angle · lod_bias · t`) and no ancestor is hit and stops.
    pub fn query(&self, frame: &SceneFrame, ray: &Ray, lod: &Lod) -> Option<(f64, Vec<Cell>)> {
        self.query_past(frame, ray, lod, &[])
    }

    /// [`Reference::query`] with the voxels `skip` taken as empty: they stop the descent to
    /// their descendants but are no hit.
    pub fn query_past(
        &self,
        frame: &SceneFrame,
        ray: &Ray,
        lod: &Lod,
        skip: &[Cell],
    ) -> Option<(f64, Vec<Cell>)> {
        let max_depth = lod.max_depth.min(31);
        let mut blocked = HashMap::new();
        let mut best: Option<(f64, Vec<Cell>)> = None;
        // BTreeSet order is by depth first, so parents come before children.
        for &c in &self.nodes {
            if c.depth > max_depth {
                continue;
            }
            let parent_blocked = c
                .parent()
                .map(|(p, _)| blocked.get(&p).copied().unwrap_or(false))
                .unwrap_or(false);
            if parent_blocked {
                blocked.insert(c, true);
                continue;
            }
            let Some((t0, _)) = box_hit(frame, c, ray) else {
                blocked.insert(c, false);
                continue;
            };
            let t = t0.max(0.0);
            let size = frame.edge / 2f64.powi(i32::from(c.depth));
            let stops = self.leaves.contains(&c)
                || c.depth == max_depth
                || (lod.pixel_angle > 0.0 && size <= t * lod.pixel_angle * lod.lod_bias);
            blocked.insert(c, stops);
            if !stops || skip.contains(&c) {
                continue;
            }
            match &mut best {
                Some((bt, cells)) if t == *bt => cells.push(c),
                Some((bt, _)) if t > *bt => {}
                _ => best = Some((t, vec![c])),
            }
        }
        best
    }
}

/// Deterministic random numbers for the tests.
pub struct Rng(pub SplitMix64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(SplitMix64::new(seed))
    }
    pub fn f(&mut self) -> f64 {
        self.0.next_f64()
    }
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.f()
    }
    pub fn below(&mut self, n: u64) -> u64 {
        self.0.next_u64() % n
    }
    pub fn unit(&mut self) -> DVec3 {
        let z = self.range(-1.0, 1.0);
        let phi = self.range(0.0, std::f64::consts::TAU);
        let r = (1.0 - z * z).sqrt();
        DVec3::new(r * phi.cos(), r * phi.sin(), z)
    }
    pub fn point_in(&mut self, frame: &SceneFrame, margin: f64) -> DVec3 {
        let e = frame.edge;
        DVec3::new(
            frame.origin[0] + self.range(-margin, 1.0 + margin) * e,
            frame.origin[1] + self.range(-margin, 1.0 + margin) * e,
            frame.origin[2] + self.range(-margin, 1.0 + margin) * e,
        )
    }
}

/// `count` distinct random cells at `depth`.
pub fn random_cells(rng: &mut Rng, depth: u8, count: usize) -> Vec<Cell> {
    let side = 1u64 << depth;
    let mut set = BTreeSet::new();
    while set.len() < count {
        set.insert(Cell {
            depth,
            x: rng.below(side) as u32,
            y: rng.below(side) as u32,
            z: rng.below(side) as u32,
        });
    }
    set.into_iter().collect()
}
