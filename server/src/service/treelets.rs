//! Treelet messages as the service sends them: the stored blocks, unchanged, behind
//! [`arbor_proto::frame::encode_treelet_header`].
//!
//! The header needs `used_nodes`, which the pool does not store next to the block. Decision: it
//! is read from the node block itself (decompressed with the scene's prepared dictionary, header
//! decoded) the first time a treelet is sent and kept in a small direct-mapped cache per scene
//! (at most 65,536 entries of 8 bytes, lock-free), so a treelet sent again — to another client, or
//! after an eviction — costs no decompression. Measured on the bunny at 1 KiB the first
//! decompression costs a few microseconds; nothing is ever recompressed.

use std::sync::atomic::{AtomicU64, Ordering};

use arbor_proto::codec::{self, MAX_RAW_TREELET};
use arbor_proto::frame::{FrameError, encode_treelet_header};
use arbor_proto::{Channel, ProtoError, TreeletId};

use super::push::TreeIndex;
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

const CACHE_MAX: usize = 1 << 16;

/// A scene opened for serving.
pub struct ServedScene {
    pub stored: StoredScene,
    dictionary: Option<zstd::dict::DecoderDictionary<'static>>,
    /// Direct-mapped `used_nodes` cache: entry = `(id + 1) << 16 | used_nodes`, 0 = empty.
    used: Vec<AtomicU64>,
    /// Treelet shapes for deep-request pushes.
    pub tree: TreeIndex,
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
    pub fn new(stored: StoredScene) -> ServedScene {
        let dictionary = stored
            .description
            .node_dictionary
            .as_deref()
            .map(zstd::dict::DecoderDictionary::copy);
        let n = (stored.description.treelet_count as usize)
            .clamp(1, CACHE_MAX)
            .next_power_of_two();
        ServedScene {
            stored,
            dictionary,
            used: (0..n).map(|_| AtomicU64::new(0)).collect(),
            tree: TreeIndex::default(),
        }
    }

    pub fn treelet_count(&self) -> u32 {
        self.stored.description.treelet_count
    }

    /// `used_nodes` of a treelet, from the cache or its node block.
    fn used_nodes(&self, id: TreeletId, nodes: &[u8]) -> Result<u16, MessageError> {
        let slot = &self.used[id.0 as usize & (self.used.len() - 1)];
        let tag = (u64::from(id.0) + 1) << 16;
        let e = slot.load(Ordering::Relaxed);
        if e & !0xffff == tag {
            return Ok((e & 0xffff) as u16);
        }
        let corrupt = |source| MessageError::Corrupt { id: id.0, source };
        let mut d = match &self.dictionary {
            Some(dict) => zstd::bulk::Decompressor::with_prepared_dictionary(dict),
            None => zstd::bulk::Decompressor::new(),
        }
        .map_err(|e| {
            corrupt(ProtoError::Compression {
                what: "decompress",
                detail: e.to_string(),
            })
        })?;
        let raw = d.decompress(nodes, MAX_RAW_TREELET).map_err(|e| {
            corrupt(ProtoError::Compression {
                what: "decompress",
                detail: e.to_string(),
            })
        })?;
        let (header, _) = codec::decode_header(&raw).map_err(corrupt)?;
        if header.id != id {
            return Err(corrupt(ProtoError::OutOfRange {
                what: "treelet header",
                detail: format!("stored under id {} but says {}", id.0, header.id.0),
            }));
        }
        slot.store(tag | u64::from(header.used_nodes), Ordering::Relaxed);
        Ok(header.used_nodes)
    }

    /// The whole treelet message for `id` with `channels` (ascending by channel id, each stored
    /// by the scene): header + node block + channel blocks, byte for byte as stored.
    pub fn message(&self, id: TreeletId, channels: &[Channel]) -> Result<Vec<u8>, MessageError> {
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
