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
    pub node_dictionary: Option<Vec<u8>>,
    /// zstd dictionary per channel, in layout order.
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

    proptest! {
        #[test]
        fn hostile_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
            let _ = SceneDescription::decode(&bytes);
        }
    }
}
