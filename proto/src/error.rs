//! Errors of decoding and validating Arbor formats.

use crate::treelet::TreeletId;

/// Everything that can be wrong with bytes claiming to be an Arbor format.
#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum ProtoError {
    /// Fewer bytes than the format needs.
    #[error("{what}: truncated, need {need} bytes, have {have}")]
    Truncated {
        /// What was being read.
        what: &'static str,
        /// Bytes needed.
        need: usize,
        /// Bytes available.
        have: usize,
    },
    /// More bytes than the format allows or announced.
    #[error("{what}: {len} bytes exceeds the limit of {limit}")]
    TooLarge {
        /// What was being read.
        what: &'static str,
        /// The length found.
        len: usize,
        /// The limit.
        limit: usize,
    },
    /// The magic number does not match.
    #[error("{what}: bad magic {found:#010x}")]
    BadMagic {
        /// What was being read.
        what: &'static str,
        /// The value found.
        found: u32,
    },
    /// A format version this build does not understand.
    #[error("{what}: unsupported version {found}")]
    UnsupportedVersion {
        /// What was being read.
        what: &'static str,
        /// The value found.
        found: u16,
    },
    /// A field holds a value outside its range.
    #[error("{what}: {detail}")]
    OutOfRange {
        /// What was being read.
        what: &'static str,
        /// What is wrong, for people.
        detail: String,
    },
    /// A treelet's node records are not a well-formed tree.
    #[error("treelet {id}: node {node}: {detail}")]
    MalformedTreelet {
        /// The treelet.
        id: TreeletId,
        /// The node record.
        node: u32,
        /// What is wrong, for people.
        detail: String,
    },
    /// zstd could not compress or decompress.
    #[error("{what}: zstd: {detail}")]
    Compression {
        /// What was being read.
        what: &'static str,
        /// What is wrong, for people.
        detail: String,
    },
    /// A serialized structure could not be decoded.
    #[error("{what}: {detail}")]
    Serialization {
        /// What was being read.
        what: &'static str,
        /// What is wrong, for people.
        detail: String,
    },
}
