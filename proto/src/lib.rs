//! Arbor's shared vocabulary, with no I/O.
//!
//! This crate owns every format that crosses a boundary: the 64-bit [`Node`] and the fixed-size
//! [`Treelet`] (docs/design.md §2), exact integer cell coordinates ([`Cell`]), the [`SceneDescription`] with
//! its [`AttributeLayout`], the binary encoding of treelets and attribute blocks with zstd
//! compression ([`codec`]), the explicit [`limits`], and the network protocol: its vocabulary
//! ([`wire`]: ALPN, control frames, error codes) and byte layout ([`frame`]: bounded frame
//! decoding, treelet messages), the one small seeded generator ([`rng`]), and the treelet-id
//! hash that keeps consecutive ids together in the maps that follow a transfer
//! ([`treelet_map`]). Server and client both depend on it, so a format change is made once,
//! here, and round-trip tests keep both sides honest.

#![warn(missing_docs)]
#![forbid(unsafe_code)]

pub mod attribute;
pub mod cell;
pub mod codec;
pub mod error;
pub mod frame;
pub mod limits;
pub mod node;
pub mod rng;
pub mod scene;
pub mod treelet;
pub mod treelet_map;
pub mod wire;

pub use attribute::{AttributeLayout, Channel};
pub use cell::Cell;
pub use error::ProtoError;
pub use node::Node;
pub use scene::{BuildParameters, SceneDescription, SceneStats, SourceKind};
pub use treelet::{Treelet, TreeletHeader, TreeletId};
pub use treelet_map::TreeletMap;
