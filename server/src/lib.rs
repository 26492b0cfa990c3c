//! The Arbor server: scan importers, the SVO builder, the sled treelet pool and the CLI.
//!
//! * [`import`] reads OBJ, PLY, LAS/LAZ, NRRD and raw volumes strictly into a [`source::Source`]
//!   of disk-backed columns;
//! * [`build`] turns a source into treelets (DESIGN §3);
//! * [`pool`] stores scenes atomically in sled, already compressed, one tree per stream;
//! * [`verify`] checks every invariant of a stored scene;
//! * [`memory`] measures the import's peak memory for its report.

#![deny(unsafe_code)]

pub mod admin;
pub mod daemon;
pub mod import;
pub mod memory;
pub mod octree;
pub mod pipeline;
pub mod pool;
pub mod prometheus;
pub mod service;
pub mod source;
pub mod verify;
