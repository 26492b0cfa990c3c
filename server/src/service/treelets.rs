//! Treelet messages as the service sends them: the stored blocks, unchanged, behind
//! [`arbor_proto::frame::encode_treelet_header`].
//!
//! The header needs `used_nodes`, which the pool does not store next to the block: it is read
//! from the node block itself (decompressed with the scene's prepared dictionary, header
//! decoded) when the message is built. Built messages are kept in a [`MessageCache`] bounded in
//! bytes (server-wide, `message_cache_bytes`), so a treelet sent again — to another client, or
//! after an eviction — costs no pool read and no decompression. A batch's messages are kept
//! back to back in the buffer they were joined in for their stream, so the same treelets in the
//! same order go out again as a slice of it, uncopied (see [`ServedScene::batch`]); never
//! re-framed or recompressed.

use std::collections::{HashMap, VecDeque};
use std::hash::{BuildHasherDefault, Hash, Hasher};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use arbor_proto::codec::{self, MAX_RAW_TREELET, PreparedDictionaries};
use arbor_proto::frame::{FrameError, encode_treelet_header};
use arbor_proto::treelet_map::RunHasher;
use arbor_proto::{Channel, ProtoError, TreeletId};
use bytes::{Bytes, BytesMut};

use arbor_client_core::slots::DecodedTreelet;
use arbor_proto::wire::ViewHint;

use super::shapes::ShapeCache;
use super::state::ServiceCaches;
use super::visibility::{CutCaster, FineCutGates, NodeCache, VisibleCut};
use crate::pool::{PoolError, StoredScene};

/// Why a treelet message could not be built. Always the server's fault (the pool), never the
/// client's.
#[derive(Debug, thiserror::Error)]
pub enum MessageError {
    /// The pool failed to read.
    #[error(transparent)]
    Pool(#[from] PoolError),
    /// A block the scene's description promises is not stored.
    #[error("treelet {id}: no stored {what} block")]
    Missing { id: u32, what: &'static str },
    /// The stored node block does not decompress or decode.
    #[error("treelet {id}: stored node block: {source}")]
    Corrupt {
        id: u32,
        #[source]
        source: ProtoError,
    },
    /// A stored block is out of the protocol's bounds.
    #[error("treelet {id}: {source}")]
    Frame {
        id: u32,
        #[source]
        source: FrameError,
    },
}

/// Most treelet messages on one stream (a batch is also at most a quarter of the connection's
/// window: [`super::schedule::batch_limit`]). Measured (`cargo bench -p arbor-tests --bench
/// serve`): QUIC's per-stream cost (open, credit, frames, acknowledgement bookkeeping, one task)
/// dominated a 4 KiB treelet; a few per stream share it. 256 rather than 64: a whole lion-4k
/// with each end on a CPU of its own went from 0.85× to 0.93× of one raw quinn stream (medians
/// of five alternating invocations each), with no change over the link emulator
/// (docs/measurements.md, stop 52).
pub const MAX_TREELETS_PER_STREAM: usize = 256;

/// Most visible cuts of one scene cast at once; a connection whose view finds them all busy
/// keeps the frustum plan and asks again with its next resting list.
pub const MAX_CUTS_RUNNING: usize = 2;

/// Which message: scene generation, treelet, channel set (bit per channel id).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct MessageKey {
    generation: u64,
    treelet: u32,
    channels: u32,
}

impl Hash for MessageKey {
    /// For [`RunHasher`]: the generation and channel set as the salt, then the treelet id, so
    /// a stream's batch (rank-adjacent treelets, mostly consecutive ids) is looked up in
    /// neighbouring buckets rather than with a cache miss per message.
    fn hash<H: Hasher>(&self, state: &mut H) {
        state.write_u64(self.generation ^ u64::from(self.channels).rotate_left(32));
        state.write_u32(self.treelet);
    }
}

/// Built treelet messages, bounded in bytes, oldest insertion evicted first (a treelet's
/// popularity follows the views of many clients; FIFO keeps the bookkeeping to one queue and
/// one map under one short lock).
///
/// A message is held as a range of the buffer it was built in, its *run*: the messages of one
/// stream's batch joined together (`MessageCache::insert_run`). A later batch whose messages
/// lie back to back in one run (the same treelets in the same order: every fetch of the same
/// list, most lists of a view that moves little) goes to the wire as a slice of the run, not
/// copied (`MessageCache::chunks`).
#[derive(Debug)]
pub struct MessageCache {
    capacity: usize,
    inner: Mutex<CacheInner>,
}

#[derive(Debug, Default)]
struct CacheInner {
    map: HashMap<MessageKey, Held, BuildHasherDefault<RunHasher>>,
    order: VecDeque<MessageKey>,
    bytes: usize,
    hits: u64,
    misses: u64,
}

impl CacheInner {
    /// Holds `held` as `key`'s, evicting the oldest until it fits in `capacity` (nothing held
    /// when it alone is larger).
    fn insert(&mut self, capacity: usize, key: MessageKey, held: Held) {
        if held.charge > capacity {
            return;
        }
        while self.bytes + held.charge > capacity {
            let Some(old) = self.order.pop_front() else {
                break;
            };
            if let Some(h) = self.map.remove(&old) {
                self.bytes -= h.charge;
            }
        }
        self.bytes += held.charge;
        self.order.push_back(key);
        self.map.insert(key, held);
    }
}

/// A held message: bytes `start..end` of `run`.
#[derive(Debug)]
struct Held {
    run: Bytes,
    start: usize,
    end: usize,
    /// What it counts for against the capacity: the whole run for the last message inserted
    /// from it, nothing for the others. A run's messages are inserted, and so evicted, one after
    /// the other: the run's buffer is counted exactly while the cache holds any of it.
    charge: usize,
}

impl Held {
    fn bytes(&self) -> &[u8] {
        &self.run[self.start..self.end]
    }

    /// The message as a buffer of its own, sharing the run's.
    fn slice(&self) -> Bytes {
        self.run.slice(self.start..self.end)
    }
}

/// Most buffers one stream's batch is written as. Each packet quinn builds finds its bytes by
/// walking the stream's unacknowledged buffers from the oldest (see [`ServedScene::batch`]), so
/// a batch spread over more runs than this is copied into one buffer instead.
pub const MAX_CHUNKS_PER_STREAM: usize = 4;

/// A run is kept whole only while it is at most this share of the cache, so one large batch
/// cannot flush it; a larger one is kept message by message.
const RUN_SHARE_OF_CACHE: usize = 8;

impl MessageCache {
    /// A cache holding at most `capacity` bytes of messages (0: nothing is kept).
    pub fn new(capacity: usize) -> MessageCache {
        MessageCache {
            capacity,
            inner: Mutex::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, CacheInner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Hits for `keys`, in order, under one lock (a stream's batch is looked up at once).
    fn get(&self, keys: &[MessageKey]) -> Vec<Option<Bytes>> {
        let mut inner = self.lock();
        let found: Vec<Option<Bytes>> = keys
            .iter()
            .map(|k| inner.map.get(k).map(Held::slice))
            .collect();
        let hits = found.iter().filter(|m| m.is_some()).count() as u64;
        inner.hits += hits;
        inner.misses += found.len() as u64 - hits;
        found
    }

    /// When every one of `keys` is held: their messages back to back, as slices of the runs
    /// they lie in (one per stretch of messages adjacent in one run), or copied into one buffer
    /// when that would be more than [`MAX_CHUNKS_PER_STREAM`]; hits counted. Else `None`,
    /// nothing counted (the caller then asks [`Self::get`]).
    fn chunks(&self, keys: &[MessageKey]) -> Option<Vec<Bytes>> {
        let mut inner = self.lock();
        // One lookup per key (the table is larger than a core's cache): the hits are gathered
        // first, then measured and sliced or copied.
        let found: Vec<&Held> = keys
            .iter()
            .map(|k| inner.map.get(k))
            .collect::<Option<_>>()?;
        let mut stretches: Vec<(&Bytes, usize, usize)> = Vec::with_capacity(MAX_CHUNKS_PER_STREAM);
        let mut spread = false;
        for h in &found {
            if let Some((run, _, end)) = stretches.last_mut()
                && run.as_ptr() == h.run.as_ptr()
                && *end == h.start
            {
                *end = h.end;
            } else if stretches.len() < MAX_CHUNKS_PER_STREAM {
                stretches.push((&h.run, h.start, h.end));
            } else {
                spread = true;
                break;
            }
        }
        let out = if spread {
            vec![concat(&found.iter().map(|h| h.bytes()).collect::<Vec<_>>())]
        } else {
            stretches
                .iter()
                .map(|&(run, start, end)| run.slice(start..end))
                .collect()
        };
        inner.hits += keys.len() as u64;
        Some(out)
    }

    /// Keeps `message` as `key`'s (unless held already).
    #[cfg(test)]
    fn insert(&self, key: MessageKey, message: Bytes) {
        let len = message.len();
        self.insert_run(&message, &[key], &[len]);
    }

    /// Keeps the messages of `keys`, which lie back to back in `run` with the lengths `lens`,
    /// each unless held already. The run is kept whole when the messages new to the cache are
    /// at least half of it and it is at most [`RUN_SHARE_OF_CACHE`] of the cache (so inserting
    /// it never evicts its own messages); else each new message is kept as a copy of its own, so
    /// a batch of mostly held messages does not keep a second copy of them alive.
    fn insert_run(&self, run: &Bytes, keys: &[MessageKey], lens: &[usize]) {
        if self.capacity == 0 {
            return;
        }
        // A key named twice is kept once (the scheduler never batches one twice), its first
        // time; found before the lock, which every stream's batch takes.
        let mut seen = rustc_hash::FxHashSet::default();
        seen.reserve(keys.len());
        let first: Vec<bool> = keys.iter().map(|k| seen.insert(*k)).collect();
        let mut inner = self.lock();
        let mut new = Vec::with_capacity(keys.len());
        let mut start = 0;
        for ((key, &len), first) in keys.iter().zip(lens).zip(first) {
            if first && !inner.map.contains_key(key) {
                new.push((*key, start, start + len));
            }
            start += len;
        }
        let kept: usize = new.iter().map(|&(_, start, end)| end - start).sum();
        let count = new.len();
        // A run that is one new message is that message as it is, whatever its size.
        let whole = (count == 1 && kept == run.len())
            || (2 * kept >= run.len() && run.len() <= self.capacity / RUN_SHARE_OF_CACHE);
        for (i, (key, start, end)) in new.into_iter().enumerate() {
            let held = if whole {
                Held {
                    run: run.clone(),
                    start,
                    end,
                    charge: if i + 1 == count { run.len() } else { 0 },
                }
            } else if end - start > self.capacity {
                // Could not be held: not copied for nothing.
                continue;
            } else {
                Held {
                    run: Bytes::copy_from_slice(&run[start..end]),
                    start: 0,
                    end: end - start,
                    charge: end - start,
                }
            };
            inner.insert(self.capacity, key, held);
        }
    }

    /// `(bytes held, hits, misses)`.
    pub fn figures(&self) -> (usize, u64, u64) {
        let inner = self.lock();
        (inner.bytes, inner.hits, inner.misses)
    }
}

/// Message cache of a scene opened on its own (tools, benches): 16 MiB.
const OWN_MESSAGE_CACHE_BYTES: usize = 16 << 20;
/// Shape cache of a scene opened on its own: 4 MiB (a server shares one of
/// `shape_cache_bytes`).
const OWN_SHAPE_CACHE_BYTES: usize = 4 << 20;
/// Cut node cache of a scene opened on its own: 4 MiB (a server shares one of
/// `visibility_node_cache_bytes`).
const OWN_CUT_NODE_CACHE_BYTES: usize = 4 << 20;

/// A stream's batch as the message cache alone gives it ([`ServedScene::cached_batch`]).
#[derive(Debug)]
pub enum CachedBatch {
    /// Every message was held: the batch as it goes out.
    Whole(Vec<Bytes>),
    /// Some were not: [`ServedScene::complete_batch`] reads them from the pool.
    Partial(PartialBatch),
}

/// A batch whose messages the cache held only in part, looked up (and counted) once.
#[derive(Debug)]
pub struct PartialBatch {
    ids: Vec<TreeletId>,
    keys: Vec<MessageKey>,
    /// Per id, the cache's message, if it held it.
    found: Vec<Option<Bytes>>,
}

/// A scene opened for serving.
pub struct ServedScene {
    pub stored: StoredScene,
    dictionaries: PreparedDictionaries,
    cache: Arc<MessageCache>,
    /// Treelet shapes for deep-request pushes.
    shapes: Arc<ShapeCache>,
    /// Decoded node records for visible cuts.
    cut_nodes: Arc<NodeCache>,
    /// The root treelet's nodes for visible cuts, read by the first cut.
    cut_caster: Mutex<Option<Arc<CutCaster>>>,
    /// Visible cuts being cast now (each holds a buffer of `visibility_cache_bytes`).
    cuts_running: AtomicUsize,
    /// Whether the fine cuts of the scenes have been of use lately.
    fine_cuts: Arc<FineCutGates>,
}

impl std::fmt::Debug for ServedScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServedScene")
            .field("name", &self.stored.description.name)
            .field("generation", &self.stored.generation)
            .finish_non_exhaustive()
    }
}

impl ServedScene {
    /// A scene with caches of its own.
    pub fn new(stored: StoredScene) -> ServedScene {
        Self::with_caches(
            stored,
            &ServiceCaches {
                messages: Arc::new(MessageCache::new(OWN_MESSAGE_CACHE_BYTES)),
                shapes: Arc::new(ShapeCache::for_shapes(OWN_SHAPE_CACHE_BYTES)),
                cut_nodes: Arc::new(NodeCache::for_nodes(OWN_CUT_NODE_CACHE_BYTES)),
                fine_cuts: Arc::default(),
            },
        )
    }

    /// A scene sharing the server's caches.
    pub fn with_caches(stored: StoredScene, caches: &ServiceCaches) -> ServedScene {
        ServedScene {
            dictionaries: PreparedDictionaries::of(&stored.description),
            stored,
            cache: caches.messages.clone(),
            shapes: caches.shapes.clone(),
            cut_nodes: caches.cut_nodes.clone(),
            cut_caster: Mutex::new(None),
            cuts_running: AtomicUsize::new(0),
            fine_cuts: caches.fine_cuts.clone(),
        }
    }

    /// The visible cut of `view` with `grid` rays along the longer side, from `seed` (a coarser
    /// cut of the same view, or nothing: [`CutCaster::cut_from`]), in a buffer of at most
    /// `budget_bytes` of node records, abandoned once `worthwhile` says a cut that large is not
    /// worth following ([`CutCaster::cut_from`]). `None` when the root treelet cannot be read or
    /// does not fit, or [`MAX_CUTS_RUNNING`] cuts of this scene are being cast already (their
    /// buffers bound the memory). Blocks for the cast (milliseconds): call it off the async
    /// workers.
    pub fn visible_cut(
        &self,
        view: &ViewHint,
        grid: u32,
        seed: &[(u8, TreeletId)],
        budget_bytes: u64,
        worthwhile: impl FnMut(usize) -> bool + Send,
    ) -> Option<VisibleCut> {
        struct Running<'a>(&'a AtomicUsize);
        impl Drop for Running<'_> {
            fn drop(&mut self) {
                self.0.fetch_sub(1, Ordering::AcqRel);
            }
        }
        let running = Running(&self.cuts_running);
        if running.0.fetch_add(1, Ordering::AcqRel) >= MAX_CUTS_RUNNING {
            return None;
        }
        let d = &self.stored.description;
        // Shared out of the cache, not copied: the cast only reads what it inserts.
        let fetch = |id: TreeletId| {
            self.cut_nodes
                .get_or_decode(self.stored.generation, id, || {
                    let block = self.stored.nodes(id).ok()??;
                    DecodedTreelet::from_blocks_prepared(
                        id,
                        &block,
                        &[],
                        d,
                        &self.dictionaries,
                        &[],
                    )
                    .ok()
                })
        };
        let caster = {
            let mut caster = self.cut_caster.lock().unwrap_or_else(|p| p.into_inner());
            if caster.is_none() {
                let root: Arc<DecodedTreelet> = fetch(d.root_treelet)?;
                let root = DecodedTreelet::clone(&root);
                match CutCaster::new(d, budget_bytes, root) {
                    Ok(c) => *caster = Some(Arc::new(c)),
                    Err(e) => {
                        tracing::warn!(scene = %d.name, "no visible cut: {e}");
                        return None;
                    }
                }
            }
            caster.clone()?
        };
        Some(caster.cut_from(view, grid, seed, fetch, worthwhile))
    }

    /// Whether a resting view's fine cut should be cast, by what this scene's last fine cuts
    /// were worth (`visibility::FineCutGate::should_cast`).
    pub fn should_cast_fine_cut(&self) -> bool {
        self.fine_cuts.should_cast(self.stored.generation)
    }

    /// A fine cut of this scene was cast: `used` when complete and followed.
    pub fn record_fine_cut(&self, used: bool) {
        self.fine_cuts.record(self.stored.generation, used);
    }

    /// The shape of treelet `id` for deep-request pushes ([`ShapeCache::shape`]).
    pub fn shape(&self, id: TreeletId) -> Option<Arc<super::push::TreeletShape>> {
        self.shapes.shape(&self.stored, &self.dictionaries, id)
    }

    /// The shape of treelet `id` if the shape cache holds it; never reads the pool, so it may
    /// be asked on an async worker ([`ShapeCache::cached`]). Counts nothing: see
    /// [`Self::count_shape_hits`].
    pub fn cached_shape(&self, id: TreeletId) -> Option<Arc<super::push::TreeletShape>> {
        self.shapes.cached(&self.stored, id)
    }

    /// Counts `n` shapes found by [`Self::cached_shape`] and used as the shape cache's hits.
    pub fn count_shape_hits(&self, n: u64) {
        self.shapes.count_hits(n);
    }

    pub fn treelet_count(&self) -> u32 {
        self.stored.description.treelet_count
    }

    /// `used_nodes` of a treelet, from its node block: from the zstd frame header when it
    /// records a treelet's length within the scene's treelets, else from the decompressed
    /// header. Decompressing only for this was half to two thirds of building a message that
    /// missed the cache (3.1 of 6.0 µs per treelet on the 10⁸-point city, 1.7 of 2.8 µs on
    /// lion-4k: `server/benches/messages.rs`, docs/measurements.md, stop 59), and misses are
    /// the rule for a scan many times the message cache. What a frame header cannot show (a
    /// block stored under another id, damaged records) every client finds when it decodes the
    /// block, and `arbor-server verify` finds in the pool.
    fn used_nodes(&self, id: TreeletId, nodes: &[u8]) -> Result<u16, MessageError> {
        if let Some(used) = codec::used_nodes_of_block(nodes)
            && u32::from(used) <= self.stored.description.treelet_nodes
        {
            return Ok(used);
        }
        let corrupt = |source| MessageError::Corrupt { id: id.0, source };
        let raw = codec::decompress_using(nodes, MAX_RAW_TREELET, self.dictionaries.nodes())
            .map_err(corrupt)?;
        let (header, _) = codec::decode_header(&raw).map_err(corrupt)?;
        if header.id != id {
            return Err(corrupt(ProtoError::OutOfRange {
                what: "treelet header",
                detail: format!("stored under id {} but says {}", id.0, header.id.0),
            }));
        }
        Ok(header.used_nodes)
    }

    /// The whole treelet message for `id` with `channels` (ascending by channel id, each stored
    /// by the scene): header + node block + channel blocks, byte for byte as stored; from the
    /// cache when it was built before.
    pub fn message(&self, id: TreeletId, channels: &[Channel]) -> Result<Bytes, MessageError> {
        Ok(joined(self.batch(std::slice::from_ref(&id), channels)?))
    }

    /// The messages of `ids` back to back, as a stream's batch carries them, in one buffer or a
    /// few (at most [`MAX_CHUNKS_PER_STREAM`]): slices of the runs the cache holds them in when
    /// it holds them all (`MessageCache::chunks`), else copied together once, that copy then
    /// kept as their run (`MessageCache::insert_run`).
    ///
    /// Why not a buffer per message: quinn finds the bytes of every STREAM frame it builds by
    /// walking the stream's unacknowledged buffers from the oldest (`SendBuffer::get`), so a
    /// stream written as 64 buffers costs a walk over up to 64 for each packet, and more than
    /// one for a packet that spans buffers. On a whole-scene fetch of lion-4k that walk was 3.4
    /// M instructions of 73 M (callgrind, `scripts/serve-instructions`; docs/measurements.md,
    /// stop 31). By time too: the 64 buffers were about 5 % slower per fetch, and still no
    /// faster with that walk replaced by a cursor (stop 35). Why not a copy per batch, as
    /// until stop 57: the copy of 2.6 MB per whole-scene fetch of lion-4k from messages spread
    /// over the heap was 0.5 ms of the server's 4.6 ms (`perf`, each end on a CPU of its own).
    pub fn batch(
        &self,
        ids: &[TreeletId],
        channels: &[Channel],
    ) -> Result<Vec<Bytes>, MessageError> {
        match self.cached_batch(ids, channels) {
            CachedBatch::Whole(chunks) => Ok(chunks),
            CachedBatch::Partial(partial) => self.complete_batch(partial, channels),
        }
    }

    /// [`Self::batch`] as far as the cache takes it, without reading the pool: whole when the
    /// cache holds every message, else what it holds and what is left to read (hits and misses
    /// counted here, once). A caller on an async worker completes it
    /// ([`Self::complete_batch`]) on a reader thread: a pool larger than the page cache reads
    /// from disk (`super::readers`).
    pub fn cached_batch(&self, ids: &[TreeletId], channels: &[Channel]) -> CachedBatch {
        let keys = self.keys(ids, channels);
        if let Some(chunks) = self.cache.chunks(&keys) {
            return CachedBatch::Whole(chunks);
        }
        let found = self.cache.get(&keys);
        if found.iter().all(Option::is_some) {
            let messages = found.into_iter().flatten().collect();
            return CachedBatch::Whole(self.keep_run(&keys, messages));
        }
        CachedBatch::Partial(PartialBatch {
            ids: ids.to_vec(),
            keys,
            found,
        })
    }

    /// A [`CachedBatch::Partial`] made whole: the messages the cache lacked built from the pool,
    /// and the batch kept as a run.
    pub fn complete_batch(
        &self,
        partial: PartialBatch,
        channels: &[Channel],
    ) -> Result<Vec<Bytes>, MessageError> {
        let PartialBatch { ids, keys, found } = partial;
        let missing: Vec<TreeletId> = ids
            .iter()
            .zip(&found)
            .filter(|(_, hit)| hit.is_none())
            .map(|(&id, _)| id)
            .collect();
        let mut built = self.build(&missing, channels)?.into_iter();
        let messages = found
            .into_iter()
            .map(|hit| hit.unwrap_or_else(|| Bytes::from(built.next().expect("one per miss"))))
            .collect();
        Ok(self.keep_run(&keys, messages))
    }

    /// `messages` (of `keys`) copied together into one buffer, kept as their run.
    fn keep_run(&self, keys: &[MessageKey], messages: Vec<Bytes>) -> Vec<Bytes> {
        let lens: Vec<usize> = messages.iter().map(Bytes::len).collect();
        let run = joined(messages);
        self.cache.insert_run(&run, keys, &lens);
        vec![run]
    }

    fn keys(&self, ids: &[TreeletId], channels: &[Channel]) -> Vec<MessageKey> {
        let mask = channels
            .iter()
            .fold(0u32, |m, c| m | 1 << (c.id() as u32 & 31));
        ids.iter()
            .map(|id| MessageKey {
                generation: self.stored.generation,
                treelet: id.0,
                channels: mask,
            })
            .collect()
    }

    /// The messages of `ids`, in order, built from the pool: each pack of consecutive ids read
    /// once per stream of blocks ([`StoredScene::nodes_of`]).
    fn build(&self, ids: &[TreeletId], channels: &[Channel]) -> Result<Vec<Vec<u8>>, MessageError> {
        if ids.is_empty() {
            return Ok(Vec::new());
        }
        let nodes = self.stored.nodes_of(ids)?;
        let blocks: Vec<Vec<Option<sled::IVec>>> = channels
            .iter()
            .map(|&c| self.stored.channel_of(c, ids))
            .collect::<Result<_, _>>()?;
        ids.iter()
            .enumerate()
            .map(|(i, &id)| {
                let nodes = nodes[i].as_ref().ok_or(MessageError::Missing {
                    id: id.0,
                    what: "node",
                })?;
                let mut parts = Vec::with_capacity(channels.len());
                for (&c, column) in channels.iter().zip(&blocks) {
                    let b = column[i].as_ref().ok_or(MessageError::Missing {
                        id: id.0,
                        what: c.name(),
                    })?;
                    parts.push((c, b));
                }
                let used = self.used_nodes(id, nodes)?;
                let lens: Vec<(Channel, usize)> =
                    parts.iter().map(|(c, b)| (*c, b.len())).collect();
                let header = encode_treelet_header(id, used, nodes.len(), &lens)
                    .map_err(|source| MessageError::Frame { id: id.0, source })?;
                let total = header.len() + nodes.len() + lens.iter().map(|l| l.1).sum::<usize>();
                let mut out = Vec::with_capacity(total);
                out.extend_from_slice(&header);
                out.extend_from_slice(nodes);
                for (_, b) in &parts {
                    out.extend_from_slice(b);
                }
                Ok(out)
            })
            .collect()
    }
}

/// Messages as one buffer: a single one as it is, several copied together once.
fn joined(messages: Vec<Bytes>) -> Bytes {
    match <[Bytes; 1]>::try_from(messages) {
        Ok([one]) => one,
        Err(messages) => concat(&messages),
    }
}

/// `parts` copied back to back into one buffer of exactly their length.
fn concat(parts: &[impl AsRef<[u8]>]) -> Bytes {
    let mut out = BytesMut::with_capacity(parts.iter().map(|p| p.as_ref().len()).sum());
    for p in parts {
        out.extend_from_slice(p.as_ref());
    }
    out.freeze()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(generation: u64, treelet: u32, channels: u32) -> MessageKey {
        MessageKey {
            generation,
            treelet,
            channels,
        }
    }

    fn hit(cache: &MessageCache, key: MessageKey) -> bool {
        cache.get(&[key])[0].is_some()
    }

    #[test]
    fn the_cache_stays_within_its_bytes_and_evicts_the_oldest() {
        let cache = MessageCache::new(100);
        for i in 0..10u32 {
            cache.insert(key(1, i, 1), Bytes::from(vec![i as u8; 30]));
            assert!(cache.figures().0 <= 100);
        }
        // The last three fit; older ones are gone.
        assert!(hit(&cache, key(1, 9, 1)));
        assert!(hit(&cache, key(1, 7, 1)));
        assert!(!hit(&cache, key(1, 6, 1)));
        // Another channel set or generation is another message.
        assert!(!hit(&cache, key(1, 9, 3)));
        assert!(!hit(&cache, key(2, 9, 1)));
        // A batch comes back in its order, hits and misses counted.
        let (_, hits, misses) = cache.figures();
        let batch = cache.get(&[key(1, 9, 1), key(1, 6, 1), key(1, 8, 1)]);
        let firsts: Vec<Option<u8>> = batch.iter().map(|m| m.as_ref().map(|b| b[0])).collect();
        assert_eq!(firsts, [Some(9), None, Some(8)]);
        assert_eq!(cache.figures(), (90, hits + 2, misses + 1));
        // A batch wholly held comes back joined, its hits counted; one miss and nothing is
        // joined or counted (the caller then builds what is missing).
        let (_, hits, misses) = cache.figures();
        assert_eq!(
            cache
                .chunks(&[key(1, 8, 1), key(1, 9, 1)])
                .map(|c| concat(&c)),
            Some(Bytes::from([vec![8u8; 30], vec![9u8; 30]].concat()))
        );
        assert_eq!(cache.chunks(&[key(1, 8, 1), key(1, 6, 1)]), None);
        assert_eq!(cache.figures(), (90, hits + 2, misses));

        // Larger than the whole cache: not kept.
        cache.insert(key(1, 99, 1), Bytes::from(vec![0; 101]));
        assert!(!hit(&cache, key(1, 99, 1)));
        let none = MessageCache::new(0);
        none.insert(key(1, 1, 1), Bytes::from_static(b"x"));
        assert_eq!(none.figures().0, 0);
    }

    #[test]
    fn messages_join_into_one_buffer_and_a_single_message_is_not_copied() {
        let single = Bytes::from(vec![1u8, 2, 3]);
        let out = joined(vec![single.clone()]);
        assert_eq!(
            out.as_ptr(),
            single.as_ptr(),
            "a single message is not copied"
        );
        let parts = vec![
            Bytes::from_static(b"ab"),
            Bytes::from_static(b"cde"),
            Bytes::from_static(b"f"),
        ];
        assert_eq!(joined(parts), Bytes::from_static(b"abcdef"));
        assert!(joined(Vec::new()).is_empty());
    }

    /// `n` messages of `len` bytes each, the i-th filled with `first + i`, joined as a run.
    fn run_of(first: u8, n: usize, len: usize) -> (Bytes, Vec<usize>) {
        let bytes: Vec<u8> = (0..n).flat_map(|i| vec![first + i as u8; len]).collect();
        (Bytes::from(bytes), vec![len; n])
    }

    fn keys(treelets: impl IntoIterator<Item = u32>) -> Vec<MessageKey> {
        treelets.into_iter().map(|t| key(1, t, 1)).collect()
    }

    /// Where `chunk` lies in `run`, if it is a slice of it.
    fn offset_in(run: &Bytes, chunk: &Bytes) -> Option<usize> {
        let (r, c) = (run.as_ptr() as usize, chunk.as_ptr() as usize);
        (c >= r && c + chunk.len() <= r + run.len()).then(|| c - r)
    }

    #[test]
    fn a_batch_held_back_to_back_in_runs_goes_out_as_slices_of_them() {
        let cache = MessageCache::new(1 << 20);
        let (a, lens) = run_of(0, 4, 10);
        cache.insert_run(&a, &keys(0..4), &lens);
        let (b, lens) = run_of(4, 4, 10);
        cache.insert_run(&b, &keys(4..8), &lens);
        assert_eq!(cache.figures().0, 80, "each run counted once, whole");

        let expect = |ts: &[u32]| -> Bytes {
            concat(&ts.iter().map(|&t| vec![t as u8; 10]).collect::<Vec<_>>())
        };
        // The whole first run, a stretch inside it, and across both: no copy.
        let whole = cache.chunks(&keys(0..4)).unwrap();
        assert_eq!(whole.len(), 1);
        assert_eq!(offset_in(&a, &whole[0]), Some(0));
        assert_eq!(whole[0].len(), 40);
        let inside = cache.chunks(&keys(1..3)).unwrap();
        assert_eq!((inside.len(), offset_in(&a, &inside[0])), (1, Some(10)));
        assert_eq!(concat(&inside), expect(&[1, 2]));
        let across = cache.chunks(&keys(2..7)).unwrap();
        assert_eq!(across.len(), 2);
        assert_eq!(offset_in(&a, &across[0]), Some(20));
        assert_eq!(offset_in(&b, &across[1]), Some(0));
        assert_eq!(concat(&across), expect(&[2, 3, 4, 5, 6]));
        // Out of order: a slice per stretch, up to MAX_CHUNKS_PER_STREAM.
        let order = [3, 0, 1, 7];
        let out = cache.chunks(&keys(order)).unwrap();
        assert_eq!(out.len(), 3);
        assert_eq!(concat(&out), expect(&order));
        // More stretches than that: one buffer, copied, with the same bytes.
        let order = [0, 2, 4, 6, 1, 3];
        let out = cache.chunks(&keys(order)).unwrap();
        assert_eq!(out.len(), 1);
        assert_eq!(offset_in(&a, &out[0]).or(offset_in(&b, &out[0])), None);
        assert_eq!(out[0], expect(&order));
        let (_, hits, misses) = cache.figures();
        assert_eq!((hits, misses), (4 + 2 + 5 + 4 + 6, 0));
    }

    #[test]
    fn a_run_counts_whole_while_any_of_it_is_held_and_a_mostly_held_batch_is_copied() {
        let cache = MessageCache::new(1000);
        // Messages 0 and 1 held, then a batch of 0..4: half of it new, the run kept whole and
        // counted whole, the part already held included.
        let (first, lens) = run_of(0, 2, 10);
        cache.insert_run(&first, &keys(0..2), &lens);
        let (run, lens) = run_of(0, 4, 10);
        cache.insert_run(&run, &keys(0..4), &lens);
        assert_eq!(cache.figures().0, 20 + 40);
        let out = cache.chunks(&keys(2..4)).unwrap();
        assert_eq!((out.len(), offset_in(&run, &out[0])), (1, Some(20)));
        // Half new again (7..11 of 8): kept whole.
        let (big, lens) = run_of(0, 8, 10);
        cache.insert_run(&big, &keys([0, 1, 2, 3, 7, 8, 9, 10]), &lens);
        let seven = cache.chunks(&keys([7])).unwrap();
        assert_eq!(
            offset_in(&big, &seven[0]),
            Some(40),
            "4 of 8 new: kept whole"
        );
        assert_eq!(cache.figures().0, 60 + 80);
        let (mostly, lens) = run_of(0, 4, 10);
        cache.insert_run(&mostly, &keys([0, 1, 2, 11]), &lens);
        let eleven = cache.chunks(&keys([11])).unwrap();
        assert_eq!(offset_in(&mostly, &eleven[0]), None, "1 of 4 new: copied");
        assert_eq!(&eleven[0][..], &[3u8; 10]);
        assert_eq!(cache.figures().0, 60 + 80 + 10);
        // Evicted oldest first, a run's messages one after the other: the run's whole length
        // leaves with its last message, and the count never exceeds the capacity.
        for t in 100..200u32 {
            let (r, lens) = run_of(t as u8, 3, 10);
            cache.insert_run(&r, &keys([3 * t, 3 * t + 1, 3 * t + 2]), &lens);
            let (bytes, ..) = cache.figures();
            assert!(bytes <= 1000, "{bytes} bytes held");
            let inner = cache.lock();
            let counted: usize = inner.map.values().map(|h| h.charge).sum();
            assert_eq!(counted, bytes);
            // Every run the cache holds a message of is counted in full.
            let mut runs: Vec<(usize, usize)> = inner
                .map
                .values()
                .map(|h| (h.run.as_ptr() as usize, h.run.len()))
                .collect();
            runs.sort_unstable();
            runs.dedup();
            assert_eq!(runs.iter().map(|r| r.1).sum::<usize>(), bytes);
        }
        // A key twice in one run: kept once, and still counted exactly once evicted.
        let (twice, lens) = run_of(0, 2, 10);
        cache.insert_run(&twice, &keys([5000, 5000]), &lens);
        assert_eq!(&cache.chunks(&keys([5000])).unwrap()[0][..], &[0u8; 10]);
        for t in 6000..6100u32 {
            cache.insert(key(1, t, 1), Bytes::from(vec![0; 30]));
        }
        let inner = cache.lock();
        assert_eq!(
            inner.map.values().map(|h| h.charge).sum::<usize>(),
            inner.bytes
        );
        assert_eq!(inner.map.len(), inner.order.len());
        drop(inner);
        // A run larger than an eighth of the cache is kept message by message.
        let (large, lens) = run_of(0, 13, 10);
        cache.insert_run(&large, &keys(1000..1013), &lens);
        let out = cache.chunks(&keys(1000..1013)).unwrap();
        assert_eq!(
            out.len(),
            1,
            "13 messages of their own are more than 4 stretches"
        );
        assert_eq!(offset_in(&large, &out[0]), None);
        assert_eq!(out[0], large);
    }
}
