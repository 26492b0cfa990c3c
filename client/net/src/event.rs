//! What the client tells its caller: events and counters.

use std::sync::Arc;
use std::time::Duration;

use arbor_proto::frame::ChannelBlocks;
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
    pub channels: AttributeBlocks,
    /// From sending the first request list naming this treelet (since it last arrived) to its
    /// arrival; zero for a treelet no list sent named.
    pub latency: Duration,
    /// Bytes of the whole message on its stream (header and blocks).
    pub wire_bytes: usize,
}

/// A received treelet's compressed attribute blocks, in the order the message carried them
/// (ascending channel id): one shared buffer holding them back to back and the header's inline
/// table of their channels and lengths. A treelet's arrival thus allocates nothing for its
/// channels and takes one reference count on the received bytes however many it carries. (With
/// a `Vec` of per-channel slices, the stream reader of a whole-scene fetch of lion-4k over
/// loopback executed about a tenth more instructions; callgrind, docs/measurements.md.)
#[derive(Clone, PartialEq, Eq)]
pub struct AttributeBlocks {
    /// The blocks back to back.
    bytes: Bytes,
    /// Each block's channel and length, in order.
    blocks: ChannelBlocks,
}

impl AttributeBlocks {
    /// `bytes` cut into the consecutive blocks a message header announced; `None` if their
    /// lengths do not add up to `bytes`.
    pub fn new(bytes: Bytes, blocks: ChannelBlocks) -> Option<Self> {
        let total = blocks
            .iter()
            .try_fold(0usize, |sum, b| sum.checked_add(b.1 as usize))?;
        (total == bytes.len()).then_some(Self { bytes, blocks })
    }

    /// Blocks held.
    pub fn len(&self) -> usize {
        self.blocks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.blocks.is_empty()
    }

    /// The blocks with their channels, in order.
    pub fn iter(&self) -> AttributeBlocksIter<'_> {
        AttributeBlocksIter {
            blocks: self,
            next: 0,
            at: 0,
        }
    }

    /// The block of `channel`, if the treelet carries it.
    pub fn get(&self, channel: Channel) -> Option<&[u8]> {
        self.iter().find(|&(c, _)| c == channel).map(|(_, b)| b)
    }
}

impl<'a> IntoIterator for &'a AttributeBlocks {
    type Item = (Channel, &'a [u8]);
    type IntoIter = AttributeBlocksIter<'a>;

    fn into_iter(self) -> Self::IntoIter {
        self.iter()
    }
}

/// The blocks of an [`AttributeBlocks`] with their channels, in order.
#[derive(Clone, Debug)]
pub struct AttributeBlocksIter<'a> {
    blocks: &'a AttributeBlocks,
    /// Index of the next block, and where its bytes start.
    next: usize,
    at: usize,
}

impl<'a> Iterator for AttributeBlocksIter<'a> {
    type Item = (Channel, &'a [u8]);

    fn next(&mut self) -> Option<Self::Item> {
        let &(channel, len) = self.blocks.blocks.get(self.next)?;
        let start = self.at;
        self.next += 1;
        self.at += len as usize;
        Some((channel, &self.blocks.bytes[start..self.at]))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.blocks.len() - self.next;
        (left, Some(left))
    }
}

impl ExactSizeIterator for AttributeBlocksIter<'_> {}

impl std::fmt::Debug for AttributeBlocks {
    /// Channels and block lengths, not the bytes.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list()
            .entries(self.blocks.iter().map(|&(c, len)| (c.name(), len)))
            .finish()
    }
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
    /// Request lists written with only the head of their items, while lists waited for the
    /// uplink ([`crate::list_cap`]).
    pub lists_capped: u64,
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

#[cfg(test)]
mod tests {
    use super::*;
    use arbor_proto::frame::{encode_treelet_header, parse_treelet_header};

    /// The channel table a header for these block lengths announces.
    fn table(channels: &[(Channel, usize)]) -> ChannelBlocks {
        let header = encode_treelet_header(TreeletId(7), 1, 3, channels).unwrap();
        parse_treelet_header(&header).unwrap().unwrap().channels
    }

    #[test]
    fn attribute_blocks_cut_one_buffer_by_the_announced_lengths() {
        let blocks = table(&[(Channel::Color, 2), (Channel::Density, 3)]);
        let bytes = Bytes::from_static(b"ccddd");
        let a = AttributeBlocks::new(bytes.clone(), blocks).unwrap();
        assert_eq!(a.len(), 2);
        assert_eq!(a.iter().len(), 2);
        let got: Vec<(Channel, &[u8])> = a.iter().collect();
        assert_eq!(
            got,
            [
                (Channel::Color, &b"cc"[..]),
                (Channel::Density, &b"ddd"[..])
            ]
        );
        assert_eq!(a.get(Channel::Density), Some(&b"ddd"[..]));
        assert_eq!(a.get(Channel::Normal), None);
        assert_eq!(format!("{a:?}"), r#"[("color", 2), ("density", 3)]"#);
        // Lengths that do not add up to the buffer are refused, either way.
        assert!(AttributeBlocks::new(bytes.slice(..4), blocks).is_none());
        assert!(AttributeBlocks::new(Bytes::from_static(b"ccdddx"), blocks).is_none());
        // No channels: an empty buffer only.
        let none = table(&[]);
        assert!(AttributeBlocks::new(Bytes::new(), none).unwrap().is_empty());
        assert!(AttributeBlocks::new(bytes, none).is_none());
    }
}
