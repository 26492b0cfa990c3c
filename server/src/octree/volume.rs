//! Volumes: the primitives are the grid cells (cubes between 8 samples) that the iso surface
//! crosses; a voxel exists where such a cell overlaps it. Attributes sample the field at the
//! voxel centre: density, and the normal from the gradient.

use arbor_proto::{AttributeLayout, Cell, Channel};

use super::geometry::{Frame, boxes_overlap_open};
use super::treelet_builder::{AttributeGenerator, TreeletBuilder};
use crate::source::{Column, ColumnError, ColumnWriter, VolumeSource};

/// Sample access on a volume.
#[derive(Debug, Clone, Copy)]
pub struct Field<'a> {
    pub vol: &'a VolumeSource,
}

impl Field<'_> {
    pub fn at(&self, i: u32, j: u32, k: u32) -> f32 {
        let [dx, dy, _] = self.vol.dims;
        self.vol.values[(i as usize) + dx as usize * (j as usize + dy as usize * k as usize)]
    }

    /// Trilinear value at grid coordinates (clamped to the grid).
    pub fn trilinear(&self, g: [f64; 3]) -> f64 {
        let d = self.vol.dims;
        let mut i0 = [0u32; 3];
        let mut f = [0f64; 3];
        for a in 0..3 {
            let max = f64::from(d[a] - 1);
            let v = g[a].clamp(0.0, max);
            let b = (v.floor() as u32).min(d[a].saturating_sub(2));
            i0[a] = b;
            f[a] = if d[a] > 1 { v - f64::from(b) } else { 0.0 };
        }
        let mut acc = 0.0;
        for c in 0..8u32 {
            let o = [(c >> 2) & 1, (c >> 1) & 1, c & 1];
            let idx = [0, 1, 2].map(|a| (i0[a] + o[a]).min(d[a] - 1));
            let w: f64 = (0..3)
                .map(|a| if o[a] == 1 { f[a] } else { 1.0 - f[a] })
                .product();
            acc += w * f64::from(self.at(idx[0], idx[1], idx[2]));
        }
        acc
    }

    pub fn to_grid(&self, p: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| (p[a] - self.vol.origin[a]) / self.vol.spacing[a])
    }

    /// Whether grid cell `(i, j, k)` (between samples i..=i+1 etc.) contains the iso surface:
    /// its corner values straddle `iso` (min < iso ≤ max).
    pub fn crosses(&self, i: u32, j: u32, k: u32, iso: f32) -> bool {
        let mut lo = f32::INFINITY;
        let mut hi = f32::NEG_INFINITY;
        for c in 0..8u32 {
            let v = self.at(i + (c >> 2 & 1), j + (c >> 1 & 1), k + (c & 1));
            lo = lo.min(v);
            hi = hi.max(v);
        }
        lo < iso && iso <= hi
    }

    /// Source-space box of grid cell `(i, j, k)`.
    pub fn cell_box(&self, ijk: [u32; 3]) -> ([f64; 3], [f64; 3]) {
        let v = self.vol;
        let min = [0, 1, 2].map(|a| v.origin[a] + f64::from(ijk[a]) * v.spacing[a]);
        let max = [0, 1, 2].map(|a| v.origin[a] + f64::from(ijk[a] + 1) * v.spacing[a]);
        (min, max)
    }

    /// Linear index → grid cell coordinates.
    pub fn cell_of(&self, linear: u32) -> [u32; 3] {
        let cx = self.vol.dims[0] - 1;
        let cy = self.vol.dims[1] - 1;
        [linear % cx, (linear / cx) % cy, linear / (cx * cy)]
    }
}

/// Lists the grid cells crossed by the iso surface into a column (linear cell indices).
pub fn crossing_cells(
    vol: &VolumeSource,
    iso: f32,
    scratch: &std::path::Path,
) -> Result<Column<u32>, ColumnError> {
    let f = Field { vol };
    let [dx, dy, dz] = vol.dims;
    let mut w = ColumnWriter::create(scratch, "iso-cells")?;
    if dx < 2 || dy < 2 || dz < 2 {
        return w.finish();
    }
    let (cx, cy) = (dx - 1, dy - 1);
    for k in 0..dz - 1 {
        for j in 0..dy - 1 {
            for i in 0..dx - 1 {
                if f.crosses(i, j, k, iso) {
                    w.push(i + cx * (j + cy * k))?;
                }
            }
        }
    }
    w.finish()
}

/// Otsu's threshold over a 256-bin histogram of the volume: the default `--iso`.
pub fn otsu_threshold(vol: &VolumeSource) -> f32 {
    let [lo, hi] = vol.value_range;
    let bins = 256usize;
    let span = (hi - lo).max(f32::MIN_POSITIVE);
    let mut h = vec![0u64; bins];
    for &v in vol.values.iter() {
        let b = (((v - lo) / span) * (bins as f32 - 1.0))
            .round()
            .clamp(0.0, bins as f32 - 1.0);
        h[b as usize] += 1;
    }
    let total: u64 = h.iter().sum();
    let sum_all: f64 = h
        .iter()
        .enumerate()
        .map(|(i, &c)| i as f64 * c as f64)
        .sum();
    let (mut w0, mut sum0, mut best, mut best_t) = (0u64, 0.0f64, -1.0f64, 0usize);
    for (t, &c) in h.iter().enumerate() {
        w0 += c;
        if w0 == 0 || w0 == total {
            continue;
        }
        sum0 += t as f64 * c as f64;
        let w1 = total - w0;
        let m0 = sum0 / w0 as f64;
        let m1 = (sum_all - sum0) / w1 as f64;
        let between = w0 as f64 * w1 as f64 * (m0 - m1).powi(2);
        if between > best {
            best = between;
            best_t = t;
        }
    }
    // Threshold between bin t and t+1, in source units.
    lo + (best_t as f32 + 0.5) / (bins as f32 - 1.0) * span
}

/// Crossing grid cells against voxels (open boxes: cells that only share a face do not count).
#[derive(Debug)]
pub struct VolumeBuilder<'a> {
    pub field: Field<'a>,
    pub cells: &'a Column<u32>,
    pub frame: Frame,
}

impl VolumeBuilder<'_> {
    /// Grid cell `prim` as a box in leaf units.
    pub fn prim_box(&self, prim: u32) -> ([f64; 3], [f64; 3]) {
        let (min, max) = self
            .field
            .cell_box(self.field.cell_of(self.cells[prim as usize]));
        (self.frame.to_leaf(min), self.frame.to_leaf(max))
    }
}

impl TreeletBuilder for VolumeBuilder<'_> {
    fn primitive_count(&self) -> u64 {
        self.cells.len() as u64
    }

    fn child_mask(&self, prim: u32, cell: Cell) -> u8 {
        let (pmin, pmax) = self.prim_box(prim);
        let mut mask = 0;
        for i in 0..8 {
            let (min, max) = cell.child(i).box_at(self.frame.depth);
            if boxes_overlap_open(pmin, pmax, min, max) {
                mask |= 1 << i;
            }
        }
        mask
    }
}

/// Volume attributes: density and gradient normal at the voxel centre.
#[derive(Debug)]
pub struct VolumeAttributes<'a> {
    pub field: Field<'a>,
    pub frame: Frame,
    pub layout: AttributeLayout,
}

impl<'a> VolumeAttributes<'a> {
    pub fn new(field: Field<'a>, frame: Frame) -> Self {
        Self {
            field,
            frame,
            layout: AttributeLayout::new([Channel::Normal, Channel::Density]),
        }
    }
}

impl AttributeGenerator for VolumeAttributes<'_> {
    fn bytes_per_voxel(&self) -> usize {
        self.layout.bytes_per_voxel()
    }

    fn leaf(&self, cell: Cell, _prims: &[u32], out: &mut [u8]) {
        let g = self.field.to_grid(self.frame.cell_centre(cell));
        let value = self.field.trilinear(g);
        let mut grad = [0f64; 3];
        for a in 0..3 {
            let mut p = g;
            let mut q = g;
            p[a] += 0.5;
            q[a] -= 0.5;
            grad[a] =
                (self.field.trilinear(p) - self.field.trilinear(q)) / self.field.vol.spacing[a];
        }
        // Surfaces face from dense material towards empty space.
        let normal = grad.map(|v| -v as f32);
        let [lo, hi] = self.field.vol.value_range;
        let density = ((value as f32 - lo) / (hi - lo).max(f32::MIN_POSITIVE)).clamp(0.0, 1.0);
        let mut at = 0;
        for ch in self.layout.channels() {
            let size = ch.size();
            match ch {
                Channel::Normal => ch.encode(&normal, &mut out[at..at + size]),
                Channel::Density => ch.encode(&[density], &mut out[at..at + size]),
                Channel::Color => {}
            }
            at += size;
        }
    }
}
