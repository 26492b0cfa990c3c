//! Points sorted by their leaf cell in Morton order, in bounded memory — the fast path of point
//! builds (target depth ≤ [`MAX_KEY_DEPTH`]).
//!
//! With every point's leaf cell as a 64-bit Morton key (x, y, z bits interleaved, x highest, so
//! a key's triples are child indices from the root down), the points of any cell are one
//! contiguous run of the sorted order. The builder then never partitions id lists: a node's
//! primitives are an id range, its children's ranges are found by binary search, and the
//! packing dry run counts a subtree in one pass over the range (distinct key prefixes per
//! level). Ties keep file order (records sort by key, then original id), so each leaf sees its
//! points in the same order as the general path and the scene is the same.
//!
//! The sort is a counting sort into buckets followed by a sort per bucket:
//! 1. count the points per cell at level `min(depth, 7)` (at most 2²¹ counters);
//! 2. group consecutive cells (Morton order) into buckets of at most `budget / 16` points;
//! 3. place each point's [`PointRecord`] (key, colour, id) in its bucket's region of
//!    one scratch file, a round of records at a time, both cores each grouping a part of the
//!    round by bucket and writing the pieces with `pwrite` (the next round is made meanwhile);
//! 4. map the file and sort each bucket where it lies (both cores).
//!
//! A cell with more points than a bucket holds is counting-sorted one step (7 levels) deeper
//! through a spare mapping, recursively; a single leaf cell needs no sorting (every pass keeps
//! file order). Memory: two rounds of records (each ≤ half the budget), the counting
//! tables of 2²¹ entries, and one bucket's pages of the mapping at a time (page cache, which the
//! kernel writes back and evicts as it needs).

use std::ops::Range;
use std::path::Path;

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;

use arbor_proto::{AttributeLayout, Cell};

use super::geometry::Frame;
use super::points::{leaf_attributes, pca_normal, point_layout};
use super::treelet_builder::{AttributeGenerator, TreeletBuilder};
use crate::source::{
    Column, ColumnError, ColumnMut, PointSource, column_path, remove_column, scratch_file,
};

/// Scratch column of the sorted records.
pub const SORTED_COLUMN: &str = "points-sorted";
/// Scratch column of the sorted records' normals (estimated, or taken from the file).
pub const NORMALS_COLUMN: &str = "point-normals";

/// Scratch column where oversized buckets are redistributed.
const SPARE_COLUMN: &str = "points-spare";

/// Deepest target depth whose leaf cells fit a 64-bit Morton key (3 × 21 bits).
pub const MAX_KEY_DEPTH: u8 = 21;
/// Level of the counting pass: 8⁷ = 2,097,152 cells.
const COUNT_LEVEL: u8 = 7;
/// Points read per step of the passes.
const STEP: usize = 1 << 16;

/// One point, as the sorted builder reads it: 16 bytes. The position stays in the source's
/// column (only the normals read it, by `id`): with it the record was 40 bytes, and writing,
/// sorting and searching 2.5× the bytes was most of the sort at 10⁸ points (4 GB of fresh
/// scratch pages).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct PointRecord {
    /// Morton key of the leaf cell.
    pub key: u64,
    /// The point's index in the source (file order).
    pub id: u32,
    /// 8-bit colour (zero when the source has none).
    pub rgb: [u8; 3],
    pub _pad: u8,
}

/// Bits of `v` (21 used) spread to every third bit.
fn spread(v: u32) -> u64 {
    let mut x = u64::from(v) & 0x1f_ffff;
    x = (x | x << 32) & 0x1f_0000_0000_ffff;
    x = (x | x << 16) & 0x1f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    x = (x | x << 2) & 0x1249_2492_4924_9249;
    x
}

/// Morton key of a leaf cell: child index `4x + 2y + z` per level, root level highest.
pub fn morton(cell: [u32; 3]) -> u64 {
    spread(cell[0]) << 2 | spread(cell[1]) << 1 | spread(cell[2])
}

/// Index (0..8) of the child of a depth-`depth` cell that holds `key`, at target depth `max`.
pub fn child_of(key: u64, depth: u8, max: u8) -> u8 {
    ((key >> (3 * u32::from(max - depth - 1))) & 7) as u8
}

/// Bytes of a record, the unit of the sort's memory budget.
const RECORD: usize = std::mem::size_of::<PointRecord>();

/// What the sort held in memory at most and wrote to disk beyond the sorted file itself.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SortStats {
    /// Largest bytes of records held at once (≤ the budget).
    pub peak_bytes: u64,
    /// Bytes of records written to the scratch file because they did not fit the budget
    /// (0 when the whole cloud was sorted in one piece).
    pub spilled_bytes: u64,
}

/// Consecutive cells grouped into buckets of at most `cap` points (a cell larger than `cap` is
/// a bucket alone): the bucket of each cell and the buckets' starts, with the total at the end.
fn group(counts: &[u32], cap: u64) -> (Vec<u32>, Vec<u64>) {
    let mut bucket_of = vec![0u32; counts.len()];
    let mut starts = vec![0u64];
    let mut filled = 0u64;
    let mut at = 0u64;
    for (cell, &c) in counts.iter().enumerate() {
        if filled > 0 && filled + u64::from(c) > cap {
            starts.push(at);
            filled = 0;
        }
        bucket_of[cell] = (starts.len() - 1) as u32;
        filled += u64::from(c);
        at += u64::from(c);
    }
    starts.push(at);
    (bucket_of, starts)
}

/// The sort's working arrays and limits.
struct Sorter<'a> {
    /// Every record, mapped from its scratch file; buckets are sorted where they lie.
    records: &'a mut [PointRecord],
    /// Same length as `records`, mapped on first need: where oversized buckets are
    /// redistributed.
    spare: Option<ColumnMut<PointRecord>>,
    scratch: &'a Path,
    depth: u8,
    cap: u64,
    stats: SortStats,
}

impl Sorter<'_> {
    /// Sorts records `start..end`, all in one cell of `level`, by (key, id).
    fn sort_bucket(&mut self, start: usize, end: usize, level: u8) -> Result<(), ColumnError> {
        let len = (end - start) as u64;
        if len <= self.cap {
            self.stats.peak_bytes = self.stats.peak_bytes.max(len * RECORD as u64);
            self.records[start..end].par_sort_unstable_by_key(|r| (r.key, r.id));
            return Ok(());
        }
        if level >= self.depth {
            // One leaf cell: the records are in file order already (every pass is stable).
            return Ok(());
        }
        // Too big to sort at once: a counting sort one step deeper, through the spare array.
        let next = (level + COUNT_LEVEL).min(self.depth);
        let shift = 3 * u32::from(self.depth - next);
        let mask = (1u64 << (3 * u32::from(next - level))) - 1;
        let sub = |key: u64| ((key >> shift) & mask) as usize;
        let mut counts = vec![0u32; mask as usize + 1];
        for r in &self.records[start..end] {
            counts[sub(r.key)] += 1;
        }
        let (bucket_of, starts) = group(&counts, self.cap);
        drop(counts);
        self.distribute(start, end, &bucket_of, &starts, sub)?;
        for b in 0..starts.len() - 1 {
            let (from, to) = (start + starts[b] as usize, start + starts[b + 1] as usize);
            self.sort_bucket(from, to, next)?;
        }
        Ok(())
    }

    /// Moves records `start..end` into their buckets (stable, both cores), through the spare
    /// array.
    fn distribute(
        &mut self,
        start: usize,
        end: usize,
        bucket_of: &[u32],
        starts: &[u64],
        sub: impl Fn(u64) -> usize + Sync,
    ) -> Result<(), ColumnError> {
        if self.spare.is_none() {
            let spare = ColumnMut::create(self.scratch, SPARE_COLUMN, self.records.len())?;
            self.spare = Some(spare);
        }
        let spare = self.spare.as_mut().expect("created above");
        let mut cursor: Vec<usize> = starts[..starts.len() - 1]
            .iter()
            .map(|&s| start + s as usize)
            .collect();
        let bucket = |r: &PointRecord| bucket_of[sub(r.key)] as usize;
        place_round(spare, &mut cursor, &self.records[start..end], bucket);
        self.records[start..end].copy_from_slice(&spare[start..end]);
        self.stats.spilled_bytes += 2 * (end - start) as u64 * RECORD as u64;
        Ok(())
    }
}

/// Sorts `points` by leaf cell of `frame` into a scratch file under `scratch`, holding at most
/// `budget` bytes of records at once (plus fixed counting tables); returns the sorted records,
/// memory-mapped, and what the sort held and spilled.
///
/// The records live in a shared mapping of the scratch file (page cache, which the kernel
/// writes back and evicts as it needs), not in anonymous memory: distributing through buffers
/// and `pwrite`, then reading each bucket back and writing it again, copied every record four
/// times and was a third of the sort.
pub fn sort_points(
    points: &PointSource,
    frame: &Frame,
    budget: usize,
    scratch: &Path,
) -> Result<(Column<PointRecord>, SortStats), ColumnError> {
    let n = points.positions.len();
    let depth = frame.depth.min(MAX_KEY_DEPTH);
    let level = depth.min(COUNT_LEVEL);
    let shift = 3 * u32::from(depth - level);
    let record = |i: usize| PointRecord {
        key: morton(frame.leaf_cell(points.positions[i])),
        id: i as u32,
        rgb: points.colors.as_ref().map_or([0; 3], |c| c[i]),
        _pad: 0,
    };
    let started = std::time::Instant::now();
    // 1. Points per count cell.
    let cells = 1usize << (3 * u32::from(level));
    let counts = (0..n.div_ceil(STEP))
        .into_par_iter()
        .fold(
            || vec![0u32; cells],
            |mut c, s| {
                for i in s * STEP..((s + 1) * STEP).min(n) {
                    let key = morton(frame.leaf_cell(points.positions[i]));
                    c[(key >> shift) as usize] += 1;
                }
                c
            },
        )
        .reduce(
            || vec![0u32; cells],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
                a
            },
        );
    // 2. Buckets of consecutive cells.
    let cap = (budget / RECORD).max(1) as u64;
    let (bucket_of, starts) = group(&counts, cap);
    drop(counts);
    // 3. Distribution into the buckets' regions of the file, in file order: records of the
    //    next round are made (both cores) while this round's are placed.
    let path = column_path(scratch, SORTED_COLUMN);
    let io = |source| ColumnError::Io {
        path: path.clone(),
        source,
    };
    let file = scratch_file(&path).map_err(io)?;
    file.set_len((n * RECORD) as u64).map_err(io)?;
    let mut staging = vec![Vec::new(); rayon::current_num_threads()];
    let buckets = starts.len() - 1;
    let mut cursor: Vec<usize> = starts[..buckets].iter().map(|&s| s as usize).collect();
    let round = (cap as usize / 2).clamp(1, rayon::current_num_threads() * STEP);
    // Two round buffers, filled and placed in turns: a fresh vector per round cost a page
    // fault per 4 KiB and an unmap per round.
    let make = |from: usize, into: &mut Vec<PointRecord>| {
        into.clear();
        (from..(from + round).min(n))
            .into_par_iter()
            .map(record)
            .collect_into_vec(into);
    };
    let bucket = |r: &PointRecord| bucket_of[(r.key >> shift) as usize] as usize;
    let (mut made, mut spare) = (Vec::with_capacity(round), Vec::with_capacity(round));
    make(0, &mut made);
    let mut from = round;
    while from < n {
        let (placed, ()) = rayon::join(
            || write_round(&file, &mut cursor, &made, bucket, &mut staging),
            || make(from, &mut spare),
        );
        placed.map_err(io)?;
        std::mem::swap(&mut made, &mut spare);
        from += round;
    }
    write_round(&file, &mut cursor, &made, bucket, &mut staging).map_err(io)?;
    drop((made, spare, staging));
    let mut sorted = ColumnMut::<PointRecord>::map_written(file, &path, n)?;
    drop(bucket_of);
    tracing::debug!(
        seconds = started.elapsed().as_secs_f64(),
        buckets,
        "points counted and placed in buckets"
    );
    let started = std::time::Instant::now();
    // 4. Each bucket sorted where it lies (oversized ones one level deeper first).
    let mut sorter = Sorter {
        records: &mut sorted,
        spare: None,
        scratch,
        depth,
        cap,
        stats: SortStats {
            peak_bytes: 0,
            spilled_bytes: if buckets > 1 { (n * RECORD) as u64 } else { 0 },
        },
    };
    for b in 0..buckets {
        sorter.sort_bucket(starts[b] as usize, starts[b + 1] as usize, level)?;
    }
    let stats = sorter.stats;
    tracing::debug!(seconds = started.elapsed().as_secs_f64(), "buckets sorted");
    drop(sorter);
    remove_column(scratch, SPARE_COLUMN);
    Ok((sorted.finish()?, stats))
}

/// A round split into one contiguous part per thread (so the order within a bucket stays the
/// round's order), and each part's records per bucket.
fn count_parts<'r>(
    records: &'r [PointRecord],
    buckets: usize,
    bucket: &(impl Fn(&PointRecord) -> usize + Sync),
) -> (Vec<&'r [PointRecord]>, Vec<Vec<usize>>) {
    let parts = rayon::current_num_threads().clamp(1, records.len().max(1));
    let part_len = records.len().div_ceil(parts).max(1);
    let chunks: Vec<&[PointRecord]> = records.chunks(part_len).collect();
    let counts = chunks
        .par_iter()
        .map(|chunk| {
            let mut c = vec![0usize; buckets];
            for r in *chunk {
                c[bucket(r)] += 1;
            }
            c
        })
        .collect();
    (chunks, counts)
}

/// Places one round of records at their buckets' cursors in `sorted`, every thread a part of
/// the round, and moves the cursors. Each thread takes its own disjoint regions of `sorted`
/// (one per bucket), so it needs no locking.
fn place_round(
    sorted: &mut [PointRecord],
    cursor: &mut [usize],
    records: &[PointRecord],
    bucket: impl Fn(&PointRecord) -> usize + Sync,
) {
    let buckets = cursor.len();
    let (chunks, counts) = count_parts(records, buckets, &bucket);
    // Each bucket's region of this round, split into the parts' pieces in part order.
    let mut pieces: Vec<Vec<&mut [PointRecord]>> = (0..chunks.len())
        .map(|_| Vec::with_capacity(buckets))
        .collect();
    let mut rest: &mut [PointRecord] = sorted;
    let mut at = 0;
    for b in 0..buckets {
        let here = std::mem::take(&mut rest).split_at_mut(cursor[b] - at).1;
        let total: usize = counts.iter().map(|c| c[b]).sum();
        let (mut region, after) = here.split_at_mut(total);
        for (part, c) in counts.iter().enumerate() {
            let (piece, tail) = std::mem::take(&mut region).split_at_mut(c[b]);
            pieces[part].push(piece);
            region = tail;
        }
        rest = after;
        at = cursor[b] + total;
        cursor[b] += total;
    }
    chunks
        .into_par_iter()
        .zip(pieces)
        .for_each(|(chunk, mut pieces)| {
            let mut next = vec![0usize; buckets];
            for r in chunk {
                let b = bucket(r);
                pieces[b][next[b]] = *r;
                next[b] += 1;
            }
        });
}

/// As [`place_round`], into `file` with `pwrite`: every thread groups its part by bucket in a
/// staging buffer of its own and writes each bucket's piece at once. Placed through a mapping of
/// the sparse file, every fresh page was faulted in as a hole and zero-filled first (the
/// placement ran at ≈ 125 % of two cores, half of its samples in the kernel's `memset`).
fn write_round(
    file: &std::fs::File,
    cursor: &mut [usize],
    records: &[PointRecord],
    bucket: impl Fn(&PointRecord) -> usize + Sync,
    staging: &mut Vec<Vec<PointRecord>>,
) -> std::io::Result<()> {
    use std::os::unix::fs::FileExt;
    let buckets = cursor.len();
    let (chunks, counts) = count_parts(records, buckets, &bucket);
    if staging.len() < chunks.len() {
        staging.resize_with(chunks.len(), Vec::new);
    }
    // Where each part's piece of each bucket goes, in records.
    let mut offsets = vec![vec![0usize; buckets]; chunks.len()];
    for b in 0..buckets {
        for (part, c) in counts.iter().enumerate() {
            offsets[part][b] = cursor[b];
            cursor[b] += c[b];
        }
    }
    chunks
        .into_par_iter()
        .zip(staging.par_iter_mut())
        .zip(counts.par_iter().zip(offsets))
        .try_for_each(|((chunk, staged), (counts, offsets))| {
            let mut next: Vec<usize> = counts
                .iter()
                .scan(0, |at, &c| {
                    let start = *at;
                    *at += c;
                    Some(start)
                })
                .collect();
            let starts = next.clone();
            staged.clear();
            staged.resize(chunk.len(), PointRecord::default());
            for r in chunk {
                let b = bucket(r);
                staged[next[b]] = *r;
                next[b] += 1;
            }
            for b in 0..buckets {
                let piece = &staged[starts[b]..next[b]];
                if !piece.is_empty() {
                    file.write_all_at(bytemuck::cast_slice(piece), (offsets[b] * RECORD) as u64)?;
                }
            }
            Ok(())
        })
}

/// The point builder over sorted records: ranges split by binary search, subtrees counted from
/// key prefixes, no id list ever written.
#[derive(Debug)]
pub struct SortedPointBuilder<'a> {
    pub records: &'a [PointRecord],
    /// The target depth (the depth of the keys).
    pub depth: u8,
}

impl TreeletBuilder for SortedPointBuilder<'_> {
    fn primitive_count(&self) -> u64 {
        self.records.len() as u64
    }

    fn child_mask(&self, prim: u32, cell: Cell) -> u8 {
        1 << child_of(self.records[prim as usize].key, cell.depth, self.depth)
    }

    fn split_range(&self, cell: Cell, range: Range<u32>) -> Option<[Range<u32>; 8]> {
        let run = &self.records[range.start as usize..range.end as usize];
        let mut out: [Range<u32>; 8] = std::array::from_fn(|_| range.end..range.end);
        let mut start = range.start;
        for (i, child) in out.iter_mut().enumerate() {
            let end = range.start
                + run.partition_point(|r| usize::from(child_of(r.key, cell.depth, self.depth)) <= i)
                    as u32;
            *child = start..end;
            start = end;
        }
        Some(out)
    }

    fn range_subtree_size(
        &self,
        cell: Cell,
        range: Range<u32>,
        max_depth: u8,
        limit: u64,
    ) -> Option<Option<u64>> {
        let run = &self.records[range.start as usize..range.end as usize];
        let Some(first) = run.first() else {
            return Some(Some(0));
        };
        let below = u64::from(max_depth.saturating_sub(cell.depth));
        let mut count = below;
        let mut previous = first.key;
        for r in &run[1..] {
            if count > limit {
                return Some(None);
            }
            let differ = r.key ^ previous;
            if differ != 0 {
                // New nodes from the depth of the first differing child index down.
                let triple = u64::from((63 - differ.leading_zeros()) / 3);
                count += (triple + 1).min(below);
                previous = r.key;
            }
        }
        Some((count <= limit).then_some(count))
    }
}

/// Point attributes over sorted records: colour from the records, normals from a column in the
/// same order.
#[derive(Debug)]
pub struct SortedPointAttributes<'a> {
    pub records: &'a [PointRecord],
    pub normals: &'a [[f32; 3]],
    pub layout: AttributeLayout,
}

impl<'a> SortedPointAttributes<'a> {
    pub fn new(records: &'a [PointRecord], normals: &'a [[f32; 3]], colour: bool) -> Self {
        Self {
            records,
            normals,
            layout: point_layout(colour),
        }
    }

    /// (normal, colour) of sorted point `p`.
    fn point(&self, p: u32) -> ([f32; 3], Option<[u8; 3]>) {
        let colour = (self.layout.channels().len() > 1).then(|| self.records[p as usize].rgb);
        (self.normals[p as usize], colour)
    }
}

impl AttributeGenerator for SortedPointAttributes<'_> {
    fn bytes_per_voxel(&self) -> usize {
        self.layout.bytes_per_voxel()
    }

    fn leaf(&self, _cell: Cell, prims: &[u32], out: &mut [u8]) {
        leaf_attributes(&self.layout, prims.iter().map(|&p| self.point(p)), out);
    }

    fn leaf_range(&self, _cell: Cell, prims: Range<u32>, out: &mut [u8]) {
        leaf_attributes(&self.layout, prims.map(|p| self.point(p)), out);
    }
}

/// Levels above the target depth whose cells give a point its normal (a cell of 4×4×4 leaves).
const NORMAL_LEVELS_UP: u8 = 2;
/// Fewest points a normal is fitted to; sparser cells use their parent cell, and so on.
const NORMAL_MIN_POINTS: usize = 8;
/// Most points a sparse point's normal is fitted to when its enclosing cell is larger.
const NORMAL_MAX_POINTS: usize = 256;

/// Normals from the voxel grid instead of each point's k nearest neighbours: every point gets
/// the PCA normal (smallest-eigenvalue axis of the covariance) of the points in its cell two
/// levels above the target depth — a contiguous run of the sorted records, so one streaming
/// pass with no neighbour search — or of the nearest enclosing cell with at least
/// `NORMAL_MIN_POINTS`; oriented away from the cloud's centre like the general path's.
pub fn cell_normals(
    records: &[PointRecord],
    positions: &[[f64; 3]],
    depth: u8,
    centre: [f64; 3],
    scratch: &Path,
) -> Result<Column<[f32; 3]>, ColumnError> {
    let mut out = ColumnMut::<[f32; 3]>::create(scratch, NORMALS_COLUMN, records.len())?;
    let level = depth.saturating_sub(NORMAL_LEVELS_UP);
    let cell_of = |key: u64, l: u8| key >> (3 * u32::from(depth - l));
    // Work in steps of about STEP points ending on cell boundaries.
    let mut starts = vec![0usize];
    while let Some(&s) = starts.last() {
        if s >= records.len() {
            break;
        }
        let guess = (s + STEP).min(records.len());
        let end = if guess == records.len() {
            guess
        } else {
            let c = cell_of(records[guess].key, level);
            guess + records[guess..].partition_point(|r| cell_of(r.key, level) == c)
        };
        starts.push(end);
    }
    // Each step writes its own part of the column, on whichever core runs it: copying every
    // step's normals in from one thread left the other core idle while the first faulted in
    // the column's fresh pages.
    let mut parts = Vec::with_capacity(starts.len());
    let mut rest: &mut [[f32; 3]] = &mut out;
    for w in starts.windows(2) {
        let (part, tail) = std::mem::take(&mut rest).split_at_mut(w[1] - w[0]);
        parts.push((w[0]..w[1], part));
        rest = tail;
    }
    parts.into_par_iter().for_each(|(step, part)| {
        part.copy_from_slice(&step_normals(
            records, positions, step, depth, level, centre,
        ));
    });
    out.finish()
}

/// The first index `i ≤ from` such that `same` holds for all of `records[i..from]`, found by
/// doubling steps back from `from` (cost logarithmic in the distance, not in the array).
fn gallop_back(records: &[PointRecord], from: usize, same: impl Fn(&PointRecord) -> bool) -> usize {
    let mut step = 1;
    let mut lo = from;
    while lo > 0 && same(&records[lo - 1]) {
        let next = lo.saturating_sub(step);
        if same(&records[next]) {
            lo = next;
            step *= 2;
        } else {
            return next + 1 + records[next + 1..lo].partition_point(|r| !same(r));
        }
    }
    lo
}

/// The first index `i ≥ from` such that `same` fails at `records[i]` (or the end), found by
/// doubling steps forward.
fn gallop_forward(
    records: &[PointRecord],
    from: usize,
    same: impl Fn(&PointRecord) -> bool,
) -> usize {
    let mut step = 1;
    let mut hi = from;
    while hi < records.len() && same(&records[hi]) {
        let next = (hi + step).min(records.len() - 1);
        if same(&records[next]) {
            hi = next + 1;
            step *= 2;
        } else {
            return hi + records[hi..next].partition_point(|r| same(r));
        }
    }
    hi
}

fn step_normals(
    records: &[PointRecord],
    positions: &[[f64; 3]],
    step: Range<usize>,
    depth: u8,
    level: u8,
    centre: [f64; 3],
) -> Vec<[f32; 3]> {
    let cell_of = |key: u64, l: u8| key >> (3 * u32::from(depth - l));
    let mut out = Vec::with_capacity(step.len());
    // Sparse sibling cells share their enclosing cell's run: fitted once.
    let mut last: Option<(usize, usize, [f64; 3])> = None;
    let mut at = step.start;
    while at < step.end {
        let c = cell_of(records[at].key, level);
        let end = at + records[at..step.end].partition_point(|r| cell_of(r.key, level) == c);
        // The smallest enclosing cell with enough points (searched in the whole array).
        let (mut lo, mut hi, mut l) = (at, end, level);
        while hi - lo < NORMAL_MIN_POINTS && l > 0 {
            l -= 1;
            let parent = cell_of(records[at].key, l);
            lo = gallop_back(records, lo, |r| cell_of(r.key, l) == parent);
            hi = gallop_forward(records, hi, |r| cell_of(r.key, l) == parent);
        }
        // A sparse point whose enclosing cell is huge takes its key-order neighbours only.
        if hi - lo > NORMAL_MAX_POINTS {
            lo = lo.max(at.saturating_sub(NORMAL_MAX_POINTS / 2));
            hi = hi.min(lo + NORMAL_MAX_POINTS);
        }
        let n = match last {
            Some((l, h, n)) if (l, h) == (lo, hi) => n,
            _ => {
                let at = |r: &PointRecord| positions[r.id as usize];
                let n = pca_normal(at(&records[lo]), records[lo..hi].iter().map(at));
                last = Some((lo, hi, n));
                n
            }
        };
        for r in &records[at..end] {
            let p = positions[r.id as usize];
            let dir = [0, 1, 2].map(|a| p[a] - centre[a]);
            let flip = n[0] * dir[0] + n[1] * dir[1] + n[2] * dir[2] < 0.0;
            out.push(n.map(|v| if flip { -v } else { v } as f32));
        }
        at = end;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_keys_order_cells_depth_first() {
        assert_eq!(morton([0, 0, 0]), 0);
        assert_eq!(morton([1, 0, 0]), 4);
        assert_eq!(morton([0, 1, 0]), 2);
        assert_eq!(morton([0, 0, 1]), 1);
        let max = (1 << 21) - 1;
        assert_eq!(morton([max, max, max]), (1u64 << 63) - 1);
        // Child index per level, from the root down.
        let depth = 5;
        let cell = [0b10110, 0b01100, 0b11011];
        let key = morton(cell);
        for d in 0..depth {
            let bit = |v: u32| (v >> (depth - d - 1)) & 1;
            let want = (bit(cell[0]) << 2 | bit(cell[1]) << 1 | bit(cell[2])) as u8;
            assert_eq!(child_of(key, d, depth), want, "level {d}");
        }
    }

    #[test]
    fn galloping_finds_the_run_of_a_cell() {
        let records: Vec<PointRecord> = [1u64, 1, 2, 2, 2, 2, 2, 2, 2, 3, 4, 4]
            .iter()
            .map(|&key| PointRecord {
                key,
                ..PointRecord::default()
            })
            .collect();
        for from in 2..=9 {
            assert_eq!(gallop_back(&records, from, |r| r.key == 2), 2, "{from}");
            assert_eq!(gallop_forward(&records, from, |r| r.key == 2), 9, "{from}");
        }
        assert_eq!(gallop_back(&records, 2, |r| r.key == 1), 0);
        assert_eq!(gallop_forward(&records, 10, |r| r.key == 4), 12);
        assert_eq!(gallop_back(&records, 0, |r| r.key == 1), 0);
    }

    #[test]
    fn sorting_in_small_buckets_equals_sorting_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let mut rng = arbor_proto::rng::SplitMix64::new(3);
        let pts: Vec<[f64; 3]> = (0..300_000)
            .map(|_| {
                [
                    rng.next_f64(),
                    rng.next_f64() * 0.5,
                    (rng.below(4) as f64) * 0.25,
                ]
            })
            .collect();
        let positions = Column::from_slice(dir.path(), "p", &pts).unwrap();
        let source = PointSource {
            positions,
            colors: None,
            normals: None,
        };
        let frame = Frame::around([0.0; 3], [1.0; 3], 12);
        let (sorted, stats) = sort_points(&source, &frame, 4000, dir.path()).unwrap();
        assert!(stats.peak_bytes <= 4000, "{stats:?}");
        assert!(stats.spilled_bytes > 0, "{stats:?}");
        let (_, roomy) = sort_points(&source, &frame, 1 << 30, dir.path()).unwrap();
        assert_eq!(roomy.spilled_bytes, 0);
        assert_eq!(roomy.peak_bytes, 300_000 * RECORD as u64);
        let mut want: Vec<(u64, u32)> = pts
            .iter()
            .enumerate()
            .map(|(i, &p)| (morton(frame.leaf_cell(p)), i as u32))
            .collect();
        want.sort_unstable();
        let got: Vec<(u64, u32)> = sorted.iter().map(|r| (r.key, r.id)).collect();
        assert_eq!(got, want);
    }
}
