//! The Arbor server: everything on the pool's side of the wire.
//!
//! Import, from a scan file to a committed scene:
//! * [`import`] reads OBJ, PLY, LAS/LAZ, NRRD and raw volumes strictly into a [`source::Source`]
//!   of disk-backed columns (errors name the file and the place);
//! * [`octree`] turns a source into treelets in bounded memory (docs/design.md §3);
//! * [`pool`] stores scenes atomically in sled, already compressed, one tree per stream;
//! * [`pipeline`] is the one entry point that runs those steps in order ([`pipeline::import_scene`]),
//!   in a [`scratch`] directory its import keeps locked, so the next import removes what a
//!   killed one left;
//! * [`verify`] checks every invariant of a stored scene; [`memory`] measures an import's peak
//!   memory for its report.
//!
//! Serving, from the pool to clients:
//! * [`service`] is the QUIC treelet service: an I/O-free scheduler and the tokio/quinn shell
//!   around it (connections, treelet streams, graceful shutdown);
//! * [`admin`] is the axum admin API (health, readiness, metrics, scenes, sessions, status page),
//!   its text metrics written through [`prometheus`];
//! * [`daemon`] starts the service and mounts the admin API beside it — what `arbor-server
//!   serve` runs; [`live_import`] imports and removes scenes in it, [`live_verify`] checks
//!   them and [`live_copy`] copies the pool, while it serves, the checks' and copies' reads
//!   held to the [`pace`] the operator sets; [`periodic`] says when the scheduled ones are due;
//!   [`config_watch`] notices a changed configuration, to reload it without a signal.
//!
//! [`logging`] sets up the binaries' log lines (text, coloured only on a terminal, or JSON).
//!
//! Unsafe code is denied except for the memory maps of scratch columns in [`source`].

#![deny(unsafe_code)]

pub mod admin;
pub mod config_watch;
pub mod daemon;
pub mod import;
mod jobs;
pub mod live_copy;
pub mod live_import;
pub mod live_verify;
pub mod logging;
pub mod memory;
pub mod octree;
pub mod pace;
pub mod periodic;
pub mod pipeline;
pub mod pool;
pub mod progress;
pub mod prometheus;
pub mod scratch;
pub mod service;
pub mod source;
pub mod verify;
