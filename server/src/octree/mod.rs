//! The generalized builder (docs/design.md §3): a build manager drives a [`TreeletBuilder`] chosen by
//! input kind and an [`AttributeGenerator`] chosen by the channels the source has.
//!
//! Two passes, each bounded in memory:
//! 1. **fill** — treelets are filled breadth-first from a FIFO of jobs (top-down, so every child
//!    id is higher than its parent's); independent jobs of one batch run in parallel; finished
//!    treelets are appended to a scratch file of packed records;
//! 2. **store** (`store`) — two streams at once into a [`TreeletSink`] (the pool): the node
//!    blocks, compressed in id order with a zstd dictionary trained on evenly spread records; and
//!    the attribute blocks, treelets read back level by level, deepest first, inner attributes
//!    averaged bottom-up (a child treelet's root attribute feeding its parent's refinable leaf)
//!    and compressed per channel.

pub mod geometry;
pub mod idlist;
pub mod pending;
pub mod points;
mod records;
pub mod sorted_points;
mod store;
pub mod treelet_builder;
pub mod triangles;
pub mod volume;

use std::fs::File;
use std::path::Path;
use std::time::Instant;

use arbor_proto::codec;
use arbor_proto::treelet::nodes_for_bytes;
use arbor_proto::{
    AttributeLayout, BuildParameters, Cell, ProtoError, SceneDescription, SceneStats, SourceKind,
    TreeletId,
};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;

use crate::progress::{ImportProgress, Phase};
use crate::source::{Column, ColumnError, ColumnWriter, Source, remove_column};
use geometry::{Frame, depth_for_resolution};
use idlist::{Budget, IdList, Lists, SpillFile};
use pending::PendingQueue;
use records::{RecordFile, RecordSink};
pub use treelet_builder::{AttributeGenerator, MAX_PRIMITIVES, TreeletBuilder, fill_treelet};
use treelet_builder::{FilledTreelet, TreeletJob};

/// Depth to build to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthChoice {
    /// Exactly this depth.
    Fixed(u8),
    /// The depth at which voxels reach the data's own resolution.
    Auto,
}

/// Parameters of one build.
#[derive(Clone, Debug)]
pub struct BuildOptions {
    pub depth: DepthChoice,
    pub treelet_bytes: u32,
    /// Iso threshold for volumes; `None` picks Otsu's threshold.
    pub iso: Option<f32>,
    pub zstd_level: i32,
    /// Train per-stream zstd dictionaries.
    pub dictionary: bool,
    /// Bytes of primitive id lists held in memory; beyond it lists stream through a spill file.
    pub memory_budget: usize,
    /// Draw progress bars on stderr.
    pub progress: bool,
}

impl Default for BuildOptions {
    fn default() -> Self {
        Self {
            depth: DepthChoice::Auto,
            treelet_bytes: arbor_proto::limits::DEFAULT_TREELET_BYTES,
            iso: None,
            zstd_level: 3,
            dictionary: true,
            memory_budget: 256 << 20,
            progress: false,
        }
    }
}

/// Errors of a build.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    /// Scratch files could not be written or read.
    #[error("build scratch I/O: {0}")]
    Io(#[from] std::io::Error),
    /// A scratch column failed.
    #[error(transparent)]
    Column(#[from] ColumnError),
    /// Encoding or compression failed.
    #[error("encoding: {0}")]
    Proto(#[from] ProtoError),
    /// The input has nothing to build from.
    #[error("nothing to build: {0}")]
    Empty(String),
    /// A coordinate is NaN or infinite.
    #[error("non-finite coordinate in {what} {index}")]
    NonFinite { what: &'static str, index: u64 },
    /// A parameter is out of range.
    #[error("invalid build parameter: {0}")]
    Parameter(String),
    /// More treelets than ids (treelet ids are 32-bit in the format).
    #[error(
        "scene needs more than {} treelets (treelet ids are 32-bit): use larger treelets (--treelet-bytes, up to 16384) or a coarser --depth",
        arbor_proto::limits::MAX_TREELETS
    )]
    TooManyTreelets,
    /// More primitives than one build can index (primitive ids are 32-bit).
    #[error(
        "{count} primitives exceed the limit of {limit} per scene (primitive ids are 32-bit): split the input into several scenes"
    )]
    TooManyPrimitives { count: u64, limit: u64 },
    /// The treelet sink (the pool) refused a write.
    #[error("storing treelets: {0}")]
    Sink(String),
}

/// Receives the compressed blocks of every treelet, as two streams that arrive interleaved: the
/// node blocks in ascending id order, and the channel blocks treelet level by level, deepest
/// level first (each treelet's channels together). Every treelet appears once in each stream.
pub trait TreeletSink {
    /// Called once with the scene's attribute layout before the first block.
    fn start(&mut self, layout: &AttributeLayout) -> Result<(), BuildError>;
    /// Node blocks of consecutive treelets, ascending.
    fn put_nodes(&mut self, blocks: Vec<(TreeletId, Vec<u8>)>) -> Result<(), BuildError>;
    /// Channel blocks (layout order) of several treelets of one level, ascending.
    fn put_channels(&mut self, blocks: Vec<(TreeletId, Vec<Vec<u8>>)>) -> Result<(), BuildError>;
}

/// Builds `source` into a scene named `name`, handing treelets to `sink`. Returns the scene
/// description (stats filled in except `peak_rss_bytes`, which the caller measures).
pub fn build_scene(
    source: &Source,
    name: &str,
    source_label: &str,
    opts: &BuildOptions,
    scratch: &Path,
    sink: &mut dyn TreeletSink,
) -> Result<SceneDescription, BuildError> {
    let target = BuildTarget {
        name,
        source_label,
        scratch,
    };
    build_scene_observed(source, &target, opts, sink, &ImportProgress::default())
}

/// What a build makes and where its scratch files go.
#[derive(Clone, Copy, Debug)]
pub struct BuildTarget<'a> {
    /// The scene's name.
    pub name: &'a str,
    /// What the input was, for the description.
    pub source_label: &'a str,
    /// Scratch directory for spill and record files.
    pub scratch: &'a Path,
}

/// Refuses what no build can take (a depth past the format's, no primitives, more than primitive
/// ids can name); returns the nodes a treelet of `opts.treelet_bytes` holds.
fn check_build_input(source: &Source, opts: &BuildOptions) -> Result<u32, BuildError> {
    let capacity = nodes_for_bytes(opts.treelet_bytes)?;
    if let DepthChoice::Fixed(d) = opts.depth
        && d > arbor_proto::limits::MAX_DEPTH
    {
        return Err(BuildError::Parameter(format!(
            "depth {d} exceeds the maximum {}",
            arbor_proto::limits::MAX_DEPTH
        )));
    }
    if source.primitive_count() == 0 {
        return Err(BuildError::Empty(source.describe()));
    }
    if source.primitive_count() > MAX_PRIMITIVES {
        return Err(BuildError::TooManyPrimitives {
            count: source.primitive_count(),
            limit: MAX_PRIMITIVES,
        });
    }
    Ok(capacity)
}

/// [`build_scene`], reporting its phases and counts to `progress` as it goes.
pub fn build_scene_observed(
    source: &Source,
    target: &BuildTarget<'_>,
    opts: &BuildOptions,
    sink: &mut dyn TreeletSink,
    progress: &ImportProgress,
) -> Result<SceneDescription, BuildError> {
    let BuildTarget {
        name,
        source_label,
        scratch,
    } = *target;
    let started = Instant::now();
    let capacity = check_build_input(source, opts)?;
    progress.enter(Phase::Placing, 0);
    let placed = place(source, opts, scratch)?;
    let frame = placed.frame;
    let depth = frame.depth;
    tracing::info!(
        depth,
        resolution = placed.resolution,
        edge = frame.edge,
        "building {} ({})",
        name,
        source.describe()
    );
    let phase = |what: &str, since: Instant| {
        tracing::info!(seconds = since.elapsed().as_secs_f64(), "{what} done");
        Instant::now()
    };
    let t = phase("placing (bounds, resolution)", started);
    let (layout, fill, iso_used) = fill_source(source, &placed, capacity, opts, scratch, progress)?;
    let t = phase("fill (with sorting and normals)", t);

    let records = RecordFile::open(fill.file, layout.bytes_per_voxel(), fill.offsets);
    let mut stats = SceneStats {
        voxels: fill.used_nodes - u64::from(fill.treelets - 1),
        leaf_voxels: fill.leaf_voxels,
        spilled_bytes: fill.spilled_bytes,
        peak_list_bytes: fill.peak_list_bytes,
        ..SceneStats::default()
    };
    let filled = store::FilledScene {
        records: &records,
        layout: &layout,
        level_starts: &fill.level_starts,
    };
    let (node_dictionary, channel_dictionaries) =
        store::store(&filled, opts, &mut stats, sink, progress)?;
    phase("store (attributes, dictionary, compression)", t);
    if let Some(cleanup) = fill.cleanup {
        cleanup
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
    }
    // The records are in the pool now; their pages go before the pool's final flush.
    drop(records);
    let _ = std::fs::remove_file(scratch.join(RECORDS_FILE));
    remove_column(scratch, OFFSETS_COLUMN);
    stats.build_seconds = started.elapsed().as_secs_f64();
    let dictionary = node_dictionary.is_some();
    Ok(SceneDescription {
        name: name.to_owned(),
        origin: frame.origin,
        edge: frame.edge,
        treelet_nodes: capacity,
        max_depth: depth,
        layout,
        treelet_count: fill.treelets,
        root_treelet: TreeletId::ROOT,
        source_kind: placed.kind,
        source: format!("{source_label} ({})", source.describe()),
        primitives: source.primitive_count(),
        build: BuildParameters {
            requested_depth: match opts.depth {
                DepthChoice::Fixed(d) => Some(d),
                DepthChoice::Auto => None,
            },
            data_resolution: placed.resolution,
            treelet_bytes: opts.treelet_bytes,
            iso: iso_used,
            zstd_level: opts.zstd_level,
            dictionary,
        },
        stats,
        node_dictionary,
        channel_dictionaries,
    })
}

/// Where the octree goes: the source's bounds, its resolution and the frame at the depth that
/// resolution asks for (or the fixed one).
struct Placement {
    min: [f64; 3],
    max: [f64; 3],
    /// The data's own resolution (mean point spacing, edge length or voxel spacing).
    resolution: f64,
    kind: SourceKind,
    frame: Frame,
}

fn place(source: &Source, opts: &BuildOptions, scratch: &Path) -> Result<Placement, BuildError> {
    let (min, max) = bounds(source)?;
    let probe = Frame::around(min, max, 0);
    let (resolution, kind) = match source {
        Source::Mesh(m) => (triangles::mean_edge_length(m), SourceKind::Mesh),
        Source::Points(p) => (
            points::mean_point_spacing(&p.positions, min, max, opts.memory_budget, scratch)?,
            SourceKind::Points,
        ),
        Source::Volume(v) => (
            v.spacing.iter().cloned().fold(f64::INFINITY, f64::min),
            SourceKind::Volume,
        ),
    };
    let depth = match opts.depth {
        DepthChoice::Fixed(d) => d,
        DepthChoice::Auto => depth_for_resolution(probe.edge, resolution),
    };
    Ok(Placement {
        min,
        max,
        resolution,
        kind,
        frame: Frame::new(probe.origin, probe.edge, depth),
    })
}

/// Pass 1 with the builder and attribute generator of the source's kind; returns the attribute
/// layout, the filled treelets and the iso threshold used (volumes).
fn fill_source(
    source: &Source,
    placed: &Placement,
    capacity: u32,
    opts: &BuildOptions,
    scratch: &Path,
    progress: &ImportProgress,
) -> Result<(AttributeLayout, Filled, Option<f32>), BuildError> {
    let frame = placed.frame;
    let fill_all = |b: &dyn TreeletBuilder, a: &dyn AttributeGenerator| {
        progress.enter(Phase::Filling, 0);
        fill_all(b, a, capacity, frame.depth, opts, scratch, progress)
    };
    match source {
        Source::Mesh(m) => {
            let b = triangles::TriangleBuilder { mesh: m, frame };
            let a = triangles::MeshAttributes::new(m, frame);
            let fill = fill_all(&b, &a)?;
            Ok((a.layout.clone(), fill, None))
        }
        Source::Points(p) if frame.depth <= sorted_points::MAX_KEY_DEPTH => {
            let t = Instant::now();
            let (records, sorted) =
                sorted_points::sort_points(p, &frame, opts.memory_budget, scratch)?;
            tracing::info!(
                seconds = t.elapsed().as_secs_f64(),
                "points sorted by leaf cell"
            );
            let t = Instant::now();
            let normals = match &p.normals {
                Some(file) => {
                    let mut w = ColumnWriter::create(scratch, sorted_points::NORMALS_COLUMN)?;
                    for r in records.iter() {
                        w.push(file[r.id as usize])?;
                    }
                    w.finish()?
                }
                None => {
                    let centre = [0, 1, 2].map(|a| (placed.min[a] + placed.max[a]) * 0.5);
                    sorted_points::cell_normals(
                        &records,
                        &p.positions,
                        frame.depth,
                        centre,
                        scratch,
                    )?
                }
            };
            tracing::info!(seconds = t.elapsed().as_secs_f64(), "normals");
            let b = sorted_points::SortedPointBuilder {
                records: &records,
                depth: frame.depth,
            };
            let a =
                sorted_points::SortedPointAttributes::new(&records, &normals, p.colors.is_some());
            let mut fill = fill_all(&b, &a)?;
            // The sort is this path's bounded working memory (it writes no id list).
            fill.spilled_bytes += sorted.spilled_bytes;
            fill.peak_list_bytes = fill.peak_list_bytes.max(sorted.peak_bytes);
            let layout = a.layout.clone();
            // Dead once the treelets are filled: 5 GB at 10⁸ points, which the store pass
            // would otherwise find in the page cache, partly still to be written back. Unmapped
            // and deleted on a thread of its own while the store pass starts: tearing down
            // 2.8 GB of mapping and page cache took a core for about a second at 10⁸.
            drop(a);
            let scratch = scratch.to_owned();
            fill.cleanup = Some(std::thread::spawn(move || {
                drop((normals, records));
                remove_column(&scratch, sorted_points::SORTED_COLUMN);
                remove_column(&scratch, sorted_points::NORMALS_COLUMN);
            }));
            Ok((layout, fill, None))
        }
        Source::Points(p) => {
            let estimated;
            let normals = match &p.normals {
                Some(n) => n,
                None => {
                    estimated = points::estimate_normals(
                        &p.positions,
                        placed.min,
                        placed.max,
                        opts.memory_budget,
                        scratch,
                    )?;
                    &estimated
                }
            };
            let b = points::PointBuilder { points: p, frame };
            let a = points::PointAttributes::new(p, normals);
            let fill = fill_all(&b, &a)?;
            Ok((a.layout.clone(), fill, None))
        }
        Source::Volume(v) => {
            let iso = match opts.iso {
                Some(i) if i.is_finite() => i,
                Some(i) => {
                    return Err(BuildError::Parameter(format!(
                        "iso threshold {i} is not finite"
                    )));
                }
                None => volume::otsu_threshold(v),
            };
            let cells = volume::crossing_cells(v, iso, scratch)?;
            if cells.is_empty() {
                return Err(BuildError::Empty(format!(
                    "iso threshold {iso} crosses no cell of the volume (values {}..{})",
                    v.value_range[0], v.value_range[1]
                )));
            }
            tracing::info!(iso, crossing_cells = cells.len(), "iso surface");
            let field = volume::Field { vol: v };
            let b = volume::VolumeBuilder {
                field,
                cells: &cells,
                frame,
            };
            let a = volume::VolumeAttributes::new(field, frame);
            let fill = fill_all(&b, &a)?;
            Ok((a.layout.clone(), fill, Some(iso)))
        }
    }
}

/// Bounding box of the source's geometry; rejects non-finite coordinates.
fn bounds(source: &Source) -> Result<([f64; 3], [f64; 3]), BuildError> {
    let mut min = [f64::INFINITY; 3];
    let mut max = [f64::NEG_INFINITY; 3];
    let mut add = |p: [f64; 3], what: &'static str, index: usize| {
        if !p.iter().all(|v| v.is_finite()) {
            return Err(BuildError::NonFinite {
                what,
                index: index as u64,
            });
        }
        for a in 0..3 {
            min[a] = min[a].min(p[a]);
            max[a] = max[a].max(p[a]);
        }
        Ok(())
    };
    match source {
        Source::Mesh(m) => {
            // Only vertices that triangles use define the scene.
            for t in m.triangles.iter() {
                for &i in t {
                    add(m.positions[i as usize], "vertex", i as usize)?;
                }
            }
        }
        Source::Points(p) => return point_bounds(&p.positions),
        Source::Volume(v) => {
            let far =
                [0, 1, 2].map(|a| v.origin[a] + f64::from(v.dims[a].max(1) - 1) * v.spacing[a]);
            add(v.origin, "volume origin", 0)?;
            add(far, "volume extent", 0)?;
            if v.dims.iter().any(|&d| d < 2) || v.spacing.iter().any(|&s| !(s > 0.0)) {
                return Err(BuildError::Empty(format!(
                    "volume {:?} with spacing {:?} has no cells",
                    v.dims, v.spacing
                )));
            }
        }
    }
    Ok((min, max))
}

/// [`bounds`] of a point cloud, both cores over chunks of it (a serial pass over every point
/// between reading and sorting); a non-finite point is named by its lowest index.
fn point_bounds(positions: &[[f64; 3]]) -> Result<([f64; 3], [f64; 3]), BuildError> {
    const CHUNK: usize = 1 << 16;
    type Partial = Result<([f64; 3], [f64; 3]), usize>;
    let empty: Partial = Ok(([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]));
    let merged = positions
        .par_chunks(CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let (mut min, mut max) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
            for (i, p) in chunk.iter().enumerate() {
                if !p.iter().all(|v| v.is_finite()) {
                    return Err(c * CHUNK + i);
                }
                for a in 0..3 {
                    min[a] = min[a].min(p[a]);
                    max[a] = max[a].max(p[a]);
                }
            }
            Ok((min, max))
        })
        .reduce(
            || empty,
            |a, b| match (a, b) {
                (Err(i), Err(j)) => Err(i.min(j)),
                (Err(i), Ok(_)) | (Ok(_), Err(i)) => Err(i),
                (Ok((amin, amax)), Ok((bmin, bmax))) => Ok((
                    [0, 1, 2].map(|k| amin[k].min(bmin[k])),
                    [0, 1, 2].map(|k| amax[k].max(bmax[k])),
                )),
            },
        );
    merged.map_err(|index| BuildError::NonFinite {
        what: "point",
        index: index as u64,
    })
}

/// Output of the fill pass.
struct Filled {
    file: File,
    /// Where each treelet's record starts in `file`, then the end (see [`RecordFile`]).
    offsets: Column<u64>,
    treelets: u32,
    /// First id of each treelet level (root = level 0), then the count: ids grow level by
    /// level because jobs run in FIFO order.
    level_starts: Vec<u32>,
    used_nodes: u64,
    leaf_voxels: u64,
    spilled_bytes: u64,
    peak_list_bytes: u64,
    /// Removes the fill's inputs from the scratch directory; joined before the build returns.
    cleanup: Option<std::thread::JoinHandle<()>>,
}

/// Name of the records file in the scratch directory.
const RECORDS_FILE: &str = "treelets.records";
/// Scratch column of where each record starts.
const OFFSETS_COLUMN: &str = "treelet-offsets";

fn spinner(enabled: bool, what: &str) -> ProgressBar {
    if !enabled {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new_spinner();
    pb.set_style(
        ProgressStyle::with_template("{spinner} {prefix} {msg} [{elapsed_precise}]")
            .unwrap_or_else(|_| ProgressStyle::default_spinner()),
    );
    pb.set_prefix(what.to_owned());
    pb
}

fn bar(enabled: bool, what: &str, len: u64) -> ProgressBar {
    if !enabled {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template(
            "{prefix:>10} [{bar:40}] {pos}/{len} treelets [{elapsed_precise}, eta {eta}]",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb.set_prefix(what.to_owned());
    pb
}

/// Independent jobs taken from the queue at once, per rayon thread. Each batch ends in a wait
/// for its slowest treelet: with 8 per thread the 10⁸-point city's fill (1.27 M treelets, 80,000
/// batches) left a core idle a quarter of the time; with 64, fill 23–24 → 19–20 s (in turns, the
/// same scene byte for byte).
const JOBS_PER_THREAD: usize = 64;

/// What pass 1 has written so far: the records, their offsets, and the counts the scene's
/// statistics need. Filled treelets are handed to it in id order.
struct RecordWriter {
    sink: RecordSink,
    offsets: ColumnWriter<u64>,
    bpv: usize,
    next_id: u64,
    /// Level of every treelet (1 byte each), to find where each level starts.
    level_of: Vec<u8>,
    written: u32,
    used_nodes: u64,
    leaf_voxels: u64,
}

impl RecordWriter {
    /// Names the filled treelets' children (ids in FIFO order), queues them and appends the
    /// records.
    fn write(
        &mut self,
        filled: Vec<std::io::Result<FilledTreelet>>,
        queue: &mut PendingQueue,
    ) -> Result<(), BuildError> {
        for f in filled {
            let mut f = f?;
            let id = f.treelet.header.id;
            debug_assert_eq!(id.0, self.written);
            for leaf in f.pending.drain(..) {
                let child = treelet_id(self.next_id)?;
                self.next_id += 1;
                self.level_of
                    .push(self.level_of[id.0 as usize].saturating_add(1));
                f.treelet.nodes[usize::from(leaf.local_index)].first_child = child.0;
                queue.push(TreeletJob {
                    id: child,
                    parent_id: id,
                    parent_leaf_index: leaf.local_index,
                    parent_leaf_parent_index: leaf.parent_local_index,
                    child_index_in_parent: leaf.child_index,
                    root: leaf.cell,
                    prims: leaf.prims,
                })?;
            }
            self.used_nodes += u64::from(f.treelet.header.used_nodes);
            self.leaf_voxels += f.leaf_voxels;
            let nodes = codec::encode_treelet(&f.treelet);
            let used = usize::from(f.treelet.header.used_nodes);
            let attributes = &f.attributes[..used * self.bpv];
            self.sink.push(&nodes)?;
            self.sink.push(attributes)?;
            self.offsets.push(self.sink.position())?;
            self.written += 1;
        }
        Ok(())
    }
}

/// Pass 1: fill every treelet, FIFO, in parallel batches. While one batch's records are
/// written and its children queued (serial), the next batch — jobs queued before — is filled.
fn fill_all(
    builder: &dyn TreeletBuilder,
    attributes: &dyn AttributeGenerator,
    capacity: u32,
    depth: u8,
    opts: &BuildOptions,
    scratch: &Path,
    progress: &ImportProgress,
) -> Result<Filled, BuildError> {
    let sink = RecordSink::create(&scratch.join(RECORDS_FILE))?;
    tracing::debug!(direct = sink.direct(), "scratch records");
    let mut offsets = ColumnWriter::<u64>::create(scratch, OFFSETS_COLUMN)?;
    offsets.push(0)?;
    let count = builder.primitive_count();
    let count = u32::try_from(count).map_err(|_| BuildError::TooManyPrimitives {
        count,
        limit: MAX_PRIMITIVES,
    })?;
    let lists = Lists {
        budget: Budget::new(opts.memory_budget),
        spill: SpillFile::create(scratch)?,
    };
    let mut queue = PendingQueue::new(&lists);
    queue.push(TreeletJob {
        id: TreeletId::ROOT,
        parent_id: TreeletId::NONE,
        parent_leaf_index: 0,
        parent_leaf_parent_index: 0,
        child_index_in_parent: 0,
        root: Cell::ROOT,
        prims: IdList::Range(0..count),
    })?;
    let mut out = RecordWriter {
        sink,
        offsets,
        bpv: attributes.bytes_per_voxel(),
        next_id: 1,
        level_of: vec![0],
        written: 0,
        used_nodes: 0,
        leaf_voxels: 0,
    };
    let pb = spinner(opts.progress, "fill");
    let batch_target = rayon::current_num_threads() * JOBS_PER_THREAD;
    // A batch of independent jobs, bounded by count and by primitive-list bytes.
    let take_batch = |queue: &mut PendingQueue| -> Result<Vec<TreeletJob>, BuildError> {
        let mut batch = Vec::new();
        let mut batch_bytes = 0usize;
        while batch.len() < batch_target && batch_bytes < opts.memory_budget.max(1 << 20) {
            let Some(job) = queue.pop()? else { break };
            batch_bytes += job.prims.memory_bytes();
            batch.push(job);
        }
        Ok(batch)
    };
    let fill = |batch: Vec<TreeletJob>| -> Vec<std::io::Result<FilledTreelet>> {
        batch
            .into_par_iter()
            .map(|job| fill_treelet(builder, attributes, job, capacity, depth, &lists))
            .collect()
    };
    let mut filled = fill(take_batch(&mut queue)?);
    loop {
        // Jobs queued before this batch's children: independent of the batch being written.
        let next = take_batch(&mut queue)?;
        if filled.is_empty() && next.is_empty() {
            break;
        }
        let (written, next_filled) = rayon::join(|| out.write(filled, &mut queue), || fill(next));
        written?;
        filled = next_filled;
        progress.set_done(u64::from(out.written));
        pb.set_message(format!(
            "{} treelets, {} leaf voxels, {} queued",
            out.written,
            out.leaf_voxels,
            queue.len()
        ));
        pb.tick();
    }
    pb.finish_and_clear();
    let spilled_bytes = lists.spill.bytes_written();
    if spilled_bytes > 0 {
        tracing::info!(
            spilled_bytes,
            budget = opts.memory_budget,
            "primitive lists spilled to disk"
        );
    }
    let RecordWriter {
        sink,
        offsets,
        written,
        level_of,
        used_nodes,
        leaf_voxels,
        ..
    } = out;
    let mut level_starts = vec![0u32];
    for (i, pair) in level_of.windows(2).enumerate() {
        debug_assert!(pair[0] <= pair[1], "FIFO order keeps levels contiguous");
        if pair[1] != pair[0] {
            level_starts.push(i as u32 + 1);
        }
    }
    level_starts.push(written);
    Ok(Filled {
        offsets: offsets.finish()?,
        file: sink.finish()?,
        treelets: written,
        level_starts,
        used_nodes,
        leaf_voxels,
        spilled_bytes,
        peak_list_bytes: lists.budget.peak() as u64,
        cleanup: None,
    })
}

/// The id of the `next`-th treelet, or the format limit's error (ids are 32-bit).
fn treelet_id(next: u64) -> Result<TreeletId, BuildError> {
    match u32::try_from(next) {
        Ok(id) if id <= arbor_proto::limits::MAX_TREELETS => Ok(TreeletId(id)),
        _ => Err(BuildError::TooManyTreelets),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::PointSource;

    /// A builder that only counts: no primitive exists, so nothing that large is allocated.
    struct Counting(u64);

    impl TreeletBuilder for Counting {
        fn primitive_count(&self) -> u64 {
            self.0
        }
        fn child_mask(&self, _prim: u32, _cell: Cell) -> u8 {
            1
        }
    }

    struct NoAttributes;

    impl AttributeGenerator for NoAttributes {
        fn bytes_per_voxel(&self) -> usize {
            0
        }
        fn leaf(&self, _cell: Cell, _prims: &[u32], _out: &mut [u8]) {}
    }

    /// The sorted path (ranges, no id lists) fills exactly the treelets of the general path
    /// (id lists partitioned point by point) on a real scan: same ids, same node records.
    #[test]
    fn sorted_points_fill_the_same_treelets_as_id_lists() {
        let dir = tempfile::tempdir().unwrap();
        let lion = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data/points/lion_takanawa.copc.laz");
        let Source::Points(p) =
            crate::import::import_file(&lion, &Default::default(), dir.path()).unwrap()
        else {
            panic!("points expected")
        };
        let opts = BuildOptions::default();
        let (min, max) = bounds(&Source::Points(PointSource {
            positions: Column::from_slice(dir.path(), "copy", &p.positions).unwrap(),
            colors: None,
            normals: None,
        }))
        .unwrap();
        let frame = Frame::around(min, max, 10);
        let progress = ImportProgress::default();
        let general = fill_all(
            &points::PointBuilder { points: &p, frame },
            &NoAttributes,
            512,
            10,
            &opts,
            dir.path(),
            &progress,
        )
        .unwrap();
        let (records, _) = sorted_points::sort_points(&p, &frame, 1 << 20, dir.path()).unwrap();
        let sorted = fill_all(
            &sorted_points::SortedPointBuilder {
                records: &records,
                depth: 10,
            },
            &NoAttributes,
            512,
            10,
            &opts,
            dir.path(),
            &progress,
        );
        let sorted = sorted.unwrap();
        assert!(general.treelets > 100, "{}", general.treelets);
        assert_eq!(general.treelets, sorted.treelets);
        assert_eq!(general.used_nodes, sorted.used_nodes);
        assert_eq!(general.leaf_voxels, sorted.leaf_voxels);
        let general_treelets = general.treelets;
        let records = |f: Filled| RecordFile::open(f.file, 0, f.offsets);
        let (a, b) = (records(general), records(sorted));
        let (mut buf_a, mut buf_b) = (Default::default(), Default::default());
        let (a, b) = (
            a.read(0..a.count(), &mut buf_a).unwrap(),
            b.read(0..b.count(), &mut buf_b).unwrap(),
        );
        for id in 0..general_treelets {
            let ra = a.nodes(id);
            let rb = b.nodes(id);
            assert!(ra == rb, "treelet {id} differs");
            // The store compresses the encoding as it is: it must be a whole, valid treelet.
            let t = codec::decode_treelet(ra, 10).unwrap();
            assert_eq!(
                (ra.len() - codec::HEADER_BYTES) / 8,
                t.used().len(),
                "treelet {id}"
            );
        }
    }

    #[test]
    fn point_bounds_in_parallel_equal_a_serial_pass_and_name_the_first_bad_point() {
        let mut rng = arbor_proto::rng::SplitMix64::new(5);
        let mut pts: Vec<[f64; 3]> = (0..300_000)
            .map(|_| [0, 1, 2].map(|a| (rng.next_f64() - 0.5) * 1e6 * (a + 1) as f64 + 6e5))
            .collect();
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for p in &pts {
            for a in 0..3 {
                min[a] = min[a].min(p[a]);
                max[a] = max[a].max(p[a]);
            }
        }
        assert_eq!(point_bounds(&pts).unwrap(), (min, max));
        assert_eq!(point_bounds(&[]).unwrap().0, [f64::INFINITY; 3]);
        // Two bad points in different chunks: the first in file order is named.
        pts[250_001][2] = f64::NAN;
        pts[70_000][0] = f64::INFINITY;
        match point_bounds(&pts) {
            Err(BuildError::NonFinite { what, index }) => {
                assert_eq!((what, index), ("point", 70_000));
            }
            other => panic!("{other:?}"),
        }
    }

    /// A sink that counts what it gets and fails on the `fail_at`-th message of one stream.
    struct FailingSink {
        fail_nodes_at: Option<usize>,
        fail_channels_at: Option<usize>,
        nodes: usize,
        channels: usize,
    }

    impl TreeletSink for FailingSink {
        fn start(&mut self, _layout: &AttributeLayout) -> Result<(), BuildError> {
            Ok(())
        }
        fn put_nodes(&mut self, _blocks: Vec<(TreeletId, Vec<u8>)>) -> Result<(), BuildError> {
            self.nodes += 1;
            if self.fail_nodes_at == Some(self.nodes) {
                return Err(BuildError::Sink("disk full (nodes)".into()));
            }
            Ok(())
        }
        fn put_channels(
            &mut self,
            _blocks: Vec<(TreeletId, Vec<Vec<u8>>)>,
        ) -> Result<(), BuildError> {
            self.channels += 1;
            if self.fail_channels_at == Some(self.channels) {
                return Err(BuildError::Sink("disk full (channels)".into()));
            }
            Ok(())
        }
    }

    #[test]
    fn a_failing_sink_ends_the_store_pass_with_its_error() {
        let dir = tempfile::tempdir().unwrap();
        let mut rng = arbor_proto::rng::SplitMix64::new(21);
        let pts: Vec<[f64; 3]> = (0..200_000)
            .map(|_| {
                [
                    rng.next_f64() * 100.0,
                    rng.next_f64() * 100.0,
                    rng.next_f64(),
                ]
            })
            .collect();
        let source = Source::Points(PointSource {
            positions: Column::from_slice(dir.path(), "p", &pts).unwrap(),
            colors: None,
            normals: None,
        });
        let opts = BuildOptions {
            treelet_bytes: 1024,
            ..BuildOptions::default()
        };
        let mut whole = FailingSink {
            fail_nodes_at: None,
            fail_channels_at: None,
            nodes: 0,
            channels: 0,
        };
        let d = build_scene(&source, "t", "t", &opts, dir.path(), &mut whole).unwrap();
        assert!(d.treelet_count > 2 * 512, "{}", d.treelet_count);
        assert!(whole.nodes >= 3 && whole.channels >= 3, "{}", whole.nodes);
        for (nodes, channels, want) in [
            (Some(2), None, "disk full (nodes)"),
            (None, Some(2), "disk full (channels)"),
        ] {
            let mut sink = FailingSink {
                fail_nodes_at: nodes,
                fail_channels_at: channels,
                nodes: 0,
                channels: 0,
            };
            match build_scene(&source, "t", "t", &opts, dir.path(), &mut sink) {
                Err(BuildError::Sink(m)) => assert_eq!(m, want),
                other => panic!("{other:?}"),
            }
            // Nothing of the failed stream was handed over after the failure.
            let failed = if nodes.is_some() {
                sink.nodes
            } else {
                sink.channels
            };
            assert_eq!(failed, 2);
        }
    }

    #[test]
    fn primitive_counts_past_32_bits_are_refused_not_wrapped() {
        let dir = tempfile::tempdir().unwrap();
        let opts = BuildOptions::default();
        for count in [MAX_PRIMITIVES + 1, 1 << 32, u64::MAX] {
            let progress = ImportProgress::default();
            let e = fill_all(
                &Counting(count),
                &NoAttributes,
                512,
                10,
                &opts,
                dir.path(),
                &progress,
            )
            .err()
            .expect("refused");
            assert!(
                matches!(e, BuildError::TooManyPrimitives { count: c, limit } if c == count && limit == MAX_PRIMITIVES),
                "{e}"
            );
            assert!(e.to_string().contains("4294967295 per scene"), "{e}");
        }
    }

    #[test]
    fn treelet_ids_stop_at_the_format_limit_naming_the_knob() {
        let last = u64::from(arbor_proto::limits::MAX_TREELETS);
        assert_eq!(
            treelet_id(last).unwrap(),
            TreeletId(arbor_proto::limits::MAX_TREELETS)
        );
        for next in [last + 1, 1 << 32, u64::MAX] {
            let e = treelet_id(next).unwrap_err().to_string();
            assert!(e.contains("treelet ids are 32-bit"), "{e}");
            assert!(
                e.contains("--treelet-bytes") && e.contains("--depth"),
                "{e}"
            );
        }
    }
}
