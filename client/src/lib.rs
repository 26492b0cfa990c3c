//! The Arbor client: connects to a treelet server, decides which treelets would most improve
//! the picture, keeps them in a fixed-size slot buffer and ray-casts them.
//!
//! It owns the viewer side of the data path (DESIGN §5): the QUIC connection, the analysis
//! (feedback) pass, presort, the incore slot buffer, GPU upload, the renderers and their CPU
//! references, and headless runs with error-against-time reports. The foundation issue only
//! fixes the formats it will read; they live in [`arbor_proto`], re-exported here so client code
//! names one crate.
//!
//! [`gpu`] runs the analysis pass, the slot upload and the render pass on wgpu (WGSL twins of
//! [`trace`], [`analysis`] and [`render`]); [`backend::CpuBackend`] runs the CPU twins.
//!
//! [`net`] is the connection to a treelet server (DESIGN §6): `quic://HOST:PORT/SCENE` URLs, a
//! pinned certificate fingerprint or a CA, `Hello`, request lists, treelets received as events
//! with decoded headers and per-treelet latency, bounded buffering with backpressure, and
//! reconnects with backoff, all in a background task that never blocks the caller.

pub mod analysis;
mod assets;
pub mod backend;
pub mod camera;
pub mod chart;
pub mod gpu;
pub mod headless;
pub mod image;
pub mod incore;
pub mod net;
pub mod presort;
pub mod render;
pub mod report;
pub mod run;
pub mod session;
pub mod slots;
pub mod trace;
pub mod upload;
pub mod viewer;

pub use arbor_proto as proto;
