//! Treelet messages as the service sends them: the stored blocks, unchanged, behind
//! [`arbor_proto::frame::encode_treelet_header`].
//!
//! The header needs `used_nodes`, which the pool does not store next to the block: it is read
//! from the node block itself (decompressed with the scene's prepared dictionary, header
//! decoded) when the message is built. Built messages are kept in a [`MessageCache`] bounded in
//! bytes (server-wide, `message_cache_bytes`), so a treelet sent again — to another client, or
//! after an eviction — costs no pool read and no decompression: a stream's batch is one copy of
//! the cached bytes, copied out under the cache's lock (see [`ServedScene::batch`]), never
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
#[derive(Debug)]
pub struct MessageCache {
    capacity: usize,
    inner: Mutex<CacheInner>,
}

#[derive(Debug, Default)]
struct CacheInner {
    map: HashMap<MessageKey, Bytes, BuildHasherDefault<RunHasher>>,
    order: VecDeque<MessageKey>,
    bytes: usize,
    hits: u64,
    misses: u64,
}

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
        let found: Vec<Option<Bytes>> = keys.iter().map(|k| inner.map.get(k).cloned()).collect();
        let hits = found.iter().filter(|m| m.is_some()).count() as u64;
        inner.hits += hits;
        inner.misses += found.len() as u64 - hits;
        found
    }

    /// When every one of `keys` is held: their messages back to back, copied out under the one
    /// lock (hits counted); else `None`, nothing counted (the caller then asks [`Self::get`]).
    /// Copying under the lock spares each message a reference-count increment and decrement on
    /// a cache line other threads' batches touch too (`bytes::shared_clone` showed in a
    /// whole-scene profile), and the `Vec` of clones.
    fn joined(&self, keys: &[MessageKey]) -> Option<Bytes> {
        let mut inner = self.lock();
        // One lookup per key (the table is larger than a core's cache): the hits are gathered
        // first, then measured and copied.
        let found: Vec<&Bytes> = keys
            .iter()
            .map(|k| inner.map.get(k))
            .collect::<Option<_>>()?;
        let out = concat(&found);
        inner.hits += keys.len() as u64;
        Some(out)
    }

    fn insert(&self, key: MessageKey, message: Bytes) {
        if message.len() > self.capacity {
            return;
        }
        let mut inner = self.lock();
        if inner.map.contains_key(&key) {
            return;
        }
        while inner.bytes + message.len() > self.capacity {
            let Some(old) = inner.order.pop_front() else {
                break;
            };
            if let Some(b) = inner.map.remove(&old) {
                inner.bytes -= b.len();
            }
        }
        inner.bytes += message.len();
        inner.order.push_back(key);
        inner.map.insert(key, message);
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
        let fetch = |id: TreeletId| {
            let decoded = self
                .cut_nodes
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
                })?;
            Some(DecodedTreelet::clone(&decoded))
        };
        let caster = {
            let mut caster = self.cut_caster.lock().unwrap_or_else(|p| p.into_inner());
            if caster.is_none() {
                let root = fetch(d.root_treelet)?;
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

    pub fn treelet_count(&self) -> u32 {
        self.stored.description.treelet_count
    }

    /// `used_nodes` of a treelet, from its node block.
    fn used_nodes(&self, id: TreeletId, nodes: &[u8]) -> Result<u16, MessageError> {
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
        self.batch(std::slice::from_ref(&id), channels)
    }

    /// The messages of `ids` back to back, as one buffer, as a stream's batch carries them: a
    /// single message as it is (the cached bytes, no copy), several copied together once —
    /// straight out of the cache when it holds them all.
    ///
    /// Why copy: quinn finds the bytes of every STREAM frame it builds by walking the stream's
    /// unacknowledged chunks from the oldest (`SendBuffer::get`), so a stream written as 64
    /// chunks costs a walk over up to 64 for each packet, and more than one for a packet that
    /// spans chunks. On a whole-scene fetch of lion-4k that walk was 3.4 M instructions of 73 M;
    /// copying the batches costs 0.3 M (callgrind, `scripts/serve-instructions`;
    /// docs/measurements.md, stop 31). By time too: the 64 chunks were about 5 % slower per
    /// fetch, and still no faster with that walk replaced by a cursor (stop 35). What is in
    /// flight is then held twice, in the message cache and in the stream's buffer, bounded by
    /// the send window either way.
    pub fn batch(&self, ids: &[TreeletId], channels: &[Channel]) -> Result<Bytes, MessageError> {
        let keys = self.keys(ids, channels);
        if keys.len() > 1
            && let Some(joined) = self.cache.joined(&keys)
        {
            return Ok(joined);
        }
        Ok(joined(self.messages(&keys, ids, channels)?))
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

    /// The message of each of `ids` (with their `keys`), in order: the cache is asked for all of
    /// them under one lock, and what it lacks is built and cached.
    fn messages(
        &self,
        keys: &[MessageKey],
        ids: &[TreeletId],
        channels: &[Channel],
    ) -> Result<Vec<Bytes>, MessageError> {
        let found = self.cache.get(keys);
        keys.iter()
            .zip(ids)
            .zip(found)
            .map(|((&key, &id), hit)| match hit {
                Some(m) => Ok(m),
                None => self.build_and_cache(key, id, channels),
            })
            .collect()
    }

    fn build_and_cache(
        &self,
        key: MessageKey,
        id: TreeletId,
        channels: &[Channel],
    ) -> Result<Bytes, MessageError> {
        let message = Bytes::from(self.build(id, channels)?);
        self.cache.insert(key, message.clone());
        Ok(message)
    }

    fn build(&self, id: TreeletId, channels: &[Channel]) -> Result<Vec<u8>, MessageError> {
        let nodes = self.stored.nodes(id)?.ok_or(MessageError::Missing {
            id: id.0,
            what: "node",
        })?;
        let mut blocks = Vec::with_capacity(channels.len());
        for &c in channels {
            let b = self.stored.channel(c, id)?.ok_or(MessageError::Missing {
                id: id.0,
                what: c.name(),
            })?;
            blocks.push((c, b));
        }
        let used = self.used_nodes(id, &nodes)?;
        let lens: Vec<(Channel, usize)> = blocks.iter().map(|(c, b)| (*c, b.len())).collect();
        let header = encode_treelet_header(id, used, nodes.len(), &lens)
            .map_err(|source| MessageError::Frame { id: id.0, source })?;
        let total = header.len() + nodes.len() + lens.iter().map(|l| l.1).sum::<usize>();
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(&header);
        out.extend_from_slice(&nodes);
        for (_, b) in &blocks {
            out.extend_from_slice(b);
        }
        Ok(out)
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
            cache.joined(&[key(1, 8, 1), key(1, 9, 1)]),
            Some(Bytes::from([vec![8u8; 30], vec![9u8; 30]].concat()))
        );
        assert_eq!(cache.joined(&[key(1, 8, 1), key(1, 6, 1)]), None);
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
}
