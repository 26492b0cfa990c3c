//! The generalized builder (docs/design.md §3): a build manager drives a [`TreeletBuilder`] chosen by
//! input kind and an [`AttributeGenerator`] chosen by the channels the source has.
//!
//! Three passes, each bounded in memory:
//! 1. **fill** — treelets are filled breadth-first from a FIFO of jobs (top-down, so every child
//!    id is higher than its parent's); independent jobs of one batch run in parallel; finished
//!    treelets are appended to a scratch file of fixed-size records;
//! 2. **attributes** — records are read back in reverse id order and inner attributes averaged
//!    bottom-up, a child treelet's root attribute feeding its parent's refinable leaf;
//! 3. **pack** — optional per-stream zstd dictionaries are trained on evenly spread records, then
//!    nodes and each attribute channel are compressed in parallel and handed to a [`TreeletSink`]
//!    (the pool) in id order.

pub mod geometry;
pub mod idlist;
pub mod pending;
pub mod points;
pub mod sorted_points;
pub mod treelet_builder;
pub mod triangles;
pub mod volume;

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::time::Instant;

use arbor_proto::codec::{self, BlockCompressor, HEADER_BYTES};
use arbor_proto::treelet::{NodePlace, nodes_for_bytes};
use arbor_proto::{
    AttributeLayout, BuildParameters, Cell, Node, ProtoError, SceneDescription, SceneStats,
    SourceKind, Treelet, TreeletId,
};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;

use crate::progress::{ImportProgress, Phase};
use crate::source::scratch_file;
use crate::source::{Column, ColumnError, ColumnWriter, Source};
use geometry::{Frame, depth_for_resolution};
use idlist::{Budget, IdList, Lists, SpillFile};
use pending::PendingQueue;
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

/// Receives the compressed blocks of each treelet, in ascending id order.
pub trait TreeletSink {
    /// Called once with the scene's attribute layout before the first `put`.
    fn start(&mut self, layout: &AttributeLayout) -> Result<(), BuildError>;
    /// `channels` are in layout order.
    fn put(
        &mut self,
        id: TreeletId,
        nodes: Vec<u8>,
        channels: Vec<Vec<u8>>,
    ) -> Result<(), BuildError>;
    /// Several treelets in ascending id order; a sink may store them concurrently (the pool
    /// writes its trees in parallel).
    fn put_many(&mut self, treelets: Vec<PackedTreelet>) -> Result<(), BuildError> {
        for t in treelets {
            self.put(t.id, t.nodes, t.channels)?;
        }
        Ok(())
    }
}

/// One treelet's compressed blocks, as a [`TreeletSink`] receives them.
#[derive(Clone, Debug)]
pub struct PackedTreelet {
    pub id: TreeletId,
    pub nodes: Vec<u8>,
    /// In layout order.
    pub channels: Vec<Vec<u8>>,
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

    let records = RecordFile {
        file: fill.file,
        bpv: layout.bytes_per_voxel(),
        offsets: fill.offsets,
    };
    progress.enter(Phase::Attributes, u64::from(fill.treelets));
    // The node streams are final after the fill, so the dictionary (one thread in zstd) is
    // trained beside the attribute pass, which leaves part of a core idle between levels.
    let (averaged, trained) = std::thread::scope(|scope| {
        let training = scope.spawn(|| {
            let t = Instant::now();
            let trained = if opts.dictionary {
                train_dictionaries(&records, &layout, fill.treelets)
            } else {
                Ok((None, vec![None; layout.channels().len()]))
            };
            tracing::info!(seconds = t.elapsed().as_secs_f64(), "dictionary training");
            trained
        });
        let averaged = average_bottom_up(
            &records,
            &layout,
            &fill.level_starts,
            depth,
            opts.progress,
            progress,
        );
        let trained = training
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        (averaged, trained)
    });
    averaged?;
    let (node_dictionary, channel_dictionaries) = trained?;
    let t = phase("attributes and dictionary training", t);
    let mut stats = SceneStats {
        voxels: fill.used_nodes - u64::from(fill.treelets - 1),
        leaf_voxels: fill.leaf_voxels,
        spilled_bytes: fill.spilled_bytes,
        peak_list_bytes: fill.peak_list_bytes,
        ..SceneStats::default()
    };
    progress.enter(Phase::Packing, u64::from(fill.treelets));
    pack(
        &records,
        &layout,
        fill.treelets,
        opts,
        node_dictionary.as_deref(),
        &channel_dictionaries,
        &mut stats,
        sink,
        progress,
    )?;
    phase("pack", t);
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
                    let mut w = ColumnWriter::create(scratch, "sorted-normals")?;
                    for r in records.iter() {
                        w.push(file[r.id as usize])?;
                    }
                    w.finish()?
                }
                None => {
                    let centre = [0, 1, 2].map(|a| (placed.min[a] + placed.max[a]) * 0.5);
                    sorted_points::cell_normals(&records, frame.depth, centre, scratch)?
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
            Ok((a.layout.clone(), fill, None))
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
        Source::Points(p) => {
            for (i, &q) in p.positions.iter().enumerate() {
                add(q, "point", i)?;
            }
        }
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
}

/// Scratch records, one per treelet in id order, packed: the raw treelet encoding (header and
/// used node records), then `used × bpv` attribute bytes. Where each starts is in a memory-mapped
/// column, so nothing here grows with the treelet count (treelets are 35–45 % full on average:
/// fixed-size records wrote 2–3× the bytes).
struct RecordFile {
    file: File,
    bpv: usize,
    /// Byte offset of every record, then the end.
    offsets: Column<u64>,
}

impl RecordFile {
    /// Byte range of a record and where its attributes start.
    fn place(&self, id: u32) -> (u64, u64, u64) {
        let (start, end) = (self.offsets[id as usize], self.offsets[id as usize + 1]);
        let used = (end - start - HEADER_BYTES as u64) / (8 + self.bpv as u64);
        (start, end, start + HEADER_BYTES as u64 + used * 8)
    }
    /// A record as stored: the raw treelet encoding (final once filled: the attribute pass
    /// rewrites attributes only), the length of that encoding and the used node count.
    fn read_raw(&self, id: u32) -> Result<(Vec<u8>, usize, usize), BuildError> {
        let (start, end, attributes) = self.place(id);
        let mut buf = vec![0u8; (end - start) as usize];
        self.file.read_exact_at(&mut buf, start)?;
        let raw_len = (attributes - start) as usize;
        let used = (raw_len - HEADER_BYTES) / 8;
        Ok((buf, raw_len, used))
    }
    fn read_with_places(
        &self,
        id: u32,
        max_depth: u8,
    ) -> Result<(Treelet, Vec<NodePlace>, Vec<u8>), BuildError> {
        let (start, end, attributes) = self.place(id);
        let mut buf = vec![0u8; (end - start) as usize];
        self.file.read_exact_at(&mut buf, start)?;
        let raw_len = (attributes - start) as usize;
        let (t, places) = codec::decode_treelet_with_places(&buf[..raw_len], max_depth)?;
        let attrs = buf.split_off(raw_len);
        Ok((t, places, attrs))
    }
    fn write_attributes(&self, id: u32, attrs: &[u8]) -> Result<(), BuildError> {
        let (_, end, at) = self.place(id);
        debug_assert_eq!(attrs.len() as u64, end - at);
        self.file.write_all_at(attrs, at)?;
        Ok(())
    }
}

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

/// Independent jobs taken from the queue at once, per rayon thread.
const JOBS_PER_THREAD: usize = 8;

/// What pass 1 has written so far: the records, their offsets, and the counts the scene's
/// statistics need. Filled treelets are handed to it in id order.
struct RecordWriter<'a> {
    file: &'a File,
    offsets: ColumnWriter<u64>,
    end: u64,
    bpv: usize,
    next_id: u64,
    /// Level of every treelet (1 byte each), to find where each level starts.
    level_of: Vec<u8>,
    written: u32,
    used_nodes: u64,
    leaf_voxels: u64,
    buf: Vec<u8>,
}

impl RecordWriter<'_> {
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
            self.buf.clear();
            self.buf
                .extend_from_slice(&codec::encode_treelet(&f.treelet));
            let used = usize::from(f.treelet.header.used_nodes);
            self.buf.extend_from_slice(&f.attributes[..used * self.bpv]);
            self.file.write_all_at(&self.buf, self.end)?;
            self.end += self.buf.len() as u64;
            self.offsets.push(self.end)?;
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
    let file = scratch_file(&scratch.join("treelets.records"))?;
    let mut offsets = ColumnWriter::<u64>::create(scratch, "treelet-offsets")?;
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
        file: &file,
        offsets,
        end: 0,
        bpv: attributes.bytes_per_voxel(),
        next_id: 1,
        level_of: vec![0],
        written: 0,
        used_nodes: 0,
        leaf_voxels: 0,
        buf: Vec::new(),
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
        file,
        treelets: written,
        level_starts,
        used_nodes,
        leaf_voxels,
        spilled_bytes,
        peak_list_bytes: lists.budget.peak() as u64,
    })
}

/// The id of the `next`-th treelet, or the format limit's error (ids are 32-bit).
fn treelet_id(next: u64) -> Result<TreeletId, BuildError> {
    match u32::try_from(next) {
        Ok(id) if id <= arbor_proto::limits::MAX_TREELETS => Ok(TreeletId(id)),
        _ => Err(BuildError::TooManyTreelets),
    }
}

/// Pass 2: inner attributes as the mean of their children, treelets in reverse id order.
fn average_bottom_up(
    records: &RecordFile,
    layout: &AttributeLayout,
    level_starts: &[u32],
    depth: u8,
    bars: bool,
    progress: &ImportProgress,
) -> Result<(), BuildError> {
    let count = level_starts.last().copied().unwrap_or(0);
    // Root attributes of the treelets one level below, for their parents' refinable leaves.
    let mut below: HashMap<u32, Vec<u8>> = HashMap::new();
    let pb = bar(bars, "attributes", u64::from(count));
    let mut done = 0u64;
    for level in (0..level_starts.len().saturating_sub(1)).rev() {
        // Treelets of one level are independent: their children are all one level deeper.
        let ids = level_starts[level]..level_starts[level + 1];
        let roots: Vec<Result<Option<RootAttribute>, BuildError>> = ids
            .clone()
            .into_par_iter()
            .map(|id| average_treelet(records, layout, id, depth, &below))
            .collect();
        below = HashMap::with_capacity(roots.len());
        for r in roots {
            if let Some((id, root)) = r? {
                below.insert(id, root);
            }
        }
        done += u64::from(ids.end - ids.start);
        pb.set_position(done);
        progress.set_done(done);
    }
    pb.finish_and_clear();
    Ok(())
}

/// A treelet id and its root voxel's attribute bytes.
type RootAttribute = (u32, Vec<u8>);

/// Averages one treelet's inner attributes bottom-up (its refinable leaves take their child
/// treelet's root attribute from `below`), writes them back, and returns its own root attribute
/// for its parent (none for the root treelet).
fn average_treelet(
    records: &RecordFile,
    layout: &AttributeLayout,
    id: u32,
    depth: u8,
    below: &HashMap<u32, Vec<u8>>,
) -> Result<Option<RootAttribute>, BuildError> {
    let bpv = records.bpv;
    let (t, places, mut attrs) = records.read_with_places(id, depth)?;
    let mut out = Vec::new();
    for i in (0..t.used().len()).rev() {
        let n: Node = t.nodes[i];
        let k = i * bpv;
        if places[i].is_leaf {
            if n.first_child != Node::NONE {
                let root = below.get(&n.first_child).ok_or_else(|| {
                    BuildError::Sink(format!(
                        "treelet {id} leaf {i}: child treelet {} was never built",
                        n.first_child
                    ))
                })?;
                attrs[k..k + bpv].copy_from_slice(root);
            }
            continue;
        }
        let first = i + n.first_child as usize;
        let kids = n.child_count() as usize;
        let mut off = 0;
        for c in layout.channels() {
            let size = c.size();
            out.clear();
            out.resize(size, 0);
            let src = &attrs;
            c.mean(
                (first..first + kids).map(|j| &src[j * bpv + off..j * bpv + off + size]),
                &mut out,
            );
            attrs[k + off..k + off + size].copy_from_slice(&out);
            off += size;
        }
    }
    records.write_attributes(id, &attrs)?;
    Ok((!t.header.parent_id.is_none()).then(|| (id, attrs[..bpv].to_vec())))
}

/// Splits a record's attribute bytes into one block per channel (used records only).
fn channel_blocks(layout: &AttributeLayout, attrs: &[u8], bpv: usize, used: usize) -> Vec<Vec<u8>> {
    let mut at = 0;
    layout
        .channels()
        .iter()
        .map(|c| {
            let size = c.size();
            let mut block = Vec::with_capacity(used * size);
            for voxel in attrs.chunks_exact(bpv).take(used) {
                block.extend_from_slice(&voxel[at..at + size]);
            }
            at += size;
            block
        })
        .collect()
}

/// Dictionary size per stream.
const DICTIONARY_BYTES: usize = 16 * 1024;
/// At most this many records are sampled for training.
const DICTIONARY_SAMPLES: u32 = 4000;

type Dictionaries = (Option<Vec<u8>>, Vec<Option<Vec<u8>>>);

/// Trains a dictionary for the node stream on evenly spread records. Attribute channels get
/// none: measured on the six real scans (`cargo bench --bench build`) a channel dictionary saved
/// at most 5 % and sometimes grew the stream, while node dictionaries save 22–35 %.
/// Too few treelets to learn from gives no dictionary.
fn train_dictionaries(
    records: &RecordFile,
    layout: &AttributeLayout,
    count: u32,
) -> Result<Dictionaries, BuildError> {
    let channels = vec![None; layout.channels().len()];
    if count < 32 {
        return Ok((None, channels));
    }
    let step = (count / DICTIONARY_SAMPLES).max(1);
    let mut samples = Vec::new();
    for id in (0..count).step_by(step as usize) {
        let (mut raw, raw_len, _) = records.read_raw(id)?;
        raw.truncate(raw_len);
        samples.push(raw);
    }
    let dictionary = match zstd::dict::from_samples(&samples, DICTIONARY_BYTES) {
        Ok(d) => Some(d),
        Err(e) => {
            tracing::warn!("dictionary training failed, compressing without: {e}");
            None
        }
    };
    Ok((dictionary, channels))
}

/// One compressor per stream (nodes, then each channel), kept for the whole pass: building
/// one loads its dictionary into zstd's tables, which cost as much as compressing a few
/// treelets.
struct Compressors {
    nodes: BlockCompressor,
    channels: Vec<BlockCompressor>,
}

/// Compressor sets returned by the rayon jobs that used them, for the next jobs to take.
struct CompressorPool<'a> {
    level: i32,
    node_dict: Option<&'a [u8]>,
    channel_dicts: &'a [Option<Vec<u8>>],
    idle: std::sync::Mutex<Vec<Compressors>>,
}

impl CompressorPool<'_> {
    fn take(&self) -> Result<Compressors, ProtoError> {
        if let Some(c) = self.idle.lock().unwrap_or_else(|e| e.into_inner()).pop() {
            return Ok(c);
        }
        Ok(Compressors {
            nodes: BlockCompressor::new(self.level, self.node_dict)?,
            channels: self
                .channel_dicts
                .iter()
                .map(|d| BlockCompressor::new(self.level, d.as_deref()))
                .collect::<Result<_, _>>()?,
        })
    }

    fn give_back(&self, c: Compressors) {
        self.idle.lock().unwrap_or_else(|e| e.into_inner()).push(c);
    }
}

/// A set taken from the pool for one rayon split, given back when the split ends.
struct Lease<'p, 'a> {
    pool: &'p CompressorPool<'a>,
    set: Result<Compressors, ProtoError>,
}

impl Drop for Lease<'_, '_> {
    fn drop(&mut self) {
        let given_back = Err(ProtoError::Compression {
            what: "compressor",
            detail: "given back to the pool".into(),
        });
        if let Ok(c) = std::mem::replace(&mut self.set, given_back) {
            self.pool.give_back(c);
        }
    }
}

/// A treelet's compressed blocks and its raw bytes.
type Packed = (PackedTreelet, u64);

/// Compresses record `id`: its stored treelet encoding as it is, its attributes split per
/// channel.
fn pack_one(
    records: &RecordFile,
    layout: &AttributeLayout,
    comp: &mut Compressors,
    id: u32,
) -> Result<Packed, BuildError> {
    let (buf, raw_len, used) = records.read_raw(id)?;
    let (raw, attrs) = buf.split_at(raw_len);
    let blocks = channel_blocks(layout, attrs, records.bpv, used);
    let raw_bytes = (raw.len() + blocks.iter().map(Vec::len).sum::<usize>()) as u64;
    let nodes = comp.nodes.compress(raw)?;
    let chans = blocks
        .iter()
        .zip(comp.channels.iter_mut())
        .map(|(b, c)| c.compress(b))
        .collect::<Result<Vec<_>, _>>()?;
    let packed = PackedTreelet {
        id: TreeletId(id),
        nodes,
        channels: chans,
    };
    Ok((packed, raw_bytes))
}

/// Treelets compressed per step of the pack pass.
const PACK_CHUNK: u32 = 512;

/// Pass 3: compress nodes and channels and hand them to the sink in id order. A scoped thread
/// compresses chunk after chunk on the rayon pool while this thread hands the previous chunk to
/// the sink (sled's inserts were a serial step between chunks, leaving a core idle).
#[allow(clippy::too_many_arguments)]
fn pack(
    records: &RecordFile,
    layout: &AttributeLayout,
    count: u32,
    opts: &BuildOptions,
    node_dict: Option<&[u8]>,
    channel_dicts: &[Option<Vec<u8>>],
    stats: &mut SceneStats,
    sink: &mut dyn TreeletSink,
    progress: &ImportProgress,
) -> Result<(), BuildError> {
    stats.channel_bytes = vec![0; layout.channels().len()];
    sink.start(layout)?;
    let pb = bar(opts.progress, "pack", u64::from(count));
    let pool = CompressorPool {
        level: opts.zstd_level,
        node_dict,
        channel_dicts,
        idle: std::sync::Mutex::new(Vec::new()),
    };
    std::thread::scope(|scope| {
        // Two chunks ahead at most: bounded memory, and the sink never waits.
        let (tx, rx) = std::sync::mpsc::sync_channel::<Result<Vec<Packed>, BuildError>>(2);
        let pool = &pool;
        scope.spawn(move || {
            for start in (0..count).step_by(PACK_CHUNK as usize) {
                let end = (start + PACK_CHUNK).min(count);
                let packed: Result<Vec<Packed>, BuildError> = (start..end)
                    .into_par_iter()
                    .map_init(
                        || Lease {
                            pool,
                            set: pool.take(),
                        },
                        |lease, id| {
                            let comp = lease
                                .set
                                .as_mut()
                                .map_err(|e| BuildError::Proto(e.clone()))?;
                            pack_one(records, layout, comp, id)
                        },
                    )
                    .collect();
                let failed = packed.is_err();
                // A closed channel: the sink failed and the pass is over.
                if tx.send(packed).is_err() || failed {
                    break;
                }
            }
        });
        let mut done = 0u64;
        for chunk in rx {
            let chunk = chunk?;
            done += chunk.len() as u64;
            let mut treelets = Vec::with_capacity(chunk.len());
            for (t, raw) in chunk {
                stats.raw_bytes += raw;
                stats.node_bytes += t.nodes.len() as u64;
                for (s, c) in stats.channel_bytes.iter_mut().zip(&t.channels) {
                    *s += c.len() as u64;
                }
                treelets.push(t);
            }
            sink.put_many(treelets)?;
            pb.set_position(done);
            progress.set_done(done);
        }
        Ok::<(), BuildError>(())
    })?;
    pb.finish_and_clear();
    Ok(())
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
        let records = |f: Filled| RecordFile {
            file: f.file,
            bpv: 0,
            offsets: f.offsets,
        };
        let (a, b) = (records(general), records(sorted));
        for id in 0..a.offsets.len() as u32 - 1 {
            let (ra, len, used) = a.read_raw(id).unwrap();
            let (rb, _, _) = b.read_raw(id).unwrap();
            assert!(ra == rb, "treelet {id} differs");
            // Pack compresses the stored encoding as it is: it must be a whole, valid treelet.
            let t = codec::decode_treelet(&ra[..len], 10).unwrap();
            assert_eq!(t.used().len(), used, "treelet {id}");
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
