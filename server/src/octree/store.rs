//! Pass 2 of the build: every filled treelet's blocks compressed and handed to the
//! [`TreeletSink`], as two streams made at the same time:
//!
//! * **nodes** — a zstd dictionary is trained on evenly spread node records (final since the
//!   fill), then each treelet's stored encoding is compressed as it is, in id order;
//! * **attributes** — treelets are read back level by level, deepest first, their inner
//!   attributes averaged bottom-up (a child treelet's root attribute feeding its parent's
//!   refinable leaf), and each channel's block is compressed as soon as its treelet is averaged.
//!
//! Why one pass and not three (average, train, pack): apart, the single-threaded training and the
//! sink's writes each left a core idle, and every record's attributes were written back to the
//! scratch file only to be read again for packing. Now the averaging, the training, the node
//! compression and the sink's writes overlap on both cores, and attributes never go back to disk.
//! Memory stays bounded: each producer is at most a few chunks ahead of the sink, and the
//! averaging keeps only one level's root attributes.

use std::sync::Mutex;
use std::sync::mpsc::{SyncSender, sync_channel};
use std::time::Instant;

use arbor_proto::codec::{self, BlockCompressor, HEADER_BYTES};
use arbor_proto::{AttributeLayout, Node, ProtoError, SceneStats, TreeletId};
use rayon::prelude::*;

use super::records::{AlignedBuf, RecordFile, Records};
use super::{BuildError, BuildOptions, TreeletSink, bar};
use crate::progress::{ImportProgress, Phase};

/// Treelets per message from a producer to the sink.
const CHUNK: u32 = 512;
/// Messages a producer may be ahead of the sink.
const AHEAD: usize = 4;
/// Dictionary size per stream.
const DICTIONARY_BYTES: usize = 16 * 1024;
/// At most this many records are sampled for training.
const DICTIONARY_SAMPLES: u32 = 4000;

/// The node stream's dictionary (if one was trained) and one per channel.
pub(super) type Dictionaries = (Option<Vec<u8>>, Vec<Option<Vec<u8>>>);

/// The scene being stored: where its records are and how they are laid out.
pub(super) struct FilledScene<'a> {
    pub records: &'a RecordFile,
    pub layout: &'a AttributeLayout,
    /// First id of each treelet level (root = level 0), then the count.
    pub level_starts: &'a [u32],
}

/// A message from a producer to the thread that feeds the sink.
enum Stored {
    /// Node blocks of consecutive treelets, and their raw bytes.
    Nodes(Vec<(TreeletId, Vec<u8>)>, u64),
    /// Channel blocks of treelets of one level, and their raw bytes.
    Channels(Vec<(TreeletId, Vec<Vec<u8>>)>, u64),
}

type Message = Result<Stored, BuildError>;

/// Stores every treelet of `scene` into `sink`, filling the byte counts of `stats`; returns the
/// dictionaries used.
pub(super) fn store(
    scene: &FilledScene<'_>,
    opts: &BuildOptions,
    stats: &mut SceneStats,
    sink: &mut dyn TreeletSink,
    progress: &ImportProgress,
) -> Result<Dictionaries, BuildError> {
    let count = scene.level_starts.last().copied().unwrap_or(0);
    let channels = scene.layout.channels().len();
    stats.channel_bytes = vec![0; channels];
    sink.start(scene.layout)?;
    progress.enter(Phase::Packing, u64::from(count));
    let pb = bar(opts.progress, "store", u64::from(count));
    let dictionary = std::thread::scope(|scope| {
        let (tx, rx) = sync_channel::<Message>(AHEAD);
        let node_tx = tx.clone();
        let nodes = scope.spawn(move || {
            let t = Instant::now();
            let d = report(store_nodes(scene.records, count, opts, &node_tx), &node_tx);
            tracing::info!(
                seconds = t.elapsed().as_secs_f64(),
                "node blocks compressed"
            );
            d.flatten()
        });
        let attributes = scope.spawn(move || {
            let t = Instant::now();
            report(store_attributes(scene, opts, &tx), &tx);
            tracing::info!(
                seconds = t.elapsed().as_secs_f64(),
                "attributes averaged and compressed"
            );
        });
        let (mut nodes_done, mut channels_done) = (0u64, 0u64);
        let mut consume = || {
            for message in &rx {
                match message? {
                    Stored::Nodes(blocks, raw) => {
                        nodes_done += blocks.len() as u64;
                        stats.raw_bytes += raw;
                        stats.node_bytes += blocks.iter().map(|(_, b)| b.len() as u64).sum::<u64>();
                        sink.put_nodes(blocks)?;
                    }
                    Stored::Channels(blocks, raw) => {
                        channels_done += blocks.len() as u64;
                        stats.raw_bytes += raw;
                        for (_, per_channel) in &blocks {
                            for (s, b) in stats.channel_bytes.iter_mut().zip(per_channel) {
                                *s += b.len() as u64;
                            }
                        }
                        sink.put_channels(blocks)?;
                    }
                }
                let done = nodes_done.min(channels_done);
                pb.set_position(done);
                progress.set_done(done);
            }
            Ok::<(), BuildError>(())
        };
        let consumed = consume();
        // A failed sink ends the producers at their next send.
        drop(rx);
        let dictionary = nodes
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        attributes
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        consumed.map(|()| dictionary)
    })?;
    pb.finish_and_clear();
    Ok((dictionary, vec![None; channels]))
}

/// A producer's result: its value, or its error handed to the sink's thread (which stops there).
fn report<T>(result: Result<T, BuildError>, tx: &SyncSender<Message>) -> Option<T> {
    match result {
        Ok(v) => Some(v),
        Err(e) => {
            // A closed channel: the sink failed first, and its error is the one reported.
            let _ = tx.send(Err(e));
            None
        }
    }
}

/// The node stream: trains the dictionary, then compresses every record's stored encoding in id
/// order. Returns the dictionary.
fn store_nodes(
    records: &RecordFile,
    count: u32,
    opts: &BuildOptions,
    tx: &SyncSender<Message>,
) -> Result<Option<Vec<u8>>, BuildError> {
    let dictionary = if opts.dictionary {
        let t = Instant::now();
        let d = train_node_dictionary(records, count)?;
        tracing::info!(seconds = t.elapsed().as_secs_f64(), "dictionary training");
        d
    } else {
        None
    };
    let pool = CompressorPool::new(opts.zstd_level, vec![dictionary.as_deref()]);
    records.for_each(chunks(0..count).collect(), |ids, chunk| {
        let compressed: Vec<(TreeletId, Vec<u8>, u64)> = ids
            .into_par_iter()
            .map_init(
                || pool.lease(),
                |lease, id| {
                    let raw = chunk.nodes(id);
                    let block = lease.get()?[0].compress(raw)?;
                    Ok((TreeletId(id), block, raw.len() as u64))
                },
            )
            .collect::<Result<_, BuildError>>()?;
        let raw = compressed.iter().map(|(_, _, r)| r).sum();
        let blocks = compressed.into_iter().map(|(id, b, _)| (id, b)).collect();
        Ok::<_, BuildError>(tx.send(Ok(Stored::Nodes(blocks, raw))).is_ok())
    })?;
    Ok(dictionary)
}

/// Trains the node stream's dictionary on evenly spread records. Attribute channels get none:
/// measured on the six real scans (`cargo bench --bench build`) a channel dictionary saved at
/// most 5 % and sometimes grew the stream, while node dictionaries save 22–35 % (and a channel
/// dictionary would hold back the attribute stream until it is trained). Too few treelets to
/// learn from gives no dictionary.
fn train_node_dictionary(records: &RecordFile, count: u32) -> Result<Option<Vec<u8>>, BuildError> {
    if count < 32 {
        return Ok(None);
    }
    let step = (count / DICTIONARY_SAMPLES).max(1);
    // Each sample is a read of its own: two at a time.
    let samples: Vec<Vec<u8>> = (0..count)
        .into_par_iter()
        .step_by(step as usize)
        .map_init(AlignedBuf::default, |buf, id| {
            Ok(records.read(id..id + 1, buf)?.nodes(id).to_vec())
        })
        .collect::<Result<_, BuildError>>()?;
    Ok(match zstd::dict::from_samples(&samples, DICTIONARY_BYTES) {
        Ok(d) => Some(d),
        Err(e) => {
            tracing::warn!("dictionary training failed, compressing without: {e}");
            None
        }
    })
}

/// `ids` in consecutive ranges of [`CHUNK`] (the last one shorter).
fn chunks(ids: std::ops::Range<u32>) -> impl Iterator<Item = std::ops::Range<u32>> {
    let end = ids.end;
    ids.step_by(CHUNK as usize)
        .map(move |start| start..(start + CHUNK).min(end))
}

/// A treelet's id, its root voxel's attribute bytes (channels in layout order), its compressed
/// channel blocks and their raw bytes.
type Averaged = (u32, Vec<u8>, Vec<Vec<u8>>, u64);

/// The attribute stream: levels deepest first, each treelet averaged and its channels
/// compressed.
fn store_attributes(
    scene: &FilledScene<'_>,
    opts: &BuildOptions,
    tx: &SyncSender<Message>,
) -> Result<(), BuildError> {
    let layout = scene.layout;
    let pool = CompressorPool::new(opts.zstd_level, vec![None; layout.channels().len()]);
    // Root attributes of the treelets one level below, for their parents' refinable leaves:
    // one level's treelets are one id range, so a flat array indexed by id (a map of small
    // vectors cost 6× the bytes and grew with the scene).
    let mut below = LevelRoots::default();
    let bpv = scene.records.bpv;
    let mut roots = LevelRoots::default();
    // Levels deepest first; treelets of one level are independent (their children are all one
    // level deeper), so each level is read and averaged in chunks.
    let starts = scene.level_starts;
    let levels = (0..starts.len().saturating_sub(1)).rev();
    let ranges = levels
        .flat_map(|l| chunks(starts[l]..starts[l + 1]))
        .collect();
    scene.records.for_each(ranges, |ids, chunk| {
        if let Ok(level) = starts.binary_search(&ids.start) {
            // A new level: the one just averaged is the level below it.
            let next = LevelRoots {
                first: ids.start,
                bpv,
                bytes: Vec::with_capacity((starts[level + 1] - ids.start) as usize * bpv),
            };
            below = std::mem::replace(&mut roots, next);
        }
        let averaged: Vec<Averaged> = ids
            .into_par_iter()
            .map_init(
                || pool.lease(),
                |lease, id| {
                    let blocks = average_treelet(&chunk, layout, id, &below)?;
                    let raw = blocks.iter().map(|b| b.len() as u64).sum();
                    let root = layout
                        .channels()
                        .iter()
                        .zip(&blocks)
                        .flat_map(|(c, b)| &b[..c.size()])
                        .copied()
                        .collect();
                    let compressed = blocks
                        .iter()
                        .zip(lease.get()?.iter_mut())
                        .map(|(b, c)| c.compress(b))
                        .collect::<Result<Vec<_>, _>>()?;
                    Ok((id, root, compressed, raw))
                },
            )
            .collect::<Result<_, BuildError>>()?;
        let mut raw = 0;
        let mut blocks = Vec::with_capacity(averaged.len());
        for (id, root, compressed, r) in averaged {
            roots.bytes.extend_from_slice(&root);
            blocks.push((TreeletId(id), compressed));
            raw += r;
        }
        Ok::<_, BuildError>(tx.send(Ok(Stored::Channels(blocks, raw))).is_ok())
    })
}

/// The root voxel's attribute bytes of every treelet of one level, in id order.
#[derive(Default)]
struct LevelRoots {
    /// The level's first treelet id.
    first: u32,
    bpv: usize,
    bytes: Vec<u8>,
}

impl LevelRoots {
    fn get(&self, id: u32) -> Option<&[u8]> {
        let at = (id.checked_sub(self.first)? as usize).checked_mul(self.bpv)?;
        self.bytes.get(at..at + self.bpv)
    }
}

/// Averages one treelet's inner attributes bottom-up (its refinable leaves take their child
/// treelet's root attribute from `below`) and returns its channel blocks (used records each,
/// the root voxel's first).
///
/// Each channel is averaged in its own block, children being consecutive records: per inner
/// node one pass over a contiguous slice, instead of gathering each child's bytes from the
/// interleaved record and splitting the record into blocks afterwards one voxel at a time.
///
/// The record is read without the full validation of a received treelet: the fill wrote it in
/// this process (its encoding is checked by the build's tests and by `verify` on the stored
/// scene), and validating every record was a tenth of this pass. What the walk relies on is
/// still checked: child blocks inside the used records and attributes for each.
fn average_treelet(
    records: &Records<'_>,
    layout: &AttributeLayout,
    id: u32,
    below: &LevelRoots,
) -> Result<Vec<Vec<u8>>, BuildError> {
    let bpv = layout.bytes_per_voxel();
    let (raw, attrs) = records.record(id);
    codec::decode_header(raw)?;
    let nodes: Vec<Node> = codec::node_records(&raw[HEADER_BYTES..]).collect();
    let used = nodes.len();
    let malformed = |node: usize, detail: &str| {
        BuildError::Proto(ProtoError::MalformedTreelet {
            id: TreeletId(id),
            node: node as u32,
            detail: detail.into(),
        })
    };
    if used == 0 || attrs.len() != used * bpv {
        return Err(malformed(0, "record sizes disagree"));
    }
    // Leafness comes from the parent's leaf mask (the root: a node without children).
    let mut is_leaf = vec![false; used];
    is_leaf[0] = nodes[0].valid_mask == 0;
    for (i, n) in nodes.iter().enumerate() {
        if is_leaf[i] {
            continue;
        }
        let first = i + n.first_child as usize;
        if n.valid_mask == 0 || first <= i || first + n.child_count() as usize > used {
            return Err(malformed(i, "child block outside the used records"));
        }
        for (bit, k) in n.children() {
            is_leaf[first + k as usize] = n.leaf_mask & (1 << bit) != 0;
        }
    }
    let channels = layout.channels();
    let mut blocks = channel_blocks(layout, attrs, bpv, used);
    // Refinable leaves first: they feed the means above them.
    for (i, n) in nodes.iter().enumerate() {
        if !is_leaf[i] || n.first_child == Node::NONE {
            continue;
        }
        let root = below.get(n.first_child).ok_or_else(|| {
            BuildError::Sink(format!(
                "treelet {id} leaf {i}: child treelet {} was never built",
                n.first_child
            ))
        })?;
        let mut off = 0;
        for (c, block) in channels.iter().zip(&mut blocks) {
            let size = c.size();
            block[i * size..(i + 1) * size].copy_from_slice(&root[off..off + size]);
            off += size;
        }
    }
    for (c, block) in channels.iter().zip(&mut blocks) {
        let size = c.size();
        for i in (0..used).rev() {
            if is_leaf[i] {
                continue;
            }
            let n = nodes[i];
            // Children come after their parent (checked above), so the split keeps them apart.
            let first = i + n.first_child as usize;
            let (head, tail) = block.split_at_mut(first * size);
            let kids = &tail[..n.child_count() as usize * size];
            c.mean(kids.chunks_exact(size), &mut head[i * size..(i + 1) * size]);
        }
    }
    Ok(blocks)
}

/// Splits a record's interleaved attribute bytes into one block per channel (used records only).
fn channel_blocks(layout: &AttributeLayout, attrs: &[u8], bpv: usize, used: usize) -> Vec<Vec<u8>> {
    let mut at = 0;
    layout
        .channels()
        .iter()
        .map(|c| {
            let voxels = attrs.chunks_exact(bpv).take(used);
            let block = match c.size() {
                2 => gather::<2>(voxels, at),
                3 => gather::<3>(voxels, at),
                4 => gather::<4>(voxels, at),
                size => voxels.flat_map(|v| &v[at..at + size]).copied().collect(),
            };
            at += c.size();
            block
        })
        .collect()
}

/// Bytes `at..at + S` of every voxel, one fixed-size copy each (a slice copy of unknown
/// length is a `memmove` call per voxel).
fn gather<'a, const S: usize>(voxels: impl Iterator<Item = &'a [u8]>, at: usize) -> Vec<u8> {
    let mut block = Vec::with_capacity(voxels.size_hint().0 * S);
    for v in voxels {
        let bytes: [u8; S] = v[at..at + S].try_into().expect("S bytes");
        block.extend_from_slice(&bytes);
    }
    block
}

/// Compressor sets (one compressor per dictionary) kept for the whole pass and handed from one
/// rayon job to the next: building one loads its dictionary into zstd's tables, which costs as
/// much as compressing a few treelets.
struct CompressorPool<'a> {
    level: i32,
    dictionaries: Vec<Option<&'a [u8]>>,
    idle: Mutex<Vec<Vec<BlockCompressor>>>,
}

impl<'a> CompressorPool<'a> {
    fn new(level: i32, dictionaries: Vec<Option<&'a [u8]>>) -> Self {
        CompressorPool {
            level,
            dictionaries,
            idle: Mutex::new(Vec::new()),
        }
    }

    fn take(&self) -> Result<Vec<BlockCompressor>, ProtoError> {
        if let Some(set) = self.idle.lock().unwrap_or_else(|e| e.into_inner()).pop() {
            return Ok(set);
        }
        self.dictionaries
            .iter()
            .map(|d| BlockCompressor::new(self.level, *d))
            .collect()
    }

    /// A set for one rayon split, given back when the split ends.
    fn lease(&self) -> Lease<'_, 'a> {
        Lease {
            pool: self,
            set: self.take(),
        }
    }
}

/// A compressor set taken from a [`CompressorPool`] for one rayon split.
struct Lease<'p, 'a> {
    pool: &'p CompressorPool<'a>,
    set: Result<Vec<BlockCompressor>, ProtoError>,
}

impl Lease<'_, '_> {
    fn get(&mut self) -> Result<&mut [BlockCompressor], BuildError> {
        self.set
            .as_deref_mut()
            .map_err(|e| BuildError::Proto(e.clone()))
    }
}

impl Drop for Lease<'_, '_> {
    fn drop(&mut self) {
        if let Ok(set) = std::mem::replace(&mut self.set, Ok(Vec::new())) {
            self.pool
                .idle
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(set);
        }
    }
}
