//! Explicit limits. Every decoder checks its input against these before allocating.

/// Smallest treelet size in bytes of node records (128 nodes).
pub const MIN_TREELET_BYTES: u32 = 1024;
/// Largest treelet size in bytes of node records (2048 nodes).
pub const MAX_TREELET_BYTES: u32 = 16 * 1024;
/// Default treelet size (docs/design.md §2: 4 KiB was a good default in the thesis).
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

// ---- network protocol (`wire`, `frame`) ----
//
// Frame lengths below are *payload* lengths: the value of a control frame's `u32` length prefix,
// which counts neither the prefix itself nor the frame-type byte
// ([`FRAME_HEADER_BYTES`]).

/// Bytes in front of every control-frame payload: `u32` payload length + `u8` frame type.
pub const FRAME_HEADER_BYTES: usize = 5;
/// Largest payload of every control frame except `SceneInfo` — in particular of everything a
/// client sends. A `RequestList` of [`MAX_REQUEST_ITEMS`] items takes 12 + 8 × 65,536 bytes
/// (512 KiB), half of this.
pub const MAX_FRAME_BYTES: usize = 1 << 20;
/// Largest payload of any control frame: `SceneInfo`, whose payload is exactly an encoded
/// scene description (which may embed zstd dictionaries), so the limit is
/// [`MAX_SCENE_DESCRIPTION_BYTES`]; the frame header comes on top. Only a client ever has to
/// accept a frame this large; a server decodes client frames with [`MAX_FRAME_BYTES`].
pub const MAX_CONTROL_FRAME_BYTES: usize = MAX_SCENE_DESCRIPTION_BYTES;
/// Most `(treelet, priority)` items in one request list.
pub const MAX_REQUEST_ITEMS: usize = 65_536;
/// Longest access token in a `Hello`, in bytes of UTF-8.
pub const MAX_TOKEN_BYTES: usize = 4096;
/// Longest human-readable message of an `Error` frame, in bytes of UTF-8.
pub const MAX_MESSAGE_BYTES: usize = 1024;
/// Header of a treelet message with the most channels: id, used nodes, channel count,
/// [`MAX_CHANNELS`] × (channel id, block length), node block length.
pub const MAX_TREELET_MESSAGE_HEADER: usize = 4 + 2 + 1 + MAX_CHANNELS * 5 + 4;
/// Largest treelet message: its header, a node block and [`MAX_CHANNELS`] channel blocks, each
/// at most [`MAX_COMPRESSED_BLOCK`].
pub const MAX_TREELET_MESSAGE_BYTES: usize =
    MAX_TREELET_MESSAGE_HEADER + (1 + MAX_CHANNELS) * MAX_COMPRESSED_BLOCK;

const _: () = assert!(12 + 8 * MAX_REQUEST_ITEMS <= MAX_FRAME_BYTES);
// A deep request list: seq, view hint, count, 12 bytes per item.
const _: () =
    assert!(8 + crate::wire::ViewHint::BYTES + 4 + 12 * MAX_REQUEST_ITEMS <= MAX_FRAME_BYTES);
// A ranked request list: seq, view hint, prefetch start, count, at most 5 + 2 bytes per item.
const _: () =
    assert!(8 + crate::wire::ViewHint::BYTES + 8 + 7 * MAX_REQUEST_ITEMS <= MAX_FRAME_BYTES);
const _: () =
    assert!(2 + 2 + MAX_SCENE_NAME + 1 + MAX_CHANNELS + 2 + MAX_TOKEN_BYTES <= MAX_FRAME_BYTES);
const _: () = assert!(MAX_FRAME_BYTES <= MAX_CONTROL_FRAME_BYTES);
const _: () = assert!(MAX_CONTROL_FRAME_BYTES <= u32::MAX as usize);
