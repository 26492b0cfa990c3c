//! The treelet service (docs/design.md §6).
//!
//! * [`schedule`] is its I/O-free core, in the style of quinn-proto: a deterministic state machine
//!   that is told what happened (`handle_*`: a request list arrived, a treelet was sent, delivered
//!   or cancelled) and asked what to do next (`poll_batch`, or `poll_transmit` for one treelet),
//!   with time passed in. It decides, for every connection, which treelets to send in which
//!   order, how many may be in flight, and which connection goes next; it is unit- and
//!   property-tested without sockets.
//! * [`config`]: `ServeConfig` from TOML + CLI overrides, validation, scene access.
//! * [`tls`]: the certificate (self-signed on first start, or given) and its fingerprint;
//!   [`certificate`]: the one a listener presents, replaced on reload for the next handshakes;
//!   [`reset`]: stateless resets that outlive the process (key from the TLS key, random ids).
//! * [`server`]: [`start_service`] → [`RunningService`]: QUIC endpoint, connection cap,
//!   dispatcher, graceful shutdown; [`connection`]: one client; [`shutdown`]: the broadcast and
//!   drop-to-finish plumbing; [`treelets`]: treelet messages from the pool and their cache
//!   bounded in bytes; `streams`: a few treelets per stream; `batches`: which stream carries
//!   which treelets and which streams a new list makes obsolete (plain data); `shared`: what the tasks share
//!   (scheduler, routes, the scenes in use while a connection holds them, the message and
//!   shape caches).
//!
//! The daemon ([`crate::daemon`]) starts this service and mounts the admin API beside it.
//! * [`state`]: metrics, sessions and readiness shared with the admin API; [`timeline`]: what
//!   was listed, pushed, sent and acknowledged when, for benchmarks (off unless started).
//! * [`push`]: what a deep request's view would refine below its listed treelets (frustum and
//!   projected size); [`visibility`]: what a resting view's rays need, cast through the server's
//!   own tree with the client's traversal (`visibility_grid`, on by default), followed where
//!   it saves enough against the frustum plan ([`push::cut_saves`]); [`shapes`]: the treelet
//!   shapes those plans walk, decoded once and kept server-wide within `shape_cache_bytes`;
//!   [`generations`]: the byte-bounded cache of two generations that holds those shapes and
//!   the node records the cuts read (`visibility_node_cache_bytes`).
//! * [`prewarm`]: the pool's files read into the page cache once at start (`pool_prewarm`), so a
//!   fresh server does not wait on a disk that limits its reads per second; [`hot_pages`]: which
//!   pages of them were cached while the last run served, saved in the data directory and read
//!   first (only they, when the pool is larger than memory).
//! * [`path_memory`]: each client address's last congestion window and RTT, so a returning
//!   client's connection resumes near the rate its path carried instead of slow-starting
//!   (careful resume; `path_memory_secs`); [`state_file`]: the JSON files it and the hot-page
//!   list keep in the data directory between runs, written whole or not at all.
pub mod access;
mod batches;
pub mod certificate;
pub mod config;
pub mod connection;
pub mod generations;
mod handler;
pub mod hot_pages;
pub mod path_memory;
pub mod prewarm;
pub mod push;
pub mod random_loss;
mod readers;
pub mod reset;
pub mod schedule;
pub mod server;
pub mod shapes;
mod shared;
pub mod shutdown;
pub mod state;
pub mod state_file;
mod streams;
pub mod timeline;
pub mod tls;
pub mod treelets;
pub mod visibility;

pub use config::{ConfigError, ConfigOverrides, ServeConfig};
pub use readers::ReadFigures;
pub use server::{AccessHandle, AccessReload, RunningService, ServeError, start_service};
pub use shutdown::ShutdownTrigger;
