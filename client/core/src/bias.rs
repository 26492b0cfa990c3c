//! The memory-adjusted target (docs/design.md §10): when the view needs more slots than the
//! budget holds, raise the LOD bias — stop refining one quarter level earlier — instead of
//! thrashing, until the needed cut fits; lower it again only when there is clearly room.
//!
//! What the view needs is judged from the pixels known under the current bias (see
//! [`crate::coverage`]):
//! * the view wants the distinct treelets its pixels still ask for, and the buffer can give it
//!   the free slots plus those that eviction may take once everything the view does not hit has
//!   aged out (a slot outside the view whose parent is outside it too);
//! * it is **oversubscribed** when it wants more than that room: raise by a quarter level. A
//!   part of the view is enough for this ([`LodBiasControl::raise_if_oversubscribed`]): a camera
//!   that moves every cycle never lets a pass slower than the frame know a whole view, and
//!   waiting for one left the 10⁸-point city's orbit at 16 MiB on the CPU backend with no raise
//!   in 600 cycles and a wrong picture throughout (docs/measurements.md, stop 61);
//! * with nothing wanted and the view using less than 1/[`LOWER_HEADROOM`] of the capacity, try
//!   a quarter level lower (a surface needs about √2× the slots per quarter level finer); only
//!   on a whole view, since the pixels not yet known may want what would not fit;
//! * a lower that had to be raised again is not tried again until the view changes
//!   (hysteresis), so a static view settles on one bias and traffic stops; and when it failed
//!   soon after it was made, not for [`LOWER_RETRY_CYCLES`] either, doubling with each such
//!   failure in a row, since a moving camera changes the view every cycle.

/// A quarter octree level: the bias moves by `2^(1/4)` per step.
pub const STEPS_PER_LEVEL: i32 = 4;
/// Highest bias, in steps above the base (16 levels).
pub const MAX_STEPS: i32 = 16 * STEPS_PER_LEVEL;
/// The view must fit this many times over before the bias is lowered.
pub const LOWER_HEADROOM: f64 = 1.6;
/// A lower raised again within this many cycles failed; after one, no lower is tried for this
/// many cycles, doubling with each failure in a row (see [`LodBiasControl::update`]).
pub const LOWER_RETRY_CYCLES: u64 = 32;
/// The retry wait doubles at most this many times (32 · 2⁵ = 1,024 cycles).
pub const LOWER_RETRY_MAX_DOUBLINGS: u32 = 5;

/// What one fully known view needs, for [`LodBiasControl::update`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ViewNeed {
    /// Slots the view's pixels hit, with their ancestors.
    pub visible_slots: u32,
    /// Distinct treelets the view's pixels want that are not resident or waiting.
    pub wanted: u32,
    /// Slots the wanted treelets could take once what the view does not hit has aged out.
    pub room: u32,
    /// Slots of the buffer.
    pub capacity: u32,
}

/// The LOD bias in effect and the state of its control.
#[derive(Clone, Debug)]
pub struct LodBiasControl {
    base: f64,
    /// Quarter levels above the base.
    steps: i32,
    /// Lowering is not tried again until [`LodBiasControl::view_changed`].
    locked: bool,
    /// The last change was a lower, at this cycle.
    lowered_at: Option<u64>,
    /// Lowers in a row raised again within [`LOWER_RETRY_CYCLES`].
    failed_lowers: u32,
    /// No lower is tried before this cycle.
    retry_at: u64,
    /// Cycle of the first raise, for the run summary.
    first_raised_at: Option<u64>,
}

impl LodBiasControl {
    /// Control around the configured bias `base`.
    pub fn new(base: f64) -> Self {
        Self {
            base,
            steps: 0,
            locked: false,
            lowered_at: None,
            failed_lowers: 0,
            retry_at: 0,
            first_raised_at: None,
        }
    }

    /// The bias in effect.
    pub fn bias(&self) -> f64 {
        self.base * 2f64.powf(f64::from(self.steps) / f64::from(STEPS_PER_LEVEL))
    }

    /// The configured bias.
    pub fn base(&self) -> f64 {
        self.base
    }

    /// Quarter levels above the configured bias.
    pub fn steps(&self) -> i32 {
        self.steps
    }

    /// The cycle the bias was first raised in, if ever.
    pub fn first_raised_at(&self) -> Option<u64> {
        self.first_raised_at
    }

    /// The user chose another configured bias: the control starts afresh around it (no steps,
    /// nothing locked).
    pub fn set_base(&mut self, base: f64) {
        *self = Self {
            first_raised_at: self.first_raised_at,
            ..Self::new(base)
        };
    }

    /// The camera moved: a lower may be tried again.
    pub fn view_changed(&mut self) {
        self.locked = false;
    }

    /// Raises the bias at `cycle` if `need` is oversubscribed; returns whether it did. This
    /// alone may be decided from a *part* of the view (the pixels known so far): the treelets
    /// a part wants are among those the whole view wants, and the slots it hits among those
    /// the whole view hits, so a part that wants more than its room means a whole view that
    /// wants more than its own, smaller room. A lower needs the whole view ([`Self::update`]):
    /// the pixels not yet known may want what would not fit.
    pub fn raise_if_oversubscribed(&mut self, cycle: u64, need: ViewNeed) -> bool {
        if need.wanted <= need.room || self.steps >= MAX_STEPS {
            return false;
        }
        if let Some(lowered) = self.lowered_at.take() {
            self.locked = true;
            if cycle < lowered + LOWER_RETRY_CYCLES {
                let doublings = self.failed_lowers.min(LOWER_RETRY_MAX_DOUBLINGS);
                self.retry_at = cycle + (LOWER_RETRY_CYCLES << doublings);
                self.failed_lowers += 1;
            }
        }
        self.steps += 1;
        self.first_raised_at.get_or_insert(cycle);
        true
    }

    /// Decides from a fully known view at `cycle`; returns whether the bias changed.
    ///
    /// A lower that had to be raised again is not tried until the view changes, and when it was
    /// raised within [`LOWER_RETRY_CYCLES`], not for that many cycles either, doubling with each
    /// such failure in a row. A camera that moves every cycle changes the view every cycle, and
    /// with a pass fast enough to know each whole view it tried a lower after almost every
    /// failed one: the next views wanted what the lowered one did not, and each try evicted for
    /// the finer level, fetched it and dropped it again (lion orbiting 2° a cycle at a half of
    /// what it needs: 4 lowers, 6,549 treelets fetched in 360 cycles).
    pub fn update(&mut self, cycle: u64, need: ViewNeed) -> bool {
        if self.raise_if_oversubscribed(cycle, need) {
            return true;
        }
        if self
            .lowered_at
            .is_some_and(|l| cycle >= l + LOWER_RETRY_CYCLES)
        {
            self.failed_lowers = 0;
        }
        let roomy = f64::from(need.visible_slots) * LOWER_HEADROOM < f64::from(need.capacity);
        if need.wanted == 0 && roomy && self.steps > 0 && !self.locked && cycle >= self.retry_at {
            self.steps -= 1;
            self.lowered_at = Some(cycle);
            return true;
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn need(visible: u32, wanted: u32) -> ViewNeed {
        ViewNeed {
            visible_slots: visible,
            wanted,
            room: 100 - visible,
            capacity: 100,
        }
    }

    #[test]
    fn a_part_of_the_view_only_ever_raises() {
        let mut c = LodBiasControl::new(1.0);
        assert!(c.raise_if_oversubscribed(3, need(90, 30)));
        assert!(c.raise_if_oversubscribed(4, need(90, 30)));
        assert_eq!(c.steps(), 2);
        assert!(
            !c.raise_if_oversubscribed(5, need(10, 0)),
            "room enough for a lower, but a part of the view cannot say so"
        );
        assert!(!c.raise_if_oversubscribed(6, need(60, 40)), "fits: hold");
        assert_eq!(c.steps(), 2);
        assert_eq!(c.first_raised_at(), Some(3));
        assert!(c.update(7, need(10, 0)), "the whole view may lower");
        assert_eq!(c.steps(), 1);
    }

    #[test]
    fn failed_lowers_wait_ever_longer_even_when_the_view_changes() {
        let mut c = LodBiasControl::new(1.0);
        assert!(c.update(0, need(90, 30)));
        assert!(c.update(1, need(90, 30)));
        assert!(c.update(10, need(30, 0)), "lower");
        assert!(
            c.update(12, need(95, 10)),
            "failed within the retry span: raise"
        );
        c.view_changed();
        assert!(
            !c.update(20, need(30, 0)),
            "waits 32 cycles though the view changed"
        );
        assert!(c.update(12 + LOWER_RETRY_CYCLES, need(30, 0)));
        let raised = 12 + LOWER_RETRY_CYCLES + 2;
        assert!(c.update(raised, need(95, 10)), "failed again");
        c.view_changed();
        assert!(
            !c.update(raised + 2 * LOWER_RETRY_CYCLES - 1, need(30, 0)),
            "64 now"
        );
        let lowered = raised + 2 * LOWER_RETRY_CYCLES;
        assert!(c.update(lowered, need(30, 0)));
        // Held for the retry span: the failures are forgotten, and a raise long after it only
        // locks until the view changes.
        assert!(!c.update(lowered + LOWER_RETRY_CYCLES, need(70, 0)));
        assert!(c.update(lowered + 200, need(95, 10)));
        assert!(!c.update(lowered + 201, need(30, 0)), "locked");
        c.view_changed();
        assert!(
            c.update(lowered + 202, need(30, 0)),
            "no wait after a lower that held"
        );
    }

    #[test]
    fn a_new_base_starts_the_control_afresh() {
        let mut c = LodBiasControl::new(1.0);
        assert!(c.update(3, need(90, 30)));
        assert!(c.update(4, need(30, 0)));
        assert!(c.update(5, need(95, 10)), "a failed lower: locked");
        c.set_base(4.0);
        assert_eq!((c.base(), c.steps(), c.bias()), (4.0, 0, 4.0));
        assert_eq!(c.first_raised_at(), Some(3), "the run's history is kept");
        assert!(c.update(6, need(90, 30)));
        assert!(
            c.update(7, need(30, 0)),
            "not locked any more: a lower is tried"
        );
    }

    #[test]
    fn raises_while_oversubscribed_then_holds() {
        let mut c = LodBiasControl::new(1.0);
        assert!(c.update(3, need(90, 30)));
        assert!(c.update(4, need(80, 25)));
        assert_eq!(c.steps(), 2);
        assert!((c.bias() - 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(c.first_raised_at(), Some(3));
        // Fits, but not with the headroom a lower needs: hold.
        assert!(!c.update(5, need(70, 0)));
        assert_eq!(c.steps(), 2);
    }

    #[test]
    fn a_failed_lower_locks_until_the_view_changes() {
        let mut c = LodBiasControl::new(2.0);
        assert!(c.update(0, need(99, 5)));
        assert!(c.update(1, need(30, 0)), "plenty of room: lower");
        assert_eq!(c.steps(), 0);
        assert!(c.update(2, need(95, 10)), "too much after all: raise");
        assert!(!c.update(3, need(30, 0)), "locked");
        let retry = 2 + LOWER_RETRY_CYCLES;
        assert!(
            !c.update(retry, need(30, 0)),
            "still locked: the view is the same"
        );
        c.view_changed();
        assert!(c.update(retry, need(30, 0)));
        assert_eq!(c.steps(), 0);
        assert!(!c.update(retry + 1, need(10, 0)), "never below the base");
        assert_eq!(c.bias(), 2.0);
    }
}
