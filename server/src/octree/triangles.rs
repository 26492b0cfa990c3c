//! Triangle meshes: triangle–box overlap for the structure, closest-point interpolation for the
//! attributes (normals from the triangles or the file's vertex normals, colour when present).

use arbor_proto::{AttributeLayout, Cell, Channel};

use super::geometry::{Frame, TOUCH_TOLERANCE, closest_barycentric, cross, triangle_touches_cell};
use super::treelet_builder::{AttributeGenerator, TreeletBuilder};
use crate::source::MeshSource;

/// Triangles in leaf units.
#[derive(Debug)]
pub struct TriangleBuilder<'a> {
    pub mesh: &'a MeshSource,
    pub frame: Frame,
}

impl TriangleBuilder<'_> {
    /// Triangle `t` in leaf units.
    pub fn triangle(&self, t: u32) -> [[f64; 3]; 3] {
        let idx = self.mesh.triangles[t as usize];
        idx.map(|i| self.frame.to_leaf(self.mesh.positions[i as usize]))
    }
}

impl TreeletBuilder for TriangleBuilder<'_> {
    fn primitive_count(&self) -> u64 {
        self.mesh.triangles.len() as u64
    }

    fn child_mask(&self, prim: u32, cell: Cell) -> u8 {
        let tri = self.triangle(prim);
        let d = self.frame.depth;
        let (min, max) = cell.box_at(d);
        let mid = [
            (min[0] + max[0]) * 0.5,
            (min[1] + max[1]) * 0.5,
            (min[2] + max[2]) * 0.5,
        ];
        // Candidate halves per axis from the triangle's bounds, with the same tolerance as the
        // exact test so the prefilter never drops a child that test would accept.
        let mut halves = [[false; 2]; 3];
        for a in 0..3 {
            let lo = tri[0][a].min(tri[1][a]).min(tri[2][a]);
            let hi = tri[0][a].max(tri[1][a]).max(tri[2][a]);
            halves[a] = [
                lo <= mid[a] + TOUCH_TOLERANCE,
                hi >= mid[a] - TOUCH_TOLERANCE,
            ];
        }
        let mut mask = 0u8;
        for i in 0..8u8 {
            let (bx, by, bz) = (
                usize::from(i >> 2 & 1),
                usize::from(i >> 1 & 1),
                usize::from(i & 1),
            );
            if !(halves[0][bx] && halves[1][by] && halves[2][bz]) {
                continue;
            }
            if triangle_touches_cell(&tri, cell.child(i), d) {
                mask |= 1 << i;
            }
        }
        mask
    }
}

/// Mesh attributes: normal (always) and colour (when the file has it).
#[derive(Debug)]
pub struct MeshAttributes<'a> {
    pub mesh: &'a MeshSource,
    pub frame: Frame,
    pub layout: AttributeLayout,
}

impl<'a> MeshAttributes<'a> {
    pub fn new(mesh: &'a MeshSource, frame: Frame) -> Self {
        let mut ch = vec![Channel::Normal];
        if mesh.colors.is_some() {
            ch.push(Channel::Color);
        }
        Self {
            mesh,
            frame,
            layout: AttributeLayout::new(ch),
        }
    }
}

impl AttributeGenerator for MeshAttributes<'_> {
    fn bytes_per_voxel(&self) -> usize {
        self.layout.bytes_per_voxel()
    }

    fn leaf(&self, cell: Cell, prims: &[u32], out: &mut [u8]) {
        let centre = self.frame.cell_centre(cell);
        let mut normal = [0f64; 3];
        let mut colour = [0f64; 3];
        let mut n_col = 0u32;
        for &t in prims {
            let idx = self.mesh.triangles[t as usize];
            let p = idx.map(|i| self.mesh.positions[i as usize]);
            // Work relative to the first vertex so huge coordinates keep their precision.
            let rel = |q: [f64; 3]| [q[0] - p[0][0], q[1] - p[0][1], q[2] - p[0][2]];
            let tri = [rel(p[0]), rel(p[1]), rel(p[2])];
            let w = closest_barycentric(rel(centre), &tri);
            let n = match &self.mesh.normals {
                Some(ns) => {
                    let mut n = [0f64; 3];
                    for k in 0..3 {
                        let v = ns[idx[k] as usize];
                        for a in 0..3 {
                            n[a] += w[k] * f64::from(v[a]);
                        }
                    }
                    n
                }
                None => cross(
                    [tri[1][0], tri[1][1], tri[1][2]],
                    [tri[2][0], tri[2][1], tri[2][2]],
                ),
            };
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if len > 0.0 && len.is_finite() {
                for a in 0..3 {
                    normal[a] += n[a] / len;
                }
            }
            if let Some(cs) = &self.mesh.colors {
                for k in 0..3 {
                    let c = cs[idx[k] as usize];
                    for a in 0..3 {
                        colour[a] += w[k] * f64::from(c[a]) / 255.0;
                    }
                }
                n_col += 1;
            }
        }
        let mut at = 0;
        for ch in self.layout.channels() {
            let size = ch.size();
            match ch {
                Channel::Normal => {
                    let v = normal.map(|x| x as f32);
                    ch.encode(&v, &mut out[at..at + size]);
                }
                Channel::Color => {
                    let v = colour.map(|x| (x / f64::from(n_col.max(1))) as f32);
                    ch.encode(&v, &mut out[at..at + size]);
                }
                Channel::Density => {}
            }
            at += size;
        }
    }
}

/// Mean edge length over all triangles (the mesh's own resolution).
pub fn mean_edge_length(mesh: &MeshSource) -> f64 {
    let mut sum = 0.0;
    let mut n = 0u64;
    for t in mesh.triangles.iter() {
        let p = t.map(|i| mesh.positions[i as usize]);
        for (a, b) in [(0, 1), (1, 2), (2, 0)] {
            let d = ((p[a][0] - p[b][0]).powi(2)
                + (p[a][1] - p[b][1]).powi(2)
                + (p[a][2] - p[b][2]).powi(2))
            .sqrt();
            if d > 0.0 {
                sum += d;
                n += 1;
            }
        }
    }
    if n == 0 { 0.0 } else { sum / n as f64 }
}
