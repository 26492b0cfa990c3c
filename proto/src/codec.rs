//! Binary encoding of treelets and attribute blocks, and their zstd compression.
//!
//! Treelet encoding (little endian): a 36-byte header followed by the `used_nodes` node
//! records; the zero records after them are not stored. Attribute blocks are the raw
//! `used_nodes × channel size` bytes. Both are compressed with zstd, optionally with a per-scene
//! trained dictionary (one per stream: nodes and each channel), and stored and sent compressed.
//! Decoders check lengths against [`crate::limits`] before allocating and validate the tree.

use std::cell::RefCell;

use zstd::zstd_safe::DCtx;

use crate::attribute::Channel;
use crate::error::ProtoError;
use crate::limits::{MAX_COMPRESSED_BLOCK, MAX_TREELET_BYTES, NODE_BYTES};
use crate::node::Node;
use crate::scene::SceneDescription;
use crate::treelet::{NodePlace, Treelet, TreeletHeader, TreeletId};

/// "ATRL" little endian.
pub const TREELET_MAGIC: u32 = u32::from_le_bytes(*b"ATRL");
/// Version of the treelet encoding.
pub const TREELET_VERSION: u16 = 1;
/// Encoded header size.
pub const HEADER_BYTES: usize = 36;
/// Largest raw (uncompressed) treelet encoding.
pub const MAX_RAW_TREELET: usize = HEADER_BYTES + MAX_TREELET_BYTES as usize;

/// Encodes a treelet without compression.
pub fn encode_treelet(t: &Treelet) -> Vec<u8> {
    let h = &t.header;
    let mut out = Vec::with_capacity(HEADER_BYTES + t.used().len() * NODE_BYTES as usize);
    out.extend_from_slice(&TREELET_MAGIC.to_le_bytes());
    out.extend_from_slice(&TREELET_VERSION.to_le_bytes());
    out.extend_from_slice(&(t.capacity() as u16).to_le_bytes());
    out.extend_from_slice(&h.id.0.to_le_bytes());
    out.extend_from_slice(&h.parent_id.0.to_le_bytes());
    out.extend_from_slice(&h.parent_leaf_index.to_le_bytes());
    out.extend_from_slice(&h.parent_leaf_parent_index.to_le_bytes());
    out.push(h.child_index_in_parent);
    out.push(h.root_depth);
    out.extend_from_slice(&h.used_nodes.to_le_bytes());
    for c in h.root_cell {
        out.extend_from_slice(&c.to_le_bytes());
    }
    debug_assert_eq!(out.len(), HEADER_BYTES);
    for n in t.used() {
        out.extend_from_slice(&n.first_child.to_le_bytes());
        out.push(n.valid_mask);
        out.push(n.leaf_mask);
        out.extend_from_slice(&n.spare.to_le_bytes());
    }
    out
}

struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take<const K: usize>(&mut self) -> [u8; K] {
        let mut a = [0u8; K];
        a.copy_from_slice(&self.b[self.at..self.at + K]);
        self.at += K;
        a
    }
    fn u8(&mut self) -> u8 {
        self.take::<1>()[0]
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
}

/// Decodes the header only (cheap; used by the pool and the network to route a treelet).
pub fn decode_header(bytes: &[u8]) -> Result<(TreeletHeader, u32), ProtoError> {
    if bytes.len() < HEADER_BYTES {
        return Err(ProtoError::Truncated {
            what: "treelet header",
            need: HEADER_BYTES,
            have: bytes.len(),
        });
    }
    let mut r = Reader { b: bytes, at: 0 };
    let magic = r.u32();
    if magic != TREELET_MAGIC {
        return Err(ProtoError::BadMagic {
            what: "treelet",
            found: magic,
        });
    }
    let version = r.u16();
    if version != TREELET_VERSION {
        return Err(ProtoError::UnsupportedVersion {
            what: "treelet",
            found: version,
        });
    }
    let capacity = u32::from(r.u16());
    crate::treelet::nodes_for_bytes(capacity * NODE_BYTES)?;
    let header = TreeletHeader {
        id: TreeletId(r.u32()),
        parent_id: TreeletId(r.u32()),
        parent_leaf_index: r.u16(),
        parent_leaf_parent_index: r.u16(),
        child_index_in_parent: r.u8(),
        root_depth: r.u8(),
        used_nodes: r.u16(),
        root_cell: [r.u32(), r.u32(), r.u32()],
    };
    if header.child_index_in_parent > 7 {
        return Err(ProtoError::OutOfRange {
            what: "treelet header",
            detail: format!("child index {} > 7", header.child_index_in_parent),
        });
    }
    if header.id.is_none() {
        return Err(ProtoError::OutOfRange {
            what: "treelet header",
            detail: "id is NONE".into(),
        });
    }
    if header.used_nodes == 0 || u32::from(header.used_nodes) > capacity {
        return Err(ProtoError::OutOfRange {
            what: "treelet header",
            detail: format!("used_nodes {} not in 1..={capacity}", header.used_nodes),
        });
    }
    if !header.root_cell().is_valid() {
        return Err(ProtoError::OutOfRange {
            what: "treelet header",
            detail: format!("root cell {:?} outside its depth", header.root_cell()),
        });
    }
    Ok((header, capacity))
}

/// The used-node count of a compressed node block, read from its zstd frame header without
/// decompressing: a treelet's raw encoding is exactly [`HEADER_BYTES`] and `used_nodes` records
/// of [`NODE_BYTES`] ([`decode_treelet`] accepts no other length), and the compressors here
/// record the raw length in the frame. `None` when the frame does not record it, or records a
/// length no treelet encoding has; then only decompressing ([`decode_header`]) tells.
///
/// Nothing else is checked: a block stored under another treelet's id, or with damaged records,
/// is found by whoever decodes it (a client decodes every block it receives).
pub fn used_nodes_of_block(block: &[u8]) -> Option<u16> {
    let raw = zstd::zstd_safe::get_frame_content_size(block).ok()??;
    if raw > MAX_RAW_TREELET as u64 {
        return None;
    }
    let records = raw.checked_sub(HEADER_BYTES as u64)?;
    if records == 0 || records % u64::from(NODE_BYTES) != 0 {
        return None;
    }
    u16::try_from(records / u64::from(NODE_BYTES)).ok()
}

/// Decodes and validates an uncompressed treelet. `max_depth` is the scene's target depth.
pub fn decode_treelet(bytes: &[u8], max_depth: u8) -> Result<Treelet, ProtoError> {
    decode_treelet_with_places(bytes, max_depth).map(|(t, _)| t)
}

/// The node records of an encoded treelet's body (what follows the header), unvalidated: for
/// callers that wrote the bytes themselves; [`decode_treelet`] checks them.
pub fn node_records(body: &[u8]) -> impl Iterator<Item = Node> + '_ {
    // Fixed offsets, no reader: this runs for every node of every treelet a build stores.
    body.chunks_exact(NODE_BYTES as usize).map(|r| Node {
        first_child: u32::from_le_bytes([r[0], r[1], r[2], r[3]]),
        valid_mask: r[4],
        leaf_mask: r[5],
        spare: u16::from_le_bytes([r[6], r[7]]),
    })
}

/// [`decode_treelet`], also returning every node's place, found by the validation walk (so
/// callers that need cells or leafness do not walk the tree a second time).
pub fn decode_treelet_with_places(
    bytes: &[u8],
    max_depth: u8,
) -> Result<(Treelet, Vec<NodePlace>), ProtoError> {
    let (header, capacity) = decode_header(bytes)?;
    let need = HEADER_BYTES + usize::from(header.used_nodes) * NODE_BYTES as usize;
    if bytes.len() != need {
        return Err(if bytes.len() < need {
            ProtoError::Truncated {
                what: "treelet nodes",
                need,
                have: bytes.len(),
            }
        } else {
            ProtoError::TooLarge {
                what: "treelet nodes",
                len: bytes.len(),
                limit: need,
            }
        });
    }
    let mut nodes = vec![Node::default(); capacity as usize];
    for (n, record) in nodes.iter_mut().zip(node_records(&bytes[HEADER_BYTES..])) {
        *n = record;
    }
    let t = Treelet { header, nodes };
    let places = t.validate(max_depth)?;
    Ok((t, places))
}

/// Compresses `raw` with zstd at `level`, with an optional dictionary.
pub fn compress(raw: &[u8], level: i32, dictionary: Option<&[u8]>) -> Result<Vec<u8>, ProtoError> {
    let mut c = match dictionary {
        Some(d) => zstd::bulk::Compressor::with_dictionary(level, d),
        None => zstd::bulk::Compressor::new(level),
    }
    .map_err(|e| ProtoError::Compression {
        what: "compress",
        detail: e.to_string(),
    })?;
    c.compress(raw).map_err(|e| ProtoError::Compression {
        what: "compress",
        detail: e.to_string(),
    })
}

/// A reusable compressor for many blocks of one stream (loading a dictionary is not free).
pub struct BlockCompressor {
    inner: zstd::bulk::Compressor<'static>,
}

impl std::fmt::Debug for BlockCompressor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("BlockCompressor")
    }
}

impl BlockCompressor {
    /// A compressor at zstd `level`, with `dictionary` if given.
    pub fn new(level: i32, dictionary: Option<&[u8]>) -> Result<Self, ProtoError> {
        let inner = match dictionary {
            Some(d) => zstd::bulk::Compressor::with_dictionary(level, d),
            None => zstd::bulk::Compressor::new(level),
        }
        .map_err(|e| ProtoError::Compression {
            what: "compressor",
            detail: e.to_string(),
        })?;
        Ok(Self { inner })
    }

    /// Compresses one block.
    pub fn compress(&mut self, raw: &[u8]) -> Result<Vec<u8>, ProtoError> {
        self.inner
            .compress(raw)
            .map_err(|e| ProtoError::Compression {
                what: "compress",
                detail: e.to_string(),
            })
    }
}

thread_local! {
    /// One decompression context per thread, reused: creating one (zstd allocates and clears
    /// its tables) cost more than decompressing a 4 KiB treelet (measured: `ZSTD_createDCtx` was
    /// the largest zstd item in a client's and a server's profile).
    static DECOMPRESSION: RefCell<Option<DCtx<'static>>> = const { RefCell::new(None) };
}

/// Decompresses `bytes` (at most [`MAX_COMPRESSED_BLOCK`]) into at most `max_len` bytes with
/// this thread's decompression context (a fresh one if the thread's is in use) and `run`.
fn decompress_with(
    bytes: &[u8],
    max_len: usize,
    run: impl FnOnce(&mut DCtx<'static>, &mut Vec<u8>) -> Result<usize, usize>,
) -> Result<Vec<u8>, ProtoError> {
    if bytes.len() > MAX_COMPRESSED_BLOCK {
        return Err(ProtoError::TooLarge {
            what: "compressed block",
            len: bytes.len(),
            limit: MAX_COMPRESSED_BLOCK,
        });
    }
    let fresh = || {
        DCtx::try_create().ok_or_else(|| ProtoError::Compression {
            what: "decompress",
            detail: "no memory for a decompression context".into(),
        })
    };
    let mut out = Vec::with_capacity(max_len);
    let done = DECOMPRESSION.with(|cell| match cell.try_borrow_mut() {
        Ok(mut slot) => {
            let dctx = match slot.as_mut() {
                Some(d) => d,
                None => slot.insert(fresh()?),
            };
            Ok(run(dctx, &mut out))
        }
        Err(_) => Ok(run(&mut fresh()?, &mut out)),
    })?;
    done.map(|_| out).map_err(|code| ProtoError::Compression {
        what: "decompress",
        detail: zstd::zstd_safe::get_error_name(code).to_owned(),
    })
}

/// A zstd dictionary as a decompression takes it.
#[derive(Clone, Copy)]
pub enum Dictionary<'a> {
    /// As stored: zstd loads it on every call, which costs more than decompressing a small
    /// block (a lion-4k node block: 5.8 µs with its 16 KiB dictionary raw, 1.5 µs prepared).
    Raw(&'a [u8]),
    /// Loaded once ([`PreparedDictionaries`]).
    Prepared(&'a zstd::dict::DecoderDictionary<'static>),
}

impl std::fmt::Debug for Dictionary<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Dictionary::Raw(d) => write!(f, "Raw({} bytes)", d.len()),
            Dictionary::Prepared(_) => f.write_str("Prepared"),
        }
    }
}

/// A scene's zstd dictionaries, loaded once for the many blocks a reader decompresses.
pub struct PreparedDictionaries {
    nodes: Option<HeldDictionary>,
    /// Per channel of the scene's layout, in layout order.
    channels: Vec<(Channel, Option<HeldDictionary>)>,
}

/// One dictionary as [`PreparedDictionaries`] holds it.
enum HeldDictionary {
    Loaded(zstd::dict::DecoderDictionary<'static>),
    /// zstd refused to load it (a damaged or hostile description): kept raw, so that every
    /// block needing it fails to decompress with zstd's error, as it does unprepared — never a
    /// panic and never a refusal of the blocks that do not need it.
    Unloadable(Vec<u8>),
}

impl HeldDictionary {
    fn of(raw: &[u8]) -> HeldDictionary {
        zstd::dict::DecoderDictionary::try_copy(raw).map_or_else(
            |_| HeldDictionary::Unloadable(raw.to_vec()),
            HeldDictionary::Loaded,
        )
    }

    fn get(&self) -> Dictionary<'_> {
        match self {
            HeldDictionary::Loaded(d) => Dictionary::Prepared(d),
            HeldDictionary::Unloadable(raw) => Dictionary::Raw(raw),
        }
    }
}

impl PreparedDictionaries {
    /// The dictionaries of `scene`.
    pub fn of(scene: &SceneDescription) -> PreparedDictionaries {
        let prepare = |d: &Option<Vec<u8>>| d.as_deref().map(HeldDictionary::of);
        PreparedDictionaries {
            nodes: prepare(&scene.node_dictionary),
            channels: scene
                .layout
                .channels()
                .iter()
                .zip(&scene.channel_dictionaries)
                .map(|(&c, d)| (c, prepare(d)))
                .collect(),
        }
    }

    /// The node stream's dictionary, if the scene has one.
    pub fn nodes(&self) -> Option<Dictionary<'_>> {
        self.nodes.as_ref().map(HeldDictionary::get)
    }

    /// `channel`'s dictionary, if the scene has one.
    pub fn channel(&self, channel: Channel) -> Option<Dictionary<'_>> {
        self.channels
            .iter()
            .find(|(c, _)| *c == channel)
            .and_then(|(_, d)| d.as_ref())
            .map(HeldDictionary::get)
    }
}

impl std::fmt::Debug for PreparedDictionaries {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let state = |d: &Option<HeldDictionary>| match d {
            None => "none",
            Some(HeldDictionary::Loaded(_)) => "loaded",
            Some(HeldDictionary::Unloadable(_)) => "unloadable",
        };
        f.debug_struct("PreparedDictionaries")
            .field("nodes", &state(&self.nodes))
            .field(
                "channels",
                &self
                    .channels
                    .iter()
                    .map(|(c, d)| (*c, state(d)))
                    .collect::<Vec<_>>(),
            )
            .finish()
    }
}

/// Where a reader of a scene's blocks takes its dictionaries from.
#[derive(Clone, Copy, Debug)]
pub enum SceneDictionaries<'a> {
    /// The description's raw bytes (loaded by zstd on every block: for a few blocks).
    Raw(&'a SceneDescription),
    /// Loaded once.
    Prepared(&'a PreparedDictionaries),
}

impl<'a> SceneDictionaries<'a> {
    /// The node stream's dictionary, if the scene has one.
    pub fn nodes(self) -> Option<Dictionary<'a>> {
        match self {
            SceneDictionaries::Raw(scene) => scene.node_dictionary.as_deref().map(Dictionary::Raw),
            SceneDictionaries::Prepared(p) => p.nodes(),
        }
    }

    /// `channel`'s dictionary, if the scene has one.
    pub fn channel(self, channel: Channel) -> Option<Dictionary<'a>> {
        match self {
            SceneDictionaries::Raw(scene) => scene.channel_dictionary(channel).map(Dictionary::Raw),
            SceneDictionaries::Prepared(p) => p.channel(channel),
        }
    }
}

/// Decompresses a block, refusing inputs or outputs larger than `max_len` bytes.
pub fn decompress(
    bytes: &[u8],
    max_len: usize,
    dictionary: Option<&[u8]>,
) -> Result<Vec<u8>, ProtoError> {
    decompress_using(bytes, max_len, dictionary.map(Dictionary::Raw))
}

/// [`decompress`] with a dictionary in either form: a reader of many blocks of one scene
/// prepares it once ([`PreparedDictionaries`]).
pub fn decompress_using(
    bytes: &[u8],
    max_len: usize,
    dictionary: Option<Dictionary<'_>>,
) -> Result<Vec<u8>, ProtoError> {
    decompress_with(bytes, max_len, |dctx, out| match dictionary {
        Some(Dictionary::Raw(dict)) => dctx.decompress_using_dict(out, bytes, dict),
        Some(Dictionary::Prepared(dict)) => {
            dctx.decompress_using_ddict(out, bytes, dict.as_ddict())
        }
        None => dctx.decompress(out, bytes),
    })
}

/// Decompresses and decodes a stored treelet.
pub fn decode_compressed_treelet(
    bytes: &[u8],
    max_depth: u8,
    dictionary: Option<&[u8]>,
) -> Result<Treelet, ProtoError> {
    decode_compressed_treelet_using(bytes, max_depth, dictionary.map(Dictionary::Raw))
}

/// [`decode_compressed_treelet`] with a dictionary in either form.
pub fn decode_compressed_treelet_using(
    bytes: &[u8],
    max_depth: u8,
    dictionary: Option<Dictionary<'_>>,
) -> Result<Treelet, ProtoError> {
    decode_compressed_treelet_with_places_using(bytes, max_depth, dictionary).map(|(t, _)| t)
}

/// [`decode_compressed_treelet`], also returning every node's place.
pub fn decode_compressed_treelet_with_places(
    bytes: &[u8],
    max_depth: u8,
    dictionary: Option<&[u8]>,
) -> Result<(Treelet, Vec<NodePlace>), ProtoError> {
    decode_compressed_treelet_with_places_using(bytes, max_depth, dictionary.map(Dictionary::Raw))
}

/// [`decode_compressed_treelet_with_places`] with a dictionary in either form.
pub fn decode_compressed_treelet_with_places_using(
    bytes: &[u8],
    max_depth: u8,
    dictionary: Option<Dictionary<'_>>,
) -> Result<(Treelet, Vec<NodePlace>), ProtoError> {
    let raw = decompress_using(bytes, MAX_RAW_TREELET, dictionary)?;
    decode_treelet_with_places(&raw, max_depth)
}

/// Decompresses an attribute block of `channel` for a treelet with `used_nodes` records and
/// checks its length exactly.
pub fn decode_compressed_attributes(
    bytes: &[u8],
    channel: Channel,
    used_nodes: u16,
    dictionary: Option<&[u8]>,
) -> Result<Vec<u8>, ProtoError> {
    decode_compressed_attributes_using(bytes, channel, used_nodes, dictionary.map(Dictionary::Raw))
}

/// [`decode_compressed_attributes`] with a dictionary in either form.
pub fn decode_compressed_attributes_using(
    bytes: &[u8],
    channel: Channel,
    used_nodes: u16,
    dictionary: Option<Dictionary<'_>>,
) -> Result<Vec<u8>, ProtoError> {
    let need = usize::from(used_nodes) * channel.size();
    let raw = decompress_using(bytes, need, dictionary)?;
    if raw.len() != need {
        return Err(ProtoError::Truncated {
            what: "attribute block",
            need,
            have: raw.len(),
        });
    }
    Ok(raw)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cell::Cell;
    use proptest::prelude::*;

    #[test]
    fn a_dictionary_zstd_cannot_load_fails_its_blocks_not_the_reader() {
        // A zstd dictionary's magic number, then entropy tables that do not parse: zstd refuses
        // to load it (the raw `DecoderDictionary::copy` would panic).
        let mut bad = vec![0x37, 0xa4, 0x30, 0xec, 1, 0, 0, 0];
        bad.extend([0xff; 256]);
        assert!(zstd::dict::DecoderDictionary::try_copy(&bad).is_err());
        let scene = SceneDescription {
            node_dictionary: Some(bad.clone()),
            ..crate::scene::tests::sample()
        };
        let prepared = PreparedDictionaries::of(&scene);
        assert!(
            format!("{prepared:?}").contains("unloadable"),
            "{prepared:?}"
        );
        let samples: Vec<Vec<u8>> = (0..64u8).map(|i| vec![i; 300]).collect();
        let good = zstd::dict::from_samples(&samples, 2048).unwrap();
        let block = compress(&samples[3], 3, Some(&good)).unwrap();
        for dictionary in [
            prepared.nodes(),
            SceneDictionaries::Prepared(&prepared).nodes(),
        ] {
            let err = decompress_using(&block, 512, dictionary).unwrap_err();
            assert!(err.to_string().contains("decompress"), "{err}");
        }
        // Blocks compressed without a dictionary still decompress.
        let plain = compress(&samples[5], 3, None).unwrap();
        assert_eq!(decompress_using(&plain, 512, None).unwrap(), samples[5]);
    }

    #[test]
    fn the_reused_decompression_context_keeps_dictionaries_apart_and_survives_errors() {
        // Two dictionaries trained on different data; blocks compressed with each.
        let samples = |seed: u8| -> Vec<Vec<u8>> {
            (0..64u32)
                .map(|i| {
                    (0..512u32)
                        .map(|j| ((i * 7 + j * 13) as u8) ^ seed)
                        .collect()
                })
                .collect()
        };
        let (a, b) = (samples(0x11), samples(0xa5));
        let dict_a = zstd::dict::from_samples(&a, 4096).unwrap();
        let dict_b = zstd::dict::from_samples(&b, 4096).unwrap();
        let block_a = compress(&a[3], 3, Some(&dict_a)).unwrap();
        let block_b = compress(&b[5], 3, Some(&dict_b)).unwrap();
        let plain = compress(&a[7], 3, None).unwrap();
        let prepared_b = zstd::dict::DecoderDictionary::copy(&dict_b);
        for _ in 0..2 {
            assert_eq!(decompress(&block_a, 512, Some(&dict_a)).unwrap(), a[3]);
            assert_eq!(decompress(&plain, 512, None).unwrap(), a[7]);
            assert_eq!(
                decompress_using(&block_b, 512, Some(Dictionary::Prepared(&prepared_b))).unwrap(),
                b[5]
            );
            assert_eq!(decompress(&block_b, 512, Some(&dict_b)).unwrap(), b[5]);
            // The wrong dictionary, a short output and garbage fail with a clear error, and the
            // next block decompresses as if nothing happened.
            assert!(decompress(&block_a, 512, Some(&dict_b)).is_err());
            let short = decompress(&block_a, 100, Some(&dict_a)).unwrap_err();
            assert!(short.to_string().contains("decompress"), "{short}");
            assert!(decompress(&[0x28, 0xb5, 0x2f, 0xfd, 1, 2, 3], 512, None).is_err());
        }
        // Other threads have contexts of their own.
        let (block_a, dict_a, want) = (block_a.clone(), dict_a.clone(), a[3].clone());
        std::thread::spawn(move || {
            assert_eq!(decompress(&block_a, 512, Some(&dict_a)).unwrap(), want);
        })
        .join()
        .unwrap();
    }

    /// A root with children 0 and 5; child 5 has children 1 and 7 (leaves); child 0 is a
    /// refinable leaf pointing at treelet 9.
    pub(crate) fn sample() -> Treelet {
        let mut nodes = vec![Node::default(); 128];
        nodes[0] = Node {
            first_child: 1,
            valid_mask: 0b0010_0001,
            leaf_mask: 0b0000_0001,
            spare: 0,
        };
        nodes[1] = Node::leaf(9);
        nodes[2] = Node {
            first_child: 1,
            valid_mask: 0b1000_0010,
            leaf_mask: 0b1000_0010,
            spare: 0,
        };
        nodes[3] = Node::leaf(Node::NONE);
        nodes[4] = Node::leaf(Node::NONE);
        Treelet {
            header: TreeletHeader {
                id: TreeletId(3),
                parent_id: TreeletId(1),
                parent_leaf_index: 17,
                parent_leaf_parent_index: 4,
                child_index_in_parent: 6,
                root_depth: 5,
                root_cell: [3, 31, 0],
                used_nodes: 5,
            },
            nodes,
        }
    }

    #[test]
    fn treelet_round_trip() {
        let t = sample();
        let places = t.validate(7).unwrap();
        assert_eq!(
            places[4].cell,
            Cell {
                depth: 7,
                x: 15,
                y: 125,
                z: 3
            }
        );
        let raw = encode_treelet(&t);
        assert_eq!(raw.len(), HEADER_BYTES + 5 * 8);
        assert_eq!(decode_treelet(&raw, 7).unwrap(), t);
        assert_eq!(
            decode_treelet_with_places(&raw, 7).unwrap(),
            (t.clone(), places)
        );
        let packed = compress(&raw, 3, None).unwrap();
        assert_eq!(decode_compressed_treelet(&packed, 7, None).unwrap(), t);
    }

    #[test]
    fn the_used_node_count_is_read_from_the_frame_header_and_only_a_treelet_length_counts() {
        let t = sample();
        let raw = encode_treelet(&t);
        let samples: Vec<Vec<u8>> = (0..64u8).map(|i| vec![i; 300]).collect();
        let dictionary = zstd::dict::from_samples(&samples, 2048).unwrap();
        for block in [
            compress(&raw, 3, None).unwrap(),
            compress(&raw, 19, Some(&dictionary)).unwrap(),
            BlockCompressor::new(1, None)
                .unwrap()
                .compress(&raw)
                .unwrap(),
        ] {
            assert_eq!(used_nodes_of_block(&block), Some(t.header.used_nodes));
        }
        // A frame that does not record its length (a streaming encoder without a pledged
        // size): only decompressing tells.
        let mut unsized_frame = zstd::stream::Encoder::new(Vec::new(), 3).unwrap();
        unsized_frame.include_contentsize(false).unwrap();
        std::io::Write::write_all(&mut unsized_frame, &raw).unwrap();
        let unsized_frame = unsized_frame.finish().unwrap();
        assert_eq!(
            decompress(&unsized_frame, MAX_RAW_TREELET, None).unwrap(),
            raw
        );
        assert_eq!(used_nodes_of_block(&unsized_frame), None);
        // Lengths no treelet encoding has: short of a header, a header alone, a partial
        // record, beyond the largest treelet.
        for len in [
            0,
            HEADER_BYTES - 1,
            HEADER_BYTES,
            HEADER_BYTES + 9,
            MAX_RAW_TREELET + NODE_BYTES as usize,
        ] {
            let block = compress(&vec![7u8; len], 3, None).unwrap();
            assert_eq!(used_nodes_of_block(&block), None, "raw length {len}");
        }
        let largest = compress(&vec![7u8; MAX_RAW_TREELET], 3, None).unwrap();
        assert_eq!(
            used_nodes_of_block(&largest).map(usize::from),
            Some(MAX_TREELET_BYTES as usize / NODE_BYTES as usize)
        );
        // Not a zstd frame at all.
        assert_eq!(used_nodes_of_block(b"not a frame"), None);
        assert_eq!(used_nodes_of_block(&[]), None);
    }

    #[test]
    fn treelet_deeper_than_scene_is_rejected() {
        let raw = encode_treelet(&sample());
        assert!(matches!(
            decode_treelet(&raw, 6),
            Err(ProtoError::MalformedTreelet { .. })
        ));
    }

    #[test]
    fn malformed_offsets_are_rejected() {
        let mut t = sample();
        t.nodes[2].first_child = 40;
        let err = decode_treelet(&encode_treelet(&t), 7).unwrap_err();
        assert!(err.to_string().contains("children at"), "{err}");
        let mut t = sample();
        t.nodes[0].leaf_mask = 0b0100_0000;
        assert!(decode_treelet(&encode_treelet(&t), 7).is_err());
        let mut t = sample();
        t.nodes[0].first_child = u32::MAX;
        assert!(decode_treelet(&encode_treelet(&t), 7).is_err());
    }

    #[test]
    fn dictionary_round_trip() {
        let raw = encode_treelet(&sample());
        let samples: Vec<Vec<u8>> = (0..200u32)
            .map(|i| {
                let mut t = sample();
                t.header.id = TreeletId(i + 1);
                encode_treelet(&t)
            })
            .collect();
        let dict = zstd::dict::from_samples(&samples, 4096).unwrap();
        let packed = compress(&raw, 3, Some(&dict)).unwrap();
        assert_eq!(
            decode_compressed_treelet(&packed, 7, Some(&dict)).unwrap(),
            sample()
        );
        assert!(decode_compressed_treelet(&packed, 7, None).is_err());
    }

    #[test]
    fn attribute_block_length_is_exact() {
        let raw = vec![7u8; 5 * 3];
        let packed = compress(&raw, 3, None).unwrap();
        assert_eq!(
            decode_compressed_attributes(&packed, Channel::Color, 5, None).unwrap(),
            raw
        );
        assert!(decode_compressed_attributes(&packed, Channel::Color, 6, None).is_err());
        assert!(decode_compressed_attributes(&packed, Channel::Color, 4, None).is_err());
    }

    proptest! {
        #[test]
        fn hostile_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
            let _ = decode_treelet(&bytes, 31);
            let _ = decode_compressed_treelet(&bytes, 31, None);
            let _ = decode_compressed_attributes(&bytes, Channel::Normal, 100, None);
        }

        #[test]
        fn mutated_treelets_never_panic(pos in 0usize..76, val in any::<u8>()) {
            let mut raw = encode_treelet(&sample());
            raw[pos] = val;
            let _ = decode_treelet(&raw, 31);
        }
    }
}
