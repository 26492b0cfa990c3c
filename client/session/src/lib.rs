//! Streaming sessions: a treelet connection (`arbor-client-net`) feeding the plain-data client
//! core (`arbor-client-core`), stepped one cycle at a time by whoever owns the clock — the
//! headless runner here ([`headless`]) or the window viewer (`arbor-client-viewer`).
//!
//! This crate is the shell around the core: it connects (the only place that waits on the
//! network, bounded by a timeout), decodes arrived treelet messages for the core, times each
//! phase of a cycle and records it as a report row (`arbor-client-report`), and detects
//! convergence, and notes stalls ([`stall`]). It also fetches whole scenes, or just the cut a view needs ([`mod@reference`]), for
//! reference renders.

#![forbid(unsafe_code)]

mod error;
pub mod headless;
pub mod reference;
pub mod session;
pub mod stall;

pub use error::RunError;
pub use session::{
    FetchedScene, RenderMode, Session, SessionConfig, Step, compare, fetch_all, reference_image,
};
