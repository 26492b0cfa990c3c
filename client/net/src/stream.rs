//! Reading treelet messages from server-opened unidirectional streams.
//!
//! A stream carries one or more treelet messages back to back. The stream is read a chunk (one
//! received STREAM frame, at most a datagram) at a time into one buffer, and each message is
//! taken from it in three bounded steps: the fixed header start, then the rest of the header (its
//! length follows from the channel count), which is validated before any block byte is needed;
//! then budget for the whole message (at most [`MAX_TREELET_MESSAGE_BYTES`]) is reserved from the
//! client's buffer bound, waiting while the caller has not taken enough earlier treelets, and only
//! then are the blocks read. A stream is thus read at most one chunk ahead of what is reserved,
//! and a message costs about one read from quinn instead of three. A reset stream (the server cancelled a treelet nobody wants any more) is dropped
//! quietly; anything malformed or unasked-for closes the connection with
//! [`ErrorCode::ProtocolViolation`].

use std::sync::{Arc, Mutex};
use std::time::Instant;

use arbor_proto::Channel;
use arbor_proto::frame::{decode_treelet_message, parse_treelet_header};
use arbor_proto::limits::MAX_TREELET_MESSAGE_BYTES;
use arbor_proto::wire::ErrorCode;
use bytes::Bytes;
use bytes::BytesMut;
use quinn::{ReadError, RecvStream, VarInt};
use tokio::sync::mpsc;

use super::event::{ClientEvent, ReceivedTreelet};
use super::shared::{Queued, Shared};

/// Bytes of a treelet message header before its channel table: id, used nodes, channel count.
const FIXED_HEADER: usize = 4 + 2 + 1;

/// Why the client itself closed a connection, if it did; the first reason wins.
pub(crate) type LocalClose = Arc<Mutex<Option<(ErrorCode, String)>>>;

/// Closes `conn` with `code` and records why (unless a reason was recorded already).
pub(crate) fn close_locally(
    conn: &quinn::Connection,
    local: &LocalClose,
    code: ErrorCode,
    reason: String,
) {
    let mut slot = local.lock().unwrap_or_else(|e| e.into_inner());
    if slot.is_none() {
        tracing::warn!(code = %code, %reason, "closing the connection");
        let mut wire_reason = reason.clone().into_bytes();
        wire_reason.truncate(arbor_proto::limits::MAX_MESSAGE_BYTES);
        conn.close(VarInt::from_u32(code.to_u32()), &wire_reason);
        *slot = Some((code, reason));
    }
}

/// What a stream reader needs; one per connection, shared by its streams.
#[derive(Debug)]
pub(crate) struct StreamContext {
    pub shared: Arc<Shared>,
    pub events: mpsc::UnboundedSender<Queued>,
    pub conn: quinn::Connection,
    pub local_close: LocalClose,
    /// Channels asked for in `Hello`.
    pub channels: Vec<Channel>,
    /// From the scene: ids must be below this.
    pub treelet_count: u32,
    /// From the scene: `used_nodes` must not exceed this.
    pub treelet_nodes: u32,
}

enum StreamEnd {
    /// The server broke the protocol on this stream.
    Violation(String),
    /// Reset by the server, the connection is gone, or the caller went away: nothing to do.
    Quiet,
}

fn read_failed(e: ReadError) -> StreamEnd {
    match e {
        ReadError::Reset(code) => {
            tracing::debug!(%code, "treelet stream reset by the server");
            StreamEnd::Quiet
        }
        ReadError::ConnectionLost(_) | ReadError::ClosedStream | ReadError::ZeroRttRejected => {
            StreamEnd::Quiet
        }
        ReadError::IllegalOrderedRead => StreamEnd::Violation("illegal ordered read".into()),
    }
}

/// Reads every treelet message of one stream, queueing each for the caller.
pub(crate) async fn read_stream(mut recv: RecvStream, ctx: Arc<StreamContext>) {
    if let StreamEnd::Violation(reason) = read_messages(&mut recv, &ctx).await {
        close_locally(
            &ctx.conn,
            &ctx.local_close,
            ErrorCode::ProtocolViolation,
            format!("treelet stream {}: {reason}", recv.id()),
        );
    }
}

/// A stream's bytes read from quinn and not yet taken as messages.
struct Incoming<'a> {
    recv: &'a mut RecvStream,
    buf: BytesMut,
}

/// Why [`Incoming::fill`] could not provide the bytes asked for.
enum FillError {
    /// The stream finished with this many bytes left unparsed.
    Finished(usize),
    Read(ReadError),
}

impl Incoming<'_> {
    /// Reads chunks until at least `n` bytes are buffered.
    async fn fill(&mut self, n: usize) -> Result<(), FillError> {
        while self.buf.len() < n {
            match self.recv.read_chunk(usize::MAX, true).await {
                Ok(Some(chunk)) => self.buf.extend_from_slice(&chunk.bytes),
                Ok(None) => return Err(FillError::Finished(self.buf.len())),
                Err(e) => return Err(FillError::Read(e)),
            }
        }
        Ok(())
    }
}

async fn read_messages(recv: &mut RecvStream, ctx: &Arc<StreamContext>) -> StreamEnd {
    let mut incoming = Incoming {
        recv,
        buf: BytesMut::new(),
    };
    loop {
        match incoming.fill(FIXED_HEADER).await {
            Ok(()) => {}
            // A clean end between messages.
            Err(FillError::Finished(0)) => return StreamEnd::Quiet,
            Err(FillError::Finished(n)) => {
                return StreamEnd::Violation(format!("stream ends {n} bytes into a message"));
            }
            Err(FillError::Read(e)) => return read_failed(e),
        }
        // Rejects a bad id, node count or channel count before reading further.
        if let Err(e) = parse_treelet_header(&incoming.buf[..FIXED_HEADER]) {
            return StreamEnd::Violation(e.to_string());
        }
        let header_len = FIXED_HEADER + 5 * usize::from(incoming.buf[6]) + 4;
        match incoming.fill(header_len).await {
            Ok(()) => {}
            Err(FillError::Finished(_)) => {
                return StreamEnd::Violation("stream ends inside a message header".into());
            }
            Err(FillError::Read(e)) => return read_failed(e),
        }
        let header = match parse_treelet_header(&incoming.buf[..header_len]) {
            Ok(Some(h)) => h,
            Ok(None) => return StreamEnd::Violation("incomplete message header".into()),
            Err(e) => return StreamEnd::Violation(e.to_string()),
        };
        if header.id.0 >= ctx.treelet_count {
            return StreamEnd::Violation(format!(
                "treelet {} is not in the scene ({} treelets)",
                header.id, ctx.treelet_count
            ));
        }
        if u32::from(header.used_nodes) > ctx.treelet_nodes {
            return StreamEnd::Violation(format!(
                "treelet {} claims {} nodes, the scene's treelets hold {}",
                header.id, header.used_nodes, ctx.treelet_nodes
            ));
        }
        if let Some(&(c, _)) = header
            .channels
            .iter()
            .find(|(c, _)| !ctx.channels.contains(c))
        {
            return StreamEnd::Violation(format!(
                "treelet {} carries channel {}, which was not asked for",
                header.id,
                c.name()
            ));
        }
        let total = header.total_len();
        if total > MAX_TREELET_MESSAGE_BYTES {
            // Cannot happen with a valid header; the check keeps the bound explicit.
            return StreamEnd::Violation(format!("message of {total} bytes"));
        }

        // Backpressure: wait for room before reading the blocks.
        let (id, block_bytes) = (header.id, total - header_len);
        let lease = ctx.shared.reserve(total).await;
        match incoming.fill(total).await {
            Ok(()) => {}
            Err(FillError::Finished(n)) => {
                return StreamEnd::Violation(format!(
                    "stream ends after {} of the {block_bytes} block bytes of treelet {id}",
                    n - header_len
                ));
            }
            Err(FillError::Read(e)) => return read_failed(e),
        }
        let bytes: Bytes = incoming.buf.split_to(total).freeze();
        let treelet = match decode_treelet_message(&bytes) {
            Ok(m) => {
                // Slice the blocks out of the one buffer without copying.
                let slice = |part: &[u8]| bytes.slice_ref(part);
                ReceivedTreelet {
                    id: m.id,
                    used_nodes: m.used_nodes,
                    nodes: slice(m.nodes),
                    channels: m.channels.iter().map(|&(c, b)| (c, slice(b))).collect(),
                    latency: Default::default(),
                    wire_bytes: total,
                }
            }
            Err(e) => return StreamEnd::Violation(e.to_string()),
        };
        let now = Instant::now();
        let latency = ctx.shared.latency().arrived(treelet.id, now);
        {
            let mut s = ctx.shared.stats();
            s.treelets_received += 1;
            s.bytes_received += total as u64;
        }
        let queued = Queued {
            event: ClientEvent::Treelet(ReceivedTreelet { latency, ..treelet }),
            _lease: Some(lease),
        };
        if ctx.events.send(queued).is_err() {
            // The caller dropped the client.
            return StreamEnd::Quiet;
        }
    }
}
