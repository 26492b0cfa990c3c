//! What the client tells its caller: events and counters.

use std::sync::Arc;
use std::time::Duration;

use arbor_proto::wire::ErrorCode;
use arbor_proto::{Channel, SceneDescription, TreeletId};
use bytes::Bytes;

/// Something that happened on the connection, in order.
#[derive(Clone, Debug)]
pub enum ClientEvent {
    /// The server accepted `Hello` and described the scene. Sent after every (re)connection;
    /// the latest request list is sent right after it.
    Connected(Arc<SceneDescription>),
    /// A treelet arrived.
    Treelet(ReceivedTreelet),
    /// The connection ended, or a connection attempt failed.
    Disconnected {
        /// The protocol's error code when the server said one (its close code, or an `Error`
        /// frame) or the client closed with one (a protocol violation by the server); `None` for
        /// a lost connection, a timeout, a TLS failure or a network error.
        code: Option<ErrorCode>,
        /// What happened, for people.
        reason: String,
        /// When the next attempt is made; `None` if the client gave up for good (a final code
        /// such as [`ErrorCode::Unauthorized`], a certificate the client does not trust, or a
        /// close asked for by the caller). After a final `Disconnected` no more events come.
        reconnect_in: Option<Duration>,
    },
}

/// A treelet as it arrived: the message header decoded, the blocks exactly as stored on the
/// server (compressed; decompressing them is the caller's business, with the scene's
/// dictionaries and [`arbor_proto::codec`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ReceivedTreelet {
    pub id: TreeletId,
    /// Node records in use, as announced by the message; the decompressed node block's own
    /// header is authoritative and the caller must check that they agree.
    pub used_nodes: u16,
    /// The compressed node block.
    pub nodes: Bytes,
    /// The compressed attribute blocks, in ascending channel id order; only channels the client
    /// asked for.
    pub channels: Vec<(Channel, Bytes)>,
    /// From sending the first request list naming this treelet (since it last arrived) to its
    /// arrival; zero for a treelet no list sent named.
    pub latency: Duration,
    /// Bytes of the whole message on its stream (header and blocks).
    pub wire_bytes: usize,
}

/// Counters since the client started.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ClientStats {
    /// Successful connections (`SceneInfo` received).
    pub connects: u64,
    /// [`ClientEvent::Disconnected`] events: ended connections and failed attempts.
    pub disconnects: u64,
    /// Request lists written to the control stream.
    pub lists_sent: u64,
    /// Request lists not written because they said exactly what the last one sent on this
    /// connection said.
    pub lists_unchanged: u64,
    /// Treelet messages received and validated.
    pub treelets_received: u64,
    /// Their bytes on the wire ([`ReceivedTreelet::wire_bytes`] summed).
    pub bytes_received: u64,
    /// The code of the last close that had one (see [`ClientEvent::Disconnected`]).
    pub last_close_code: Option<ErrorCode>,
    /// Bytes of treelet messages held now: queued for the caller or being read.
    pub buffered_bytes: usize,
    /// The most `buffered_bytes` ever was.
    pub peak_buffered_bytes: usize,
    /// Connections made to a different server than the one before (failovers to a replica).
    pub failovers: u64,
    /// The server of the current (or last) connection.
    pub server: Option<super::url::ServerUrl>,
}
