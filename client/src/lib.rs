//! The Arbor client: connects to a treelet server, decides which treelets would most improve
//! the picture, keeps them in a fixed-size slot buffer and ray-casts them.
//!
//! It owns the viewer side of the data path (DESIGN §5): the QUIC connection, the analysis
//! (feedback) pass, presort, the incore slot buffer, GPU upload, the renderers and their CPU
//! references, and headless runs with error-against-time reports. The foundation issue only
//! fixes the formats it will read; they live in [`arbor_proto`], re-exported here so client code
//! names one crate.

pub use arbor_proto as proto;
