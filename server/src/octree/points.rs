//! Point clouds: each point lies in exactly one (half-open) cell, found with integer arithmetic
//! on its leaf cell; attributes average colour and normals (file normals, or estimated from each
//! point's neighbourhood by PCA).

use arbor_proto::{AttributeLayout, Cell, Channel};
use rayon::prelude::*;

use super::geometry::Frame;
use super::treelet_builder::{AttributeGenerator, TreeletBuilder};
use crate::source::scratch_file;
use crate::source::{Column, ColumnError, ColumnMut, PointSource};

#[derive(Debug)]
pub struct PointBuilder<'a> {
    pub points: &'a PointSource,
    pub frame: Frame,
}

impl TreeletBuilder for PointBuilder<'_> {
    fn primitive_count(&self) -> u64 {
        self.points.positions.len() as u64
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
        Self {
            points,
            normals,
            layout: point_layout(points.colors.is_some()),
        }
    }
}

impl AttributeGenerator for PointAttributes<'_> {
    fn bytes_per_voxel(&self) -> usize {
        self.layout.bytes_per_voxel()
    }

    fn leaf(&self, _cell: Cell, prims: &[u32], out: &mut [u8]) {
        let colors = self.points.colors.as_ref();
        leaf_attributes(
            &self.layout,
            prims
                .iter()
                .map(|&p| (self.normals[p as usize], colors.map(|c| c[p as usize]))),
            out,
        );
    }
}

/// The attribute layout of a point scene: normal, and colour when the source has it.
pub(crate) fn point_layout(colour: bool) -> AttributeLayout {
    let mut ch = vec![Channel::Normal];
    if colour {
        ch.push(Channel::Color);
    }
    AttributeLayout::new(ch)
}

/// A leaf voxel's attributes from its points' (normal, colour): the normals summed with their
/// signs aligned to the first (estimated normals have no consistent sign everywhere), the mean
/// colour; f32 sums in the given order.
pub(crate) fn leaf_attributes(
    layout: &AttributeLayout,
    points: impl Iterator<Item = ([f32; 3], Option<[u8; 3]>)>,
    out: &mut [u8],
) {
    let mut n = [0f32; 3];
    let mut c = [0f32; 3];
    let mut k = 0usize;
    for (v, col) in points {
        let s = if n[0] * v[0] + n[1] * v[1] + n[2] * v[2] < 0.0 {
            -1.0
        } else {
            1.0
        };
        for a in 0..3 {
            n[a] += s * v[a];
        }
        if let Some(col) = col {
            for a in 0..3 {
                c[a] += f32::from(col[a]) / 255.0;
            }
        }
        k += 1;
    }
    let k = k.max(1) as f32;
    let mut at = 0;
    for ch in layout.channels() {
        let size = ch.size();
        match ch {
            Channel::Normal => ch.encode(&n, &mut out[at..at + size]),
            Channel::Color => ch.encode(&c.map(|x| x / k), &mut out[at..at + size]),
            Channel::Density => {}
        }
        at += size;
    }
}

/// A uniform hash grid over some of the points (ids sorted by cell), for neighbourhood queries.
struct Grid {
    origin: [f64; 3],
    cell: f64,
    keys: Vec<(u64, u32)>,
}

impl Grid {
    fn new(pos: &[[f64; 3]], ids: &[u32], origin: [f64; 3], cell: f64) -> Self {
        let mut g = Grid {
            origin,
            cell,
            keys: Vec::new(),
        };
        let mut keys: Vec<(u64, u32)> = ids
            .par_iter()
            .map(|&i| (g.key(g.coords(pos[i as usize])), i))
            .collect();
        keys.par_sort_unstable();
        g.keys = keys;
        g
    }

    fn coords(&self, p: [f64; 3]) -> [i64; 3] {
        [0, 1, 2].map(|a| floor_i64((p[a] - self.origin[a]) / self.cell))
    }

    fn key(&self, c: [i64; 3]) -> u64 {
        // 21 bits per axis; coordinates are non-negative by construction (clamped).
        let m = |v: i64| (v.clamp(0, (1 << 21) - 1)) as u64;
        m(c[0]) << 42 | m(c[1]) << 21 | m(c[2])
    }

    /// Calls `f` with the key of every grid cell of the 3×3×3 block around `p`.
    fn cells_around(&self, p: [f64; 3], mut f: impl FnMut(u64)) {
        let c = self.coords(p);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let cc = [c[0] + dx, c[1] + dy, c[2] + dz];
                    if cc.iter().any(|v| !(0..1 << 21).contains(v)) {
                        continue;
                    }
                    f(self.key(cc));
                }
            }
        }
    }

    /// Calls `f` for every point in the 3×3×3 cells around `p`.
    fn around(&self, p: [f64; 3], mut f: impl FnMut(u32)) {
        self.cells_around(p, |k| {
            let start = self.keys.partition_point(|e| e.0 < k);
            for e in &self.keys[start..] {
                if e.0 != k {
                    break;
                }
                f(e.1);
            }
        });
    }
}

fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
}

/// Grid cell size giving about `per_cell` points per occupied cell for a surface-like cloud.
fn grid_cell(n: usize, min: [f64; 3], max: [f64; 3], per_cell: f64) -> f64 {
    let ext = (0..3)
        .map(|a| max[a] - min[a])
        .fold(0.0f64, f64::max)
        .max(1e-300);
    // A surface of extent `ext` holds n points: spacing ≈ ext / sqrt(n).
    let spacing = ext / (n as f64).sqrt().max(1.0);
    (spacing * per_cell.sqrt()).max(ext / (1 << 20) as f64)
}

/// Neighbourhood work on a point cloud in bounded memory: the cloud is cut into slabs one grid
/// cell thick along its longest axis, slabs are grouped so a group holds at most about
/// `max_points` points, and point ids are counting-sorted by group into a scratch file. `visit`
/// then gets, group by group, the group's ids and the ids of the group plus one slab of halo on
/// each side (so every 3×3×3 neighbourhood of a group point is complete). Memory: the ids of three
/// groups and their grid, never the whole cloud.
fn for_each_slab_group(
    pos: &[[f64; 3]],
    min: [f64; 3],
    max: [f64; 3],
    cell: f64,
    max_points: usize,
    scratch: &std::path::Path,
    mut visit: impl FnMut(&[u32], &[u32]) -> Result<(), ColumnError>,
) -> Result<(), ColumnError> {
    let io = |source| ColumnError::Io {
        path: scratch.join("slabs.ids"),
        source,
    };
    let axis = (0..3)
        .max_by(|&a, &b| (max[a] - min[a]).total_cmp(&(max[b] - min[b])))
        .unwrap_or(0);
    let slabs = (((max[axis] - min[axis]) / cell).floor() as usize + 1).min(1 << 24);
    let slab_of =
        |p: [f64; 3]| (((p[axis] - min[axis]) / cell).floor().max(0.0) as usize).min(slabs - 1);
    // Pass 1: points per slab, then groups of consecutive slabs.
    let mut per_slab = vec![0u64; slabs];
    for p in pos {
        per_slab[slab_of(*p)] += 1;
    }
    let mut group_of_slab = vec![0u32; slabs];
    let mut group_first_slab = vec![0usize];
    let mut group_len: Vec<u64> = vec![0];
    for (s, &c) in per_slab.iter().enumerate() {
        let g = group_len.len() - 1;
        if group_len[g] > 0 && group_len[g] + c > max_points as u64 {
            group_first_slab.push(s);
            group_len.push(0);
        }
        let g = group_len.len() - 1;
        group_of_slab[s] = g as u32;
        group_len[g] += c;
    }
    drop(per_slab);
    let groups = group_len.len();
    let mut start = vec![0u64; groups + 1];
    for g in 0..groups {
        start[g + 1] = start[g] + group_len[g];
    }
    // Pass 2: ids into the scratch file, grouped.
    let file = scratch_file(&scratch.join("slabs.ids")).map_err(io)?;
    {
        use std::os::unix::fs::FileExt;
        let mut cursor: Vec<u64> = start[..groups].to_vec();
        let mut bufs: Vec<Vec<u32>> = vec![Vec::new(); groups];
        let flush = |g: usize, buf: &mut Vec<u32>, cursor: &mut [u64]| {
            file.write_all_at(bytemuck::cast_slice(buf), cursor[g] * 4)?;
            cursor[g] += buf.len() as u64;
            buf.clear();
            Ok::<(), std::io::Error>(())
        };
        for (i, p) in pos.iter().enumerate() {
            let g = group_of_slab[slab_of(*p)] as usize;
            bufs[g].push(i as u32);
            if bufs[g].len() >= 4096 {
                flush(g, &mut bufs[g], &mut cursor).map_err(io)?;
            }
        }
        for (g, b) in bufs.iter_mut().enumerate() {
            flush(g, b, &mut cursor).map_err(io)?;
        }
    }
    let read = |g: usize| -> Result<Vec<u32>, ColumnError> {
        use std::os::unix::fs::FileExt;
        let mut v = vec![0u32; (start[g + 1] - start[g]) as usize];
        file.read_exact_at(bytemuck::cast_slice_mut(&mut v), start[g] * 4)
            .map_err(io)?;
        Ok(v)
    };
    // Pass 3: group by group, with one slab of halo from each neighbour.
    for g in 0..groups {
        let own = read(g)?;
        let first = group_first_slab[g];
        let last = group_first_slab.get(g + 1).map_or(slabs, |&s| s) - 1;
        let mut local = own.clone();
        if g > 0 {
            local.extend(
                read(g - 1)?
                    .into_iter()
                    .filter(|&i| slab_of(pos[i as usize]) + 1 >= first),
            );
        }
        if g + 1 < groups {
            local.extend(
                read(g + 1)?
                    .into_iter()
                    .filter(|&i| slab_of(pos[i as usize]) <= last + 1),
            );
        }
        visit(&own, &local)?;
    }
    Ok(())
}

/// Points per slab group for a memory budget (ids, grid keys and halos cost about 40 bytes per
/// point of a group).
fn points_per_group(memory_budget: usize) -> usize {
    (memory_budget / 40).max(1 << 16)
}

/// Mean distance to the nearest neighbour, estimated from up to 20,000 evenly spread points
/// (every `n / 20,000`-th in file order). Each sample's nearest neighbour is searched in the 3×3×3
/// grid cells around it, in one streaming pass over the cloud: every point whose cell lies around
/// some sample updates those samples' nearest distances (a table of the samples' cells, a
/// running minimum per sample and thread). Nothing is gathered, so memory is fixed (≈ 30 bytes per
/// sample cell and 8 bytes per sample and thread) and one pass suffices whatever the cloud's
/// shape: gathering the points around the samples first held 13 M of 10⁸ city points and needed
/// six passes over the cloud to stay bounded.
pub fn mean_point_spacing(
    pos: &[[f64; 3]],
    min: [f64; 3],
    max: [f64; 3],
    _memory_budget: usize,
    _scratch: &std::path::Path,
) -> Result<f64, ColumnError> {
    if pos.len() < 2 {
        return Ok(0.0);
    }
    let grid = Grid {
        origin: min,
        cell: grid_cell(pos.len(), min, max, 4.0),
        keys: Vec::new(),
    };
    let step = (pos.len() / 20_000).max(1);
    let samples: Vec<usize> = (0..pos.len()).step_by(step).collect();
    let nearest = nearest_around(pos, &grid, &samples);
    // Summed in sample order: the same figure whatever the threads.
    let (sum, n) = nearest
        .iter()
        .filter(|d| d.is_finite())
        .fold((0.0, 0u64), |(s, n), d| (s + d.sqrt(), n + 1));
    Ok(if n == 0 { 0.0 } else { sum / n as f64 })
}

/// Squared distance from each sample to its nearest point at a positive distance in the 3×3×3
/// grid cells around it (infinite when there is none), in one pass over `pos`.
fn nearest_around(pos: &[[f64; 3]], grid: &Grid, samples: &[usize]) -> Vec<f64> {
    const CHUNK: usize = 1 << 16;
    // (cell, sample) for every cell around every sample, sorted by cell; the table maps a cell
    // to its run. Probed once per point of the whole cloud: a fast hash.
    let mut pairs: Vec<(u64, u32)> = Vec::with_capacity(samples.len() * 27);
    for (s, &i) in samples.iter().enumerate() {
        grid.cells_around(pos[i], |k| pairs.push((k, s as u32)));
    }
    pairs.sort_unstable();
    let mut runs: rustc_hash::FxHashMap<u64, (u32, u32)> = rustc_hash::FxHashMap::default();
    for (at, &(k, _)) in pairs.iter().enumerate() {
        runs.entry(k)
            .and_modify(|r| r.1 = at as u32 + 1)
            .or_insert((at as u32, at as u32 + 1));
    }
    let sample_pos: Vec<[f64; 3]> = samples.iter().map(|&i| pos[i]).collect();
    let fresh = || vec![f64::INFINITY; samples.len()];
    pos.par_chunks(CHUNK)
        .fold(fresh, |mut best, chunk| {
            for &p in chunk {
                let Some(&(from, to)) = runs.get(&grid.key(grid.coords(p))) else {
                    continue;
                };
                for &(_, s) in &pairs[from as usize..to as usize] {
                    let d = dist2(p, sample_pos[s as usize]);
                    // The sample itself, and duplicates of it, are at distance 0.
                    if d > 0.0 && d < best[s as usize] {
                        best[s as usize] = d;
                    }
                }
            }
            best
        })
        .reduce(fresh, |mut a, b| {
            for (x, y) in a.iter_mut().zip(b) {
                *x = x.min(y);
            }
            a
        })
}

/// `v.floor() as i64` without the libm call `floor` is on baseline x86-64 (this runs for
/// every point of a cloud): the cast truncates, one step down fixes negative non-integers.
fn floor_i64(v: f64) -> i64 {
    let t = v as i64;
    if (t as f64) > v {
        t.saturating_sub(1)
    } else {
        t
    }
}

/// Estimates a normal per point by PCA of its up-to-16 nearest neighbours within the 3×3×3
/// grid neighbourhood, oriented away from the cloud's centre. Works slab group by slab group
/// (bounded by `memory_budget`) and writes into a memory-mapped column.
pub fn estimate_normals(
    pos: &[[f64; 3]],
    min: [f64; 3],
    max: [f64; 3],
    memory_budget: usize,
    scratch: &std::path::Path,
) -> Result<Column<[f32; 3]>, ColumnError> {
    const K: usize = 16;
    let cell = grid_cell(pos.len(), min, max, 12.0);
    let centre = [0, 1, 2].map(|a| (min[a] + max[a]) * 0.5);
    let mut out = ColumnMut::<[f32; 3]>::create(scratch, "point-normals", pos.len())?;
    for_each_slab_group(
        pos,
        min,
        max,
        cell,
        points_per_group(memory_budget),
        scratch,
        |own, local| {
            let grid = Grid::new(pos, local, min, cell);
            for chunk in own.chunks(1 << 16) {
                let normals: Vec<[f32; 3]> = chunk
                    .par_iter()
                    .map(|&i| {
                        let p = pos[i as usize];
                        let mut near: Vec<(f64, u32)> = Vec::with_capacity(64);
                        grid.around(p, |j| near.push((dist2(p, pos[j as usize]), j)));
                        let k = near.len().min(K);
                        if k > 0 {
                            near.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
                        }
                        let mut n = pca_normal(p, near[..k].iter().map(|e| pos[e.1 as usize]));
                        let out_dir = [0, 1, 2].map(|a| p[a] - centre[a]);
                        if n[0] * out_dir[0] + n[1] * out_dir[1] + n[2] * out_dir[2] < 0.0 {
                            n = n.map(|v| -v);
                        }
                        n.map(|v| v as f32)
                    })
                    .collect();
                for (&i, n) in chunk.iter().zip(normals) {
                    out[i as usize] = n;
                }
            }
            Ok(())
        },
    )?;
    out.finish()
}

/// Smallest-eigenvalue eigenvector of the covariance of `pts` around their mean (+Z when fewer
/// than 3 points or degenerate).
pub(crate) fn pca_normal(
    origin: [f64; 3],
    pts: impl Iterator<Item = [f64; 3]> + Clone,
) -> [f64; 3] {
    // Two passes over the points (mean, then covariance) instead of collecting them: this runs
    // once per cell of every point import.
    let rel = pts.map(|p| [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]]);
    let mut count = 0usize;
    let mut sum = [0f64; 3];
    for p in rel.clone() {
        count += 1;
        for (s, v) in sum.iter_mut().zip(p) {
            *s += v;
        }
    }
    if count < 3 {
        return [0.0, 0.0, 1.0];
    }
    let n = count as f64;
    let mean = sum.map(|s| s / n);
    let mut c = [[0f64; 3]; 3];
    for p in rel {
        let d = [p[0] - mean[0], p[1] - mean[1], p[2] - mean[2]];
        for r in 0..3 {
            for s in 0..3 {
                c[r][s] += d[r] * d[s];
            }
        }
    }
    smallest_eigenvector(c)
}

/// Smallest-eigenvalue eigenvector of a symmetric 3×3 matrix (unit length, sign arbitrary).
///
/// Closed form first: the smallest eigenvalue by the trigonometric formula (Smith 1961), the
/// vector as the longest cross product of two rows of `A − λ·I`. That is a few dozen flops and
/// one `acos`, against ~9 Jacobi rotations — normals were a tenth of a point import. When the
/// two smallest eigenvalues (nearly) coincide the cross products vanish and carry no
/// direction; Jacobi rotations, robust there, decide.
pub(crate) fn smallest_eigenvector(a: [[f64; 3]; 3]) -> [f64; 3] {
    let scale = a.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    if !(scale > 0.0) || !scale.is_finite() {
        return [0.0, 0.0, 1.0];
    }
    let a = a.map(|row| row.map(|v| v / scale));
    let off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
    let q = (a[0][0] + a[1][1] + a[2][2]) / 3.0;
    let d = [a[0][0] - q, a[1][1] - q, a[2][2] - q];
    let p = ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + 2.0 * off) / 6.0).sqrt();
    if p > 0.0 {
        // det((A − qI) / p) / 2, in [−1, 1] up to rounding.
        let b = |r: usize, c: usize| (a[r][c] - if r == c { q } else { 0.0 }) / p;
        let det = b(0, 0) * (b(1, 1) * b(2, 2) - b(1, 2) * b(2, 1))
            - b(0, 1) * (b(1, 0) * b(2, 2) - b(1, 2) * b(2, 0))
            + b(0, 2) * (b(1, 0) * b(2, 1) - b(1, 1) * b(2, 0));
        let phi = (det / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
        let smallest = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
        let rows = [0, 1, 2].map(|r| {
            let mut row = a[r];
            row[r] -= smallest;
            row
        });
        let cross = |u: [f64; 3], v: [f64; 3]| {
            [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ]
        };
        let norm2 = |v: [f64; 3]| v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        let best = [
            cross(rows[0], rows[1]),
            cross(rows[0], rows[2]),
            cross(rows[1], rows[2]),
        ]
        .into_iter()
        .max_by(|x, y| norm2(*x).total_cmp(&norm2(*y)))
        .unwrap_or([0.0; 3]);
        // |cross|² ≈ ((λ₁ − λ₃)(λ₂ − λ₃))² with λ₁ ≤ 3 here: below this the smallest eigenvalue
        // is not separated enough for the cross product to point anywhere in particular.
        let len2 = norm2(best);
        if len2 > CLOSED_FORM_MIN_CROSS2 {
            let len = len2.sqrt();
            return best.map(|v| v / len);
        }
    }
    smallest_eigenvector_jacobi(a)
}

/// Squared cross-product length below which [`smallest_eigenvector`] hands over to Jacobi:
/// an eigenvalue gap product of 1e-5 of the largest entry.
const CLOSED_FORM_MIN_CROSS2: f64 = 1e-10;

/// Smallest eigenvector of a symmetric 3×3 matrix by Jacobi rotations (the reference, and the
/// fallback of [`smallest_eigenvector`] for nearly equal small eigenvalues).
#[allow(clippy::needless_range_loop)] // index form mirrors the textbook rotation formulas
fn smallest_eigenvector_jacobi(mut a: [[f64; 3]; 3]) -> [f64; 3] {
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

    /// `R · diag(λ) · Rᵀ` for the rotation of unit quaternion `q`, with `R`'s columns (the
    /// eigenvectors).
    fn with_eigen(q: [f64; 4], lambda: [f64; 3]) -> ([[f64; 3]; 3], [[f64; 3]; 3]) {
        let [w, x, y, z] = q;
        let r = [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ];
        let mut a = [[0.0; 3]; 3];
        for (i, row) in a.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = (0..3).map(|k| r[i][k] * lambda[k] * r[j][k]).sum();
            }
        }
        let columns = [0, 1, 2].map(|k| [r[0][k], r[1][k], r[2][k]]);
        (a, columns)
    }

    #[test]
    fn closed_form_eigenvector_meets_the_constructed_answer_on_stiff_cases() {
        let mut rng = arbor_proto::rng::SplitMix64::new(17);
        let mut rotations = vec![
            [1.0, 0.0, 0.0, 0.0],
            [0.5f64.sqrt(), 0.5f64.sqrt(), 0.0, 0.0],
        ];
        for _ in 0..300 {
            let q = [0; 4].map(|_| rng.next_f64() * 2.0 - 1.0);
            let len = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            rotations.push(q.map(|v| v / len));
        }
        // Largest first; the last is the one whose eigenvector is wanted.
        let spectra: [[f64; 3]; 9] = [
            [1.0, 0.5, 0.0],       // a plane
            [1.0, 1.0, 1e-12],     // a flat disc
            [1.0, 1e-3, 0.0],      // a thin strip
            [1.0, 0.2, 0.1],       // a noisy surface
            [1.0, 0.0, 0.0],       // a line: smallest two equal
            [1.0, 1e-7, 1e-7],     // a line with noise
            [1.0, 1.0, 1.0],       // isotropic
            [3.0, 1e-6, 0.0],      // gap at the hand-over threshold
            [1.0, 0.999_999, 0.5], // two large nearly equal
        ];
        for q in &rotations {
            for lambda in spectra {
                for magnitude in [1e-15, 1.0, 1e15] {
                    let lambda = lambda.map(|l| l * magnitude);
                    let (a, vectors) = with_eigen(*q, lambda);
                    for (solver, v) in [
                        ("closed form", smallest_eigenvector(a)),
                        ("jacobi", smallest_eigenvector_jacobi(a)),
                    ] {
                        let len = v.iter().map(|c| c * c).sum::<f64>().sqrt();
                        assert!((len - 1.0).abs() < 1e-12, "{solver}: {v:?} {lambda:?}");
                        // Rayleigh quotient: the smallest eigenvalue, up to rounding of λ₁.
                        let av = [0, 1, 2].map(|i| (0..3).map(|k| a[i][k] * v[k]).sum::<f64>());
                        let rq: f64 = (0..3).map(|i| v[i] * av[i]).sum();
                        assert!(
                            (rq - lambda[2]).abs() <= 1e-9 * lambda[0],
                            "{solver}: quotient {rq} for {lambda:?}"
                        );
                        if lambda[1] - lambda[2] >= 1e-4 * lambda[0] {
                            let dot: f64 = (0..3).map(|i| v[i] * vectors[2][i]).sum();
                            assert!(dot.abs() > 1.0 - 1e-9, "{solver}: {dot} for {lambda:?}");
                        }
                    }
                }
            }
        }
        assert_eq!(smallest_eigenvector([[0.0; 3]; 3]), [0.0, 0.0, 1.0]);
        assert_eq!(smallest_eigenvector([[f64::NAN; 3]; 3]), [0.0, 0.0, 1.0]);
    }

    #[test]
    fn floor_without_libm_equals_floor() {
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            2.999_999_999,
            -2.000_000_001,
        ];
        values.extend([f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e300, -1e300]);
        values.extend([
            9.3e18,
            -9.3e18,
            4_503_599_627_370_495.5,
            -4_503_599_627_370_495.5,
        ]);
        let mut rng = arbor_proto::rng::SplitMix64::new(9);
        values.extend((0..100_000).map(|_| (rng.next_f64() - 0.5) * 1e7));
        for v in values {
            assert_eq!(floor_i64(v), v.floor() as i64, "{v:e}");
        }
    }

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
        let dir = tempfile::tempdir().unwrap();
        let s = mean_point_spacing(&pts, [0.0; 3], [49.5, 49.5, 0.0], 1 << 30, dir.path()).unwrap();
        assert!((s - 0.5).abs() < 1e-9, "{s}");
        // The budget does not enter the estimate.
        let s = mean_point_spacing(&pts, [0.0; 3], [49.5, 49.5, 0.0], 1, dir.path()).unwrap();
        assert!((s - 0.5).abs() < 1e-9, "{s}");
    }

    #[test]
    fn spacing_pass_finds_each_samples_nearest_neighbour_like_brute_force() {
        // A long thin strip, the shape whose sample neighbourhoods hold many points per cell,
        // with duplicated points (distance 0 is not a neighbour).
        let mut rng = arbor_proto::rng::SplitMix64::new(11);
        let mut pts: Vec<[f64; 3]> = (0..20_000)
            .map(|_| {
                [
                    rng.next_f64() * 1000.0,
                    rng.next_f64() * 2.0,
                    rng.next_f64() * 0.1,
                ]
            })
            .collect();
        pts.extend_from_within(..500);
        let (min, max) = ([0.0; 3], [1000.0, 2.0, 0.1]);
        let grid = Grid {
            origin: min,
            cell: grid_cell(pts.len(), min, max, 4.0),
            keys: Vec::new(),
        };
        let samples: Vec<usize> = (0..pts.len()).step_by(7).collect();
        let found = nearest_around(&pts, &grid, &samples);
        let mut true_nearest = 0;
        for (m, &i) in samples.iter().enumerate() {
            let mut cells = Vec::new();
            grid.cells_around(pts[i], |k| cells.push(k));
            let d2 = |j: usize| dist2(pts[i], pts[j]);
            let positive = |d: &f64| *d > 0.0;
            // The reference: every point of the cells around the sample, by brute force.
            let in_cells = (0..pts.len())
                .filter(|&j| cells.contains(&grid.key(grid.coords(pts[j]))))
                .map(d2)
                .filter(positive)
                .fold(f64::INFINITY, f64::min);
            assert_eq!(found[m], in_cells, "sample {m}");
            let anywhere = (0..pts.len())
                .map(d2)
                .filter(positive)
                .fold(f64::INFINITY, f64::min);
            assert!(found[m] >= anywhere, "sample {m}");
            true_nearest += usize::from(found[m] == anywhere);
        }
        // The cells are large enough that the search almost never misses the true nearest.
        assert!(true_nearest * 100 >= samples.len() * 99, "{true_nearest}");
    }
}
