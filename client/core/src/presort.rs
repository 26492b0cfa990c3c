//! Presort (docs/design.md §5): from one cycle's feedback samples, the set of *visible* treelets and
//! the *request list*, de-duplicated and sorted by priority.
//!
//! A plain data structure with no I/O, no GPU and no slot buffer: the caller passes a lookup
//! from slot to `(treelet, parent slot)`, so presort is tested on its own and runs the same
//! behind the CPU and the GPU analysis pass.
//!
//! * **Visible**: the slot of every hit node and all its ancestor slots up to the root. The slot
//!   buffer refreshes their visibility, so a treelet the camera sees is never evicted, and
//!   neither is any treelet on its path to the root.
//! * **Requests**: the subtreelets of hit leaves whose voxel is coarser than a pixel (`error >
//!   0`). Each keeps the largest error any sample saw and the number of samples that saw it.
//!   Priorities are computed by the selected [`PriorityPolicy`]; the list is sorted highest
//!   first (ties by lower id, the server's own tie rule), then capped.

use arbor_proto::TreeletId;
use rustc_hash::FxHashMap;

use crate::analysis::FeedbackSample;

/// How a request's priority is computed from what the feedback saw, or, for
/// [`PriorityPolicy::Frustum`], whether the feedback decides at all.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PriorityPolicy {
    /// The largest screen-space error any sample saw (the thesis's rule).
    MaxError,
    /// Largest error × pixels that saw it: a treelet covering many pixels matters more.
    #[default]
    ErrorTimesPixels,
    /// Largest error × pixels that saw it, each pixel weighted by its closeness to the screen
    /// centre ([`centre_weight`]): what the user looks at refines first.
    Centre,
    /// The peer's rule (Potree, Cesium): refinable leaves in the view frustum by projected size,
    /// no feedback, no occlusion (see [`crate::frustum`]).
    Frustum,
}

impl PriorityPolicy {
    /// Every policy, in the order the CLI lists them.
    pub const ALL: [PriorityPolicy; 4] = [
        PriorityPolicy::MaxError,
        PriorityPolicy::ErrorTimesPixels,
        PriorityPolicy::Centre,
        PriorityPolicy::Frustum,
    ];

    /// Parses `max-error`, `error-pixels`, `centre` or `frustum` (the CLI spelling).
    pub fn parse(text: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|p| p.name() == text)
    }

    /// The command-line spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::MaxError => "max-error",
            Self::ErrorTimesPixels => "error-pixels",
            Self::Centre => "centre",
            Self::Frustum => "frustum",
        }
    }
}

/// Weight of pixel `(x, y)` of a `width × height` frame for [`PriorityPolicy::Centre`]:
/// `exp(−2 r²)` with `r` the distance from the centre in half frame heights (1 at the centre,
/// 0.14 at the middle of the top edge).
pub fn centre_weight(x: u32, y: u32, width: u32, height: u32) -> f32 {
    let half = f64::from(height.max(1)) * 0.5;
    let dx = (f64::from(x) + 0.5 - f64::from(width) * 0.5) / half;
    let dy = (f64::from(y) + 0.5 - f64::from(height) * 0.5) / half;
    (-2.0 * (dx * dx + dy * dy)).exp() as f32
}

/// One de-duplicated request.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RequestItem {
    /// The treelet that refines what the samples hit.
    pub id: TreeletId,
    /// Largest screen-space error (octree levels) of any sample that hit the refinable leaf.
    pub error: f32,
    /// Samples that hit it.
    pub samples: u32,
    /// Sum of the samples' weights (1 each, except for [`PriorityPolicy::Centre`]).
    pub weight: f32,
    /// What the list is sorted by (see [`PriorityPolicy`]); finite and > 0.
    pub priority: f32,
}

/// The result of one presort.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Presorted {
    /// Slots of hit treelets and all their ancestors, ascending, each once.
    pub visible_slots: Vec<u32>,
    /// Highest priority first, at most the cap.
    pub requests: Vec<RequestItem>,
    /// Distinct refinable treelets seen before the cap cut the list.
    pub distinct_requests: usize,
}

/// Reusable presort state: the maps are kept between cycles so a cycle allocates nothing once
/// warm.
#[derive(Debug, Default)]
pub struct Presort {
    policy: PriorityPolicy,
    max_requests: usize,
    seen_slots: Vec<bool>,
    /// Per requested treelet: largest error, samples, summed weight.
    requests: FxHashMap<TreeletId, (f32, u32, f32)>,
}

impl Presort {
    /// `max_requests` caps the list (at least 1).
    pub fn new(policy: PriorityPolicy, max_requests: usize) -> Self {
        Self {
            policy,
            max_requests: max_requests.max(1),
            seen_slots: Vec::new(),
            requests: FxHashMap::default(),
        }
    }

    /// The ranking policy.
    pub fn policy(&self) -> PriorityPolicy {
        self.policy
    }

    /// Runs presort over `samples`, each weighing 1. `treelet_nodes` is `N`;
    /// `parent_slot(slot)` gives the slot of a slot's parent treelet (`None` for the root slot);
    /// `skip(id)` says a subtreelet must not be requested (already resident or waiting to be
    /// inserted).
    pub fn run(
        &mut self,
        samples: &[FeedbackSample],
        treelet_nodes: u32,
        slot_count: u32,
        parent_slot: impl Fn(u32) -> Option<u32>,
        skip: impl Fn(TreeletId) -> bool,
    ) -> Presorted {
        self.run_weighted(
            samples.iter().map(|s| (1.0, s)),
            treelet_nodes,
            slot_count,
            parent_slot,
            skip,
            |_| None,
        )
    }

    /// [`run`](Self::run) over `(weight, sample)` pairs (the weight counts for
    /// [`PriorityPolicy::Centre`]). `resident_slot(id)` gives the slot of a resident treelet:
    /// a sample that wants a subtreelet already resident was taken before it arrived (the
    /// slot buffer changes between a sample and its presort: the GPU's feedback is a cycle
    /// late, and any pixel's sample may be many cycles old), so its ray now enters that
    /// subtreelet, and the subtreelet counts as visible. Without it, a full buffer evicted
    /// what had just arrived for the view as "seen by no pixel", and asked for it again as
    /// soon as the pixel was sampled afresh.
    pub fn run_weighted<'a>(
        &mut self,
        samples: impl Iterator<Item = (f32, &'a FeedbackSample)>,
        treelet_nodes: u32,
        slot_count: u32,
        parent_slot: impl Fn(u32) -> Option<u32>,
        skip: impl Fn(TreeletId) -> bool,
        resident_slot: impl Fn(TreeletId) -> Option<u32>,
    ) -> Presorted {
        self.seen_slots.clear();
        self.seen_slots.resize(slot_count as usize, false);
        self.requests.clear();
        let mut visible = Vec::new();
        let mut run: Option<Run> = None;
        for (weight, s) in samples.filter(|(_, s)| s.is_hit()) {
            let mut slot = s.node / treelet_nodes;
            // Walk up until a slot already marked: its ancestors are marked too.
            while let Some(seen) = self.seen_slots.get_mut(slot as usize) {
                if *seen {
                    break;
                }
                *seen = true;
                visible.push(slot);
                match parent_slot(slot) {
                    Some(p) => slot = p,
                    None => break,
                }
            }
            if !s.wants_refinement() {
                continue;
            }
            // Neighbouring pixels mostly want the same treelet: a run of them is looked up
            // and checked once, and adds to its entry in the same order as one by one.
            let id = TreeletId(s.subtreelet);
            if run.as_ref().is_none_or(|r| r.id != id) {
                if let Some(r) = run.take() {
                    r.store(&mut self.requests);
                }
                let skipped = skip(id);
                if skipped
                    && let Some(child) = resident_slot(id)
                    && let Some(seen) = self.seen_slots.get_mut(child as usize)
                    && !*seen
                {
                    // Its parent is the slot this sample hit, marked above.
                    *seen = true;
                    visible.push(child);
                }
                let sums = self.requests.get(&id).copied().unwrap_or((s.error, 0, 0.0));
                run = Some(Run { id, skipped, sums });
            }
            if let Some(r) = run.as_mut().filter(|r| !r.skipped) {
                r.sums.0 = r.sums.0.max(s.error);
                r.sums.1 += 1;
                r.sums.2 += weight;
            }
        }
        if let Some(r) = run {
            r.store(&mut self.requests);
        }
        visible.sort_unstable();
        let policy = self.policy;
        let mut requests: Vec<RequestItem> = self
            .requests
            .iter()
            .map(|(&id, &(error, samples, weight))| RequestItem {
                id,
                error,
                samples,
                weight,
                priority: match policy {
                    PriorityPolicy::MaxError | PriorityPolicy::Frustum => error,
                    PriorityPolicy::ErrorTimesPixels => error * samples as f32,
                    // A tiny floor keeps the priority > 0 far from the centre.
                    PriorityPolicy::Centre => error * weight.max(1e-6),
                },
            })
            .collect();
        let distinct_requests = requests.len();
        sort_by_priority(&mut requests);
        requests.truncate(self.max_requests);
        Presorted {
            visible_slots: visible,
            requests,
            distinct_requests,
        }
    }
}

/// Consecutive samples wanting the same treelet: whether it is skipped, and its sums so far
/// (largest error, samples, summed weight).
struct Run {
    id: TreeletId,
    skipped: bool,
    sums: (f32, u32, f32),
}

impl Run {
    fn store(self, requests: &mut FxHashMap<TreeletId, (f32, u32, f32)>) {
        if !self.skipped {
            requests.insert(self.id, self.sums);
        }
    }
}

/// Highest priority first, ties by lower id (the server's own tie rule).
pub fn sort_by_priority(requests: &mut [RequestItem]) {
    requests.sort_unstable_by(|a, b| {
        b.priority
            .total_cmp(&a.priority)
            .then_with(|| a.id.cmp(&b.id))
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hit(node: u32, sub: u32, error: f32) -> FeedbackSample {
        FeedbackSample {
            node,
            subtreelet: sub,
            error,
            t: 1.0,
        }
    }

    /// Slots 0 ← 1 ← 2, 0 ← 3 (parent links).
    fn parent(slot: u32) -> Option<u32> {
        match slot {
            0 => None,
            1 => Some(0),
            2 => Some(1),
            3 => Some(0),
            _ => panic!("no slot {slot}"),
        }
    }

    #[test]
    fn visible_slots_include_ancestors_once() {
        let n = 16;
        let samples = [
            hit(2 * n + 5, u32::MAX, -1.0),
            hit(2 * n + 6, u32::MAX, -1.0),
            FeedbackSample::MISS,
        ];
        let mut p = Presort::new(PriorityPolicy::MaxError, 10);
        let out = p.run(&samples, n, 4, parent, |_| false);
        assert_eq!(out.visible_slots, vec![0, 1, 2]);
        assert!(out.requests.is_empty());
        let out = p.run(&[hit(3 * n, 7, 0.5)], n, 4, parent, |_| false);
        assert_eq!(out.visible_slots, vec![0, 3]);
    }

    #[test]
    fn requests_keep_max_error_and_count_samples() {
        let samples = [
            hit(1, 9, 1.0),
            hit(2, 9, 3.0),
            hit(3, 4, 2.0),
            hit(4, 4, 0.0),
        ];
        let mut p = Presort::new(PriorityPolicy::MaxError, 10);
        let out = p.run(&samples, 16, 4, parent, |_| false);
        assert_eq!(out.requests.len(), 2, "error 0 is not a request");
        assert_eq!(out.requests[0].id, TreeletId(9));
        assert_eq!(out.requests[0].error, 3.0);
        assert_eq!(out.requests[0].samples, 2);
        assert_eq!(out.requests[1].samples, 1);
    }

    #[test]
    fn policies_order_differently_and_cap_applies() {
        // Treelet 5: one sample at error 3. Treelet 6: four samples at error 1.
        let mut samples = vec![hit(1, 5, 3.0)];
        samples.extend((0..4).map(|i| hit(2 + i, 6, 1.0)));
        let mut thesis = Presort::new(PriorityPolicy::MaxError, 10);
        let ids: Vec<_> = thesis
            .run(&samples, 16, 4, parent, |_| false)
            .requests
            .iter()
            .map(|r| r.id.0)
            .collect();
        assert_eq!(ids, vec![5, 6]);
        let mut arbor = Presort::new(PriorityPolicy::ErrorTimesPixels, 1);
        let out = arbor.run(&samples, 16, 4, parent, |_| false);
        assert_eq!(out.requests.len(), 1);
        assert_eq!(out.requests[0].id, TreeletId(6));
        assert_eq!(out.requests[0].priority, 4.0);
        assert_eq!(out.distinct_requests, 2);
    }

    #[test]
    fn ties_break_by_lower_id_and_skip_filters() {
        let samples = [hit(1, 8, 2.0), hit(2, 3, 2.0), hit(3, 5, 2.0)];
        let mut p = Presort::new(PriorityPolicy::MaxError, 10);
        let out = p.run(&samples, 16, 4, parent, |id| id == TreeletId(5));
        let ids: Vec<_> = out.requests.iter().map(|r| r.id.0).collect();
        assert_eq!(ids, vec![3, 8]);
    }

    #[test]
    fn centre_weights_favour_the_middle_of_the_frame() {
        let c = centre_weight(50, 50, 100, 100);
        assert!(c > 0.99, "{c}");
        let edge = centre_weight(50, 0, 100, 100);
        assert!((edge - (-2.0f32).exp()).abs() < 0.01, "{edge}");
        // Treelet 5 seen by one central sample at error 2, treelet 6 by two edge samples at 2.
        let mut p = Presort::new(PriorityPolicy::Centre, 10);
        let (a, b) = (hit(1, 5, 2.0), hit(2, 6, 2.0));
        let out = p.run_weighted(
            [(c, &a), (edge, &b), (edge, &b)].into_iter(),
            16,
            4,
            parent,
            |_| false,
            |_| None,
        );
        assert_eq!(out.requests[0].id, TreeletId(5));
        assert_eq!(out.requests[1].samples, 2);
        for policy in PriorityPolicy::ALL {
            assert_eq!(PriorityPolicy::parse(policy.name()), Some(policy));
        }
    }

    #[test]
    fn a_sample_taken_before_its_subtreelet_arrived_keeps_that_subtreelet_visible() {
        // The samples hit leaves of slot 1 wanting treelets 9 and 7; 9 has arrived since, in
        // slot 2 (a child of slot 1), 7 has not.
        let n = 16;
        let samples = [hit(n + 3, 9, 2.0), hit(n + 4, 9, 2.0), hit(n + 5, 7, 1.0)];
        let resident = |id: TreeletId| (id == TreeletId(9)).then_some(2);
        let mut p = Presort::new(PriorityPolicy::MaxError, 10);
        let out = p.run_weighted(
            samples.iter().map(|s| (1.0, s)),
            n,
            4,
            parent,
            |id| resident(id).is_some(),
            resident,
        );
        assert_eq!(out.visible_slots, vec![0, 1, 2]);
        assert_eq!(out.requests.len(), 1);
        assert_eq!(out.requests[0].id, TreeletId(7));
        // Without the resident lookup the arrival looks unseen: what the fix is for.
        let out = p.run(&samples, n, 4, parent, |id| resident(id).is_some());
        assert_eq!(out.visible_slots, vec![0, 1]);
    }

    #[test]
    fn nodes_outside_the_slot_range_are_ignored_not_panicking() {
        let mut p = Presort::new(PriorityPolicy::MaxError, 10);
        let out = p.run(&[hit(1000, 2, 1.0)], 16, 4, parent, |_| false);
        assert!(out.visible_slots.is_empty());
        assert_eq!(out.requests.len(), 1);
    }

    proptest::proptest! {
        /// Runs of one treelet are looked up once: the result equals summing sample by sample,
        /// weights included bit for bit, with runs, interleavings, misses, fine hits and skips.
        #[test]
        fn runs_sum_as_sample_by_sample(
            samples in proptest::collection::vec(
                (0u32..64, 0u32..6, -1.0f32..4.0, 0.0f32..1.0, proptest::bool::ANY),
                0..300,
            ),
        ) {
            let samples: Vec<(f32, FeedbackSample)> = samples
                .into_iter()
                .map(|(node, sub, error, weight, miss)| {
                    let s = if miss { FeedbackSample::MISS } else { hit(node, sub, error) };
                    (weight, s)
                })
                .collect();
            let skip = |id: TreeletId| id.0 == 3;
            let mut p = Presort::new(PriorityPolicy::Centre, 100);
            let got = p.run_weighted(
                samples.iter().map(|(w, s)| (*w, s)),
                16,
                4,
                parent,
                skip,
                |_| None,
            );
            let mut want: std::collections::BTreeMap<u32, (f32, u32, f32)> = Default::default();
            for (w, s) in &samples {
                if s.wants_refinement() && !skip(TreeletId(s.subtreelet)) {
                    let e = want.entry(s.subtreelet).or_insert((s.error, 0, 0.0));
                    e.0 = e.0.max(s.error);
                    e.1 += 1;
                    e.2 += w;
                }
            }
            proptest::prop_assert_eq!(got.requests.len(), want.len());
            for r in &got.requests {
                let (error, count, weight) = want[&r.id.0];
                proptest::prop_assert_eq!((r.error, r.samples, r.weight.to_bits()), (error, count, weight.to_bits()));
            }
        }
    }
}
