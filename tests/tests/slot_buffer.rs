//! The slot buffer against a model, on real scans: random sequences of cycles, visibility marks
//! and inserts (orphans, duplicates and load limits included) at small capacities, checked after
//! every step against the original treelets only — never against the buffer's own bookkeeping —
//! plus fully resident buffers and the upload ranges of a realistic dirty pattern.

use std::sync::LazyLock;

use arbor_client_core::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig};
use arbor_client_core::upload::{DEFAULT_FILL_RATIO, UploadPlan, merge_ranges};
use arbor_proto::{Channel, Node, SceneDescription, TreeletId};
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_tests::support::{SCANS, build_file, decoded_treelets};
use proptest::prelude::*;
use proptest::sample::Index;

/// A real scan's treelets, decoded, with what the model needs of each.
struct Scan {
    name: &'static str,
    scene: SceneDescription,
    channels: Vec<Channel>,
    /// Indexed by treelet id (ids are 0..count).
    treelets: Vec<DecodedTreelet>,
    /// Per treelet, per used node: whether it is a leaf of its treelet.
    leaf: Vec<Vec<bool>>,
    /// Per treelet, the ids of its child treelets.
    children: Vec<Vec<u32>>,
}

impl Scan {
    fn load(name: &'static str) -> Scan {
        let rel = SCANS.iter().find(|(n, _)| *n == name).unwrap().1;
        let opts = BuildOptions {
            depth: DepthChoice::Fixed(7),
            treelet_bytes: 1024,
            ..BuildOptions::default()
        };
        let built = build_file(rel, name, &opts);
        let scene = built.scene.description.clone();
        let channels = scene.layout.channels().to_vec();
        let treelets = decoded_treelets(&built.scene);
        let leaf = treelets
            .iter()
            .map(|t| {
                let places = t.treelet.validate(scene.max_depth).unwrap();
                places.iter().map(|p| p.is_leaf).collect()
            })
            .collect();
        let mut children = vec![Vec::new(); treelets.len()];
        for t in &treelets[1..] {
            children[t.treelet.header.parent_id.0 as usize].push(t.treelet.header.id.0);
        }
        Scan {
            name,
            scene,
            channels,
            treelets,
            leaf,
            children,
        }
    }

    fn n(&self) -> u32 {
        self.scene.treelet_nodes
    }

    fn node(&self, id: u32, k: u32) -> Node {
        self.treelets[id as usize].treelet.nodes[k as usize]
    }

    fn is_leaf(&self, id: u32, k: u32) -> bool {
        self.leaf[id as usize][k as usize]
    }

    fn used(&self, id: u32) -> u32 {
        u32::from(self.treelets[id as usize].treelet.header.used_nodes)
    }

    fn parent(&self, id: u32) -> TreeletId {
        self.treelets[id as usize].treelet.header.parent_id
    }
}

static BUNNY: LazyLock<Scan> = LazyLock::new(|| Scan::load("bunny"));
static LION: LazyLock<Scan> = LazyLock::new(|| Scan::load("lion"));

fn scan(i: usize) -> &'static Scan {
    if i == 0 { &BUNNY } else { &LION }
}

/// The resident treelet refining leaf `k` of `id`, if any.
fn resident_sub(b: &SlotBuffer, s: &Scan, id: u32, k: u32) -> Option<u32> {
    let sub = s.node(id, k).first_child;
    (s.is_leaf(id, k) && sub != Node::NONE && b.is_resident(TreeletId(sub))).then_some(sub)
}

/// Where the children of node `k` of `id` are stored, following resident refinements: the
/// `(treelet, local index)` of the inner node whose records a traversal uses, or `None` if the
/// node is a leaf in the buffer.
fn stored(b: &SlotBuffer, s: &Scan, mut id: u32, mut k: u32) -> Option<(u32, u32)> {
    loop {
        if !s.is_leaf(id, k) {
            return Some((id, k));
        }
        (id, k) = (resident_sub(b, s, id, k)?, 0);
    }
}

/// The record the model expects at global index `g` for node `k` of treelet `id`: the original
/// record, with a resident refinement's root in place of a leaf (pointing at its node 1,
/// relative to `g`, when that root has children), and the leaf bits of refined children
/// cleared.
fn expected(b: &SlotBuffer, s: &Scan, id: u32, k: u32, g: u32) -> Node {
    let n = s.n();
    if let Some(sub) = resident_sub(b, s, id, k) {
        let mut r = expected(b, s, sub, 0, g);
        if s.node(sub, 0).valid_mask != 0 {
            r.first_child = (b.slot_of(TreeletId(sub)).unwrap() * n + 1).wrapping_sub(g);
        }
        return r;
    }
    let mut r = s.node(id, k);
    if !s.is_leaf(id, k) {
        let orig = s.node(id, k);
        for (ci, pos) in orig.children() {
            let j = k + orig.first_child + pos;
            if stored(b, s, id, j).is_some() {
                r.leaf_mask &= !(1 << ci);
            }
        }
    }
    r
}

/// Checks the buffer against the model; returns the number of nodes a traversal reaches.
fn check(b: &SlotBuffer, s: &Scan) -> u32 {
    let n = s.n();
    let cap = b.capacity();
    assert!(b.used_slots() <= cap);
    let mut resident = Vec::new();
    let mut free = 0;
    for slot in 0..cap {
        match b.treelet_in(slot) {
            Some(id) => {
                assert_eq!(b.slot_of(id), Some(slot), "slot_of/treelet_in disagree");
                resident.push(id.0);
            }
            None => free += 1,
        }
    }
    assert_eq!(resident.len() as u32, b.used_slots());
    assert_eq!(resident.len() as u32 + free, cap, "a slot leaked");
    assert_eq!(b.treelet_in(0), Some(TreeletId::ROOT));
    for &id in &resident {
        if id != 0 {
            let p = s.parent(id);
            let ps = b
                .slot_of(p)
                .unwrap_or_else(|| panic!("treelet {id}'s parent {p} gone"));
            assert_eq!(b.parent_slot(b.slot_of(TreeletId(id)).unwrap()), Some(ps));
        }
    }
    // Walk the view from global 0, the model alongside.
    let view = b.view();
    let mut seen = std::collections::HashSet::new();
    let root_leaf = view.nodes[0].valid_mask == 0;
    let mut stack = vec![(0u32, 0u32, 0u32, root_leaf)];
    while let Some((id, k, g, view_leaf)) = stack.pop() {
        assert!(seen.insert(g), "global {g} reached twice");
        let rec = view.nodes[g as usize];
        assert_eq!(
            rec,
            expected(b, s, id, k, g),
            "treelet {id} node {k} at {g}"
        );
        let inner = stored(b, s, id, k);
        assert_eq!(
            view_leaf,
            inner.is_none(),
            "leafness of treelet {id} node {k}"
        );
        let Some((sid, sk)) = inner else { continue };
        let slot = b.slot_of(TreeletId(sid)).unwrap();
        let base = g.wrapping_add(rec.first_child);
        let orig = s.node(sid, sk);
        for (ci, pos) in orig.children() {
            let j = sk + orig.first_child + pos;
            assert_eq!(
                base + pos,
                slot * n + j,
                "child {ci} of treelet {sid} node {sk}"
            );
            stack.push((sid, j, slot * n + j, rec.leaf_mask & (1 << ci) != 0));
        }
    }
    let want: u32 =
        resident.iter().map(|&id| s.used(id)).sum::<u32>() - (resident.len() as u32 - 1);
    assert_eq!(seen.len() as u32, want, "nodes reached");
    want
}

#[derive(Clone, Debug)]
enum Step {
    Cycle,
    /// Mark these resident slots visible, with their ancestors.
    Mark(Vec<Index>),
    /// Insert any treelet.
    Any(Index),
    /// Insert a child of a resident treelet (the useful case).
    Child(Index, Index),
}

fn step() -> impl Strategy<Value = Step> {
    prop_oneof![
        1 => Just(Step::Cycle),
        2 => prop::collection::vec(any::<Index>(), 0..6).prop_map(Step::Mark),
        2 => any::<Index>().prop_map(Step::Any),
        5 => (any::<Index>(), any::<Index>()).prop_map(|(a, b)| Step::Child(a, b)),
    ]
}

fn run(scan_index: usize, capacity: u32, load_limit: u32, visibility: u16, steps: &[Step]) {
    let s = scan(scan_index);
    let config = SlotConfig {
        budget_bytes: u64::from(capacity) * SlotBuffer::slot_bytes(s.n(), &s.channels),
        treelet_nodes: s.n(),
        channels: s.channels.clone(),
        visibility_max: visibility,
        load_limit,
    };
    let mut b = SlotBuffer::new(config.clone(), s.treelets[0].clone()).unwrap();
    // The same steps on a buffer whose arrays grow as slots fill (the server's visible cuts).
    let mut g = SlotBuffer::new_growing(config, s.treelets[0].clone()).unwrap();
    assert_eq!(b.capacity(), capacity);
    check(&b, s);
    same_records(&b, &g);
    let mut loaded = 0;
    for st in steps {
        let resident: Vec<u32> = (0..capacity)
            .filter(|&x| b.treelet_in(x).is_some())
            .collect();
        let id = match st {
            Step::Cycle => {
                b.begin_cycle();
                g.begin_cycle();
                loaded = 0;
                None
            }
            Step::Mark(picks) => {
                for p in picks {
                    let mut slot = Some(*p.get(&resident));
                    while let Some(x) = slot {
                        b.mark_visible(x);
                        g.mark_visible(x);
                        slot = b.parent_slot(x);
                    }
                }
                None
            }
            Step::Any(i) => Some(i.index(s.treelets.len()) as u32),
            Step::Child(a, c) => {
                let parent = b.treelet_in(*a.get(&resident)).unwrap().0;
                let kids = &s.children[parent as usize];
                (!kids.is_empty()).then(|| *c.get(kids))
            }
        };
        if let Some(id) = id {
            let was = b.is_resident(TreeletId(id));
            let parent_was = id == 0 || b.is_resident(s.parent(id));
            let used_before = b.used_slots();
            let ancestors: Vec<TreeletId> = std::iter::successors(Some(s.parent(id)), |p| {
                (!p.is_none()).then(|| s.parent(p.0))
            })
            .filter(|p| !p.is_none())
            .collect();
            let outcome = b.insert(s.treelets[id as usize].clone());
            assert_eq!(g.insert(&s.treelets[id as usize]), outcome);
            match outcome {
                InsertOutcome::LoadLimit => assert!(loaded >= load_limit),
                InsertOutcome::AlreadyResident => assert!(loaded < load_limit && was),
                InsertOutcome::ParentMissing => assert!(!was && !parent_was),
                InsertOutcome::NoRoom => {
                    assert!(!was && parent_was && used_before == capacity)
                }
                InsertOutcome::Inserted { slot, evicted } => {
                    assert!(loaded < load_limit && !was && parent_was);
                    loaded += 1;
                    assert_eq!(b.treelet_in(slot), Some(TreeletId(id)));
                    assert_eq!(b.used_slots() + evicted, used_before + 1);
                    assert!(evicted == 0 || used_before == capacity);
                    for a in ancestors {
                        assert!(b.is_resident(a), "ancestor {a} of {id} evicted for it");
                    }
                }
            }
        }
        check(&b, s);
        same_records(&b, &g);
    }
}

/// A growing buffer `g` driven like the written buffer `b` holds the same records: its arrays
/// are `b`'s up to the highest slot it filled and cover every resident slot, and `b` has only
/// default records beyond them.
fn same_records(b: &SlotBuffer, g: &SlotBuffer) {
    let (w, v) = (b.view(), g.view());
    let n = w.treelet_nodes as usize;
    let len = v.nodes.len();
    assert!(len % n == 0 && len <= w.nodes.len(), "{len} records");
    assert!(v.nodes == &w.nodes[..len], "node records differ");
    assert!(w.nodes[len..].iter().all(|r| *r == Node::default()));
    for slot in (0..b.capacity()).filter(|&x| b.treelet_in(x).is_some()) {
        assert_eq!(g.treelet_in(slot), b.treelet_in(slot));
        assert!(
            (slot as usize + 1) * n <= len,
            "slot {slot} beyond the records"
        );
    }
    for (ours, theirs) in [
        (v.color, w.color),
        (v.normal, w.normal),
        (v.density, w.density),
    ] {
        assert_eq!(ours.is_some(), theirs.is_some());
        if let (Some(ours), Some(theirs)) = (ours, theirs) {
            assert_eq!(ours.len() / len.max(1), theirs.len() / w.nodes.len().max(1));
            assert!(ours == &theirs[..ours.len()], "attributes differ");
            assert!(theirs[ours.len()..].iter().all(|&x| x == 0));
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 192, ..ProptestConfig::default() })]

    #[test]
    fn slot_buffer_matches_the_model(
        scan_index in 0usize..2,
        capacity in 2u32..40,
        load_limit in 1u32..8,
        visibility in 1u16..4,
        steps in prop::collection::vec(step(), 1..80),
    ) {
        run(scan_index, capacity, load_limit, visibility, &steps);
    }
}

#[test]
fn fully_resident_reaches_every_node() {
    for s in [&*BUNNY, &*LION] {
        let b =
            SlotBuffer::fully_resident(&s.scene, &s.channels, s.treelets.iter().cloned()).unwrap();
        assert_eq!(b.capacity(), s.scene.treelet_count);
        let reached = check(&b, s);
        let used: u32 = (0..s.scene.treelet_count).map(|id| s.used(id)).sum();
        println!(
            "{}: {} treelets, {} nodes reached of {} used",
            s.name, s.scene.treelet_count, reached, used
        );
        assert_eq!(reached, used - (s.scene.treelet_count - 1));
    }
}

/// Contiguous runs of sorted slots, counted without merge_ranges.
fn runs(dirty: &[u32]) -> usize {
    dirty.windows(2).filter(|w| w[1] != w[0] + 1).count() + usize::from(!dirty.is_empty())
}

#[test]
fn upload_ranges_of_a_realistic_dirty_pattern() {
    // A buffer of 64 slots kept full on the lion: each cycle the viewer sees a drifting window
    // of the resident treelets and requests children of what it sees; evictions free the
    // invisible rest. The dirty set of a cycle after warm-up is what an upload carries.
    let s = &*LION;
    let capacity = 64;
    let config = SlotConfig {
        budget_bytes: capacity * SlotBuffer::slot_bytes(s.n(), &s.channels),
        treelet_nodes: s.n(),
        channels: s.channels.clone(),
        visibility_max: 2,
        load_limit: 24,
    };
    let mut b = SlotBuffer::new(config, s.treelets[0].clone()).unwrap();
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    let mut dirty: Vec<u32> = Vec::new();
    for _ in 0..40 {
        b.begin_cycle();
        let resident: Vec<u32> = (0..b.capacity())
            .filter(|&x| b.treelet_in(x).is_some())
            .collect();
        for &slot in &resident {
            if next() % 10 == 0 {
                let mut x = Some(slot);
                while let Some(y) = x {
                    b.mark_visible(y);
                    x = b.parent_slot(y);
                }
            }
        }
        for _ in 0..32 {
            let slot = resident[(next() % resident.len() as u64) as usize];
            let id = b.treelet_in(slot).unwrap().0;
            let kids = &s.children[id as usize];
            if !kids.is_empty() {
                let kid = kids[(next() % kids.len() as u64) as usize];
                b.insert(s.treelets[kid as usize].clone());
            }
        }
        // Keep the largest upload once the buffer is full (the steady state: loads evict).
        let d = b.take_dirty();
        if b.used_slots() == b.capacity() && d.len() > dirty.len() {
            dirty = d;
        }
    }
    check(&b, s);
    assert!(!dirty.is_empty());
    let per_slot = SlotBuffer::slot_data_bytes(s.n(), &s.channels);
    println!("dirty slots ({}): {dirty:?}", dirty.len());
    let mut counts = Vec::new();
    for fill in [0.0, DEFAULT_FILL_RATIO, 1.0] {
        let plan = UploadPlan::new(&dirty, fill, per_slot);
        println!(
            "fill {fill}: {} ranges, {} slots, {} bytes: {:?}",
            plan.ranges.len(),
            plan.slots,
            plan.bytes,
            plan.ranges
        );
        assert!(plan.ranges.windows(2).all(|w| w[0].end < w[1].start));
        for d in &dirty {
            assert!(plan.ranges.iter().any(|r| r.contains(d)));
        }
        assert_eq!(plan.ranges, merge_ranges(&dirty, fill));
        counts.push((plan.ranges.len(), plan.slots));
    }
    // The pattern is deterministic (fixed build, fixed generator): pin what it measured.
    assert_eq!(dirty.len(), 25);
    assert_eq!(counts, vec![(1, 59), (6, 32), (12, 25)]);
    let first_to_last = dirty.last().unwrap() - dirty[0] + 1;
    assert_eq!(counts[0], (1, first_to_last));
    assert_eq!(counts[2], (runs(&dirty), dirty.len() as u32));
    assert!(counts[1].0 >= counts[0].0 && counts[1].0 <= counts[2].0);
    assert!(counts[1].1 <= counts[0].1 && counts[1].1 >= counts[2].1);
    // At 0.6 at least 60 % of every range is dirty, so at most 1/0.6 of the dirty slots go up.
    assert!(f64::from(counts[1].1) * 0.6 <= dirty.len() as f64 + 1e-9);
}
