//! Exact-as-possible geometric predicates in *leaf units*: the root cube maps to `[0, 2^D]³`
//! where `D` is the target depth, so the box of any cell is a set of small integers and exact in
//! `f64` (docs/design.md §9). Only the primitive's own coordinates carry rounding, once.

use arbor_proto::Cell;

/// Tolerance, in leaf voxels, by which boxes are grown for the triangle test. The separating axis
/// test rounds differently for a box and for its children (different centres), so a triangle
/// grazing a parent could miss all eight children by an ulp; growing every box by far more than
/// the rounding (≤ 2^31 · 2^-52 ≈ 5e-7 leaf units at the deepest level) and far less than a voxel
/// keeps parent and children consistent.
pub const TOUCH_TOLERANCE: f64 = 1e-6;

/// Whether a triangle (leaf units) touches the cell's box grown by [`TOUCH_TOLERANCE`]: the
/// predicate the builder uses and the brute-force tests re-check.
pub fn triangle_touches_cell(tri: &[[f64; 3]; 3], cell: arbor_proto::Cell, depth: u8) -> bool {
    let (min, max) = cell.box_at(depth);
    triangle_touches_box(
        tri,
        min.map(|v| v - TOUCH_TOLERANCE),
        max.map(|v| v + TOUCH_TOLERANCE),
    )
}

/// Maps source coordinates into leaf units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    pub origin: [f64; 3],
    pub edge: f64,
    pub depth: u8,
    /// `2^depth / edge`.
    pub scale: f64,
}

impl Frame {
    /// The root cube around `[min, max]`: a cube with the largest extent as edge, starting at
    /// `min`. A degenerate extent (one point) gets edge 1 so that the scene still has a size.
    pub fn around(min: [f64; 3], max: [f64; 3], depth: u8) -> Frame {
        let extent = (0..3).map(|i| max[i] - min[i]).fold(0.0f64, f64::max);
        // A tiny relative pad keeps the maximum inside the last cell after rounding.
        let mut edge = extent * (1.0 + 1e-9);
        let magnitude = min
            .iter()
            .chain(max.iter())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        let floor = (magnitude * 1e-12).max(f64::MIN_POSITIVE);
        if !(edge > floor) {
            edge = if extent > 0.0 { extent * 2.0 } else { 1.0 };
        }
        Frame::new(min, edge, depth)
    }

    pub fn new(origin: [f64; 3], edge: f64, depth: u8) -> Frame {
        Frame {
            origin,
            edge,
            depth,
            scale: (1u64 << depth) as f64 / edge,
        }
    }

    /// A point in leaf units.
    pub fn to_leaf(&self, p: [f64; 3]) -> [f64; 3] {
        [
            (p[0] - self.origin[0]) * self.scale,
            (p[1] - self.origin[1]) * self.scale,
            (p[2] - self.origin[2]) * self.scale,
        ]
    }

    /// The leaf cell that contains `p` (half-open cells; points on the far face of the root cube
    /// go to the last cell).
    pub fn leaf_cell(&self, p: [f64; 3]) -> [u32; 3] {
        let u = self.to_leaf(p);
        let max = ((1u64 << self.depth) - 1) as f64;
        // The cast truncates, which is the floor for the non-negative values left after the
        // clamp (and `floor` is a libm call on baseline x86-64, three per point in the sort).
        u.map(|v| v.clamp(0.0, max) as u32)
    }

    /// Centre of a cell in source units.
    pub fn cell_centre(&self, c: Cell) -> [f64; 3] {
        let s = self.edge / (1u64 << c.depth) as f64;
        [
            self.origin[0] + (c.x as f64 + 0.5) * s,
            self.origin[1] + (c.y as f64 + 0.5) * s,
            self.origin[2] + (c.z as f64 + 0.5) * s,
        ]
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Whether a triangle touches the closed box `[min, max]` (separating axis test, Akenine-Möller).
/// Degenerate triangles (segments, points) are handled: a zero axis never separates.
pub fn triangle_touches_box(tri: &[[f64; 3]; 3], min: [f64; 3], max: [f64; 3]) -> bool {
    let c = [
        (min[0] + max[0]) * 0.5,
        (min[1] + max[1]) * 0.5,
        (min[2] + max[2]) * 0.5,
    ];
    let h = [
        (max[0] - min[0]) * 0.5,
        (max[1] - min[1]) * 0.5,
        (max[2] - min[2]) * 0.5,
    ];
    let v = [sub(tri[0], c), sub(tri[1], c), sub(tri[2], c)];
    // Box face normals: the triangle's bounds against the box.
    for a in 0..3 {
        let lo = v[0][a].min(v[1][a]).min(v[2][a]);
        let hi = v[0][a].max(v[1][a]).max(v[2][a]);
        if lo > h[a] || hi < -h[a] {
            return false;
        }
    }
    let e = [sub(v[1], v[0]), sub(v[2], v[1]), sub(v[0], v[2])];
    // Edge × box axis.
    for edge in &e {
        for a in 0..3 {
            let mut axis = [0.0; 3];
            axis[a] = 1.0;
            let ax = cross(*edge, axis);
            if separates(&v, ax, h) {
                return false;
            }
        }
    }
    // Triangle normal.
    let n = cross(e[0], e[1]);
    !separates(&v, n, h)
}

fn separates(v: &[[f64; 3]; 3], axis: [f64; 3], h: [f64; 3]) -> bool {
    let p = [dot(v[0], axis), dot(v[1], axis), dot(v[2], axis)];
    let r = h[0] * axis[0].abs() + h[1] * axis[1].abs() + h[2] * axis[2].abs();
    let lo = p[0].min(p[1]).min(p[2]);
    let hi = p[0].max(p[1]).max(p[2]);
    lo > r || hi < -r
}

/// Whether two boxes overlap with positive volume (open boxes: touching faces do not count).
pub fn boxes_overlap_open(amin: [f64; 3], amax: [f64; 3], bmin: [f64; 3], bmax: [f64; 3]) -> bool {
    (0..3).all(|i| amin[i] < bmax[i] && bmin[i] < amax[i])
}

/// Closest point on a triangle to `p`, as barycentric weights (Ericson, RTCD 5.1.5).
pub fn closest_barycentric(p: [f64; 3], t: &[[f64; 3]; 3]) -> [f64; 3] {
    let (a, b, c) = (t[0], t[1], t[2]);
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return [1.0, 0.0, 0.0];
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return [0.0, 1.0, 0.0];
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return [1.0 - v, v, 0.0];
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return [0.0, 0.0, 1.0];
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return [1.0 - w, 0.0, w];
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return [0.0, 1.0 - w, w];
    }
    let denom = va + vb + vc;
    if !(denom.abs() > 0.0) || !denom.is_finite() {
        return [1.0 / 3.0; 3];
    }
    let v = vb / denom;
    let w = vc / denom;
    [1.0 - v - w, v, w]
}

/// Depth at which voxels reach `resolution` (the data's own detail), clamped to the limits.
pub fn depth_for_resolution(edge: f64, resolution: f64) -> u8 {
    if !(resolution.is_finite() && resolution > 0.0 && edge > 0.0) {
        return 0;
    }
    let levels = (edge / resolution).log2().ceil();
    levels.clamp(0.0, f64::from(arbor_proto::limits::MAX_DEPTH)) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn triangle_box_cases() {
        let min = [0.0; 3];
        let max = [1.0; 3];
        // Inside.
        assert!(triangle_touches_box(
            &[[0.1, 0.1, 0.1], [0.5, 0.1, 0.1], [0.1, 0.5, 0.1]],
            min,
            max
        ));
        // Lying exactly on a face counts (closed box).
        assert!(triangle_touches_box(
            &[[1.0, 0.2, 0.2], [1.0, 0.8, 0.2], [1.0, 0.2, 0.8]],
            min,
            max
        ));
        // Touching only a corner.
        assert!(triangle_touches_box(
            &[[1.0, 1.0, 1.0], [2.0, 1.0, 1.0], [1.0, 2.0, 1.0]],
            min,
            max
        ));
        // Near miss across the diagonal: the plane x+y+z = 3.01 misses the box.
        assert!(!triangle_touches_box(
            &[[3.01, 0.0, 0.0], [0.0, 3.01, 0.0], [0.0, 0.0, 3.01]],
            min,
            max
        ));
        assert!(triangle_touches_box(
            &[[3.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 3.0]],
            min,
            max
        ));
        // Big triangle whose corners are all outside but which cuts through the box.
        assert!(triangle_touches_box(
            &[[-10.0, -10.0, 0.5], [10.0, -10.0, 0.5], [0.0, 20.0, 0.5]],
            min,
            max
        ));
        // Degenerate: a segment through the box and a point outside it.
        assert!(triangle_touches_box(
            &[[-1.0, 0.5, 0.5], [2.0, 0.5, 0.5], [2.0, 0.5, 0.5]],
            min,
            max
        ));
        assert!(!triangle_touches_box(&[[1.5, 0.5, 0.5]; 3], min, max));
        // Sliver along the box edge diagonal, just outside.
        assert!(!triangle_touches_box(
            &[
                [1.0 + 1e-9, -1.0, 0.0],
                [1.0 + 1e-9, 2.0, 0.0],
                [1.0 + 2e-9, 2.0, 0.0]
            ],
            min,
            max
        ));
    }

    #[test]
    fn frame_cells_are_half_open_and_clamped() {
        let f = Frame::new([0.0; 3], 8.0, 3);
        assert_eq!(f.leaf_cell([1.0, 0.999_999, 8.0]), [1, 0, 7]);
        assert_eq!(f.leaf_cell([-0.0, 0.0, 7.999]), [0, 0, 7]);
    }

    #[test]
    fn huge_coordinates_keep_millimetres() {
        // A 1 km cube at UTM-like coordinates, depth 20 (~1 mm voxels).
        let f = Frame::new([500_000.0, 5_000_000.0, 0.0], 1024.0, 20);
        let p = [500_512.345_6, 5_000_000.001_5, 0.000_5];
        let c = f.leaf_cell(p);
        assert_eq!(c, [524_641, 1, 0]);
    }

    #[test]
    fn closest_point_regions() {
        let t = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        assert_eq!(closest_barycentric([-1.0, -1.0, 0.0], &t), [1.0, 0.0, 0.0]);
        let b = closest_barycentric([0.25, 0.25, 5.0], &t);
        assert!((b[1] - 0.25).abs() < 1e-12 && (b[2] - 0.25).abs() < 1e-12);
        let d = closest_barycentric([0.3, 0.3, 0.0], &[[1.0; 3]; 3]);
        assert!(d.iter().all(|x| x.is_finite()));
    }

    #[test]
    fn auto_depth() {
        assert_eq!(depth_for_resolution(1.0, 1.0 / 256.0), 8);
        assert_eq!(depth_for_resolution(1.0, 1.0 / 200.0), 8);
        assert_eq!(depth_for_resolution(1.0, 2.0), 0);
        assert_eq!(depth_for_resolution(1.0, 0.0), 0);
        assert_eq!(depth_for_resolution(1e9, 1e-9), 31);
    }
}
