//! The JSON shapes of `/v1/scenes` and `/v1/server` (`/v1/sessions` serializes
//! [`SessionInfo`](crate::service::state::SessionInfo) as it is).

use std::collections::BTreeMap;
use std::time::Duration;

use arbor_proto::{SceneDescription, SourceKind};
use serde::Serialize;

use crate::service::state::ServiceState;

/// A scene's figures. The zstd dictionaries (up to tens of KiB each) are never included.
#[derive(Debug, Serialize)]
pub(super) struct SceneView<'a> {
    pub name: &'a str,
    /// `mesh`, `points` or `volume`.
    pub kind: &'static str,
    /// Source file name and a short description of its contents.
    pub source: &'a str,
    pub primitives: u64,
    /// Target depth.
    pub depth: u8,
    /// Depth asked for at import; `null` for `--depth auto`.
    pub requested_depth: Option<u8>,
    pub treelet_bytes: u32,
    pub treelet_nodes: u32,
    pub treelets: u32,
    pub voxels: u64,
    pub leaf_voxels: u64,
    pub channels: Vec<&'static str>,
    pub compressed_bytes: CompressedBytes,
    /// Uncompressed bytes of the used records (nodes and attributes).
    pub raw_bytes: u64,
    /// Compressed bytes (all streams) per voxel.
    pub bytes_per_voxel: f64,
    pub build_seconds: f64,
    /// Minimum corner of the root cube, in source units.
    pub origin: [f64; 3],
    /// Edge of the root cube.
    pub edge: f64,
    pub zstd_level: i32,
    /// Whether per-stream zstd dictionaries were trained (their bytes are not shown).
    pub dictionaries: bool,
}

/// Compressed bytes of a scene in the pool.
#[derive(Debug, Serialize)]
pub(super) struct CompressedBytes {
    pub total: u64,
    pub nodes: u64,
    /// Per attribute channel, by name.
    pub channels: BTreeMap<&'static str, u64>,
}

pub(super) fn kind_name(k: SourceKind) -> &'static str {
    match k {
        SourceKind::Mesh => "mesh",
        SourceKind::Points => "points",
        SourceKind::Volume => "volume",
    }
}

impl<'a> SceneView<'a> {
    pub(super) fn new(d: &'a SceneDescription) -> Self {
        let s = &d.stats;
        let channels: BTreeMap<_, _> = d
            .layout
            .channels()
            .iter()
            .zip(&s.channel_bytes)
            .map(|(c, &b)| (c.name(), b))
            .collect();
        let total = s.node_bytes + channels.values().sum::<u64>();
        Self {
            name: &d.name,
            kind: kind_name(d.source_kind),
            source: &d.source,
            primitives: d.primitives,
            depth: d.max_depth,
            requested_depth: d.build.requested_depth,
            treelet_bytes: d.build.treelet_bytes,
            treelet_nodes: d.treelet_nodes,
            treelets: d.treelet_count,
            voxels: s.voxels,
            leaf_voxels: s.leaf_voxels,
            channels: d.layout.channels().iter().map(|c| c.name()).collect(),
            compressed_bytes: CompressedBytes {
                total,
                nodes: s.node_bytes,
                channels,
            },
            raw_bytes: s.raw_bytes,
            bytes_per_voxel: total as f64 / s.voxels.max(1) as f64,
            build_seconds: s.build_seconds,
            origin: d.origin,
            edge: d.edge,
            zstd_level: d.build.zstd_level,
            dictionaries: d.build.dictionary,
        }
    }
}

/// `/v1/server`.
#[derive(Debug, Serialize)]
pub(super) struct ServerView {
    pub name: &'static str,
    pub version: &'static str,
    /// SHA-256 of the certificate QUIC clients are shown now (DER), lowercase hex: what they
    /// pin.
    pub fingerprint: String,
    /// When that certificate expires, seconds since the Unix epoch (`null`: not read).
    pub certificate_expiry_unix: Option<i64>,
    pub ready: bool,
    pub shutting_down: bool,
    pub uptime_seconds: f64,
    /// Live connections.
    pub sessions: usize,
}

impl ServerView {
    pub(super) fn new(state: &ServiceState, uptime: Duration) -> Self {
        let quic = state.certificate("quic");
        Self {
            name: env!("CARGO_PKG_NAME"),
            version: env!("CARGO_PKG_VERSION"),
            fingerprint: state.fingerprint(),
            certificate_expiry_unix: quic.and_then(|c| c.not_after_unix),
            ready: state.is_ready(),
            shutting_down: state.is_shutting_down(),
            uptime_seconds: uptime.as_secs_f64(),
            sessions: state.sessions().len(),
        }
    }
}
