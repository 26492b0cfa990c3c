//! Server-assisted deep requests (docs/design.md §10): the descendants a client's view would
//! refine below the treelets it asked for, sent without waiting to be asked.
//!
//! A child treelet can be named only once its parent has arrived and been sampled, so refinement
//! driven by feedback alone pays a round trip per treelet level. The server holds the whole tree:
//! given the view and, per listed treelet, the error the client measured at the leaf it refines,
//! [`plan_pushes`] walks down from each listed treelet, breadth first over all of them (parents
//! before children), and keeps every descendant whose root voxel
//! * lies in the view frustum and projects larger than a pixel ([`ViewHint::box_error`] > 0),
//! * and is coarser than the depth the client's error says is enough (root depth < the listed
//!   leaf's depth + its error),
//!
//! up to a budget: the free slots the client announced beyond its listed items. Occlusion still
//! comes from the client's own samples at the first level; the push only removes the chain of
//! round trips below it. The plan is pure — the tree shape comes from a lookup — so it is tested
//! without a pool. The service appends the plan to the list at priorities below every listed
//! item, so the scheduler sends it last, at lower QUIC priority, and a newer list that no longer
//! implies a push cancels it like any other treelet.
//!
//! A list implies the pushes below its listed treelets and, while the view stays the same, below
//! what was already sent for that view ([`PushAnchors`], [`plan_pushes_anchored`]): a client
//! stops listing a treelet once it is on its way, and without the anchors the pushes still
//! queued below it would be dropped with the next list.
//!
//! The shapes the plans walk (the root voxel and the refinable leaves of each treelet) come from
//! [`super::shapes::ShapeCache`], decoded from the stored node blocks and kept server-wide within
//! `shape_cache_bytes`.

use std::collections::{BTreeSet, VecDeque};
use std::sync::Arc;

use arbor_proto::wire::ViewHint;
use arbor_proto::{Cell, TreeletId};
use rustc_hash::{FxHashMap, FxHashSet};

use super::visibility::VisibleCut;

/// A treelet's place in the tree: its root voxel and its refinable leaves.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TreeletShape {
    /// The root voxel.
    pub root: Cell,
    /// `(child treelet, the leaf's voxel = the child's root voxel)`, in node order.
    pub children: Vec<(TreeletId, Cell)>,
}

/// Where the scene's root cube lies in the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldCube {
    /// Minimum corner.
    pub origin: [f64; 3],
    /// Edge length.
    pub edge: f64,
}

impl WorldCube {
    /// The root cube of `scene`.
    pub fn of(scene: &arbor_proto::SceneDescription) -> WorldCube {
        WorldCube {
            origin: scene.origin,
            edge: scene.edge,
        }
    }

    /// The box of `cell`.
    pub fn cell_box(&self, cell: Cell) -> ([f64; 3], [f64; 3]) {
        let size = self.edge / (1u64 << cell.depth.min(63)) as f64;
        let min = [
            self.origin[0] + f64::from(cell.x) * size,
            self.origin[1] + f64::from(cell.y) * size,
            self.origin[2] + f64::from(cell.z) * size,
        ];
        (min, [min[0] + size, min[1] + size, min[2] + size])
    }
}

/// The treelets to push, in sending order (parents before children), with their generation below
/// the listed item they descend from (1 = a child of a listed treelet).
pub fn plan_pushes(
    cube: WorldCube,
    view: &ViewHint,
    items: &[(TreeletId, f32, f32)],
    budget: usize,
    shape: impl FnMut(TreeletId) -> Option<Arc<TreeletShape>>,
) -> Vec<(TreeletId, u32)> {
    plan_pushes_anchored(cube, view, items, [], |_| None, budget, shape)
        .pushes
        .into_iter()
        .map(|(id, generation, _)| (id, generation))
        .collect()
}

/// A planned push: the treelet, its generation below the listed item or anchor it descends
/// from, and the depth its own descendants' roots must stay above.
pub type PlannedPush = (TreeletId, u32, f64);

/// What [`plan_pushes_anchored`] made: the pushes, and the anchors it walked from that proved
/// *exhausted* — every child sent, too deep for the anchor's limit, or out of view or finer
/// than a pixel — for [`PushAnchors::note_exhausted`].
#[derive(Debug, Default, PartialEq)]
pub struct AnchoredPlan {
    /// The pushes, in sending order.
    pub pushes: Vec<PlannedPush>,
    /// Anchors with nothing left below them to push.
    pub exhausted: Vec<TreeletId>,
}

/// [`plan_pushes`] below the listed items and then below `roots` — anchors that may have
/// something new below them ([`PushAnchors::roots`]), each with the depth its descendants'
/// roots must stay above, in id order — one breadth-first walk over both. `anchor` gives the
/// limit of every treelet already sent for the view: those are never pushed again, and one not
/// walked from counts as walked with its own limit (what lies below it was sent or fails the
/// tests, and its sent children are anchors of their own). Every push comes with the depth
/// limit it inherited, so it can be an anchor in turn.
///
/// The roots are taken one by one and their shapes looked up as they are walked, and the walk
/// stops at the budget: a plan costs what it pushes and the exhausted anchors it meets (each
/// met once), however many anchors are open.
pub fn plan_pushes_anchored(
    cube: WorldCube,
    view: &ViewHint,
    items: &[(TreeletId, f32, f32)],
    roots: impl IntoIterator<Item = (TreeletId, f64)>,
    anchor: impl Fn(TreeletId) -> Option<f64>,
    budget: usize,
    mut shape: impl FnMut(TreeletId) -> Option<Arc<TreeletShape>>,
) -> AnchoredPlan {
    let mut plan = AnchoredPlan::default();
    if budget == 0 {
        return plan;
    }
    let frustum = view.frustum();
    let listed: FxHashSet<TreeletId> = items.iter().map(|i| i.0).collect();
    let mut pushed: FxHashSet<TreeletId> = FxHashSet::default();
    // The largest limit each treelet was walked with. A treelet has one parent, so without
    // anchors each is walked once; an anchor (or a push below one) may also be reached from a
    // listed treelet or another anchor with a larger limit, and is then walked again with it —
    // never pushed twice.
    let mut walked: FxHashMap<TreeletId, f64> = FxHashMap::default();
    let listed_roots: Vec<(TreeletId, f64)> = items
        .iter()
        .filter_map(|&(id, _, error)| {
            let s = shape(id)?;
            Some((id, f64::from(s.root.depth) + f64::from(error.max(0.0))))
        })
        .collect();
    for &(id, limit) in &listed_roots {
        let w = walked.entry(id).or_insert(limit);
        *w = w.max(limit);
    }
    // Generation 0 — the listed treelets, then the anchors — before everything below them.
    let mut firsts = listed_roots
        .into_iter()
        .map(|(id, limit)| (id, limit, false))
        .chain(roots.into_iter().map(|(id, limit)| (id, limit, true)));
    // (treelet, generation, the depth its descendants' roots must stay above)
    let mut queue: VecDeque<(TreeletId, u32, f64)> = VecDeque::new();
    loop {
        let (id, generation, limit, is_anchor) = match firsts.next() {
            Some((id, limit, is_anchor)) => (id, 0, limit, is_anchor),
            None => match queue.pop_front() {
                Some((id, generation, limit)) => (id, generation, limit, false),
                None => break,
            },
        };
        if is_anchor {
            let w = walked.entry(id).or_insert(limit);
            *w = w.max(limit);
        }
        if walked.get(&id).is_some_and(|&w| w > limit) {
            continue;
        }
        let Some(s) = shape(id) else {
            continue;
        };
        // Whether every child of this anchor was sent or fails the tests.
        let mut exhausted = true;
        for &(child, cell) in &s.children {
            if f64::from(cell.depth) >= limit {
                continue;
            }
            if listed.contains(&child) {
                exhausted = false;
                continue;
            }
            let sent = anchor(child);
            if walked
                .get(&child)
                .copied()
                .or(sent)
                .is_some_and(|w| w >= limit)
            {
                exhausted &= sent.is_some();
                continue;
            }
            let (min, max) = cube.cell_box(cell);
            if !frustum.refines(min, max) {
                continue;
            }
            walked.insert(child, limit);
            if sent.is_none() {
                exhausted = false;
                if pushed.insert(child) {
                    plan.pushes.push((child, generation + 1, limit));
                    if plan.pushes.len() >= budget {
                        return plan;
                    }
                }
            }
            queue.push_back((child, generation + 1, limit));
        }
        if is_anchor && exhausted {
            plan.exhausted.push(id);
        }
    }
    plan
}

/// The list a deep request becomes: the listed items at their priorities, then the planned
/// pushes at priorities below every listed item ([`push_priority`]), within the free slots the
/// client announced beyond its listed items and the list size limit. Returns the list and the
/// number of pushes in it.
pub fn deep_list(
    cube: WorldCube,
    view: &ViewHint,
    items: &[(TreeletId, f32, f32)],
    max_items: usize,
    shape: impl FnMut(TreeletId) -> Option<Arc<TreeletShape>>,
) -> (Vec<(TreeletId, f32)>, usize) {
    let (list, plan) = deep_list_anchored(cube, view, items, [], |_| None, max_items, shape);
    (list, plan.pushes.len())
}

/// [`deep_list`] with pushes below `roots` too ([`plan_pushes_anchored`]): returns the list
/// and the plan (the pushes in the list, each with its generation and depth limit, and the
/// anchors found exhausted).
pub fn deep_list_anchored(
    cube: WorldCube,
    view: &ViewHint,
    items: &[(TreeletId, f32, f32)],
    roots: impl IntoIterator<Item = (TreeletId, f64)>,
    anchor: impl Fn(TreeletId) -> Option<f64>,
    max_items: usize,
    shape: impl FnMut(TreeletId) -> Option<Arc<TreeletShape>>,
) -> (Vec<(TreeletId, f32)>, AnchoredPlan) {
    let budget = (view.free_slots as usize)
        .saturating_sub(items.len())
        .min(max_items.saturating_sub(items.len()));
    let plan = plan_pushes_anchored(cube, view, items, roots, anchor, budget, shape);
    let lowest = items.iter().map(|i| i.1).fold(f32::INFINITY, f32::min);
    let mut list: Vec<(TreeletId, f32)> = items.iter().map(|&(id, p, _)| (id, p)).collect();
    list.extend(
        plan.pushes
            .iter()
            .map(|&(id, generation, _)| (id, push_priority(lowest, generation))),
    );
    (list, plan)
}

/// What a connection was already sent for the view it rests on, to plan pushes below.
///
/// [`plan_pushes`] walks down from the *listed* treelets only. But a client lists a treelet
/// only until it is on its way: once a listed treelet and the first pushes below it were sent,
/// the next list (built before they arrived) names neither, the pushes still waiting behind
/// them in the queue are no longer implied, and the scheduler drops them — the chain of round
/// trips the push exists to remove comes back, one level per list. Measured on engine over the
/// link emulator: by 0.35 s every treelet the view needs had been named by a plan, but 87–100
/// of them were in no current list, and were sent only when the client listed them itself at
/// 0.5 s, while the link stood idle in between.
///
/// So, as long as the view stays the same ([`same_view`](super::visibility::same_view): a
/// resting camera), every treelet listed or pushed for it is kept with the depth limit it was
/// planned with, and once it has been handed to a stream it is an *anchor*: the next plan walks
/// down from the anchors too, skipping what was already sent. A new view starts over (a moving
/// camera's old subtrees are not implied by its new view), and a treelet whose stream was reset
/// or lost stops being an anchor (the client may not hold it).
///
/// Only *open* anchors are walked: an anchor the plan found exhausted (every child sent, or too
/// deep for its limit, or out of view or finer than a pixel: [`AnchoredPlan::exhausted`]) is
/// closed, and opened again only if its limit grows or a stream is reset. Plans walk the open
/// anchors in id order and stop at the budget, so a list costs what it pushes plus the
/// exhausted anchors it closes, each once — not a pass over everything sent (measured at city
/// scale by `cargo bench -p arbor-server --bench push_plan`: testing every open anchor's
/// children on each list cost up to hundreds of milliseconds). Bounded: at most
/// [`PushAnchors::MAX`] treelets are kept (by default); once a plan or list brings more, the
/// anchors are *full* and none is walked for the rest of the view (a push that could not be
/// kept could not be told from a new one, and would be pushed again on every list): the plan
/// below the listed treelets goes on as without anchors.
#[derive(Clone, Debug, PartialEq)]
pub struct PushAnchors {
    view: Option<ViewHint>,
    /// Most treelets kept.
    max: usize,
    /// More than `max` came for the view: no anchor is walked.
    full: bool,
    /// Treelets listed or pushed for `view`, with the depth their descendants' roots must stay
    /// above.
    limits: FxHashMap<TreeletId, f64>,
    /// Those of them handed to a stream (and not reset since).
    sent: FxHashSet<TreeletId>,
    /// Sent treelets not found exhausted yet, in id order (the order plans walk them in).
    open: BTreeSet<TreeletId>,
}

impl Default for PushAnchors {
    fn default() -> Self {
        Self::with_max(Self::MAX)
    }
}

impl PushAnchors {
    /// Most treelets kept by default.
    pub const MAX: usize = 1 << 17;

    /// Anchors that keep at most `max` treelets per view.
    pub fn with_max(max: usize) -> Self {
        PushAnchors {
            view: None,
            max,
            full: false,
            limits: FxHashMap::default(),
            sent: FxHashSet::default(),
            open: BTreeSet::new(),
        }
    }

    /// Starts over unless `view` is the view the anchors were kept for.
    pub fn for_view(&mut self, view: &ViewHint) {
        if !self
            .view
            .as_ref()
            .is_some_and(|v| super::visibility::same_view(v, view))
        {
            self.full = false;
            self.limits.clear();
            self.sent.clear();
            self.open.clear();
            self.view = Some(*view);
        }
    }

    /// The anchors to walk from besides `items`, with their limits: open, and not listed again,
    /// in id order (parents before children); none once full. Lazy: a plan takes only as many
    /// as it walks.
    pub fn roots(
        &self,
        items: &[(TreeletId, f32, f32)],
    ) -> impl Iterator<Item = (TreeletId, f64)> + '_ {
        let listed: FxHashSet<TreeletId> = items.iter().map(|i| i.0).collect();
        self.open
            .iter()
            // Full: none, taken as nothing rather than by skipping each open anchor.
            .take(if self.full { 0 } else { usize::MAX })
            .filter(move |id| !listed.contains(id))
            .filter_map(|id| self.limits.get(id).map(|&limit| (*id, limit)))
    }

    /// Open anchors.
    pub fn open_len(&self) -> usize {
        self.open.len()
    }

    /// The limit of `id` if it was sent for the view: an anchor, never pushed again.
    pub fn sent_limit(&self, id: TreeletId) -> Option<f64> {
        if self.sent.contains(&id) {
            self.limits.get(&id).copied()
        } else {
            None
        }
    }

    /// Closes the anchors a plan found exhausted ([`AnchoredPlan::exhausted`]): later plans do
    /// not walk them again.
    pub fn note_exhausted(&mut self, exhausted: &[TreeletId]) {
        for id in exhausted {
            self.open.remove(id);
        }
    }

    /// A plan was made: its listed items (limit from the error the client measured; a listed
    /// treelet's newest error wins) and its pushes (the limit they inherited; the first wins).
    /// One that cannot be kept makes the anchors full.
    pub fn record(
        &mut self,
        items: &[(TreeletId, f32, f32)],
        pushes: &[PlannedPush],
        mut shape: impl FnMut(TreeletId) -> Option<Arc<TreeletShape>>,
    ) {
        for &(id, _, error) in items {
            if self.limits.len() >= self.max && !self.limits.contains_key(&id) {
                self.full = true;
                continue;
            }
            if let Some(s) = shape(id) {
                let limit = f64::from(s.root.depth) + f64::from(error.max(0.0));
                if self.limits.insert(id, limit).is_some_and(|old| old < limit)
                    && self.sent.contains(&id)
                {
                    // Deeper now: what lies below may no longer be exhausted.
                    self.open.insert(id);
                }
            }
        }
        for &(id, _, limit) in pushes {
            if self.limits.len() >= self.max && !self.limits.contains_key(&id) {
                self.full = true;
                break;
            }
            self.limits.entry(id).or_insert(limit);
        }
    }

    /// `batch` was handed to a stream.
    pub fn note_sent(&mut self, batch: &[TreeletId]) {
        for &id in batch.iter().filter(|id| self.limits.contains_key(id)) {
            if self.sent.insert(id) {
                self.open.insert(id);
            }
        }
    }

    /// `batch`'s stream was reset or lost: the client may not hold it. (Rare: every anchor is
    /// open again, since the exhausted ones counted it as sent.)
    pub fn note_unsent(&mut self, batch: &[TreeletId]) {
        let mut any = false;
        for id in batch {
            any |= self.sent.remove(id);
        }
        if any {
            self.open = self.sent.iter().copied().collect();
        }
    }

    /// Treelets kept (listed or pushed for the view).
    pub fn len(&self) -> usize {
        self.limits.len()
    }

    /// Whether none is kept.
    pub fn is_empty(&self) -> bool {
        self.limits.is_empty()
    }

    /// Whether more treelets came for the view than can be kept, so none is walked.
    pub fn is_full(&self) -> bool {
        self.full
    }
}

/// A connection's [`PushAnchors`], which a plan made on a reader thread borrows
/// ([`frustum_list`] run where the pool may be read): what the connection's streams report
/// while they are away is kept, and replayed in order when they come back, so the anchors
/// end as if they had stayed.
#[derive(Debug, Default)]
pub struct LentAnchors {
    /// `None` while lent.
    home: Option<PushAnchors>,
    /// Batches sent (`true`) or reset (`false`) while lent, in order.
    missed: Vec<(bool, Vec<TreeletId>)>,
}

impl LentAnchors {
    /// The anchors, unless they are lent.
    pub fn get_mut(&mut self) -> Option<&mut PushAnchors> {
        self.home.as_mut()
    }

    /// Whether the anchors are lent.
    pub fn is_lent(&self) -> bool {
        self.home.is_none()
    }

    /// Lends the anchors out; `None` if they are lent already.
    pub fn lend(&mut self) -> Option<PushAnchors> {
        self.home.take()
    }

    /// The anchors come back (`None`: lost with the plan that had them; they start again,
    /// empty, and what was kept for them is dropped).
    pub fn give_back(&mut self, anchors: Option<PushAnchors>) {
        let missed = std::mem::take(&mut self.missed);
        let Some(mut anchors) = anchors else {
            self.home = Some(PushAnchors::default());
            return;
        };
        for (sent, batch) in missed {
            if sent {
                anchors.note_sent(&batch);
            } else {
                anchors.note_unsent(&batch);
            }
        }
        self.home = Some(anchors);
    }

    /// [`PushAnchors::note_sent`], now or when they come back.
    pub fn note_sent(&mut self, batch: &[TreeletId]) {
        match &mut self.home {
            Some(a) => a.note_sent(batch),
            None => self.missed.push((true, batch.to_vec())),
        }
    }

    /// [`PushAnchors::note_unsent`], now or when they come back.
    pub fn note_unsent(&mut self, batch: &[TreeletId]) {
        match &mut self.home {
            Some(a) => a.note_unsent(batch),
            None => self.missed.push((false, batch.to_vec())),
        }
    }
}

/// Which deep list's frustum plan is being made on a reader, and which deep list waits for
/// its pushes, against the lists applied to the scheduler meanwhile: the handler's rules for a
/// plan that comes back after other lists, as plain data. `L` is the deep list as the handler
/// keeps it, with its sequence number.
///
/// The rules: one plan at a time; a plan's list replaces the one applied without its pushes
/// only if no list was applied since (a newer list, a visible cut's re-plan, another plan's);
/// only the latest deep list waits for pushes, and only while it is the last list applied.
#[derive(Debug)]
pub struct DeferredPlans<L> {
    /// Lists applied to the scheduler so far, new or re-planned.
    generation: u64,
    /// The plan being made: its list's sequence number and the generation the list was
    /// applied as.
    running: Option<(u64, u64)>,
    /// The latest deep list applied without its pushes, and its generation.
    waiting: Option<(L, u64)>,
}

impl<L> Default for DeferredPlans<L> {
    fn default() -> Self {
        DeferredPlans {
            generation: 0,
            running: None,
            waiting: None,
        }
    }
}

impl<L> DeferredPlans<L> {
    /// A list was applied to the scheduler.
    pub fn applied(&mut self) {
        self.generation += 1;
    }

    /// The deep list just applied went without its pushes: it waits for a plan.
    pub fn defer(&mut self, list: L) {
        self.waiting = Some((list, self.generation));
    }

    /// A deep list was applied with its pushes: none waits.
    pub fn planned_at_once(&mut self) {
        self.waiting = None;
    }

    /// The waiting list to plan now, unless a plan is being made (its end decides). `seq` gives
    /// a list's sequence number.
    pub fn start(&mut self, seq: impl Fn(&L) -> u64) -> Option<L> {
        if self.running.is_some() {
            return None;
        }
        let (list, generation) = self.waiting.take()?;
        self.running = Some((seq(&list), generation));
        Some(list)
    }

    /// The plan being made ended: the sequence number its list is applied under, if it is to
    /// be (no list was applied since its own).
    pub fn finish(&mut self) -> Option<u64> {
        let (seq, generation) = self.running.take()?;
        (generation == self.generation).then_some(seq)
    }

    /// The list waiting for pushes, if it is still the last one applied (else it is dropped:
    /// a later list replaced it).
    pub fn take_waiting(&mut self) -> Option<L> {
        let (list, generation) = self.waiting.take()?;
        (generation == self.generation).then_some(list)
    }
}

impl From<PushAnchors> for LentAnchors {
    fn from(anchors: PushAnchors) -> Self {
        LentAnchors {
            home: Some(anchors),
            missed: Vec::new(),
        }
    }
}

/// A request list as the service hands it to the scheduler: what the client listed, planned
/// with the server's pushes ([`cut_list`], [`deep_list_anchored`]) or as it came.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedList {
    /// The listed items, the prefetch set apart and the pushes (the last `pushed`), each at the
    /// priority it is sent by.
    pub items: Vec<(TreeletId, f32)>,
    /// How many of `items`, at its end, are pushes.
    pub pushed: usize,
    /// The prefetch set apart ranks below this and nothing else does
    /// ([`super::schedule::Scheduler::handle_list_with_prefetch`]); `None`: nothing is.
    pub prefetch_below: Option<f32>,
    /// How many items are set apart so.
    pub set_apart: usize,
}

impl PlannedList {
    /// A list as the client sent it: no pushes, nothing set apart.
    pub fn plain(items: Vec<(TreeletId, f32)>) -> PlannedList {
        PlannedList {
            items,
            pushed: 0,
            prefetch_below: None,
            set_apart: 0,
        }
    }
}

/// A shape lookup found the shape not at hand: it is not in the cache, and this lookup may not
/// read the pool (an async worker must not wait for the disk).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShapeMissing;

/// The list a deep request becomes without a visible cut: [`deep_list_anchored`] below the
/// listed items and `anchors`' open anchors, with the plan recorded in `anchors` for the next
/// one. `shape` may answer [`ShapeMissing`]: the plan is then given up before `anchors` learn
/// anything of it (beyond [`PushAnchors::for_view`]), to be made again where the pool may be
/// read, with the same result as if every shape had been at hand.
pub fn frustum_list(
    cube: WorldCube,
    view: &ViewHint,
    items: &[(TreeletId, f32, f32)],
    anchors: &mut PushAnchors,
    max_items: usize,
    mut shape: impl FnMut(TreeletId) -> Result<Option<Arc<TreeletShape>>, ShapeMissing>,
) -> Result<PlannedList, ShapeMissing> {
    anchors.for_view(view);
    let missing = std::cell::Cell::new(false);
    // After the first missing shape the plan is lost anyway: looking further is skipped.
    let mut lookup = |id| {
        if missing.get() {
            return None;
        }
        shape(id).unwrap_or_else(|ShapeMissing| {
            missing.set(true);
            None
        })
    };
    // `record` looks every listed item up, also when the plan has no budget to walk below them.
    for &(id, _, _) in items {
        lookup(id);
    }
    if missing.get() {
        return Err(ShapeMissing);
    }
    let (list, plan) = deep_list_anchored(
        cube,
        view,
        items,
        anchors.roots(items),
        |id| anchors.sent_limit(id),
        max_items,
        &mut lookup,
    );
    if missing.get() {
        return Err(ShapeMissing);
    }
    anchors.record(items, &plan.pushes, &mut lookup);
    anchors.note_exhausted(&plan.exhausted);
    Ok(PlannedList {
        items: list,
        pushed: plan.pushes.len(),
        prefetch_below: None,
        set_apart: 0,
    })
}

/// The push generation of the first prefetch item outside a cut: below every level's pushes.
const PREFETCH_GENERATION: u32 = u8::MAX as u32 + 2;

/// The list a deep request becomes when the server knows the view's visible cut
/// ([`super::visibility`]): the listed items at their priorities, then the cut's treelets the
/// client neither listed nor was `delivered` (parents first, a level's pushes below the level
/// above), within the free slots it announced beyond its listed items and the list size limit,
/// then the client's prefetch (`items[prefetch_from..]`) that the cut does not hold, in the
/// client's order. The cut says what the view needs; the prefetch outside it is a guess at a
/// later view, so it goes after every need and is marked to be kept to a few in flight
/// ([`PlannedList::prefetch_below`]). Prefetch the cut holds keeps its place. Unlike
/// [`deep_list`], the pushes need not descend from a listed treelet: the cut already says which
/// treelets the view needs, and a needed treelet below one delivered earlier is pushed as soon
/// as its own parent was.
pub fn cut_list(
    cut: &VisibleCut,
    view: &ViewHint,
    items: &[(TreeletId, f32, f32)],
    prefetch_from: usize,
    max_items: usize,
    delivered: impl Fn(TreeletId) -> bool,
) -> PlannedList {
    let budget = (view.free_slots as usize)
        .saturating_sub(items.len())
        .min(max_items.saturating_sub(items.len()));
    let prefetch_from = prefetch_from.min(items.len());
    let in_cut: FxHashSet<TreeletId> = if prefetch_from < items.len() {
        cut.treelets.iter().map(|&(_, id)| id).collect()
    } else {
        FxHashSet::default()
    };
    let (mut list, mut outside) = (Vec::with_capacity(items.len()), Vec::new());
    for (i, &(id, priority, _)) in items.iter().enumerate() {
        if i < prefetch_from || in_cut.contains(&id) {
            list.push((id, priority));
        } else {
            outside.push((id, priority));
        }
    }
    let lowest = list.iter().map(|i| i.1).fold(f32::INFINITY, f32::min);
    outside.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let prefetch_below =
        (!outside.is_empty()).then(|| push_priority(lowest, PREFETCH_GENERATION - 1));
    list.extend(
        outside
            .iter()
            .zip(PREFETCH_GENERATION..)
            .map(|(&(id, _), generation)| (id, push_priority(lowest, generation))),
    );
    let listed: FxHashSet<TreeletId> = items.iter().map(|i| i.0).collect();
    let before = list.len();
    list.extend(
        cut.treelets
            .iter()
            .filter(|(_, id)| !listed.contains(id) && !delivered(*id))
            .take(budget)
            .map(|&(level, id)| (id, push_priority(lowest, u32::from(level)))),
    );
    let pushed = list.len() - before;
    PlannedList {
        items: list,
        pushed,
        prefetch_below,
        set_apart: outside.len(),
    }
}

/// Whether a visible cut could change the deep list of `listed` items for `view` whose
/// prefetch starts at `prefetch_from` ([`cut_list`]): it chooses the pushes, which only the
/// free slots beyond the listed items take, and sets apart the prefetch it does not hold. A
/// list with neither leaves a cut nothing to decide. That is the usual list of a client whose
/// budget bounds its view (docs/measurements.md, stop 49): each one fills every free slot
/// itself, and while its LOD bias settles it sends no prefetch either, so a cut cast for each
/// bias step would be thrown away.
pub fn cut_has_work(view: &ViewHint, listed: usize, prefetch_from: usize) -> bool {
    view.free_slots as usize > listed || prefetch_from < listed
}

/// Whether following a visible cut of `treelets` treelets for `view` is worth it: whether it
/// holds at most `share` of the treelets the frustum plan would push for the same view from the
/// root (every descendant in the frustum that projects larger than a pixel). A view that sees
/// most of what lies in its frustum (a statue from the front, a city from above) gains little
/// from its cut and loses what the frustum plan would have prefetched for the next view; an
/// occluded one (an engine, a building's interior) saves most of its bytes. The frustum plan is
/// walked only as far as the decision needs, so the work is bounded by `treelets` over
/// `share`. `share` ≥ 1: always. A larger cut of the same view saves less: the answer for a
/// cut still being cast (`CutCaster::cut_from`'s `worthwhile`) holds for what it grows into.
pub fn cut_saves(
    cube: WorldCube,
    view: &ViewHint,
    treelets: usize,
    root: TreeletId,
    share: f64,
    shape: impl FnMut(TreeletId) -> Option<Arc<TreeletShape>>,
) -> bool {
    if share >= 1.0 {
        return true;
    }
    if share.is_nan() || share <= 0.0 {
        return false;
    }
    // The frustum plan must hold at least this many for the cut to be within `share` of it
    // (`as` saturates: a tiny share asks for more than any plan holds).
    let needed = (treelets as f64 / share).ceil().max(1.0) as usize;
    let root_item = [(root, f32::MAX, ViewHint::MAX_ERROR)];
    plan_pushes(cube, view, &root_item, needed, shape).len() >= needed
}

/// In-flight windows' worth of pushes one list may carry ([`push_cap`]).
pub const PUSH_WINDOWS_PER_LIST: usize = 8;
/// Pushes one list may always carry, however small the window ([`push_cap`]).
pub const MIN_PUSHES_PER_LIST: usize = 1024;

/// Most pushes one list is given when the connection keeps `window` treelets in flight:
/// [`PUSH_WINDOWS_PER_LIST`] windows, at least [`MIN_PUSHES_PER_LIST`].
///
/// A list is replaced by the next within a few round trips, and the link sends about one
/// window a round trip, so pushes planned beyond a few windows are planned again (or dropped)
/// before they could go out. Planning up to the client's free slots instead cost about 20 ms
/// a list at city scale (65,535 pushes, `cargo bench -p arbor-server --bench push_plan`)
/// where the link sent about a thousand of them before the next list; over the link emulator
/// and on loopback a fixed cap of 256 or 1,024 pushes changed no time to RMSE 0 beyond the
/// spread (docs/measurements.md, stop 42).
pub fn push_cap(window: usize) -> usize {
    window
        .saturating_mul(PUSH_WINDOWS_PER_LIST)
        .max(MIN_PUSHES_PER_LIST)
}

/// The priority a push of `generation` gets in a list whose lowest listed priority is
/// `lowest`: below every listed item, and below the pushes of earlier generations.
///
/// The step grows with the magnitude so that the result stays strictly below even where a
/// fixed step would be absorbed by rounding; a list whose lowest priority is near `-f32::MAX`
/// gets non-finite push priorities, which the scheduler drops (no pushes rather than pushes that
/// tie with listed items).
pub fn push_priority(lowest: f32, generation: u32) -> f32 {
    let base = lowest.min(0.0);
    let step = (base.abs() * f32::EPSILON * 4.0).max(1.0);
    base - step * (1.0 + generation as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::{HashMap, HashSet};

    fn cell(depth: u8, x: u32, y: u32, z: u32) -> Cell {
        Cell { depth, x, y, z }
    }

    /// A complete tree of treelets: treelet `k` at depth `d` has the 8 children of its root cell
    /// as child treelets, down to `levels` levels; ids are assigned breadth first.
    fn tree(levels: u8) -> HashMap<TreeletId, Arc<TreeletShape>> {
        let mut out = HashMap::new();
        let mut queue = VecDeque::from([(TreeletId(0), cell(0, 0, 0, 0))]);
        let mut next = 1u32;
        while let Some((id, root)) = queue.pop_front() {
            let mut children = Vec::new();
            if root.depth < levels {
                for i in 0..8 {
                    let c = root.child(i);
                    children.push((TreeletId(next), c));
                    queue.push_back((TreeletId(next), c));
                    next += 1;
                }
            }
            out.insert(id, Arc::new(TreeletShape { root, children }));
        }
        out
    }

    /// A complete cut of `view` holding `treelets` as `(level, id)`.
    fn cut_of(view: ViewHint, treelets: &[(u8, u32)]) -> VisibleCut {
        VisibleCut {
            view,
            treelets: treelets
                .iter()
                .map(|&(level, id)| (level, TreeletId(id)))
                .collect(),
            complete: true,
            abandoned: false,
            grid: 8,
            rays_cast: 0,
            took: std::time::Duration::ZERO,
        }
    }

    #[test]
    fn a_cut_list_pushes_the_cut_minus_listed_and_delivered_parents_first_within_the_slots() {
        let mut view = view_from([0.5, 0.5, 3.0], 0.001);
        let cut = cut_of(view, &[(1, 4), (1, 7), (2, 9), (2, 12), (3, 20)]);
        let items = [(TreeletId(7), 5.0, 2.0), (TreeletId(30), -3.0, 1.0)];
        let delivered = |id: TreeletId| id == TreeletId(9);
        view.free_slots = 2 + 10;
        let PlannedList {
            items: list,
            pushed,
            prefetch_below,
            set_apart,
        } = cut_list(&cut, &view, &items, items.len(), 100, delivered);
        assert_eq!((pushed, prefetch_below, set_apart), (3, None, 0));
        let ids: Vec<u32> = list.iter().map(|&(id, _)| id.0).collect();
        assert_eq!(
            ids,
            [7, 30, 4, 12, 20],
            "listed first, then the cut by level"
        );
        assert_eq!(&list[..2], &[(TreeletId(7), 5.0), (TreeletId(30), -3.0)]);
        let p: Vec<f32> = list[2..].iter().map(|&(_, p)| p).collect();
        assert!(p[0] < -3.0, "below every listed item");
        assert!(
            p[0] > p[1] && p[1] > p[2],
            "a level below the one above: {p:?}"
        );
        // Two free slots beyond the listed items: the two shallowest.
        view.free_slots = 4;
        let PlannedList {
            items: list,
            pushed,
            ..
        } = cut_list(&cut, &view, &items, 2, 100, delivered);
        assert_eq!(pushed, 2);
        assert_eq!(list.len(), 4);
        assert_eq!((list[2].0, list[3].0), (TreeletId(4), TreeletId(12)));
        // No room beyond the listed items, or the list limit reached: no pushes.
        view.free_slots = 1;
        assert_eq!(cut_list(&cut, &view, &items, 2, 100, delivered).pushed, 0);
        view.free_slots = 100;
        assert_eq!(cut_list(&cut, &view, &items, 2, 3, delivered).pushed, 1);
    }

    #[test]
    fn a_cut_list_sends_the_prefetch_the_cut_does_not_hold_after_its_pushes() {
        let mut view = view_from([0.5, 0.5, 3.0], 0.001);
        view.free_slots = 100;
        let cut = cut_of(view, &[(1, 4), (1, 7), (2, 12), (3, 20)]);
        // Prefetch from the third item: 20 is in the cut, 41 and 40 are not (41 ranks first).
        let items = [
            (TreeletId(7), 5.0, 2.0),
            (TreeletId(30), 1.0, 1.0),
            (TreeletId(20), 0.5, 0.0),
            (TreeletId(41), 0.25, 0.0),
            (TreeletId(40), 0.125, 0.0),
        ];
        let planned = cut_list(&cut, &view, &items, 2, 100, |_| false);
        let below = planned.prefetch_below.expect("prefetch outside the cut");
        let ids: Vec<u32> = planned.items.iter().map(|&(id, _)| id.0).collect();
        assert_eq!(ids, [7, 30, 20, 41, 40, 4, 12], "the pushes last");
        assert_eq!((planned.pushed, planned.set_apart), (2, 2));
        let priority = |id: u32| planned.items.iter().find(|x| x.0.0 == id).unwrap().1;
        // What the cut holds keeps its place; the pushes rank below every listed item, the
        // prefetch outside the cut below every push, in the client's order; the mark lies
        // between them.
        assert_eq!((priority(7), priority(30), priority(20)), (5.0, 1.0, 0.5));
        assert!(priority(12) < 0.5 && priority(12) > below);
        assert!(below > priority(41) && priority(41) > priority(40));
        // Without prefetch, or all of it in the cut: nothing is marked.
        assert_eq!(
            cut_list(&cut, &view, &items, 5, 100, |_| false).prefetch_below,
            None
        );
        assert_eq!(
            cut_list(&cut, &view, &items[..3], 2, 100, |_| false).prefetch_below,
            None
        );
        // A start past the items is no prefetch.
        assert_eq!(
            cut_list(&cut, &view, &items, 99, 100, |_| false).prefetch_below,
            None
        );
    }

    #[test]
    fn a_cut_is_followed_only_where_it_saves_enough_of_the_frustum_plan() {
        let t = tree(3);
        let shape = |id: TreeletId| t.get(&id).cloned();
        let view = view_from([0.5, 0.5, 3.0], 0.001);
        let frustum = plan_pushes(
            CUBE,
            &view,
            &[(TreeletId(0), f32::MAX, ViewHint::MAX_ERROR)],
            usize::MAX,
            shape,
        )
        .len();
        assert_eq!(frustum, 8 + 64 + 512, "the whole tree is in view");
        let saves = |n: usize, share: f64| cut_saves(CUBE, &view, n, TreeletId(0), share, shape);
        // Exactly half the frustum plan is within a share of one half; one more is not.
        assert!(saves(frustum / 2, 0.5));
        assert!(!saves(frustum / 2 + 1, 0.5));
        assert!(saves(frustum / 10, 0.1));
        assert!(!saves(frustum / 10 + 1, 0.1));
        // A share of one follows every cut, even one larger than the plan; none follows none.
        assert!(saves(frustum + 5, 1.0));
        assert!(!saves(1, 0.0));
        assert!(!saves(1, f64::NAN));
        // An empty cut (nothing visible below the root) always saves.
        assert!(saves(0, 0.5));
        // A view that sees only part of the tree has a smaller frustum plan.
        let aside = view_from([1.5, 0.5, 2.0], 0.001);
        let side = plan_pushes(
            CUBE,
            &aside,
            &[(TreeletId(0), f32::MAX, ViewHint::MAX_ERROR)],
            usize::MAX,
            shape,
        )
        .len();
        assert!(side > 0 && side < frustum, "{side} of {frustum}");
        assert_eq!(
            cut_saves(CUBE, &aside, 100, TreeletId(0), 0.5, shape),
            100 * 2 <= side
        );
    }

    fn view_from(eye: [f64; 3], footprint: f32) -> ViewHint {
        ViewHint {
            eye,
            forward: [0.0, 0.0, -1.0],
            up: [0.0, 1.0, 0.0],
            tan_half_fov_y: 0.6,
            aspect: 1.0,
            footprint,
            free_slots: 0,
        }
    }

    const CUBE: WorldCube = WorldCube {
        origin: [0.0; 3],
        edge: 1.0,
    };

    fn open_roots(anchors: &PushAnchors, items: &[(TreeletId, f32, f32)]) -> Vec<TreeletId> {
        anchors.roots(items).map(|r| r.0).collect()
    }

    /// The plan the handler makes for `items` with `anchors`, over the test tree `t`.
    fn plan_with_anchors(
        t: &HashMap<TreeletId, Arc<TreeletShape>>,
        anchors: &PushAnchors,
        view: &ViewHint,
        items: &[(TreeletId, f32, f32)],
        budget: usize,
    ) -> AnchoredPlan {
        plan_pushes_anchored(
            CUBE,
            view,
            items,
            anchors.roots(items),
            |id| anchors.sent_limit(id),
            budget,
            |id| t.get(&id).cloned(),
        )
    }

    #[test]
    fn anchors_carry_the_plan_below_what_was_sent_for_the_same_view() {
        let t = tree(3);
        let shape = |id: TreeletId| t.get(&id).cloned();
        let mut view = view_from([0.5, 0.5, 3.0], 0.001);
        view.free_slots = 1 + 12;
        let root = [(TreeletId(0), 1.0, 10.0)];
        let mut anchors = PushAnchors::default();
        anchors.for_view(&view);
        let first = plan_with_anchors(&t, &anchors, &view, &root, 12);
        assert!(first.exhausted.is_empty(), "no anchors yet");
        let first = first.pushes;
        assert_eq!(
            first.len(),
            12,
            "the root's 8 children, then 4 grandchildren"
        );
        anchors.record(&root, &first, shape);
        // The root and its children went out; the grandchildren were still queued when the
        // client's next list came, naming only a leaf treelet elsewhere (the root and its
        // children are on their way).
        let sent: Vec<TreeletId> = std::iter::once(TreeletId(0))
            .chain(first[..8].iter().map(|p| p.0))
            .collect();
        anchors.note_sent(&sent);
        let other = [(TreeletId(100), 1.0, 0.0)];
        let (plain, plain_pushed) = deep_list(CUBE, &view, &other, 100, shape);
        assert_eq!(
            plain_pushed, 0,
            "without anchors, nothing below a zero error"
        );
        assert_eq!(plain.len(), 1);
        anchors.for_view(&view);
        assert_eq!(
            open_roots(&anchors, &other),
            sent,
            "every sent treelet is open"
        );
        assert_eq!(
            anchors.sent_limit(TreeletId(0)),
            Some(10.0),
            "an anchor, with its limit"
        );
        let (list, again) = deep_list_anchored(
            CUBE,
            &view,
            &other,
            anchors.roots(&other),
            |id| anchors.sent_limit(id),
            100,
            shape,
        );
        assert_eq!(
            again.exhausted,
            [TreeletId(0)],
            "the root is exhausted (all its children went); its children are not"
        );
        anchors.note_exhausted(&again.exhausted);
        assert_eq!(open_roots(&anchors, &other), sent[1..]);
        let again_ids: Vec<TreeletId> = again.pushes.iter().map(|p| p.0).collect();
        for p in &first[8..] {
            assert!(
                again_ids.contains(&p.0),
                "queued grandchild {:?} dropped",
                p.0
            );
        }
        assert!(
            again.pushes.len() <= 12,
            "within the free slots beyond the list"
        );
        assert!(
            again_ids
                .iter()
                .all(|id| !sent.contains(id) && *id != TreeletId(100))
        );
        assert_eq!(list[0], (TreeletId(100), 1.0), "the listed item first");
        for p in &again.pushes {
            assert_eq!(p.2, 10.0, "the limit the root's error gave");
        }
        // The budget stops the walk: anchors not reached stay open, the one being walked when
        // it filled is not judged.
        let cut_short = plan_with_anchors(&t, &anchors, &view, &other, 1);
        assert_eq!(cut_short.pushes.len(), 1);
        assert!(cut_short.exhausted.is_empty());

        // A stream reset: that child is no anchor any more (the client may not hold it), and
        // every other sent treelet is open again.
        anchors.note_unsent(&sent[1..2]);
        assert_eq!(open_roots(&anchors, &other).len(), 8);
        // A listed treelet is no anchor.
        assert_eq!(anchors.roots(&[(sent[2], 1.0, 1.0)]).count(), 7);
        // Another view starts over.
        let mut moved = view;
        moved.eye[0] += 0.25;
        anchors.for_view(&moved);
        assert_eq!(anchors.roots(&other).count(), 0);
        assert!(anchors.is_empty());
        // The free slots alone do not make a new view.
        anchors.record(&root, &first, shape);
        anchors.note_sent(&sent);
        let mut fewer = moved;
        fewer.free_slots = 3;
        anchors.for_view(&fewer);
        assert_eq!(anchors.roots(&[]).count(), 9);
    }

    proptest! {
        /// Whatever was listed, pushed and sent before: an anchored plan pushes each treelet
        /// once, never a listed or an anchor treelet, only below a listed, an anchor or an
        /// earlier push (parents first), no deeper than the limit it inherited, within the
        /// budget; and it holds every push the plain plan of the same list would make.
        #[test]
        fn anchored_plans_keep_the_plain_plans_rules(
            listed in proptest::collection::vec((0u32..73, 0f32..2.0), 1..5),
            later in proptest::collection::vec((0u32..73, 0f32..8.0), 0..5),
            sent_share in 0.0f64..1.0,
            budget in 0usize..600,
        ) {
            let t = tree(3);
            let shape = |id: TreeletId| t.get(&id).cloned();
            let mut view = view_from([0.4, 0.6, 2.5], 0.002);
            view.free_slots = u32::MAX;
            let items: Vec<_> = listed.iter().map(|&(id, e)| (TreeletId(id), 1.0, e)).collect();
            let mut anchors = PushAnchors::default();
            anchors.for_view(&view);
            let first =
                plan_pushes_anchored(CUBE, &view, &items, [], |_| None, 10_000, shape).pushes;
            anchors.record(&items, &first, shape);
            let sent: Vec<TreeletId> = items
                .iter()
                .map(|i| i.0)
                .chain(first.iter().map(|p| p.0))
                .enumerate()
                .filter(|(k, _)| (*k as f64 * 0.618).fract() < sent_share)
                .map(|(_, id)| id)
                .collect();
            anchors.note_sent(&sent);
            let later: Vec<_> = later.iter().map(|&(id, e)| (TreeletId(id), 1.0, e)).collect();
            let plan = plan_with_anchors(&t, &anchors, &view, &later, budget).pushes;
            prop_assert!(plan.len() <= budget);
            let mut parent_of = HashMap::new();
            for (id, s) in &t {
                for (c, _) in &s.children {
                    parent_of.insert(*c, *id);
                }
            }
            let listed_ids: HashSet<_> = later.iter().map(|i| i.0).collect();
            let is_anchor = |id: &TreeletId| anchors.sent_limit(*id).is_some();
            let mut seen = HashSet::new();
            for &(id, _, limit) in &plan {
                prop_assert!(seen.insert(id), "pushed twice");
                prop_assert!(!listed_ids.contains(&id) && !is_anchor(&id));
                let parent = parent_of[&id];
                prop_assert!(
                    listed_ids.contains(&parent) || is_anchor(&parent) || seen.contains(&parent),
                    "a push before its parent"
                );
                prop_assert!(f64::from(t[&id].root.depth) < limit, "deeper than its limit");
            }
            if plan.len() < budget {
                let plain = plan_pushes(CUBE, &view, &later, 10_000, shape);
                for (id, _) in plain {
                    prop_assert!(seen.contains(&id) || is_anchor(&id), "{id:?} lost");
                }
            }
        }
    }

    #[test]
    fn full_anchors_walk_nothing_so_nothing_sent_is_pushed_again() {
        let t = tree(3);
        let shape = |id: TreeletId| t.get(&id).cloned();
        let view = view_from([0.5, 0.5, 3.0], 0.001);
        let root = [(TreeletId(0), 1.0, 10.0)];
        let mut anchors = PushAnchors::with_max(5);
        anchors.for_view(&view);
        let first = plan_pushes_anchored(CUBE, &view, &root, [], |_| None, 12, shape).pushes;
        assert_eq!(first.len(), 12);
        anchors.record(&root, &first, shape);
        assert_eq!(anchors.len(), 5, "the root and four pushes kept");
        assert!(anchors.is_full(), "eight more came than could be kept");
        let sent: Vec<TreeletId> = std::iter::once(TreeletId(0))
            .chain(first.iter().map(|p| p.0))
            .collect();
        anchors.note_sent(&sent);
        // Walking the kept anchors would push the sent children that could not be kept (and
        // so are not known as sent) again, on every list.
        let other = [(TreeletId(100), 1.0, 0.0)];
        assert_eq!(anchors.roots(&other).count(), 0);
        let plan = plan_with_anchors(&t, &anchors, &view, &other, 100);
        assert!(plan.pushes.iter().all(|p| !sent.contains(&p.0)), "{plan:?}");
        // A new view starts empty and not full.
        let mut moved = view;
        moved.eye[1] += 0.25;
        anchors.for_view(&moved);
        assert!(anchors.is_empty() && !anchors.is_full());
    }

    proptest! {
        /// However the sends come (in batches, parents before or after children, a reset
        /// stream, a listed treelet's limit deepened) and however small the budgets: a plan
        /// never closes an anchor with a child still to send (one not sent that passes the
        /// depth and view tests); and a plan with room for everything closes every anchor
        /// with none, so the open anchors are exactly those a full rescan finds.
        #[test]
        fn plans_close_exactly_the_exhausted_anchors(
            error in 0f32..4.0,
            batches in proptest::collection::vec(
                (
                    proptest::collection::vec(any::<proptest::sample::Index>(), 0..40),
                    0usize..30,
                ),
                1..6,
            ),
            reset_at in proptest::option::of(0usize..6),
            deepen_at in proptest::option::of(0usize..6),
        ) {
            let t = tree(3);
            let shape = |id: TreeletId| t.get(&id).cloned();
            let view = view_from([0.4, 0.6, 2.5], 0.002);
            let mut items = vec![(TreeletId(0), 1.0, error)];
            let mut anchors = PushAnchors::default();
            anchors.for_view(&view);
            let first =
                plan_pushes_anchored(CUBE, &view, &items, [], |_| None, 10_000, shape).pushes;
            anchors.record(&items, &first, shape);
            let candidates: Vec<TreeletId> = std::iter::once(TreeletId(0))
                .chain(first.iter().map(|p| p.0))
                .collect();
            let rescan = |anchors: &PushAnchors| -> BTreeSet<TreeletId> {
                candidates
                    .iter()
                    .copied()
                    .filter(|&id| {
                        let Some(limit) = anchors.sent_limit(id) else {
                            return false;
                        };
                        t[&id].children.iter().any(|&(child, cell)| {
                            let (min, max) = CUBE.cell_box(cell);
                            anchors.sent_limit(child).is_none()
                                && f64::from(cell.depth) < limit
                                && view.box_error(min, max).is_some_and(|e| e > 0.0)
                        })
                    })
                    .collect()
            };
            let plan_with = |anchors: &mut PushAnchors, budget: usize| {
                let plan = plan_with_anchors(&t, anchors, &view, &[], budget);
                anchors.record(&[], &plan.pushes, shape);
                anchors.note_exhausted(&plan.exhausted);
            };
            let open = |anchors: &PushAnchors| -> BTreeSet<TreeletId> {
                anchors.roots(&[]).map(|r| r.0).collect()
            };
            let mut sent_so_far = Vec::new();
            let mut deepened = false;
            for (k, (batch, budget)) in batches.iter().enumerate() {
                let batch: Vec<TreeletId> =
                    batch.iter().map(|i| candidates[i.index(candidates.len())]).collect();
                anchors.note_sent(&batch);
                sent_so_far.extend_from_slice(&batch);
                if reset_at == Some(k) && !sent_so_far.is_empty() {
                    anchors.note_unsent(&sent_so_far[..1]);
                }
                if deepen_at == Some(k) {
                    items[0].2 += 1.5;
                    anchors.record(&items, &[], shape);
                    deepened = true;
                }
                plan_with(&mut anchors, *budget);
                let expected = rescan(&anchors);
                prop_assert!(open(&anchors).is_superset(&expected), "after batch {}", k);
                if !deepened {
                    // One limit for all (the root's error), so no anchor is walked again from
                    // above with a larger one: room for everything judges every anchor.
                    plan_with(&mut anchors, usize::MAX);
                    prop_assert_eq!(open(&anchors), expected, "after batch {}", k);
                }
            }
        }
    }

    /// What a handler's plan sees: the test tree's shapes, of which a cache holds `held`.
    fn from_cache<'a>(
        t: &'a HashMap<TreeletId, Arc<TreeletShape>>,
        held: &'a HashSet<TreeletId>,
    ) -> impl FnMut(TreeletId) -> Result<Option<Arc<TreeletShape>>, ShapeMissing> + 'a {
        move |id| {
            if held.contains(&id) {
                Ok(t.get(&id).cloned())
            } else {
                Err(ShapeMissing)
            }
        }
    }

    #[test]
    fn a_frustum_list_missing_a_shape_is_given_up_and_made_again_the_same() {
        let t = tree(3);
        let all = |id: TreeletId| Ok(t.get(&id).cloned());
        let mut view = view_from([0.5, 0.5, 3.0], 0.001);
        view.free_slots = 1 + 12;
        let root = [(TreeletId(0), 1.0, 10.0)];
        // `reference` always has every shape; `cached` only what its cache holds, and makes
        // a plan it has to give up again with every shape, as the handler does on a reader.
        let mut reference = PushAnchors::default();
        let mut cached = PushAnchors::default();
        let expected = frustum_list(CUBE, &view, &root, &mut reference, 100, all).unwrap();
        assert_eq!(expected.pushed, 12);
        let mut held = HashSet::from([TreeletId(0)]);
        let before = PushAnchors::default();
        assert_eq!(
            frustum_list(CUBE, &view, &root, &mut cached, 100, from_cache(&t, &held)),
            Err(ShapeMissing),
            "the root's children are not held"
        );
        let mut fresh = PushAnchors::default();
        fresh.for_view(&view);
        assert_eq!(
            cached, fresh,
            "a plan given up leaves the anchors as they were"
        );
        assert_ne!(cached, before, "(but moved to the view)");
        let again = frustum_list(CUBE, &view, &root, &mut cached, 100, all).unwrap();
        assert_eq!(again, expected);
        assert_eq!(cached, reference);

        // What went out becomes anchors; the next list names a leaf elsewhere, and the plan
        // goes on below the anchors, whose shapes the cache must hold as well.
        let sent: Vec<TreeletId> = std::iter::once(TreeletId(0))
            .chain(expected.items[1..9].iter().map(|i| i.0))
            .collect();
        reference.note_sent(&sent);
        cached.note_sent(&sent);
        let other = [(TreeletId(100), 1.0, 0.0)];
        let expected = frustum_list(CUBE, &view, &other, &mut reference, 100, all).unwrap();
        assert!(expected.pushed > 0, "the queued grandchildren again");
        held.insert(TreeletId(100));
        let before = cached.clone();
        assert_eq!(
            frustum_list(CUBE, &view, &other, &mut cached, 100, from_cache(&t, &held)),
            Err(ShapeMissing),
            "the anchors' shapes are not held"
        );
        assert_eq!(cached, before, "nothing recorded, nothing closed");
        held.extend(t.keys().copied());
        assert_eq!(
            frustum_list(CUBE, &view, &other, &mut cached, 100, from_cache(&t, &held)),
            Ok(expected),
            "with every shape held the plan is made at once, the same"
        );
        assert_eq!(cached, reference);

        // No room for pushes: no walk, but the listed items are still recorded with the
        // limits their shapes give, so their shapes must be held too.
        view.free_slots = 1;
        let leaf = [(TreeletId(200), 1.0, 3.0)];
        held.remove(&TreeletId(200));
        assert_eq!(
            frustum_list(CUBE, &view, &leaf, &mut cached, 100, from_cache(&t, &held)),
            Err(ShapeMissing)
        );
        let expected = frustum_list(CUBE, &view, &leaf, &mut reference, 100, all).unwrap();
        assert_eq!((expected.items.len(), expected.pushed), (1, 0));
        assert_eq!(
            frustum_list(CUBE, &view, &leaf, &mut cached, 100, all),
            Ok(expected)
        );
        assert_eq!(cached, reference);
    }

    #[test]
    fn lent_anchors_come_back_as_if_they_had_stayed() {
        let t = tree(3);
        let shape = |id: TreeletId| t.get(&id).cloned();
        let mut view = view_from([0.5, 0.5, 3.0], 0.001);
        view.free_slots = 1 + 12;
        let root = [(TreeletId(0), 1.0, 10.0)];
        let mut stayed = PushAnchors::default();
        stayed.for_view(&view);
        let plan = plan_with_anchors(&t, &stayed, &view, &root, 12);
        stayed.record(&root, &plan.pushes, shape);
        let mut lent = LentAnchors::from(stayed.clone());
        let ids: Vec<TreeletId> = plan.pushes.iter().map(|p| p.0).collect();
        let away = lent.lend().unwrap();
        assert!(lent.is_lent() && lent.get_mut().is_none() && lent.lend().is_none());
        // Streams report while the anchors are away; the same reports reach `stayed` at once.
        let reports: [(bool, &[TreeletId]); 4] = [
            (true, &[TreeletId(0)]),
            (true, &ids[..8]),
            (false, &ids[2..3]),
            (true, &ids[8..]),
        ];
        for (sent, batch) in reports {
            if sent {
                lent.note_sent(batch);
                stayed.note_sent(batch);
            } else {
                lent.note_unsent(batch);
                stayed.note_unsent(batch);
            }
        }
        lent.give_back(Some(away));
        assert!(!lent.is_lent());
        assert_eq!(lent.get_mut(), Some(&mut stayed));
        assert_eq!(
            open_roots(&stayed, &[]).len(),
            12,
            "{:?}",
            open_roots(&stayed, &[])
        );
        // Reports while home go straight in; anchors lost with their plan start again.
        lent.note_unsent(&ids[..1]);
        stayed.note_unsent(&ids[..1]);
        assert_eq!(lent.get_mut(), Some(&mut stayed));
        let _lost = lent.lend();
        lent.note_sent(&ids);
        lent.give_back(None);
        assert_eq!(lent.get_mut(), Some(&mut PushAnchors::default()));
    }

    #[test]
    fn a_deferred_plan_replaces_its_list_only_if_none_came_since() {
        let seq = |l: &(u64, &str)| l.0;
        let mut plans = DeferredPlans::default();
        // List 1 goes without its pushes; its plan starts and comes back with nothing applied
        // since: applied under 1.
        plans.applied();
        plans.defer((1, "one"));
        assert_eq!(plans.start(seq), Some((1, "one")));
        plans.defer((1, "one again"));
        assert_eq!(plans.start(seq), None, "a plan is being made");
        assert_eq!(plans.finish(), Some(1));
        plans.planned_at_once();
        assert_eq!(plans.take_waiting(), None);
        plans.applied();

        // List 2 is deferred and planning; list 3 is deferred meanwhile and waits for the plan
        // being made, whose list is then stale.
        plans.applied();
        plans.defer((2, "two"));
        assert_eq!(plans.start(seq), Some((2, "two")));
        plans.applied();
        plans.defer((3, "three"));
        assert_eq!(plans.start(seq), None, "one plan at a time");
        assert_eq!(plans.finish(), None, "list 3 came since");
        assert_eq!(plans.take_waiting(), Some((3, "three")));
        // Planned at once now (the shapes came with list 2's plan) and applied.
        plans.applied();

        // List 4 is deferred; before its plan ends list 5 is planned at once: list 4's plan
        // is stale and nothing waits.
        plans.applied();
        plans.defer((4, "four"));
        assert_eq!(plans.start(seq), Some((4, "four")));
        plans.applied();
        plans.planned_at_once();
        assert_eq!(plans.finish(), None);
        assert_eq!(plans.take_waiting(), None);

        // List 6 is deferred and planning; list 7 is deferred meanwhile, and then a visible
        // cut's re-plan of list 7 is applied: list 6's plan is stale, and list 7 waits no more.
        plans.applied();
        plans.defer((6, "six"));
        assert_eq!(plans.start(seq), Some((6, "six")));
        plans.applied();
        plans.defer((7, "seven"));
        plans.applied();
        assert_eq!(plans.finish(), None);
        assert_eq!(plans.take_waiting(), None, "the cut's list replaced list 7");
        plans.defer((8, "eight"));
        assert_eq!(
            plans.start(seq),
            Some((8, "eight")),
            "no plan is being made"
        );
    }

    #[test]
    fn a_list_carries_a_few_windows_of_pushes() {
        assert_eq!(push_cap(0), MIN_PUSHES_PER_LIST);
        assert_eq!(
            push_cap(8),
            MIN_PUSHES_PER_LIST,
            "the default smallest window"
        );
        assert_eq!(
            push_cap(300),
            2400,
            "about a 100 Mbit/s, 50 ms link's window"
        );
        assert_eq!(push_cap(1024), 8192, "the default largest window");
        assert_eq!(push_cap(usize::MAX), usize::MAX);
        // The cap limits the plan like the free slots do, whichever is smaller.
        let t = tree(4);
        let shape = |id: TreeletId| t.get(&id).cloned();
        let mut view = view_from([0.5, 0.5, 3.0], 0.001);
        view.free_slots = 100_000;
        let root = [(TreeletId(0), 1.0, 10.0)];
        let cap = push_cap(8);
        let (list, pushed) = deep_list(CUBE, &view, &root, root.len() + cap, shape);
        assert_eq!((list.len(), pushed), (1 + cap, cap));
        let (_, all) = deep_list(CUBE, &view, &root, usize::MAX, shape);
        assert!(all > cap, "the view implies more than the cap: {all}");
    }

    #[test]
    fn a_cut_has_work_only_with_room_for_pushes_or_prefetch_to_set_apart() {
        let mut view = view_from([0.5, 0.5, 3.0], 0.001);
        view.free_slots = 10;
        assert!(
            !cut_has_work(&view, 10, 10),
            "every free slot listed, no prefetch"
        );
        assert!(!cut_has_work(&view, 12, 12), "more listed than free");
        assert!(cut_has_work(&view, 9, 9), "one slot left to push into");
        assert!(cut_has_work(&view, 10, 8), "prefetch to set apart");
        view.free_slots = 0;
        assert!(!cut_has_work(&view, 0, 0), "an empty list of a full client");
        assert!(cut_has_work(&view, 3, 0), "all of it prefetch");
    }

    #[test]
    fn pushes_follow_the_view_the_error_and_the_budget() {
        let t = tree(4);
        let shape = |id: TreeletId| t.get(&id).cloned();
        let view = view_from([0.5, 0.5, 3.0], 0.001);
        // Root listed with a large error: everything in view down to depth 4, parents first.
        let all = plan_pushes(CUBE, &view, &[(TreeletId(0), 1.0, 10.0)], 10_000, shape);
        assert_eq!(all.len(), 8 + 64 + 512 + 4096);
        assert!(
            all.windows(2).all(|w| w[0].1 <= w[1].1),
            "generations ascend"
        );
        // The error limits the depth: 2.5 levels below the root's depth 0 → children at depth
        // 1 and 2 only.
        let shallow = plan_pushes(CUBE, &view, &[(TreeletId(0), 1.0, 2.5)], 10_000, shape);
        assert_eq!(shallow.len(), 8 + 64);
        // The budget cuts the plan, keeping the first (coarsest) ones.
        let cut = plan_pushes(CUBE, &view, &[(TreeletId(0), 1.0, 10.0)], 20, shape);
        assert_eq!(cut, all[..20]);
        // Looking away: nothing. A zero budget: nothing.
        let away = view_from([0.5, 0.5, -3.0], 0.001);
        assert!(plan_pushes(CUBE, &away, &[(TreeletId(0), 1.0, 10.0)], 100, shape).is_empty());
        assert!(plan_pushes(CUBE, &view, &[(TreeletId(0), 1.0, 10.0)], 0, shape).is_empty());
        // A coarse footprint: only boxes larger than a pixel.
        let coarse = view_from([0.5, 0.5, 3.0], 0.2);
        let few = plan_pushes(CUBE, &coarse, &[(TreeletId(0), 1.0, 10.0)], 10_000, shape);
        assert!(few.len() < all.len() && !few.is_empty());
        // Listed items are never pushed.
        let listed = [(TreeletId(0), 1.0, 10.0), (TreeletId(1), 1.0, 10.0)];
        let p = plan_pushes(CUBE, &view, &listed, 10_000, shape);
        assert!(p.iter().all(|(id, _)| id.0 > 1));
    }

    proptest! {
        /// Whatever the lists and budgets: never over budget, no duplicates, nothing listed,
        /// every push a descendant of a listed item, parents before children.
        #[test]
        fn plans_keep_their_invariants(
            listed in proptest::collection::vec((0u32..585, 0f32..8.0), 1..6),
            budget in 0usize..300,
            eye in (-2.0f64..3.0, -2.0f64..3.0, 1.5f64..6.0),
            footprint in 0.0005f32..0.05,
        ) {
            let t = tree(3);
            let items: Vec<_> = listed.iter().map(|&(id, e)| (TreeletId(id), 1.0, e)).collect();
            let view = view_from([eye.0, eye.1, eye.2], footprint);
            let plan = plan_pushes(CUBE, &view, &items, budget, |id| t.get(&id).cloned());
            prop_assert!(plan.len() <= budget);
            let mut seen = HashSet::new();
            let mut parent_of = HashMap::new();
            for (id, shape) in &t {
                for (c, _) in &shape.children {
                    parent_of.insert(*c, *id);
                }
            }
            let listed_ids: HashSet<_> = items.iter().map(|i| i.0).collect();
            for (id, _) in &plan {
                prop_assert!(seen.insert(*id), "pushed twice");
                prop_assert!(!listed_ids.contains(id), "a listed item pushed");
                let parent = parent_of[id];
                prop_assert!(
                    listed_ids.contains(&parent) || seen.contains(&parent),
                    "a push before its parent"
                );
            }
        }
    }

    #[test]
    fn push_priorities_stay_below_the_list() {
        assert!(push_priority(0.5, 1) < 0.5);
        assert!(push_priority(-3.0, 1) < -3.0);
        assert!(push_priority(2.0, 2) < push_priority(2.0, 1));
        // Where `x - 1.0 == x` in f32: still strictly below, generations still ordered.
        for lowest in [-3.0e7f32, -1.0e20, -1.0e37] {
            assert!(push_priority(lowest, 1) < lowest);
            assert!(push_priority(lowest, 2) < push_priority(lowest, 1));
        }
        assert!(!push_priority(-f32::MAX, 1).is_finite());
    }

    proptest! {
        /// The deep list through the real scheduler: every listed item starts before any push
        /// (whatever the listed priorities), the pushes stay within the announced free slots,
        /// and a newer list that no longer implies the pushes in flight makes them obsolete
        /// (the service then resets their streams).
        #[test]
        fn deep_lists_through_the_scheduler(
            listed in proptest::collection::vec((0u32..73, -1.0e30f32..1.0e30, 0f32..8.0), 1..6),
            free_slots in 0u32..400,
            window in 1usize..64,
            eye in (0.0f64..1.0, 0.0f64..1.0, 1.5f64..4.0),
        ) {
            use crate::service::schedule::{ConnectionConfig, ConnectionId, ListOutcome, Scheduler};
            use std::time::{Duration, Instant};
            let t = tree(3);
            let items: Vec<_> = listed.iter().map(|&(id, p, e)| (TreeletId(id), p, e)).collect();
            let mut view = view_from([eye.0, eye.1, eye.2], 0.001);
            view.free_slots = free_slots;
            let shape = |id: TreeletId| t.get(&id).cloned();
            let (list, pushed) = deep_list(CUBE, &view, &items, 4096, shape);
            let listed_ids: HashSet<_> = items.iter().map(|i| i.0).collect();
            prop_assert!(pushed <= (free_slots as usize).saturating_sub(items.len()));

            let conn = ConnectionId(1);
            let cfg = ConnectionConfig { window, redelivery_guard: Duration::ZERO, ..Default::default() };
            let now = Instant::now();
            let start = |list: Vec<(TreeletId, f32)>| {
                let mut s = Scheduler::default();
                s.add_connection(conn, cfg.clone()).unwrap();
                s.handle_request_list(conn, 1, list, now).unwrap();
                s
            };
            // Everything sent, each delivered at once: the order of starts.
            let mut s = start(list.clone());
            let mut order = Vec::new();
            while let Some((_, id)) = s.poll_transmit(now) {
                order.push(id);
                s.handle_delivered(conn, id, now);
            }
            let first_push = order.iter().position(|id| !listed_ids.contains(id));
            if let Some(i) = first_push {
                prop_assert!(order[i..].iter().all(|id| !listed_ids.contains(id)), "listed after a push");
            }
            prop_assert_eq!(order.iter().filter(|id| listed_ids.contains(id)).count(), listed_ids.len());
            prop_assert_eq!(order.len(), listed_ids.len() + pushed);

            // The first push in flight; a newer list looking away implies no pushes.
            if pushed > 0 {
                let mut s = start(list);
                let in_flight = loop {
                    let (_, id) = s.poll_transmit(now).expect("the push is sent");
                    if !listed_ids.contains(&id) {
                        break id;
                    }
                    s.handle_delivered(conn, id, now);
                };
                let away = view_from([eye.0, eye.1, -eye.2], 0.001);
                let (newer, none) = deep_list(CUBE, &ViewHint { free_slots, ..away }, &items, 4096, shape);
                prop_assert_eq!(none, 0);
                match s.handle_request_list(conn, 2, newer, now).unwrap() {
                    ListOutcome::Applied { obsolete_in_flight, .. } => {
                        prop_assert_eq!(obsolete_in_flight, vec![in_flight]);
                    }
                    other => prop_assert!(false, "{other:?}"),
                }
            }
        }
    }
}
