//! The scene description: everything a client needs to interpret a scene's treelets.

use serde::{Deserialize, Serialize};

use crate::attribute::{AttributeLayout, Channel};
use crate::error::ProtoError;
use crate::limits::{MAX_DEPTH, MAX_DICTIONARY_BYTES, MAX_SCENE_DESCRIPTION_BYTES, MAX_SCENE_NAME};
use crate::treelet::{TreeletId, nodes_for_bytes};

/// What kind of input a scene was built from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum SourceKind {
    /// Triangles (OBJ, PLY faces or strips).
    Mesh,
    /// A point cloud (LAS/LAZ, PLY vertices).
    Points,
    /// Volume samples with an iso threshold (NRRD, raw).
    Volume,
}

/// How the scene was built.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BuildParameters {
    /// Depth asked for; `None` means `--depth auto`.
    pub requested_depth: Option<u8>,
    /// The data's own resolution in scene units (mean point spacing, mean edge length, voxel
    /// spacing) from which `auto` chose the depth.
    pub data_resolution: f64,
    /// Treelet size in bytes of node records.
    pub treelet_bytes: u32,
    /// Iso threshold for volumes.
    pub iso: Option<f32>,
    /// zstd level the blocks were compressed with.
    pub zstd_level: i32,
    /// Whether per-stream dictionaries were trained.
    pub dictionary: bool,
}

/// Figures measured while building.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneStats {
    /// Node records in use over all treelets (inner and leaf voxels).
    pub voxels: u64,
    /// Voxels at the target depth.
    pub leaf_voxels: u64,
    /// Compressed node bytes over all treelets.
    pub node_bytes: u64,
    /// Compressed attribute bytes per channel, in layout order.
    pub channel_bytes: Vec<u64>,
    /// Uncompressed bytes (nodes + attributes) of the used records.
    pub raw_bytes: u64,
    /// Wall time of the build.
    pub build_seconds: f64,
    /// Bytes of primitive id lists written to the builder's spill file.
    pub spilled_bytes: u64,
    /// Most bytes of primitive id lists the builder held in memory at once (≤ its budget).
    pub peak_list_bytes: u64,
    /// Peak resident set of the importing process (includes mapped source pages).
    pub peak_rss_bytes: u64,
    /// Peak anonymous resident memory of the importing process (what it held itself).
    pub peak_anon_bytes: u64,
}

impl SceneStats {
    /// Compressed bytes of every treelet block stored: nodes and every channel.
    pub fn stored_bytes(&self) -> u64 {
        self.node_bytes + self.channel_bytes.iter().sum::<u64>()
    }
}

/// A scene as stored in the pool and announced to clients.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneDescription {
    /// The scene's name in the pool.
    pub name: String,
    /// Minimum corner of the root cube, in source units (f64: projected coordinates keep mm).
    pub origin: [f64; 3],
    /// Edge length of the root cube.
    pub edge: f64,
    /// Node records per treelet (`N`).
    pub treelet_nodes: u32,
    /// Target depth: no voxel is deeper.
    pub max_depth: u8,
    /// The attribute channels stored.
    pub layout: AttributeLayout,
    /// Treelets of the scene; ids are `0..treelet_count`.
    pub treelet_count: u32,
    /// The root treelet (always [`TreeletId::ROOT`]).
    pub root_treelet: TreeletId,
    /// What the scene was built from.
    pub source_kind: SourceKind,
    /// Source file name and a short description of its contents.
    pub source: String,
    /// Primitives of the source (triangles, points, volume samples).
    pub primitives: u64,
    /// How the scene was built.
    pub build: BuildParameters,
    /// Figures of the build and the stored streams.
    pub stats: SceneStats,
    /// zstd dictionary of the node stream, when trained.
    #[serde(with = "byte_fields::option")]
    pub node_dictionary: Option<Vec<u8>>,
    /// zstd dictionary per channel, in layout order.
    #[serde(with = "byte_fields::option_list")]
    pub channel_dictionaries: Vec<Option<Vec<u8>>>,
}

impl SceneDescription {
    /// Edge length of a voxel at `depth`.
    pub fn voxel_size(&self, depth: u8) -> f64 {
        self.edge / (1u64 << depth) as f64
    }

    /// Dictionary of `channel`, if one was trained.
    pub fn channel_dictionary(&self, channel: Channel) -> Option<&[u8]> {
        let i = self.layout.index_of(channel)?;
        self.channel_dictionaries.get(i)?.as_deref()
    }

    /// Checks every field against the limits.
    pub fn validate(&self) -> Result<(), ProtoError> {
        let bad = |detail: String| ProtoError::OutOfRange {
            what: "scene description",
            detail,
        };
        validate_scene_name(&self.name)?;
        if !(self.edge.is_finite() && self.edge > 0.0 && self.origin.iter().all(|v| v.is_finite()))
        {
            return Err(bad(format!(
                "root cube origin {:?} edge {} not finite and positive",
                self.origin, self.edge
            )));
        }
        nodes_for_bytes(self.treelet_nodes.saturating_mul(8))?;
        if self.max_depth > MAX_DEPTH {
            return Err(bad(format!("depth {} > {MAX_DEPTH}", self.max_depth)));
        }
        self.layout.validate()?;
        if self.channel_dictionaries.len() != self.layout.channels().len() {
            return Err(bad("one dictionary slot per channel required".into()));
        }
        let dicts = self
            .node_dictionary
            .iter()
            .chain(self.channel_dictionaries.iter().flatten());
        for d in dicts {
            if d.len() > MAX_DICTIONARY_BYTES {
                return Err(ProtoError::TooLarge {
                    what: "zstd dictionary",
                    len: d.len(),
                    limit: MAX_DICTIONARY_BYTES,
                });
            }
        }
        if self.treelet_count == 0 || self.root_treelet != TreeletId::ROOT {
            return Err(bad("a scene has at least its root treelet 0".into()));
        }
        Ok(())
    }

    /// The description's bytes (bincode), as stored and as sent in `SceneInfo`.
    pub fn encode(&self) -> Result<Vec<u8>, ProtoError> {
        bincode::serde::encode_to_vec(self, bincode_config()).map_err(|e| {
            ProtoError::Serialization {
                what: "scene description",
                detail: e.to_string(),
            }
        })
    }

    /// Decodes and validates a description; bounded in size before anything is allocated.
    pub fn decode(bytes: &[u8]) -> Result<Self, ProtoError> {
        if bytes.len() > MAX_SCENE_DESCRIPTION_BYTES {
            return Err(ProtoError::TooLarge {
                what: "scene description",
                len: bytes.len(),
                limit: MAX_SCENE_DESCRIPTION_BYTES,
            });
        }
        let (s, used): (Self, usize) = bincode::serde::decode_from_slice(bytes, bincode_config())
            .map_err(|e| ProtoError::Serialization {
            what: "scene description",
            detail: e.to_string(),
        })?;
        if used != bytes.len() {
            return Err(ProtoError::Serialization {
                what: "scene description",
                detail: format!("{} trailing bytes", bytes.len() - used),
            });
        }
        s.validate()?;
        Ok(s)
    }
}

/// The dictionaries as serde byte strings: one bulk copy each way, where serde's `Vec<u8>` is a
/// sequence, one call per byte (lion-4k's description took 0.41 million instructions to decode
/// that way, on the server per connection and again on the client). bincode writes a byte
/// string and a sequence of `u8` alike, its length and the bytes, so the stored and sent
/// descriptions do not change; readers of other formats that give a sequence (JSON) are taken
/// too.
mod byte_fields {
    use serde::de::{Deserializer, SeqAccess, Visitor};
    use serde::{Deserialize, Serialize, Serializer};

    /// Serializes a byte slice as a byte string.
    struct Bytes<'a>(&'a [u8]);

    impl Serialize for Bytes<'_> {
        fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
            s.serialize_bytes(self.0)
        }
    }

    /// Deserializes a byte string (or a sequence of bytes) into a vector.
    struct ByteBuf(Vec<u8>);

    impl<'de> Deserialize<'de> for ByteBuf {
        fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            // Borrowed where the format can (bincode from a slice): only the bytes present are
            // copied, however long a hostile length prefix claims the string is.
            d.deserialize_bytes(ByteBufVisitor).map(ByteBuf)
        }
    }

    struct ByteBufVisitor;

    impl<'de> Visitor<'de> for ByteBufVisitor {
        type Value = Vec<u8>;

        fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str("a byte string")
        }

        fn visit_bytes<E>(self, v: &[u8]) -> Result<Vec<u8>, E> {
            Ok(v.to_vec())
        }

        fn visit_byte_buf<E>(self, v: Vec<u8>) -> Result<Vec<u8>, E> {
            Ok(v)
        }

        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<u8>, A::Error> {
            // A claimed length is not trusted with more than a small start.
            let mut v = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(4096));
            while let Some(b) = seq.next_element()? {
                v.push(b);
            }
            Ok(v)
        }
    }

    /// `Option<Vec<u8>>` as an optional byte string.
    pub(super) mod option {
        use super::*;

        pub(crate) fn serialize<S: Serializer>(
            v: &Option<Vec<u8>>,
            s: S,
        ) -> Result<S::Ok, S::Error> {
            v.as_deref().map(Bytes).serialize(s)
        }

        pub(crate) fn deserialize<'de, D: Deserializer<'de>>(
            d: D,
        ) -> Result<Option<Vec<u8>>, D::Error> {
            Ok(Option::<ByteBuf>::deserialize(d)?.map(|b| b.0))
        }
    }

    /// `Vec<Option<Vec<u8>>>` as a sequence of optional byte strings.
    pub(super) mod option_list {
        use super::*;

        pub(crate) fn serialize<S: Serializer>(
            v: &[Option<Vec<u8>>],
            s: S,
        ) -> Result<S::Ok, S::Error> {
            s.collect_seq(v.iter().map(|o| o.as_deref().map(Bytes)))
        }

        pub(crate) fn deserialize<'de, D: Deserializer<'de>>(
            d: D,
        ) -> Result<Vec<Option<Vec<u8>>>, D::Error> {
            Ok(Vec::<Option<ByteBuf>>::deserialize(d)?
                .into_iter()
                .map(|o| o.map(|b| b.0))
                .collect())
        }
    }
}

fn bincode_config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<MAX_SCENE_DESCRIPTION_BYTES>()
}

/// Scene names: 1..=128 characters of `[A-Za-z0-9._-]`, not starting with '.'.
pub fn validate_scene_name(name: &str) -> Result<(), ProtoError> {
    let ok = !name.is_empty()
        && name.len() <= MAX_SCENE_NAME
        && !name.starts_with('.')
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'));
    if ok {
        Ok(())
    } else {
        Err(ProtoError::OutOfRange {
            what: "scene name",
            detail: format!(
                "{name:?}: use 1..={MAX_SCENE_NAME} characters of A-Z a-z 0-9 . _ -, not starting with '.'"
            ),
        })
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A valid description (the codec's tests borrow it).
    pub(crate) fn sample() -> SceneDescription {
        SceneDescription {
            name: "bunny".into(),
            origin: [512_345.678, 5_012_345.001, -3.5],
            edge: 1234.5,
            treelet_nodes: 512,
            max_depth: 13,
            layout: AttributeLayout::new([Channel::Color, Channel::Normal]),
            treelet_count: 10,
            root_treelet: TreeletId::ROOT,
            source_kind: SourceKind::Points,
            source: "x.las".into(),
            primitives: 100,
            build: BuildParameters {
                requested_depth: None,
                data_resolution: 0.01,
                treelet_bytes: 4096,
                iso: None,
                zstd_level: 9,
                dictionary: true,
            },
            stats: SceneStats::default(),
            node_dictionary: Some(vec![1, 2, 3]),
            channel_dictionaries: vec![None, Some(vec![4])],
        }
    }

    #[test]
    fn round_trip_keeps_f64_exact() {
        let s = sample();
        let d = SceneDescription::decode(&s.encode().unwrap()).unwrap();
        assert_eq!(d, s);
        assert_eq!(d.origin[0], 512_345.678);
        assert_eq!(d.channel_dictionary(Channel::Normal), Some(&[4u8][..]));
    }

    #[test]
    fn invalid_descriptions_are_rejected() {
        let mut s = sample();
        s.edge = f64::NAN;
        assert!(SceneDescription::decode(&s.encode().unwrap()).is_err());
        let mut s = sample();
        s.name = "../etc".into();
        assert!(SceneDescription::decode(&s.encode().unwrap()).is_err());
        let mut s = sample();
        s.max_depth = 40;
        assert!(SceneDescription::decode(&s.encode().unwrap()).is_err());
    }

    /// The description's dictionaries as they were written before they became byte strings.
    #[derive(Serialize, Deserialize, PartialEq, Debug)]
    struct PlainDictionaries {
        node: Option<Vec<u8>>,
        channels: Vec<Option<Vec<u8>>>,
    }

    /// The same fields through [`byte_fields`].
    #[derive(Serialize, Deserialize, PartialEq, Debug)]
    struct ByteDictionaries {
        #[serde(with = "byte_fields::option")]
        node: Option<Vec<u8>>,
        #[serde(with = "byte_fields::option_list")]
        channels: Vec<Option<Vec<u8>>>,
    }

    #[test]
    fn dictionaries_keep_their_bytes_on_disk_and_on_the_wire() {
        let big: Vec<u8> = (0..70_000u32).map(|i| (i * 7 % 251) as u8).collect();
        for (node, channels) in [
            (
                Some(big.clone()),
                vec![None, Some(vec![4, 0, 255]), Some(big.clone())],
            ),
            (None, vec![]),
            (Some(vec![]), vec![Some(vec![])]),
        ] {
            let plain = PlainDictionaries {
                node: node.clone(),
                channels: channels.clone(),
            };
            let bytes = ByteDictionaries { node, channels };
            let config = bincode_config();
            let plain_enc = bincode::serde::encode_to_vec(&plain, config).unwrap();
            let bytes_enc = bincode::serde::encode_to_vec(&bytes, config).unwrap();
            // Written alike, so pools and clients of either side read each other.
            assert_eq!(plain_enc, bytes_enc);
            let (read, used): (ByteDictionaries, usize) =
                bincode::serde::decode_from_slice(&plain_enc, config).unwrap();
            assert_eq!((read, used), (bytes, plain_enc.len()));
            // A self-describing format (JSON) writes and reads the same arrays as before.
            let json = serde_json::to_string(&plain).unwrap();
            let via_bytes: ByteDictionaries = serde_json::from_str(&json).unwrap();
            assert_eq!(serde_json::to_string(&via_bytes).unwrap(), json);
        }
    }

    #[test]
    fn a_dictionary_longer_than_its_bytes_is_an_error() {
        let mut enc = sample().encode().unwrap();
        // The last channel dictionary's one byte, cut off: its length now claims more than is
        // there.
        enc.pop();
        assert!(SceneDescription::decode(&enc).is_err());
    }

    proptest! {
        #[test]
        fn hostile_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
            let _ = SceneDescription::decode(&bytes);
        }
    }
}
