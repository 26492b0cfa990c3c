//! The shared read-only view of the incore octree: what the ray caster (CPU and GPU) and the
//! analysis pass read, and what the [`SlotBuffer`](crate::slots::SlotBuffer) owns.
//!
//! The buffer is `slots × N` node records, slot-major: node `k` of slot `s` has the global
//! index `s·N + k`. Slot 0 holds the root treelet, so global index 0 is the root voxel. An inner
//! node's children start at `index.wrapping_add(first_child)`; the wrapping add is what lets a
//! patched leaf point at a child treelet in a slot *before* its own (docs/design.md §5). Attributes sit
//! beside the nodes, one array per channel, indexed by the same global index.

use arbor_proto::{Channel, Node, SceneDescription};

/// The incore nodes and attributes, borrowed.
#[derive(Clone, Copy, Debug)]
pub struct IncoreView<'a> {
    /// `slots × treelet_nodes` records, slot 0 = the root treelet (up to the highest slot
    /// filled so far, for a buffer made by `SlotBuffer::new_growing`).
    pub nodes: &'a [Node],
    /// `N`, the scene's node records per treelet.
    pub treelet_nodes: u32,
    /// 3 bytes (sRGB 8-bit) per node, when the client holds colour.
    pub color: Option<&'a [u8]>,
    /// 4 bytes (octahedral 2 × u16 LE) per node, when the client holds normals.
    pub normal: Option<&'a [u8]>,
    /// 2 bytes (u16 LE) per node, when the client holds density.
    pub density: Option<&'a [u8]>,
}

impl<'a> IncoreView<'a> {
    /// The attribute array of `channel`, if held.
    pub fn channel(&self, channel: Channel) -> Option<&'a [u8]> {
        match channel {
            Channel::Color => self.color,
            Channel::Normal => self.normal,
            Channel::Density => self.density,
        }
    }

    /// Attribute bytes of `channel` for global node `index`.
    pub fn attribute(&self, channel: Channel, index: u32) -> Option<&'a [u8]> {
        let size = channel.size();
        let start = index as usize * size;
        self.channel(channel)?.get(start..start + size)
    }

    /// The slot holding global node `index`.
    pub fn slot_of(&self, index: u32) -> u32 {
        index / self.treelet_nodes
    }
}

/// Where the octree sits in the world: the scene's root cube and target depth (f64, exact
/// integer cells below it, docs/design.md §2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneFrame {
    /// Minimum corner of the root cube.
    pub origin: [f64; 3],
    /// Edge length of the root cube.
    pub edge: f64,
    /// Depth of the finest voxels.
    pub max_depth: u8,
}

impl SceneFrame {
    /// The unit root cube (origin 0, edge 1). Camera paths are placed relative to the root
    /// cube, so a path's camera in this frame is the view a client can name before it knows
    /// the scene: `Hello`'s view ([`arbor_proto::wire::HELLO_VIEW`]).
    pub const UNIT: SceneFrame = SceneFrame {
        origin: [0.0; 3],
        edge: 1.0,
        max_depth: 0,
    };

    /// The frame of `scene`.
    pub fn of(scene: &SceneDescription) -> Self {
        Self {
            origin: scene.origin,
            edge: scene.edge,
            max_depth: scene.max_depth,
        }
    }

    /// Edge length of a voxel at `depth` (exact: a power-of-two scaling).
    pub fn voxel_size(&self, depth: u8) -> f64 {
        self.edge / (1u64 << depth) as f64
    }

    /// Centre of the root cube.
    pub fn centre(&self) -> [f64; 3] {
        let h = self.edge * 0.5;
        [self.origin[0] + h, self.origin[1] + h, self.origin[2] + h]
    }
}
