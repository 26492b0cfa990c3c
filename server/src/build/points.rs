//! Point clouds: each point lies in exactly one (half-open) cell, found with integer arithmetic
//! on its leaf cell; attributes average colour and normals (file normals, or estimated from each
//! point's neighbourhood by PCA).

use arbor_proto::{AttributeLayout, Cell, Channel};
use rayon::prelude::*;

use super::geometry::Frame;
use super::treelet_builder::{AttributeGenerator, TreeletBuilder};
use crate::source::{Column, ColumnError, ColumnWriter, PointSource};

#[derive(Debug)]
pub struct PointBuilder<'a> {
    pub points: &'a PointSource,
    pub frame: Frame,
}

impl TreeletBuilder for PointBuilder<'_> {
    fn primitive_count(&self) -> u32 {
        self.points.positions.len() as u32
    }

    fn child_mask(&self, prim: u32, cell: Cell) -> u8 {
        let leaf = self.frame.leaf_cell(self.points.positions[prim as usize]);
        let shift = self.frame.depth - cell.depth - 1;
        let bit = |v: u32| ((v >> shift) & 1) as u8;
        1 << (bit(leaf[0]) << 2 | bit(leaf[1]) << 1 | bit(leaf[2]))
    }
}

/// Point attributes: normal (always) and colour (when present).
#[derive(Debug)]
pub struct PointAttributes<'a> {
    pub points: &'a PointSource,
    /// File normals or estimated ones.
    pub normals: &'a Column<[f32; 3]>,
    pub layout: AttributeLayout,
}

impl<'a> PointAttributes<'a> {
    pub fn new(points: &'a PointSource, normals: &'a Column<[f32; 3]>) -> Self {
        let mut ch = vec![Channel::Normal];
        if points.colors.is_some() {
            ch.push(Channel::Color);
        }
        Self {
            points,
            normals,
            layout: AttributeLayout::new(ch),
        }
    }
}

impl AttributeGenerator for PointAttributes<'_> {
    fn bytes_per_voxel(&self) -> usize {
        self.layout.bytes_per_voxel()
    }

    fn leaf(&self, _cell: Cell, prims: &[u32], out: &mut [u8]) {
        let mut n = [0f32; 3];
        let mut c = [0f32; 3];
        for &p in prims {
            let v = self.normals[p as usize];
            // Estimated normals have no consistent sign everywhere: align with the first.
            let s = if n[0] * v[0] + n[1] * v[1] + n[2] * v[2] < 0.0 {
                -1.0
            } else {
                1.0
            };
            for a in 0..3 {
                n[a] += s * v[a];
            }
            if let Some(cs) = &self.points.colors {
                let col = cs[p as usize];
                for a in 0..3 {
                    c[a] += f32::from(col[a]) / 255.0;
                }
            }
        }
        let k = prims.len().max(1) as f32;
        let mut at = 0;
        for ch in self.layout.channels() {
            let size = ch.size();
            match ch {
                Channel::Normal => ch.encode(&n, &mut out[at..at + size]),
                Channel::Color => ch.encode(&c.map(|x| x / k), &mut out[at..at + size]),
                Channel::Density => {}
            }
            at += size;
        }
    }
}

/// A uniform hash grid over the points (ids sorted by cell), for neighbourhood queries.
struct Grid<'a> {
    _pos: std::marker::PhantomData<&'a [[f64; 3]]>,
    origin: [f64; 3],
    cell: f64,
    keys: Vec<(u64, u32)>,
}

impl<'a> Grid<'a> {
    fn new(pos: &'a [[f64; 3]], origin: [f64; 3], cell: f64) -> Self {
        let mut g = Grid {
            _pos: std::marker::PhantomData,
            origin,
            cell,
            keys: Vec::new(),
        };
        let mut keys: Vec<(u64, u32)> = (0..pos.len() as u32)
            .into_par_iter()
            .map(|i| (g.key(g.coords(pos[i as usize])), i))
            .collect();
        keys.par_sort_unstable();
        g.keys = keys;
        g
    }

    fn coords(&self, p: [f64; 3]) -> [i64; 3] {
        [0, 1, 2].map(|a| ((p[a] - self.origin[a]) / self.cell).floor() as i64)
    }

    fn key(&self, c: [i64; 3]) -> u64 {
        // 21 bits per axis; coordinates are non-negative by construction (clamped).
        let m = |v: i64| (v.clamp(0, (1 << 21) - 1)) as u64;
        m(c[0]) << 42 | m(c[1]) << 21 | m(c[2])
    }

    /// Calls `f` for every point in the 3×3×3 cells around `p`.
    fn around(&self, p: [f64; 3], mut f: impl FnMut(u32)) {
        let c = self.coords(p);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let cc = [c[0] + dx, c[1] + dy, c[2] + dz];
                    if cc.iter().any(|v| !(0..1 << 21).contains(v)) {
                        continue;
                    }
                    let k = self.key(cc);
                    let start = self.keys.partition_point(|e| e.0 < k);
                    for e in &self.keys[start..] {
                        if e.0 != k {
                            break;
                        }
                        f(e.1);
                    }
                }
            }
        }
    }
}

fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
}

/// Grid cell size giving about `per_cell` points per occupied cell for a surface-like cloud.
fn grid_cell(pos: &[[f64; 3]], min: [f64; 3], max: [f64; 3], per_cell: f64) -> f64 {
    let ext = (0..3)
        .map(|a| max[a] - min[a])
        .fold(0.0f64, f64::max)
        .max(1e-300);
    // A surface of extent `ext` holds n points: spacing ≈ ext / sqrt(n).
    let spacing = ext / (pos.len() as f64).sqrt().max(1.0);
    (spacing * per_cell.sqrt()).max(ext / (1 << 20) as f64)
}

/// Mean distance to the nearest neighbour, estimated from up to 20,000 evenly spread points.
pub fn mean_point_spacing(pos: &[[f64; 3]], min: [f64; 3], max: [f64; 3]) -> f64 {
    if pos.len() < 2 {
        return 0.0;
    }
    let grid = Grid::new(pos, min, grid_cell(pos, min, max, 4.0));
    let step = (pos.len() / 20_000).max(1);
    let (sum, n) = (0..pos.len())
        .into_par_iter()
        .step_by(step)
        .map(|i| {
            let mut best = f64::INFINITY;
            grid.around(pos[i], |j| {
                if j as usize != i {
                    let d = dist2(pos[i], pos[j as usize]);
                    if d > 0.0 && d < best {
                        best = d;
                    }
                }
            });
            if best.is_finite() {
                (best.sqrt(), 1u64)
            } else {
                (0.0, 0)
            }
        })
        .reduce(|| (0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if n == 0 { 0.0 } else { sum / n as f64 }
}

/// Estimates a normal per point by PCA of its up-to-16 nearest neighbours within the 3×3×3
/// grid neighbourhood, oriented away from the cloud's centre.
pub fn estimate_normals(
    pos: &[[f64; 3]],
    min: [f64; 3],
    max: [f64; 3],
    scratch: &std::path::Path,
) -> Result<Column<[f32; 3]>, ColumnError> {
    const K: usize = 16;
    let grid = Grid::new(pos, min, grid_cell(pos, min, max, 12.0));
    let centre = [0, 1, 2].map(|a| (min[a] + max[a]) * 0.5);
    let mut out = ColumnWriter::create(scratch, "point-normals")?;
    for chunk in (0..pos.len()).collect::<Vec<_>>().chunks(1 << 16) {
        let normals: Vec<[f32; 3]> = chunk
            .par_iter()
            .map(|&i| {
                let mut near: Vec<(f64, u32)> = Vec::with_capacity(64);
                grid.around(pos[i], |j| near.push((dist2(pos[i], pos[j as usize]), j)));
                let k = near.len().min(K);
                if k > 0 {
                    near.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
                }
                let mut n = pca_normal(pos[i], near[..k].iter().map(|e| pos[e.1 as usize]));
                let out_dir = [0, 1, 2].map(|a| pos[i][a] - centre[a]);
                if n[0] * out_dir[0] + n[1] * out_dir[1] + n[2] * out_dir[2] < 0.0 {
                    n = n.map(|v| -v);
                }
                n.map(|v| v as f32)
            })
            .collect();
        for n in normals {
            out.push(n)?;
        }
    }
    out.finish()
}

/// Smallest-eigenvalue eigenvector of the covariance of `pts` around their mean (+Z when fewer
/// than 3 points or degenerate).
fn pca_normal(origin: [f64; 3], pts: impl Iterator<Item = [f64; 3]>) -> [f64; 3] {
    let rel: Vec<[f64; 3]> = pts
        .map(|p| [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]])
        .collect();
    if rel.len() < 3 {
        return [0.0, 0.0, 1.0];
    }
    let n = rel.len() as f64;
    let mean = [0, 1, 2].map(|a| rel.iter().map(|p| p[a]).sum::<f64>() / n);
    let mut c = [[0f64; 3]; 3];
    for p in &rel {
        let d = [p[0] - mean[0], p[1] - mean[1], p[2] - mean[2]];
        for r in 0..3 {
            for s in 0..3 {
                c[r][s] += d[r] * d[s];
            }
        }
    }
    smallest_eigenvector(c)
}

/// Smallest eigenvector of a symmetric 3×3 matrix by Jacobi rotations.
#[allow(clippy::needless_range_loop)] // index form mirrors the textbook rotation formulas
fn smallest_eigenvector(mut a: [[f64; 3]; 3]) -> [f64; 3] {
    let scale = a.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    if !(scale > 0.0) || !scale.is_finite() {
        return [0.0, 0.0, 1.0];
    }
    for r in a.iter_mut() {
        for v in r.iter_mut() {
            *v /= scale;
        }
    }
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..32 {
        let (mut p, mut q, mut big) = (0, 1, 0.0);
        for r in 0..3 {
            for s in r + 1..3 {
                if a[r][s].abs() > big {
                    big = a[r][s].abs();
                    p = r;
                    q = s;
                }
            }
        }
        if big < 1e-15 {
            break;
        }
        let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
        let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
        let t = if theta == 0.0 { 1.0 } else { t };
        let c = 1.0 / (t * t + 1.0).sqrt();
        let s = t * c;
        for k in 0..3 {
            let akp = a[k][p];
            let akq = a[k][q];
            a[k][p] = c * akp - s * akq;
            a[k][q] = s * akp + c * akq;
        }
        for k in 0..3 {
            let apk = a[p][k];
            let aqk = a[q][k];
            a[p][k] = c * apk - s * aqk;
            a[q][k] = s * apk + c * aqk;
        }
        for row in v.iter_mut() {
            let vp = row[p];
            let vq = row[q];
            row[p] = c * vp - s * vq;
            row[q] = s * vp + c * vq;
        }
    }
    let k = (0..3)
        .min_by(|&i, &j| a[i][i].total_cmp(&a[j][j]))
        .unwrap_or(2);
    let n = [v[0][k], v[1][k], v[2][k]];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 {
        n.map(|x| x / len)
    } else {
        [0.0, 0.0, 1.0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pca_of_a_plane_is_its_normal() {
        let pts: Vec<[f64; 3]> = (0..25)
            .map(|i| {
                [
                    f64::from(i % 5),
                    f64::from(i / 5),
                    0.3 * f64::from(i % 5) + 7.0,
                ]
            })
            .collect();
        let n = pca_normal([0.0; 3], pts.into_iter());
        // Plane z = 0.3 x + 7 has normal ∝ (-0.3, 0, 1).
        let len = (0.09f64 + 1.0).sqrt();
        let dot = (n[0] * -0.3 + n[2]) / len;
        assert!(dot.abs() > 0.999_999, "{n:?}");
    }

    #[test]
    fn spacing_of_a_regular_grid() {
        let pts: Vec<[f64; 3]> = (0..10_000)
            .map(|i| [f64::from(i % 100) * 0.5, f64::from(i / 100) * 0.5, 0.0])
            .collect();
        let s = mean_point_spacing(&pts, [0.0; 3], [49.5, 49.5, 0.0]);
        assert!((s - 0.5).abs() < 1e-9, "{s}");
    }
}
