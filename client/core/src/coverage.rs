//! What the client knows about every pixel of the current view, which pixels to sample next,
//! and when the view has converged.
//!
//! The thesis samples a fixed 1/n grid and waits n² cycles for a full round. [`Coverage`] keeps
//! instead the latest feedback sample of *every* pixel since the view last changed (camera, LOD
//! bias, an eviction), and plans each cycle's analysis pass from it:
//!
//! 1. **pixels whose awaited treelet has arrived** first — they were coarser than a pixel, the
//!    treelet that refines them is resident now, and resampling them finds the next level;
//! 2. then **pixels never sampled** since the view changed, in the grid's progressive order
//!    (round by round of the 1/n grid, so every prefix is spread evenly over the frame);
//! 3. nothing else: a pixel known to be final stays final while the view is unchanged, and a
//!    pixel still waiting for its treelet would only see the same leaf again.
//!
//! How many pixels a cycle may sample is the caller's budget (a measured cost per sample, see
//! [`SampleBudget`]): a fast backend samples the whole frame every cycle, a slow one a part of
//! it; never fewer than the 1/n grid's share.
//!
//! **Why convergence is exact.** A pixel is *clean* when its latest sample does not want
//! refinement (it stopped at a final leaf or at a voxel at most a pixel wide). Inserting a
//! treelet never changes a clean pixel: the refined leaf was not hit in front of the pixel's
//! voxel (it would have been the hit), and its subtree lies inside its box. So once every pixel
//! is clean under one camera and bias with no eviction since, the image equals the fully
//! resident render bit for bit ([`Coverage::converged`]). An eviction can uncover a coarse leaf
//! in front of a clean pixel — but only where a ray meets the evicted subtree's root cell, whose
//! box the restored leaf fills: the pixels of that box's screen rectangle are forgotten
//! ([`Coverage::forget`]) and sampled again first, the rest of the view stays known. (Forgetting
//! the whole view for every eviction made a 16 MiB view of a 10⁸-point city re-sample all of
//! its 786,432 pixels after each of ten single evictions.)
//!
//! The knowledge is also what presort reads: every known pixel marks its slot visible, and every
//! pixel waiting for a treelet counts for that treelet's priority — the request list covers the
//! whole view, not only this cycle's samples.
//!
//! Pipelined backends hand feedback back a cycle late: every plan is kept until its feedback
//! arrives, and a plan whose feedback never comes (a skipped pass) is sampled again. Feedback of
//! a cycle before the last reset describes another view: it never counts as knowledge (nor for
//! convergence), but the newest pass of the last [`HINT_VIEWS`] views is kept as a **hint** for
//! the pixels not yet sampled in this one — what a moving camera saw a few cycles ago is what it
//! nearly sees now (a software GPU hands passes back two to four cycles late). A new LOD bias is
//! another target, not another view: it drops the hints ([`Coverage::reset_target`]).
//! Without hints a pipelined backend under a camera that moves every cycle would never know a
//! pixel and never ask for anything (measured: an orbit on lavapipe, 240 cycles, 0 requests).

use std::collections::VecDeque;

use arbor_proto::TreeletId;
use rustc_hash::FxHashSet;

use crate::analysis::{Feedback, FeedbackSample, feedback_size, jitter, pack_pixel, unpack_pixel};

/// Views back (resets) whose feedback still serves as a hint.
pub const HINT_VIEWS: usize = 4;

/// Cycles after which a plan whose feedback has not come is taken as lost and its pixels are
/// sampled again, even though no later feedback has come to show it was skipped. A pipelined
/// backend answers two to four cycles late; a pass it skipped, or one lost with its device, is
/// otherwise noticed only by a later pass's feedback — and when that plan was the last one
/// with pixels in it (the rest of the view known), no later pass ever came: its pixels stayed
/// unknown, nothing was asked for, and the view never converged (a viewer on lavapipe, 96.2 %
/// of its pixels known for 44,000 cycles after its device was replaced).
pub const LOST_PLAN_CYCLES: u64 = 8;

/// Plans, feedback and convergence over the pixels of one view.
#[derive(Debug)]
pub struct Coverage {
    width: u32,
    height: u32,
    /// The grid ratio `n` of the progressive order (and of the minimum sample share).
    base_ratio: u32,
    /// Increases at every reset; a pixel's sample counts only in its epoch.
    epoch: u32,
    /// Per pixel: the epoch of its latest sample.
    epochs: Vec<u32>,
    /// Per pixel: the latest sample (valid when its epoch is current).
    samples: Vec<FeedbackSample>,
    /// Per pixel: the low bits of the cycle it was last planned in, to not resample a pixel
    /// whose previous sample is still in flight.
    planned: Vec<u32>,
    known: u32,
    dirty: u32,
    /// Progressive order: the grid round (0..n²) and the next element of that round.
    round: u32,
    element: u32,
    /// Plans sent and not answered yet.
    outstanding: VecDeque<(u64, Vec<u32>)>,
    /// Pixels of plans whose feedback never came.
    retry: Vec<u32>,
    /// Feedback of earlier cycles describes another view.
    valid_from: u64,
    /// Where the last [`HINT_VIEWS`] views began: feedback from the oldest on is a hint.
    recent_views: VecDeque<u64>,
    /// The newest pass of a recent earlier view, `(pixel index, sample)`: requests and
    /// visibility for pixels not sampled in this view yet.
    hints: Vec<(u32, FeedbackSample)>,
    /// The cycle of the pass in `hints`.
    hints_cycle: u64,
    /// Pixels sampled since the last reset.
    sampled_since_reset: u64,
    /// Per pixel: the cycle it was last forgotten at ([`Coverage::forget`]; 0 if never):
    /// feedback of an earlier cycle for it describes the view before an eviction. Per pixel,
    /// not one cycle for a set of pixels: with one, a later eviction elsewhere made the pending
    /// resample of a pixel forgotten earlier look stale too, and the pixel was never planned
    /// again (the view never became wholly known, and a full buffer stalled).
    forgotten_at: Vec<u64>,
    /// Changes whenever what [`Coverage::known_samples`] yields may have changed.
    generation: u64,
}

impl Coverage {
    /// Knowledge of a `width × height` view, nothing known yet.
    pub fn new(width: u32, height: u32, base_ratio: u32) -> Self {
        let pixels = (width as usize) * (height as usize);
        Self {
            width,
            height,
            base_ratio: base_ratio.max(1),
            epoch: 1,
            epochs: vec![0; pixels],
            samples: vec![FeedbackSample::MISS; pixels],
            planned: vec![u32::MAX; pixels],
            known: 0,
            dirty: 0,
            round: 0,
            element: 0,
            outstanding: VecDeque::new(),
            retry: Vec::new(),
            valid_from: 0,
            recent_views: VecDeque::from([0]),
            hints: Vec::new(),
            hints_cycle: 0,
            sampled_since_reset: 0,
            forgotten_at: vec![0; pixels],
            generation: 0,
        }
    }

    /// Frame size.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Pixels of the view.
    pub fn pixels(&self) -> u32 {
        self.width * self.height
    }

    /// Pixels with a sample since the last reset.
    pub fn known(&self) -> u32 {
        self.known
    }

    /// Known pixels whose voxel is coarser than a pixel and refinable.
    pub fn dirty(&self) -> u32 {
        self.dirty
    }

    /// Pixels sampled since the last reset (resamples included).
    pub fn sampled_since_reset(&self) -> u64 {
        self.sampled_since_reset
    }

    /// Every pixel is known and none wants refinement: the image is exact.
    pub fn converged(&self) -> bool {
        self.known == self.pixels() && self.dirty == 0
    }

    /// A number that changes whenever what [`Coverage::known_samples`] yields may have changed
    /// (samples taken, pixels forgotten, a reset, new hints): equal numbers, equal samples.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// Forgets everything (the view changed at `cycle`): feedback of earlier cycles is ignored.
    pub fn reset(&mut self, cycle: u64) {
        self.generation += 1;
        self.epoch = self.epoch.wrapping_add(1);
        if self.epoch == 0 {
            // Wrapped: old stamps could alias the new epoch.
            self.epochs.fill(0);
            self.epoch = 1;
        }
        self.known = 0;
        self.dirty = 0;
        self.round = 0;
        self.element = 0;
        self.outstanding.clear();
        self.retry.clear();
        self.valid_from = cycle;
        self.recent_views.push_back(cycle);
        if self.recent_views.len() > HINT_VIEWS {
            self.recent_views.pop_front();
        }
        if self.hints_cycle < self.hints_from() {
            self.hints.clear();
        }
        self.sampled_since_reset = 0;
    }

    /// Forgets the pixels inside `rects` (`[x0, y0, x1, y1]`, inclusive, clamped to the frame)
    /// at `cycle`: they are sampled again first, and feedback of earlier cycles for them no
    /// longer counts. For an eviction, whose restored leaf only rays through its box can meet.
    pub fn forget(&mut self, cycle: u64, rects: &[[u32; 4]]) {
        self.generation += 1;
        let (w, h) = (self.width, self.height);
        if w == 0 || h == 0 {
            return;
        }
        // A pixel forgotten before whose resample is still in flight is queued again all the
        // same: that pass was planned before this cycle and is ignored (stale) when it comes
        // back. Skipping it left the pixel unknown and never planned again (the progressive
        // order visits a pixel once per reset): the view never became wholly known, nothing
        // outside it could be evicted, and a full buffer stalled.
        let mut queued = FxHashSet::default();
        for &[x0, y0, x1, y1] in rects {
            for y in y0.min(h - 1)..=y1.min(h - 1) {
                for x in x0.min(w - 1)..=x1.min(w - 1) {
                    let i = y * w + x;
                    if !queued.insert(i) {
                        continue;
                    }
                    let i = i as usize;
                    self.forgotten_at[i] = cycle;
                    if self.epochs[i] == self.epoch {
                        self.known -= 1;
                        if self.samples[i].wants_refinement() {
                            self.dirty -= 1;
                        }
                        // 0 is never a current epoch (see `reset`).
                        self.epochs[i] = 0;
                    }
                    self.retry.push(i as u32);
                }
            }
        }
    }

    /// [`reset`](Self::reset) for a new target (LOD bias) at `cycle`: earlier passes judged
    /// refinement against the old one, so they are no hint either.
    pub fn reset_target(&mut self, cycle: u64) {
        self.reset(cycle);
        self.recent_views.clear();
        self.recent_views.push_back(cycle);
        self.hints.clear();
    }

    /// The first cycle whose passes are hints: the start of the oldest recent view.
    fn hints_from(&self) -> u64 {
        self.recent_views.front().copied().unwrap_or(0)
    }

    /// The pixels to sample in `cycle`, at most `max_samples` (at least the 1/n grid's share
    /// when that many are wanted). `is_resident` tells whether a treelet has arrived.
    pub fn plan(
        &mut self,
        cycle: u64,
        max_samples: usize,
        is_resident: impl Fn(TreeletId) -> bool,
    ) -> Vec<u32> {
        let floor = {
            let (fw, fh) = feedback_size(self.width, self.height, self.base_ratio);
            (fw * fh) as usize
        };
        let budget = max_samples.max(floor);
        // While part of the view is unknown, half the budget stays for it: a steady stream of
        // arrivals would otherwise keep the unknown part unseen, and what it needs unasked
        // (measured: 39 % of a 512² view unseen for 30 cycles over a 100 Mbit/s link).
        let revisit = if self.round < self.base_ratio * self.base_ratio {
            budget - budget / 2
        } else {
            budget
        };
        let mut out = Vec::new();
        let stamp = cycle as u32;
        while self
            .outstanding
            .front()
            .is_some_and(|(c, _)| cycle.saturating_sub(*c) >= LOST_PLAN_CYCLES)
        {
            self.retry_oldest_plan();
        }
        // Lost plans and forgotten pixels first: they are unknown pixels too. What the budget
        // leaves waits for the next cycle.
        let take = self.retry.len().min(budget);
        for p in self.retry.drain(..take) {
            self.planned[p as usize] = stamp;
            out.push(pack_index(p, self.width));
        }
        if self.dirty > 0 {
            let cap = budget.min(out.len().saturating_add(revisit));
            self.plan_arrived(stamp, cap, &is_resident, &mut out);
        }
        self.plan_unknown(stamp, budget, &mut out);
        if !out.is_empty() {
            self.outstanding.push_back((cycle, out.clone()));
        }
        out
    }

    /// Dirty pixels whose awaited treelet is resident, not planned in the last two cycles.
    fn plan_arrived(
        &mut self,
        stamp: u32,
        budget: usize,
        is_resident: &impl Fn(TreeletId) -> bool,
        out: &mut Vec<u32>,
    ) {
        for i in 0..self.samples.len() {
            if out.len() >= budget {
                return;
            }
            if self.epochs[i] != self.epoch {
                continue;
            }
            let s = &self.samples[i];
            if !s.wants_refinement() || !is_resident(TreeletId(s.subtreelet)) {
                continue;
            }
            if stamp.wrapping_sub(self.planned[i]) < 2 {
                continue;
            }
            self.planned[i] = stamp;
            out.push(pack_index(i as u32, self.width));
        }
    }

    /// The next pixels of the progressive order (all of them unknown: the order visits each
    /// pixel once per reset).
    fn plan_unknown(&mut self, stamp: u32, budget: usize, out: &mut Vec<u32>) {
        let n = self.base_ratio;
        let (fw, fh) = feedback_size(self.width, self.height, n);
        let elements = fw * fh;
        while out.len() < budget && self.round < n * n {
            let (ox, oy) = jitter(u64::from(self.round), n);
            while out.len() < budget && self.element < elements {
                let (fx, fy) = (self.element % fw, self.element / fw);
                self.element += 1;
                let (px, py) = (fx * n + ox, fy * n + oy);
                if px < self.width && py < self.height {
                    self.planned[(py * self.width + px) as usize] = stamp;
                    out.push(pack_pixel(px, py));
                }
            }
            if self.element >= elements {
                self.element = 0;
                self.round += 1;
            }
        }
    }

    /// Every plan still unanswered is lost (its backend was replaced: no pass of the old one
    /// will answer): their pixels are sampled first, from the next plan on.
    pub fn retry_unanswered(&mut self) {
        while !self.outstanding.is_empty() {
            self.retry_oldest_plan();
        }
    }

    /// The oldest plan still unanswered is lost: its pixels are sampled again.
    fn retry_oldest_plan(&mut self) {
        let Some((_, lost)) = self.outstanding.pop_front() else {
            return;
        };
        let (width, pixels) = (self.width, self.pixels());
        self.retry.extend(
            lost.iter()
                .map(|&p| unpack_index(p, width))
                .filter(|&i| i < pixels),
        );
    }

    /// Takes the feedback of a pass: samples of the current view are recorded, plans answered
    /// by nothing are sampled again.
    pub fn handle_feedback(&mut self, feedback: &Feedback) {
        if feedback.samples.is_empty() && feedback.pixels.is_empty() {
            return;
        }
        // Plans older than this feedback were skipped by the backend: sample them again.
        while self
            .outstanding
            .front()
            .is_some_and(|(c, _)| *c < feedback.cycle)
        {
            self.retry_oldest_plan();
        }
        if self
            .outstanding
            .front()
            .is_some_and(|(c, _)| *c == feedback.cycle)
        {
            self.outstanding.pop_front();
        }
        if feedback.cycle < self.valid_from {
            if feedback.cycle >= self.hints_from() && feedback.cycle >= self.hints_cycle {
                let (width, height) = (self.width, self.height);
                self.generation += 1;
                self.hints.clear();
                self.hints_cycle = feedback.cycle;
                self.hints.extend(
                    feedback
                        .pixels
                        .iter()
                        .zip(&feedback.samples)
                        .map(|(&p, s)| (unpack_pixel(p), *s))
                        .filter(|&((x, y), _)| x < width && y < height)
                        .map(|((x, y), s)| (y * width + x, s)),
                );
            }
            return;
        }
        for (&p, s) in feedback.pixels.iter().zip(&feedback.samples) {
            let (x, y) = unpack_pixel(p);
            if x >= self.width || y >= self.height {
                continue;
            }
            let i = (y * self.width + x) as usize;
            // Planned before the pixel was forgotten: it saw what an eviction has changed.
            if feedback.cycle < self.forgotten_at[i] {
                continue;
            }
            if self.epochs[i] == self.epoch {
                if self.samples[i] == *s {
                    // Resampled alike (a pipelined backend hands its last pass back again).
                    self.sampled_since_reset += 1;
                    continue;
                }
                if self.samples[i].wants_refinement() {
                    self.dirty -= 1;
                }
            } else {
                self.epochs[i] = self.epoch;
                self.known += 1;
            }
            self.generation += 1;
            self.samples[i] = *s;
            if s.wants_refinement() {
                self.dirty += 1;
            }
            self.sampled_since_reset += 1;
        }
    }

    /// The latest sample of every known pixel, with its pixel index (`y · width + x`), then the
    /// previous view's hints for pixels not known yet (see the module docs).
    pub fn known_samples(&self) -> impl Iterator<Item = (u32, &FeedbackSample)> + '_ {
        let known = self
            .samples
            .iter()
            .enumerate()
            .filter(move |(i, _)| self.epochs[*i] == self.epoch)
            .map(|(i, s)| (i as u32, s));
        let hints = self
            .hints
            .iter()
            .filter(move |(i, _)| self.epochs[*i as usize] != self.epoch)
            .map(|(i, s)| (*i, s));
        known.chain(hints)
    }
}

fn pack_index(i: u32, width: u32) -> u32 {
    pack_pixel(i % width, i / width)
}

fn unpack_index(p: u32, width: u32) -> u32 {
    let (x, y) = unpack_pixel(p);
    y * width + x
}

/// Samples of the first pass, before any cost is measured: enough to measure it and to see
/// which of the root's children the view touches, a few milliseconds on the CPU twin (the
/// whole frame would take 150–180 ms at 512² there, all of it before the first request).
pub const FIRST_PASS_SAMPLES: usize = 16_384;

/// How many pixels a cycle may sample: a per-cycle time budget divided by the measured cost of
/// one sample (an exponential mean over recent passes). Plain data: the caller passes the
/// measured durations in.
#[derive(Clone, Copy, Debug)]
pub struct SampleBudget {
    /// Wall time the analysis pass may take per cycle, seconds.
    pub budget_s: f64,
    /// Measured seconds per sample (exponential mean); `None` before the first measurement.
    pub cost_s: Option<f64>,
}

impl SampleBudget {
    /// A budget of `budget_s` seconds per cycle, nothing measured yet.
    pub fn new(budget_s: f64) -> Self {
        Self {
            budget_s,
            cost_s: None,
        }
    }

    /// Records that `samples` samples took `seconds`.
    pub fn record(&mut self, samples: usize, seconds: f64) {
        // Small passes are dominated by fixed costs: they would underestimate the rate.
        if samples < 256 || !(seconds.is_finite() && seconds > 0.0) {
            return;
        }
        let cost = seconds / samples as f64;
        self.cost_s = Some(match self.cost_s {
            Some(c) => 0.7 * c + 0.3 * cost,
            None => cost,
        });
    }

    /// Samples the next pass may take: [`FIRST_PASS_SAMPLES`] until the cost is known.
    pub fn max_samples(&self, pixels: u32) -> usize {
        match self.cost_s {
            None => FIRST_PASS_SAMPLES.min(pixels as usize),
            Some(c) => ((self.budget_s / c) as usize).min(pixels as usize),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arbor_proto::Node;

    fn sample(sub: u32, error: f32) -> FeedbackSample {
        FeedbackSample {
            node: 1,
            subtreelet: sub,
            error,
            t: 1.0,
        }
    }

    fn answer(cycle: u64, pixels: &[u32], f: impl Fn(u32, u32) -> FeedbackSample) -> Feedback {
        Feedback {
            cycle,
            pixels: pixels.to_vec(),
            samples: pixels
                .iter()
                .map(|&p| {
                    let (x, y) = unpack_pixel(p);
                    f(x, y)
                })
                .collect(),
        }
    }

    #[test]
    fn the_generation_changes_exactly_when_the_known_samples_may() {
        let mut c = Coverage::new(8, 8, 8);
        let g0 = c.generation();
        let plan = c.plan(0, 64, |_| false);
        assert_eq!(c.generation(), g0, "planning changes no sample");
        let fb = answer(0, &plan, |x, _| sample(5, x as f32 + 1.0));
        c.handle_feedback(&fb);
        let g1 = c.generation();
        assert_ne!(g1, g0);
        // The same pass handed back again (a pipelined backend with nothing new): no change.
        c.handle_feedback(&fb);
        assert_eq!(c.generation(), g1);
        assert_eq!(c.known(), 64);
        // One pixel resampled differently.
        c.handle_feedback(&answer(1, &[pack_pixel(3, 3)], |_, _| {
            sample(Node::NONE, -1.0)
        }));
        let g2 = c.generation();
        assert_ne!(g2, g1);
        assert_eq!(c.dirty(), 63);
        c.forget(2, &[[0, 0, 1, 1]]);
        assert_ne!(c.generation(), g2);
        let g3 = c.generation();
        c.reset(3);
        assert_ne!(c.generation(), g3);
    }

    #[test]
    fn the_progressive_order_visits_every_pixel_once() {
        let mut c = Coverage::new(13, 7, 4);
        let mut seen = vec![0; 91];
        let mut cycle = 0;
        loop {
            let plan = c.plan(cycle, 10, |_| false);
            if plan.is_empty() {
                break;
            }
            assert!(plan.len() <= 10);
            for &p in &plan {
                let (x, y) = unpack_pixel(p);
                seen[(y * 13 + x) as usize] += 1;
            }
            c.handle_feedback(&answer(cycle, &plan, |_, _| sample(Node::NONE, -1.0)));
            cycle += 1;
        }
        assert!(seen.iter().all(|&k| k == 1), "{seen:?}");
        assert!(c.converged());
    }

    #[test]
    fn arrived_pixels_are_resampled_first_and_convergence_follows() {
        let mut c = Coverage::new(8, 8, 8);
        // One cycle samples the whole frame; pixels of the left half wait for treelet 5.
        let plan = c.plan(0, 64, |_| false);
        assert_eq!(plan.len(), 64);
        c.handle_feedback(&answer(0, &plan, |x, _| {
            if x < 4 {
                sample(5, 2.0)
            } else {
                sample(Node::NONE, 0.5)
            }
        }));
        assert_eq!((c.known(), c.dirty()), (64, 32));
        assert!(!c.converged());
        // Nothing arrived: nothing worth sampling.
        assert!(c.plan(1, 64, |_| false).is_empty());
        // Treelet 5 arrived: exactly the 32 waiting pixels come back.
        let plan = c.plan(2, 64, |id| id == TreeletId(5));
        assert_eq!(plan.len(), 32);
        assert!(plan.iter().all(|&p| unpack_pixel(p).0 < 4));
        c.handle_feedback(&answer(2, &plan, |_, _| sample(Node::NONE, 0.0)));
        assert!(c.converged());
    }

    /// An 8×8 view at feedback ratio `ratio`, wholly known after cycle 0's pass (planned with
    /// `budget`): column 0 wants treelet 5 (dirty), the rest is clean.
    fn known_with_a_dirty_column(ratio: u32, budget: usize) -> Coverage {
        let mut c = Coverage::new(8, 8, ratio);
        let plan = c.plan(0, budget, |_| false);
        assert_eq!(plan.len(), 64);
        c.handle_feedback(&answer(0, &plan, |x, _| {
            if x == 0 {
                sample(5, 2.0)
            } else {
                sample(Node::NONE, 0.0)
            }
        }));
        assert_eq!((c.known(), c.dirty()), (64, 8));
        c
    }

    #[test]
    fn forgetting_a_rectangle_resamples_only_it_and_ignores_older_passes() {
        let mut c = known_with_a_dirty_column(8, 64);
        // A pass planned at cycle 1 is still in flight (a pipelined backend) when an eviction
        // at cycle 2 forgets columns 0–2 of rows 2–3 (and a rectangle reaching off the frame).
        let in_flight = c.plan(1, 64, |_| false);
        assert!(in_flight.is_empty(), "nothing to sample while waiting");
        c.forget(2, &[[0, 2, 2, 3], [7, 7, 20, 20]]);
        assert_eq!((c.known(), c.dirty()), (64 - 7, 8 - 2));
        assert!(!c.converged());
        // The forgotten pixels come first, at most the budget per cycle; the rest waits.
        let first = c.plan(2, 4, |_| false);
        let second = c.plan(3, 4, |_| false);
        let mut again: Vec<(u32, u32)> = first
            .iter()
            .chain(&second)
            .map(|&p| unpack_pixel(p))
            .collect();
        again.sort_unstable();
        assert_eq!(
            again,
            vec![(0, 2), (0, 3), (1, 2), (1, 3), (2, 2), (2, 3), (7, 7)]
        );
        // An older pass for a forgotten pixel does not count; the new ones do.
        c.handle_feedback(&answer(1, &[pack_pixel(0, 2)], |_, _| {
            sample(Node::NONE, 0.0)
        }));
        assert_eq!(c.known(), 57);
        c.handle_feedback(&answer(2, &first, |_, _| sample(Node::NONE, 0.0)));
        c.handle_feedback(&answer(3, &second, |_, _| sample(Node::NONE, 0.0)));
        assert_eq!((c.known(), c.dirty()), (64, 6));
        assert!(c.plan(4, 64, |_| false).is_empty());
    }

    /// An unbounded budget (`ClientCore::plan` passes `usize::MAX`) with forgotten pixels and
    /// dirty ones waiting: the cap on arrived pixels saturates instead of overflowing (found by
    /// a camera inside lion with evictions, `tests/tests/render_memo.rs`).
    #[test]
    fn an_unbounded_budget_with_forgotten_and_dirty_pixels_plans_them_all() {
        let mut c = known_with_a_dirty_column(1, usize::MAX);
        // Later than two cycles after the first pass: the dirty column is due again.
        c.forget(3, &[[4, 2, 6, 3]]);
        let again = c.plan(3, usize::MAX, |_| true);
        let mut pixels: Vec<(u32, u32)> = again.iter().map(|&p| unpack_pixel(p)).collect();
        pixels.sort_unstable();
        pixels.dedup();
        assert_eq!(pixels.len(), again.len(), "each pixel once");
        for p in [(4, 2), (5, 3), (6, 2), (0, 0), (0, 7)] {
            assert!(pixels.contains(&p), "{p:?} not planned: {pixels:?}");
        }
    }

    /// An 8×8 view known and clean at cycle 0; at cycle 1 an eviction forgets pixel (0, 0) and
    /// its resample is planned (returned), its pass not back yet.
    fn converged_then_resampling_the_corner() -> (Coverage, Vec<u32>) {
        let mut c = Coverage::new(8, 8, 8);
        let plan = c.plan(0, 64, |_| false);
        c.handle_feedback(&answer(0, &plan, |_, _| sample(Node::NONE, 0.0)));
        assert!(c.converged());
        c.forget(1, &[[0, 0, 0, 0]]);
        let resample = c.plan(1, 64, |_| false);
        assert_eq!(resample, vec![pack_pixel(0, 0)]);
        (c, resample)
    }

    #[test]
    fn a_pixel_forgotten_again_before_its_resample_returns_is_planned_again() {
        // An eviction at cycle 1 forgets pixel (0, 0); its resample is planned at cycle 1 ...
        let (mut c, retry) = converged_then_resampling_the_corner();
        // ... and before that pass comes back, an eviction at cycle 2 forgets it again.
        c.forget(2, &[[0, 0, 0, 0]]);
        // The pass of cycle 1 predates the second eviction: it does not count.
        c.handle_feedback(&answer(1, &retry, |_, _| sample(Node::NONE, 0.0)));
        assert_eq!(c.known(), 63);
        assert!(!c.converged());
        // The pixel is planned again (it used to be lost here: unknown for good), and its new
        // pass counts.
        let again = c.plan(2, 64, |_| false);
        assert_eq!(again, vec![pack_pixel(0, 0)]);
        c.handle_feedback(&answer(2, &again, |_, _| sample(Node::NONE, 0.0)));
        assert!(c.converged());
        assert!(c.plan(3, 64, |_| false).is_empty());
    }

    #[test]
    fn a_resample_in_flight_counts_when_another_pixel_is_forgotten_meanwhile() {
        // An eviction at cycle 1 forgets pixel (0, 0); its resample is planned at cycle 1 ...
        let (mut c, first) = converged_then_resampling_the_corner();
        // ... and before that pass comes back (a pipelined backend), an eviction at cycle 2
        // forgets another pixel, whose resample is planned at cycle 2.
        c.forget(2, &[[5, 5, 5, 5]]);
        let second = c.plan(2, 64, |_| false);
        assert_eq!(second, vec![pack_pixel(5, 5)]);
        // The pass of cycle 1 came after (0, 0) was forgotten: it counts. (It used to be
        // ignored as older than the latest forgetting, and (0, 0) was never planned again.)
        c.handle_feedback(&answer(1, &first, |_, _| sample(Node::NONE, 0.0)));
        assert_eq!(c.known(), 63);
        c.handle_feedback(&answer(2, &second, |_, _| sample(Node::NONE, 0.0)));
        assert!(c.converged());
        assert!(c.plan(3, 64, |_| false).is_empty());
    }

    #[test]
    fn stale_feedback_is_ignored_and_lost_plans_come_back() {
        let mut c = Coverage::new(4, 4, 2);
        let first = c.plan(0, 16, |_| false);
        c.reset(1);
        // The pass of cycle 0 describes the old view.
        c.handle_feedback(&answer(0, &first, |_, _| sample(Node::NONE, 0.0)));
        assert_eq!(c.known(), 0);
        assert!(!c.converged());
        let a = c.plan(1, 4, |_| false);
        let b = c.plan(2, 4, |_| false);
        assert_eq!((a.len(), b.len()), (4, 4));
        // Cycle 1's pass was skipped; cycle 2's arrives: cycle 1's pixels are planned again.
        c.handle_feedback(&answer(2, &b, |_, _| sample(Node::NONE, 0.0)));
        assert_eq!(c.known(), 4);
        let again = c.plan(3, 4, |_| false);
        let mut again_sorted = again.clone();
        again_sorted.sort_unstable();
        let mut a_sorted = a.clone();
        a_sorted.sort_unstable();
        assert_eq!(again_sorted, a_sorted);
    }

    #[test]
    fn a_last_plan_never_answered_is_sampled_again_after_the_lost_plan_cycles() {
        let mut c = Coverage::new(4, 4, 2);
        let first = c.plan(0, 12, |_| false);
        c.handle_feedback(&answer(0, &first, |_, _| sample(Node::NONE, 0.0)));
        // The last four pixels are planned, and their pass never answers (skipped, or lost
        // with its device); nothing else is left to sample, so no later pass comes either.
        let last = c.plan(1, 12, |_| false);
        assert_eq!((c.known(), last.len()), (12, 4));
        for cycle in 2..1 + LOST_PLAN_CYCLES {
            assert!(c.plan(cycle, 12, |_| false).is_empty(), "cycle {cycle}");
        }
        let again = c.plan(1 + LOST_PLAN_CYCLES, 12, |_| false);
        let sorted = |v: &[u32]| {
            let mut v = v.to_vec();
            v.sort_unstable();
            v
        };
        assert_eq!(sorted(&again), sorted(&last));
        c.handle_feedback(&answer(1 + LOST_PLAN_CYCLES, &again, |_, _| {
            sample(Node::NONE, 0.0)
        }));
        assert!(c.converged());
        // A late answer of the lost pass changes nothing.
        c.handle_feedback(&answer(1, &last, |_, _| sample(Node::NONE, 0.0)));
        assert!(c.converged());
        assert_eq!(c.known(), 16);
    }

    #[test]
    fn a_late_pass_of_the_previous_view_is_a_hint_not_knowledge() {
        let mut c = Coverage::new(4, 4, 2);
        // A camera moving every cycle, feedback a cycle late (a pipelined backend).
        let plan0 = c.plan(0, 16, |_| false);
        c.reset(1);
        let plan1 = c.plan(1, 16, |_| false);
        c.handle_feedback(&answer(0, &plan0, |x, _| sample(7 + x, 3.0)));
        // Not knowledge: nothing known, no convergence, the pixels still planned.
        assert_eq!((c.known(), c.dirty()), (0, 0));
        assert!(!c.converged());
        assert_eq!(plan1.len(), 16);
        // But presort sees what the previous view wanted.
        let hinted: Vec<u32> = c.known_samples().map(|(_, s)| s.subtreelet).collect();
        assert_eq!(hinted.len(), 16);
        assert!(hinted.iter().all(|&t| (7..11).contains(&t)));
        // A fresh sample of a pixel replaces its hint.
        c.handle_feedback(&answer(1, &plan1[..1], |_, _| sample(Node::NONE, 0.0)));
        assert_eq!(c.known(), 1);
        assert_eq!(c.known_samples().count(), 16);
        assert_eq!(
            c.known_samples()
                .filter(|(_, s)| s.subtreelet == Node::NONE)
                .count(),
            1
        );
        // A later pass of an earlier view replaces the hints; an older one does not.
        c.reset(2);
        c.handle_feedback(&answer(1, &plan1, |_, _| sample(9, 3.0)));
        assert!(c.known_samples().all(|(_, s)| s.subtreelet == 9));
        c.handle_feedback(&answer(0, &plan0, |_, _| sample(8, 3.0)));
        assert!(c.known_samples().all(|(_, s)| s.subtreelet == 9));
        assert_eq!(c.known_samples().count(), 16);
        // The hints describe the view begun at cycle 1: they serve while it is one of the last
        // HINT_VIEWS views, then go.
        assert_eq!(HINT_VIEWS, 4);
        c.reset(3);
        c.reset(4);
        assert_eq!(c.known_samples().count(), 16);
        c.reset(5);
        assert_eq!(c.known_samples().count(), 0);
        // A new target drops the hints, and passes from before it are none.
        c.handle_feedback(&answer(4, &plan1, |_, _| sample(9, 3.0)));
        assert_eq!(c.known_samples().count(), 16);
        c.reset_target(6);
        assert_eq!(c.known_samples().count(), 0);
        c.handle_feedback(&answer(5, &plan1, |_, _| sample(9, 3.0)));
        assert_eq!(c.known_samples().count(), 0);
        assert!(!c.converged());
    }

    #[test]
    fn the_budget_follows_the_measured_cost_with_a_floor() {
        let mut b = SampleBudget::new(0.010);
        assert_eq!(b.max_samples(1000), 1000);
        assert_eq!(b.max_samples(1 << 20), FIRST_PASS_SAMPLES);
        b.record(10_000, 0.020); // 2 µs per sample
        assert_eq!(b.max_samples(1_000_000), 5000);
        b.record(10, 100.0); // too small to count
        assert_eq!(b.max_samples(1_000_000), 5000);
        let mut c = Coverage::new(64, 64, 8);
        // Budget 1 still samples the 1/8 grid's 64 pixels.
        assert_eq!(c.plan(0, 1, |_| false).len(), 64);
    }
}
