//! The Arbor client's core, as plain data: everything that decides what the client sees, asks
//! for and keeps, with no sockets, no GPU, no window and no clock.
//!
//! It owns the client side of the algorithm (docs/design.md §5): the camera and its paths
//! ([`camera`]), the CPU traversal ([`traverse`], twin of `shaders/traverse.wgsl`), the analysis
//! pass ([`analysis`], twin of `analysis.wgsl`) and the renderer ([`render`], twin of
//! `render.wgsl`), presort ([`presort`]), the incore slot buffer ([`slots`], [`incore`]), upload
//! range planning ([`upload`]) and the cycle that ties them together ([`cycle::ClientCore`]),
//! holding undecodable arrivals off the lists for a while ([`backoff`]), running its
//! passes on a [`backend::Backend`] — the CPU twins here, wgpu in
//! `arbor-client-gpu`.
//!
//! Keeping this crate free of I/O is what makes it testable the quinn-proto way: tests feed it
//! treelets read straight from a pool and step it cycle by cycle; time is whatever the caller
//! passes in. The connection (`arbor-client-net`), the GPU (`arbor-client-gpu`), sessions and
//! reports are thin shells around it.

#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod analysis;
pub mod backend;
pub mod backoff;
pub mod bias;
pub mod camera;
pub mod coverage;
pub mod cycle;
pub mod frustum;
pub mod image;
pub mod incore;
pub mod presort;
pub mod render;
pub mod slots;
pub mod summary;
pub mod traverse;
pub mod upload;

pub use arbor_proto as proto;
