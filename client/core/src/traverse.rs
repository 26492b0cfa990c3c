//! The CPU reference traversal of the incore octree: one ray in, the nearest voxel it stops at
//! out. The analysis pass, the CPU renderer and the brute-force tests use it, and the WGSL
//! shader is meant to be a line-by-line twin of it (docs/design.md §5, §9), so it uses no recursion, no
//! heap, only fixed-size arrays indexed by depth, and a bounded loop.
//!
//! # Numerics
//!
//! Positions stay exact integer cells ([`Cell`]); floats appear only as *camera-relative*
//! coordinates. The box of cell `c` at depth `d` is
//! `lo = (frame.origin − ray.origin) + c·size_d`, `hi = (frame.origin − ray.origin) + (c+1)·size_d`
//! with `size_d = edge / 2^d`. Both faces come from the same formula of an integer face
//! coordinate, and `k·size_d` equals `2k·size_{d+1}` bit for bit (the factor is a power of two),
//! so a face shared by two voxels, or by a voxel and its parent, has one floating-point value at
//! every depth. That makes the comparisons below consistent (a child's entry is never before its
//! parent's, neighbours meet exactly) and keeps huge world coordinates harmless: the large
//! `origin − ray.origin` is taken once, while the camera is near.
//!
//! # Algorithm, step by step
//!
//! 1. Reject rays with a non-finite origin or direction, a zero direction, a scene frame with a
//!    non-positive or non-finite edge, and an empty node buffer: no hit.
//! 2. Slab test of the root box (`slab`). Per axis `a`: if `dir[a] == 0`, the ray is inside
//!    the closed slab iff `lo[a] ≤ 0 ≤ hi[a]` (no division, so no `0·∞` NaN); otherwise the face
//!    distances are `lo[a]/dir[a]` and `hi[a]/dir[a]`, ordered by the sign of `dir[a]`.
//!    `t_enter` is the largest entry, `t_exit` the smallest exit; the box is hit iff
//!    `t_enter ≤ t_exit` and `t_exit ≥ 0`. The axis giving `t_enter` is the entry face.
//! 3. Every box that is hit gets the key `t = max(t_enter, 0)` (0 when the camera is inside).
//! 4. A node *stops* (is terminal) when it is a leaf, or its depth is `min(lod.max_depth, 31)`,
//!    or `pixel_angle > 0` and `voxel_size ≤ t·pixel_angle·lod_bias` (it projects to at most a
//!    pixel). If the root stops, it is the answer.
//! 5. Otherwise keep a stack indexed by depth: for the node being expanded at depth `d`, its
//!    global index, the mask of children not yet visited, and the smallest key among those
//!    children (−∞ until computed). The current cell is kept as integers; descending appends
//!    the child index bits (`cell·2 + bit`), popping shifts them off (`cell >> 1`).
//! 6. Loop (at most [`MAX_STEPS`] times): at level `d`, if the remaining mask is empty, or its
//!    smallest key is not below the best hit found so far, pop (finish when popping the root).
//!    Otherwise slab-test every remaining child. The eight children share their low, middle
//!    and high faces per axis, so those 9 distances are divided once per node, not 6 per
//!    child (the same quotients), and the ray's interval in each half of each axis is ordered
//!    by the direction's sign once per node too: a child's test is then the largest of three
//!    entries against the smallest of three exits, without branches, and the entry face is
//!    found only for the child picked — bit for bit the per-child `slab` test, 1.4–1.7×
//!    faster per ray. Drop the children missed or whose key is not below the best hit; pick
//!    the smallest key (ties: lower child index), clear its bit and record the smallest key
//!    of the rest. The child's record is at
//!    `index + first_child + rank` (wrapping add, rank = number of valid children with a lower
//!    child index); its leafness comes from the parent's `leaf_mask`. A record outside the
//!    buffer, or a non-leaf without children (a malformed buffer), is skipped as empty. If the
//!    child stops, it becomes the best hit when its key is smaller; else push it.
//! 7. Return the best hit.
//!
//! Why keep going after the first hit: sibling boxes are disjoint, so their ray intervals are
//! ordered and front-to-back order alone would be exact — except for degenerate rays. A ray
//! lying in the plane between two siblings enters both at the same `t`, and a ray that grazes
//! one sibling's edge where it enters the other has a zero-length interval in the first; in
//! both cases the nearest voxel may be in the sibling visited second. The bound on the key
//! (a child's voxels are never nearer than the child itself, by the face argument above) makes
//! the search exact at the cost of one comparison per stack level in the common case, because
//! the stored smallest key of the rest lets a level be popped without testing its boxes again.

use arbor_proto::limits::MAX_DEPTH;
use arbor_proto::{Cell, Node, TreeletId};
use glam::DVec3;

use crate::incore::{IncoreView, SceneFrame};

/// Upper bound on loop iterations of one [`trace`]: a real octree needs a few hundred per ray
/// at most; the bound only guarantees termination on a malformed buffer (the best hit found
/// until then is returned).
pub const MAX_STEPS: u32 = 1 << 16;

/// Largest magnitude [`screen_error`] returns, in octree levels.
pub const MAX_SCREEN_ERROR: f32 = 64.0;

/// Entries of the traversal stack: one per depth `0..=MAX_DEPTH`.
const STACK: usize = MAX_DEPTH as usize + 1;

/// A ray in world space. `dir` should have unit length (the LOD test and `t` assume it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Start point, world units.
    pub origin: DVec3,
    /// Direction, unit length.
    pub dir: DVec3,
}

/// Where traversal stops refining.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lod {
    /// Angle subtended by one pixel (radians per pixel at the image centre); 0 disables the
    /// projection stop.
    pub pixel_angle: f64,
    /// Multiplies the pixel footprint: above 1 stops earlier (coarser), below 1 later.
    pub lod_bias: f64,
    /// Deepest level to descend to (capped at [`MAX_DEPTH`]).
    pub max_depth: u8,
}

/// The voxel a ray stopped at.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Global index of the node in the incore buffer.
    pub node: u32,
    /// Exact cell of the voxel.
    pub cell: Cell,
    /// Distance along the ray to the entry point, `max(t_enter, 0)`.
    pub t: f64,
    /// Whether the node is a leaf in the buffer (as opposed to an LOD or depth stop).
    pub leaf: bool,
    /// The treelet refining this leaf when it is a refinable leaf, else [`TreeletId::NONE`].
    pub subtreelet: TreeletId,
    /// [`screen_error`] of this voxel at `t`.
    pub error: f32,
    /// Axis (0..3) of the face the ray entered through.
    pub entry_axis: u8,
    /// Sign of that face's outward normal: −1 for the low face, +1 for the high face.
    pub entry_sign: i8,
}

/// Screen-space error of a voxel in the log domain (docs/design.md §5):
/// `log2(voxel_size) − log2(max(t, tiny)) − log2(pixel_angle·lod_bias)`, clamped to
/// ±[`MAX_SCREEN_ERROR`]. Positive: the voxel covers more than a pixel by about that many
/// octree levels.
///
/// Always finite. Each factor's logarithm is taken separately (so products never overflow or
/// underflow); a factor that is zero, negative or NaN counts as the smallest normal `f64` and
/// `+∞` as the largest. Thus `t → 0` (camera inside the voxel) and `pixel_angle = 0` give
/// `+MAX_SCREEN_ERROR` (infinitely coarse), a NaN voxel size `−MAX_SCREEN_ERROR`.
pub fn screen_error(voxel_size: f64, t: f64, pixel_angle: f64, lod_bias: f64) -> f32 {
    let e = safe_log2(voxel_size) - safe_log2(t) - safe_log2(pixel_angle) - safe_log2(lod_bias);
    let m = f64::from(MAX_SCREEN_ERROR);
    // `e` is finite: every term is in [-1023, 1024].
    e.clamp(-m, m) as f32
}

/// `log2` that stays finite: zero, negative and NaN count as the smallest normal f64, `+∞` as
/// the largest. The GPU backend takes its uniform's log terms from here too.
pub fn safe_log2(x: f64) -> f64 {
    if x.is_nan() || x <= 0.0 {
        f64::MIN_POSITIVE.log2()
    } else if x == f64::INFINITY {
        f64::MAX.log2()
    } else {
        x.log2()
    }
}

/// Result of a slab test against one box.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Slab {
    t_enter: f64,
    entry_axis: u8,
    entry_sign: i8,
}

/// Slab test of the camera-relative box `[lo, hi]` against a ray from the origin along `dir`
/// (see the module docs, step 2). `None` when missed.
fn slab(lo: [f64; 3], hi: [f64; 3], dir: [f64; 3]) -> Option<Slab> {
    let t_lo = [0, 1, 2].map(|a| lo[a] / dir[a]);
    let t_hi = [0, 1, 2].map(|a| hi[a] / dir[a]);
    slab_with(lo, hi, t_lo, t_hi, dir)
}

/// [`slab`] with the face distances `t_lo = lo / dir` and `t_hi = hi / dir` given: the children
/// of one node share their faces, so the traversal divides 9 face coordinates per node instead
/// of 6 per child — the same quotients, so the same results (as `slab_with` in
/// `traverse.wgsl`). Components where `dir` is 0 are not read.
fn slab_with(
    lo: [f64; 3],
    hi: [f64; 3],
    t_lo: [f64; 3],
    t_hi: [f64; 3],
    dir: [f64; 3],
) -> Option<Slab> {
    let mut t_enter = f64::NEG_INFINITY;
    let mut t_exit = f64::INFINITY;
    let mut entry_axis = 0u8;
    let mut entry_sign = -1i8;
    for a in 0..3 {
        let d = dir[a];
        if d == 0.0 {
            // Parallel: inside the closed slab or never in it.
            if !(lo[a] <= 0.0 && 0.0 <= hi[a]) {
                return None;
            }
            continue;
        }
        let (near, far, sign) = if d > 0.0 {
            (t_lo[a], t_hi[a], -1)
        } else {
            (t_hi[a], t_lo[a], 1)
        };
        if near > t_enter {
            t_enter = near;
            entry_axis = a as u8;
            entry_sign = sign;
        }
        if far < t_exit {
            t_exit = far;
        }
    }
    (t_enter <= t_exit && t_exit >= 0.0).then_some(Slab {
        t_enter,
        entry_axis,
        entry_sign,
    })
}

/// The slabs of the eight children of one node: per axis and half (0: the low child, 1: the
/// high one) the ray's interval inside that half's slab, from the three faces the children
/// share per axis (low, middle, high) — what [`slab_with`] derives per axis, taken once per
/// node instead of once per child, from the same quotients.
struct ChildFaces {
    /// Where the ray enters the half's slab: `t` of its near face; for an axis the ray runs
    /// parallel to, −∞ when the ray lies inside the closed slab and +∞ when outside (`far` is
    /// then −∞, so the child is missed, as [`slab_with`] returns `None`).
    near: [[f64; 2]; 3],
    /// Where the ray leaves the half's slab: `t` of its far face (parallel axes: +∞ inside, −∞
    /// outside).
    far: [[f64; 2]; 3],
}

/// Per axis, which half child `i` lies in (bit 2: x, bit 1: y, bit 0: z).
#[inline]
fn halves(i: u8) -> [usize; 3] {
    [2, 1, 0].map(|shift| usize::from((i >> shift) & 1))
}

impl ChildFaces {
    /// Slab test of child `i` (bit 2: x, bit 1: y, bit 0: z upper half): the same result as
    /// [`slab_with`] on the child's faces, bit for bit. Entry is the largest of the three
    /// nears and exit the smallest far, which is what `slab_with`'s loop computes (no value
    /// here is NaN: faces are sums of finite values, at worst ±∞, and a zero direction never
    /// divides); a parallel axis's ±∞ never wins the entry, as `slab_with` skips it. The
    /// entry face (the first axis reaching the entry, as in `slab_with`) is only needed for
    /// the child picked, so [`ChildFaces::slab`] finds it then.
    #[inline]
    fn enter(&self, i: u8) -> Option<f64> {
        let b = halves(i);
        let n = [self.near[0][b[0]], self.near[1][b[1]], self.near[2][b[2]]];
        let f = [self.far[0][b[0]], self.far[1][b[1]], self.far[2][b[2]]];
        let t_enter = n[0].max(n[1]).max(n[2]);
        let t_exit = f[0].min(f[1]).min(f[2]);
        (t_enter <= t_exit && t_exit >= 0.0).then_some(t_enter)
    }

    /// The [`Slab`] of child `i`, whose entry [`ChildFaces::enter`] gave.
    fn slab(&self, i: u8, t_enter: f64, dir: [f64; 3]) -> Slab {
        let b = halves(i);
        let mut entry = (f64::NEG_INFINITY, 0u8, -1i8);
        for a in 0..3 {
            let near = self.near[a][b[a]];
            if dir[a] != 0.0 && near > entry.0 {
                entry = (near, a as u8, if dir[a] > 0.0 { -1 } else { 1 });
            }
        }
        debug_assert_eq!(entry.0.to_bits(), t_enter.to_bits());
        Slab {
            t_enter,
            entry_axis: entry.1,
            entry_sign: entry.2,
        }
    }
}

/// Everything about a ray that is fixed for one traversal.
struct Setup {
    /// `frame.origin − ray.origin`.
    rel: [f64; 3],
    dir: [f64; 3],
    edge: f64,
}

impl Setup {
    fn new(frame: &SceneFrame, ray: &Ray) -> Option<Self> {
        let o = ray.origin.to_array();
        let dir = ray.dir.to_array();
        if !ray.origin.is_finite() || !ray.dir.is_finite() || ray.dir == DVec3::ZERO {
            return None;
        }
        if !(frame.edge > 0.0) || !frame.edge.is_finite() {
            return None;
        }
        let rel = [0, 1, 2].map(|a| frame.origin[a] - o[a]);
        if !rel.iter().all(|r| r.is_finite()) {
            return None;
        }
        Some(Self {
            rel,
            dir,
            edge: frame.edge,
        })
    }

    /// Edge of a voxel at `depth` (≤ 31): an exact power-of-two scaling.
    fn size(&self, depth: u32) -> f64 {
        self.edge / (1u64 << depth) as f64
    }

    /// Slab test of cell `cell` at a depth whose voxel edge is `size`.
    fn test(&self, cell: [u32; 3], size: f64) -> Option<Slab> {
        let lo = [0, 1, 2].map(|a| self.rel[a] + f64::from(cell[a]) * size);
        let hi = [0, 1, 2].map(|a| self.rel[a] + (f64::from(cell[a]) + 1.0) * size);
        slab(lo, hi, self.dir)
    }

    /// The slabs of the children of `cell`, whose voxel edge is `size`. Child `b` (0 or 1) of
    /// an axis spans `2·cell + b .. 2·cell + b + 1`; each face is computed with the formula of
    /// [`Setup::test`] (integers below 2^53 are exact in `f64`), so bit for bit the same.
    fn child_faces(&self, cell: [u32; 3], size: f64) -> ChildFaces {
        let mut near = [[0.0; 2]; 3];
        let mut far = [[0.0; 2]; 3];
        for a in 0..3 {
            let k0 = f64::from(cell[a]) * 2.0;
            let face = [0.0, 1.0, 2.0].map(|k| self.rel[a] + (k0 + k) * size);
            let d = self.dir[a];
            if d == 0.0 {
                for b in 0..2 {
                    let inside = face[b] <= 0.0 && 0.0 <= face[b + 1];
                    near[a][b] = if inside {
                        f64::NEG_INFINITY
                    } else {
                        f64::INFINITY
                    };
                    far[a][b] = if inside {
                        f64::INFINITY
                    } else {
                        f64::NEG_INFINITY
                    };
                }
                continue;
            }
            let t = face.map(|f| f / d);
            for b in 0..2 {
                (near[a][b], far[a][b]) = if d > 0.0 {
                    (t[b], t[b + 1])
                } else {
                    (t[b + 1], t[b])
                };
            }
        }
        ChildFaces { near, far }
    }
}

/// Whether a voxel of edge `size` hit at key `t` stops the descent by projection.
fn projects_small(size: f64, t: f64, lod: &Lod) -> bool {
    lod.pixel_angle > 0.0 && size <= t * lod.pixel_angle * lod.lod_bias
}

/// Builds the [`Hit`] for a terminal node.
#[allow(clippy::too_many_arguments)]
fn make_hit(
    index: u32,
    node: &Node,
    leaf: bool,
    cell: [u32; 3],
    depth: u32,
    size: f64,
    s: &Slab,
    lod: &Lod,
) -> Hit {
    let t = s.t_enter.max(0.0);
    let subtreelet = if leaf {
        TreeletId(node.first_child)
    } else {
        TreeletId::NONE
    };
    Hit {
        node: index,
        cell: Cell {
            depth: depth as u8,
            x: cell[0],
            y: cell[1],
            z: cell[2],
        },
        t,
        leaf,
        subtreelet,
        error: screen_error(size, t, lod.pixel_angle, lod.lod_bias),
        entry_axis: s.entry_axis,
        entry_sign: s.entry_sign,
    }
}

/// Casts `ray` into the incore octree and returns the nearest voxel where it stops (module
/// docs, steps 1–7), or `None` on a miss. Never panics, whatever the buffer or ray holds.
pub fn trace(view: &IncoreView<'_>, frame: &SceneFrame, ray: &Ray, lod: &Lod) -> Option<Hit> {
    trace_past(view, frame, ray, lod, &[])
}

/// [`trace`] as if the voxels stopped at `skip` (node indices of earlier hits) were empty: the
/// nearest stop behind them. A coarse voxel is a conservative hull of what it holds, so a ray
/// that stops at one may well pass through once it is refined; what it would meet then is what
/// the ray needs next (the look-past requests of [`crate::cycle`]). Descendants of a skipped
/// voxel are not visited (it stops the ray's descent, it is just not a hit).
pub fn trace_past(
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    ray: &Ray,
    lod: &Lod,
    skip: &[u32],
) -> Option<Hit> {
    let setup = Setup::new(frame, ray)?;
    let root = *view.nodes.first()?;
    let max_depth = u32::from(lod.max_depth.min(MAX_DEPTH));

    let root_slab = setup.test([0; 3], setup.edge)?;
    let root_t = root_slab.t_enter.max(0.0);
    let root_leaf = root.valid_mask == 0;
    if root_leaf || max_depth == 0 || projects_small(setup.edge, root_t, lod) {
        if skip.contains(&0) {
            return None;
        }
        return Some(make_hit(
            0, &root, root_leaf, [0; 3], 0, setup.edge, &root_slab, lod,
        ));
    }

    let mut stack_node = [0u32; STACK];
    let mut stack_mask = [0u8; STACK];
    let mut stack_next = [f64::NEG_INFINITY; STACK];
    stack_mask[0] = root.valid_mask;
    let mut depth = 0usize;
    let mut cell = [0u32; 3];
    let mut best: Option<Hit> = None;
    let mut best_t = f64::INFINITY;

    for _ in 0..MAX_STEPS {
        let mask = stack_mask[depth];
        if mask == 0 || stack_next[depth] >= best_t {
            if depth == 0 {
                return best;
            }
            depth -= 1;
            cell = cell.map(|c| c >> 1);
            continue;
        }
        let parent_index = stack_node[depth];
        // In range: checked before it was pushed (the root: `first()` above).
        let Some(&parent) = view.nodes.get(parent_index as usize) else {
            return best;
        };
        let child_depth = depth as u32 + 1;
        let size = setup.size(child_depth);

        // Pick the nearest remaining child that is hit and could beat the best hit.
        let mut remaining = mask;
        let mut pick: Option<(u8, f64, f64)> = None;
        let mut next = f64::INFINITY;
        let faces = setup.child_faces(cell, size);
        // The set bits in increasing order, as a loop over 0..8 skipping the clear ones.
        let mut todo = mask;
        while todo != 0 {
            let i = todo.trailing_zeros() as u8;
            todo &= todo - 1;
            let Some(t_enter) = faces.enter(i) else {
                remaining &= !(1 << i);
                continue;
            };
            let t = t_enter.max(0.0);
            if t >= best_t {
                remaining &= !(1 << i);
                continue;
            }
            match pick {
                Some((_, _, pt)) if t >= pt => next = next.min(t),
                _ => {
                    if let Some((_, _, pt)) = pick {
                        next = next.min(pt);
                    }
                    pick = Some((i, t_enter, t));
                }
            }
        }
        let Some((i, t_enter, t)) = pick else {
            stack_mask[depth] = 0;
            continue;
        };
        let half = halves(i);
        let child_cell = [0, 1, 2].map(|a| cell[a] * 2 + half[a] as u32);
        let s = faces.slab(i, t_enter, setup.dir);
        stack_mask[depth] = remaining & !(1 << i);
        stack_next[depth] = next;

        let rank = (parent.valid_mask & ((1u8 << i) - 1)).count_ones();
        let child_index = parent_index
            .wrapping_add(parent.first_child)
            .wrapping_add(rank);
        let Some(&child) = view.nodes.get(child_index as usize) else {
            continue;
        };
        let leaf = parent.leaf_mask & (1 << i) != 0;
        if leaf || child_depth >= max_depth || projects_small(size, t, lod) {
            if t < best_t && !skip.contains(&child_index) {
                best_t = t;
                best = Some(make_hit(
                    child_index,
                    &child,
                    leaf,
                    child_cell,
                    child_depth,
                    size,
                    &s,
                    lod,
                ));
            }
            continue;
        }
        if child.valid_mask == 0 {
            // An inner node without children: malformed, nothing to hit inside.
            continue;
        }
        depth += 1;
        cell = child_cell;
        stack_node[depth] = child_index;
        stack_mask[depth] = child.valid_mask;
        stack_next[depth] = f64::NEG_INFINITY;
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn screen_error_is_finite_and_clamped() {
        let vals = [
            0.0,
            -0.0,
            -1.0,
            f64::MIN_POSITIVE,
            5e-324,
            1e-300,
            1.0,
            1e300,
            f64::MAX,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for &a in &vals {
            for &b in &vals {
                for &c in &vals {
                    for &d in &[0.0, 1.0, f64::NAN, 1e-300] {
                        let e = screen_error(a, b, c, d);
                        assert!(e.is_finite(), "{a} {b} {c} {d}");
                        assert!(e.abs() <= MAX_SCREEN_ERROR);
                    }
                }
            }
        }
    }

    #[test]
    fn screen_error_counts_levels() {
        // A voxel of 4 units at distance 1 with 1-unit pixels: 2 levels too coarse.
        assert_eq!(screen_error(4.0, 1.0, 1.0, 1.0), 2.0);
        assert_eq!(screen_error(1.0, 8.0, 0.125, 1.0), 0.0);
        assert_eq!(screen_error(1.0, 8.0, 0.125, 2.0), -1.0);
        assert_eq!(screen_error(1.0, 0.0, 0.001, 1.0), MAX_SCREEN_ERROR);
        assert_eq!(screen_error(1.0, 1.0, 0.0, 1.0), MAX_SCREEN_ERROR);
        assert_eq!(screen_error(1e-300, 1e300, 1.0, 1.0), -MAX_SCREEN_ERROR);
    }

    /// The per-node child test ([`ChildFaces`]) against the per-child [`slab`] test it
    /// replaced: the same hit or miss, the same entry bits, entry axis and sign, for every
    /// child of random cells at random depths, with directions that are random, axis-parallel
    /// (one or two zero components), tiny, and origins on faces and far away.
    #[test]
    fn child_faces_agree_with_the_per_child_slab_test() {
        let mut rng = arbor_proto::rng::SplitMix64::new(11);
        let (mut checked, mut ties) = (0u32, 0u32);
        for case in 0..20_000u32 {
            let scale = [1.0, 1e-3, 1e6, 4e12][(case % 4) as usize];
            let depth = case % 24;
            let edge = 2.0 * scale;
            let size = edge / f64::from(1u32 << depth);
            let span = 1u32 << depth;
            let cell = [0, 1, 2].map(|_| (rng.next_u64() % u64::from(span)) as u32);
            // The frame's origin relative to the ray's origin, up to a few edges away.
            let mut rel = [0, 1, 2].map(|_| (rng.next_f64() * 2.0 - 1.0) * 3.0 * edge);
            // Aimed at a point of the node's box, most rays hit some child.
            let mut dir = [0, 1, 2].map(|a| rel[a] + (f64::from(cell[a]) + rng.next_f64()) * size);
            let parallel: &[usize] = match case % 5 {
                1 => &[(case / 5 % 3) as usize],
                2 => &[(case / 5 % 3) as usize, ((case / 5 + 1) % 3) as usize],
                _ => &[],
            };
            for &a in parallel {
                dir[a] = 0.0;
                // The origin inside the node's slab of that axis, on its middle face in some cases.
                let u = if case % 3 == 0 { 0.5 } else { rng.next_f64() };
                rel[a] = -(f64::from(cell[a]) + u) * size;
            }
            if case % 5 == 3 {
                dir[(case / 5 % 3) as usize] = 1e-300;
            }
            if case % 5 == 4 && case % 2 == 0 {
                // Along a diagonal of a cube placed alike on every axis: entries tie between
                // axes, and the first axis must win, as in `slab_with`.
                let c = cell[0];
                let cell = [c; 3];
                let (r, d) = (rel[0], dir[0]);
                let setup = Setup {
                    rel: [r; 3],
                    dir: [d; 3],
                    edge,
                };
                let faces = setup.child_faces(cell, size / 2.0);
                for i in [0u8, 7] {
                    let child = [c * 2 + u32::from(i & 1); 3];
                    let e = setup.test(child, size / 2.0);
                    let g = faces.enter(i).map(|t| faces.slab(i, t, [d; 3]));
                    assert_eq!(e, g, "diagonal case {case} child {i}");
                    ties += u32::from(g.is_some());
                }
            }
            if dir.iter().all(|&d| d == 0.0) {
                continue;
            }
            let setup = Setup { rel, dir, edge };
            let child_size = size / 2.0;
            let faces = setup.child_faces(cell, child_size);
            for i in 0..8u8 {
                let child = [
                    cell[0] * 2 + u32::from((i >> 2) & 1),
                    cell[1] * 2 + u32::from((i >> 1) & 1),
                    cell[2] * 2 + u32::from(i & 1),
                ];
                let expected = setup.test(child, child_size);
                let got = faces.enter(i).map(|t| faces.slab(i, t, dir));
                match (expected, got) {
                    (None, None) => {}
                    (Some(e), Some(g)) => {
                        assert_eq!(
                            e.t_enter.to_bits(),
                            g.t_enter.to_bits(),
                            "case {case} child {i}"
                        );
                        assert_eq!((e.entry_axis, e.entry_sign), (g.entry_axis, g.entry_sign));
                        checked += 1;
                    }
                    (e, g) => panic!("case {case} child {i}: slab {e:?}, child faces {g:?}"),
                }
            }
        }
        assert!(checked > 10_000, "only {checked} hits compared");
        assert!(ties > 1_000, "only {ties} tied entries compared");
    }

    #[test]
    fn slab_handles_parallel_rays_on_faces() {
        let lo = [-1.0, 0.0, 1.0];
        let hi = [1.0, 2.0, 2.0];
        // Along +z from the origin, which lies on the y = 0 face: hit, closed slabs.
        let s = slab(lo, hi, [0.0, 0.0, 1.0]).unwrap();
        assert_eq!(s.t_enter, 1.0);
        assert_eq!((s.entry_axis, s.entry_sign), (2, -1));
        // Parallel and outside in x.
        assert!(slab([0.5, 0.0, 1.0], hi, [0.0, 0.0, 1.0]).is_none());
        // Box behind the ray.
        assert!(slab(lo, hi, [0.0, 0.0, -1.0]).is_none());
    }
}
