//! The client's connection to a treelet server (docs/design.md §6): it owns the QUIC side of
//! the client and nothing of the cycle, so the plain-data core never sees a socket.
//!
//! ```no_run
//! # async fn demo() -> Result<(), arbor_client_net::ClientError> {
//! use arbor_client_net::{ClientConfig, ClientEvent, TreeletClient, Trust, parse_server_url};
//! use arbor_proto::{Channel, TreeletId};
//!
//! let url = parse_server_url("quic://viewer.example:4433/lion")?;
//! let trust = Trust::Fingerprint("…64 hex digits printed by the server…".into());
//! let config = ClientConfig::new(url, trust)
//!     .with_token("secret")
//!     .with_channels([Channel::Color]);
//! let mut client = TreeletClient::start(config)?;
//! client.request(vec![(TreeletId::ROOT, 10.0)])?;
//! while let Some(event) = client.next_event().await {
//!     match event {
//!         ClientEvent::Connected(scene) => println!("{} treelets", scene.treelet_count),
//!         ClientEvent::Treelet(t) => println!("treelet {} after {:?}", t.id, t.latency),
//!         ClientEvent::Disconnected { reason, reconnect_in, .. } => {
//!             println!("{reason}; again in {reconnect_in:?}")
//!         }
//!     }
//! }
//! # Ok(()) }
//! ```
//!
//! * [`url`]: `quic://HOST:PORT/SCENE` ([`parse_server_url`]).
//! * [`tls`]: trusting the server by pinned certificate fingerprint or by CA ([`Trust`]).
//! * [`transport`]: QUIC transport parameters and timeouts.
//! * [`backoff`]: reconnect delays ([`Backoff`]).
//! * [`list_cap`]: how many items a request list carries while lists wait for the uplink.
//! * Replicas ([`ClientConfig::with_replicas`]): other servers of the same pool; on a lost
//!   connection the client moves to the next one at once and re-sends the latest list; a server
//!   describing the scene differently is refused.
//! * [`TreeletClient`]: the handle; a background task owns the connection, reconnects, sends
//!   request lists and reads treelet streams (validating every message, only the channels asked
//!   for, within a byte bound that pushes back on the server when the caller falls behind).

#![forbid(unsafe_code)]

pub mod backoff;
mod client;
mod config;
mod connection;
mod error;
mod event;
pub mod list_cap;
mod replicas;
mod shared;
mod stream;
pub mod tls;
pub mod transport;
pub mod url;

pub use backoff::{Backoff, Jitter};
pub use client::TreeletClient;
pub use config::{
    ClientConfig, DEFAULT_FAILOVER_AFTER, DEFAULT_MAX_BUFFERED_BYTES, MAX_REPLICAS,
    MIN_FAILOVER_AFTER, MIN_LIST_SEND_WINDOW,
};
pub use connection::is_final_code;
pub use error::ClientError;
pub use event::{AttributeBlocks, AttributeBlocksIter, ClientEvent, ClientStats, ReceivedTreelet};
pub use tls::{Trust, certificate_fingerprint};
pub use url::{ServerUrl, parse_server_url};
