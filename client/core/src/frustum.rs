//! The peer's policy, for comparison in one client (`--policy frustum`): how Potree and Cesium
//! choose nodes. No feedback pass decides anything: every refinable leaf of a resident treelet
//! whose voxel lies in the view frustum and projects larger than a pixel (times the LOD bias) is
//! requested, largest projection first; occlusion is not known. Resident treelets whose root
//! voxel is in the frustum count as visible.
//!
//! The selector keeps, per resident treelet, its root voxel and its refinable leaves (computed
//! once when the treelet arrives), so a cycle is one box test per refinable leaf.

use std::collections::HashMap;

use arbor_proto::{Cell, Node, Treelet, TreeletId};
use glam::DVec3;

use crate::camera::Camera;
use crate::incore::SceneFrame;

/// The view frustum of a camera: four side planes through the eye (the near plane is the eye
/// itself, so a box behind the camera is outside).
#[derive(Clone, Copy, Debug)]
pub struct Frustum {
    eye: DVec3,
    forward: DVec3,
    /// Inward normals of the left, right, bottom and top planes (all through the eye).
    planes: [DVec3; 4],
}

impl Frustum {
    /// The frustum of `camera`.
    pub fn of(camera: &Camera) -> Self {
        let h = (camera.fov_y * 0.5).tan();
        let aspect = f64::from(camera.width) / f64::from(camera.height.max(1));
        let w = h * aspect;
        let f = camera.forward;
        let up = camera.up;
        let right = f.cross(up);
        // Edge directions of the view pyramid; each side plane holds two of them.
        let left_dir = f - right * w;
        let right_dir = f + right * w;
        let bottom_dir = f - up * h;
        let top_dir = f + up * h;
        Self {
            eye: camera.position,
            forward: f,
            planes: [
                left_dir.cross(up).normalize_or_zero(),
                up.cross(right_dir).normalize_or_zero(),
                right.cross(bottom_dir).normalize_or_zero(),
                top_dir.cross(right).normalize_or_zero(),
            ],
        }
    }

    /// Whether the box `[min, max]` may intersect the frustum (conservative: a box is culled
    /// only when it lies wholly outside one plane).
    pub fn intersects(&self, min: DVec3, max: DVec3) -> bool {
        let outside = |n: DVec3| {
            // The box corner farthest along the plane's inward normal.
            let p = DVec3::new(
                if n.x >= 0.0 { max.x } else { min.x },
                if n.y >= 0.0 { max.y } else { min.y },
                if n.z >= 0.0 { max.z } else { min.z },
            );
            n.dot(p - self.eye) < 0.0
        };
        if self.planes.iter().any(|&n| outside(n)) {
            return false;
        }
        !outside(self.forward)
    }

    /// Distance from the eye to the box (0 inside it).
    pub fn distance(&self, min: DVec3, max: DVec3) -> f64 {
        let d = (min - self.eye).max(self.eye - max).max(DVec3::ZERO);
        d.length()
    }
}

/// The pixel rectangle `[x0, y0, x1, y1]` (may reach past the frame) that the box `[min, max]`
/// covers on `camera`'s image: the bounds of its corners' projections. A box reaching behind
/// the eye's plane covers the whole frame (conservative); `None` when it lies wholly behind.
pub fn screen_rect(camera: &Camera, min: DVec3, max: DVec3) -> Option<[f64; 4]> {
    let h = (camera.fov_y * 0.5).tan();
    let (width, height) = (f64::from(camera.width), f64::from(camera.height.max(1)));
    let w = h * width / height;
    let right = camera.right();
    let mut rect = [
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    ];
    let mut behind = 0;
    for corner in 0..8 {
        let p = DVec3::new(
            if corner & 1 == 0 { min.x } else { max.x },
            if corner & 2 == 0 { min.y } else { max.y },
            if corner & 4 == 0 { min.z } else { max.z },
        );
        let v = p - camera.position;
        let z = v.dot(camera.forward);
        if !(z > 1e-12 * v.length().max(f64::MIN_POSITIVE)) {
            behind += 1;
            continue;
        }
        // Inverse of `Camera::ray`: sx = (2·px/W − 1)·w, sy = (1 − 2·py/H)·h.
        let px = (v.dot(right) / z / w + 1.0) * 0.5 * width;
        let py = (1.0 - v.dot(camera.up) / z / h) * 0.5 * height;
        rect = [
            rect[0].min(px),
            rect[1].min(py),
            rect[2].max(px),
            rect[3].max(py),
        ];
    }
    match behind {
        8 => None,
        0 => Some(rect),
        _ => Some([0.0, 0.0, width, height]),
    }
}

/// A voxel's box in world coordinates.
pub fn world_box(frame: &SceneFrame, cell: Cell) -> (DVec3, DVec3) {
    let size = frame.edge / (1u64 << cell.depth.min(63)) as f64;
    let o = DVec3::from_array(frame.origin);
    let min = o + DVec3::new(f64::from(cell.x), f64::from(cell.y), f64::from(cell.z)) * size;
    (min, min + DVec3::splat(size))
}

/// What a resident treelet offers the selector.
#[derive(Clone, Debug)]
struct TreeletLeaves {
    root: Cell,
    parent: TreeletId,
    /// Refinable leaves: the treelet refining each, and the leaf's voxel.
    leaves: Vec<(TreeletId, Cell)>,
}

/// One request of the frustum policy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrustumRequest {
    /// The treelet refining the leaf.
    pub id: TreeletId,
    /// `log2` of the leaf's projected size in pixels (times the LOD bias): how many levels it is
    /// coarser than a pixel; > 0.
    pub error: f32,
    /// The leaf's voxel (the requested treelet's root voxel).
    pub cell: Cell,
}

/// The frustum policy's state: the refinable leaves of every resident treelet.
#[derive(Debug, Default)]
pub struct FrustumSelector {
    treelets: HashMap<TreeletId, TreeletLeaves>,
}

impl FrustumSelector {
    /// Records a treelet that became resident (its refinable leaves and root voxel).
    pub fn add(&mut self, treelet: &Treelet, max_depth: u8) {
        let Ok(places) = treelet.validate(max_depth) else {
            return;
        };
        let leaves = places
            .iter()
            .zip(&treelet.nodes)
            .filter(|(p, n)| p.is_leaf && n.first_child != Node::NONE)
            .map(|(p, n)| (TreeletId(n.first_child), p.cell))
            .collect();
        self.treelets.insert(
            treelet.header.id,
            TreeletLeaves {
                root: treelet.header.root_cell(),
                parent: treelet.header.parent_id,
                leaves,
            },
        );
    }

    /// Forgets treelets that are no longer resident.
    pub fn retain(&mut self, is_resident: impl Fn(TreeletId) -> bool) {
        self.treelets.retain(|id, _| is_resident(*id));
    }

    /// The resident treelets in the frustum (with their resident ancestors), and the requests:
    /// refinable leaves in the frustum coarser than a pixel whose treelet `skip` does not rule
    /// out, largest projection first (ties by lower id).
    pub fn select(
        &self,
        frame: &SceneFrame,
        camera: &Camera,
        lod_bias: f64,
        skip: impl Fn(TreeletId) -> bool,
    ) -> (Vec<TreeletId>, Vec<FrustumRequest>) {
        let frustum = Frustum::of(camera);
        let footprint = camera.pixel_angle() * lod_bias;
        let mut visible = Vec::new();
        let mut requests = Vec::new();
        for (&id, t) in &self.treelets {
            let (min, max) = world_box(frame, t.root);
            if !frustum.intersects(min, max) {
                continue;
            }
            visible.push(id);
            for &(child, cell) in &t.leaves {
                if skip(child) {
                    continue;
                }
                let (min, max) = world_box(frame, cell);
                if !frustum.intersects(min, max) {
                    continue;
                }
                let size = max.x - min.x;
                let d = frustum.distance(min, max).max(size * 1e-9);
                let error = (size / (d * footprint)).log2();
                if error > 0.0 && error.is_finite() {
                    requests.push(FrustumRequest {
                        id: child,
                        error: error as f32,
                        cell,
                    });
                }
            }
        }
        // A visible treelet's ancestors stay resident too (they hold the patched leaves).
        let mut with_ancestors = visible.clone();
        for id in visible {
            let mut p = self.treelets.get(&id).map(|t| t.parent);
            while let Some(parent) = p.filter(|p| !p.is_none()) {
                with_ancestors.push(parent);
                p = self.treelets.get(&parent).map(|t| t.parent);
            }
        }
        with_ancestors.sort_unstable();
        with_ancestors.dedup();
        requests.sort_unstable_by(|a, b| b.error.total_cmp(&a.error).then(a.id.cmp(&b.id)));
        (with_ancestors, requests)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Camera {
        Camera::look_at(
            DVec3::new(0.5, 0.5, 5.0),
            DVec3::new(0.5, 0.5, 0.5),
            DVec3::Y,
            60f64.to_radians(),
            64,
            64,
        )
        .unwrap()
    }

    #[test]
    fn boxes_in_front_are_in_and_boxes_behind_or_aside_are_out() {
        let f = Frustum::of(&camera());
        assert!(f.intersects(DVec3::ZERO, DVec3::ONE));
        assert!(!f.intersects(DVec3::new(0.0, 0.0, 6.0), DVec3::new(1.0, 1.0, 7.0)));
        assert!(!f.intersects(DVec3::new(100.0, 0.0, 0.0), DVec3::new(101.0, 1.0, 1.0)));
        // Straddling the eye: in.
        assert!(f.intersects(DVec3::new(0.0, 0.0, 4.0), DVec3::new(1.0, 1.0, 6.0)));
        assert_eq!(f.distance(DVec3::ZERO, DVec3::ONE), 4.0);
        assert_eq!(f.distance(DVec3::splat(-10.0), DVec3::splat(10.0)), 0.0);
    }

    #[test]
    fn world_boxes_halve_per_level() {
        let frame = SceneFrame {
            origin: [10.0, 0.0, 0.0],
            edge: 8.0,
            max_depth: 5,
        };
        let (min, max) = world_box(
            &frame,
            Cell {
                depth: 2,
                x: 3,
                y: 0,
                z: 1,
            },
        );
        assert_eq!(min, DVec3::new(16.0, 0.0, 2.0));
        assert_eq!(max, DVec3::new(18.0, 2.0, 4.0));
    }

    /// `screen_rect` inverts `Camera::ray`: a small box around a point on a pixel's ray covers
    /// that pixel, at every pixel of a grid, whatever the aspect and distance; boxes behind
    /// the eye are `None`, and a box around the eye covers the whole frame.
    #[test]
    fn screen_rects_cover_the_pixels_whose_rays_cross_the_box() {
        for (w, h, distance) in [(64, 64, 0.5), (96, 40, 7.0), (33, 200, 1e4)] {
            let c = Camera::look_at(
                DVec3::new(3.0, -2.0, 1.0),
                DVec3::new(3.5, 1.0, 0.0),
                DVec3::Z,
                50f64.to_radians(),
                w,
                h,
            )
            .unwrap();
            for py in (0..h).step_by(7) {
                for px in (0..w).step_by(5) {
                    let (x, y) = (f64::from(px) + 0.5, f64::from(py) + 0.5);
                    let r = c.ray(x, y);
                    let p = r.origin + r.dir * distance;
                    let e = distance * 1e-6;
                    let rect = screen_rect(&c, p - DVec3::splat(e), p + DVec3::splat(e)).unwrap();
                    assert!(
                        rect[0] <= x + 1e-6 && x - 1e-6 <= rect[2],
                        "{w}×{h} at {distance}: x {x} not in {rect:?}"
                    );
                    assert!(
                        rect[1] <= y + 1e-6 && y - 1e-6 <= rect[3],
                        "{w}×{h} at {distance}: y {y} not in {rect:?}"
                    );
                    assert!(rect[2] - rect[0] < 1.0 && rect[3] - rect[1] < 1.0);
                }
            }
            let behind = c.position - c.forward * 2.0;
            assert_eq!(
                screen_rect(&c, behind - DVec3::splat(0.5), behind + DVec3::splat(0.5)),
                None
            );
            let around = screen_rect(&c, c.position - DVec3::ONE, c.position + DVec3::ONE);
            assert_eq!(around, Some([0.0, 0.0, f64::from(w), f64::from(h)]));
        }
    }
}
