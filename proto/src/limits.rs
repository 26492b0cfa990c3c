//! Explicit limits. Every decoder checks its input against these before allocating.

/// Smallest treelet size in bytes of node records (128 nodes).
pub const MIN_TREELET_BYTES: u32 = 1024;
/// Largest treelet size in bytes of node records (2048 nodes).
pub const MAX_TREELET_BYTES: u32 = 16 * 1024;
/// Default treelet size (DESIGN §2: 4 KiB was a good default in the thesis).
pub const DEFAULT_TREELET_BYTES: u32 = 4 * 1024;
/// Size of one node record.
pub const NODE_BYTES: u32 = 8;
/// Deepest octree level. Cells at depth `d` have integer coordinates `< 2^d`, so `u32` cells
/// and exact `f64` arithmetic on them hold up to 31 levels (kilometres at sub-millimetre).
pub const MAX_DEPTH: u8 = 31;
/// Largest treelet count of one scene (ids are `u32`, `u32::MAX` is `NONE`).
pub const MAX_TREELETS: u32 = u32::MAX - 1;
/// Largest attribute channel count of one scene.
pub const MAX_CHANNELS: usize = 8;
/// Largest compressed treelet or attribute block accepted by a decoder.
pub const MAX_COMPRESSED_BLOCK: usize = 256 * 1024;
/// Largest zstd dictionary accepted in a scene description.
pub const MAX_DICTIONARY_BYTES: usize = 1 << 20;
/// Largest encoded scene description.
pub const MAX_SCENE_DESCRIPTION_BYTES: usize = 8 << 20;
/// Longest scene name.
pub const MAX_SCENE_NAME: usize = 128;
