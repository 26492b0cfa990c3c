//! Errors of decoding and validating Arbor formats.

use crate::treelet::TreeletId;

/// Everything that can be wrong with bytes claiming to be an Arbor format.
#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum ProtoError {
    /// Fewer bytes than the format needs.
    #[error("{what}: truncated, need {need} bytes, have {have}")]
    Truncated {
        what: &'static str,
        need: usize,
        have: usize,
    },
    /// More bytes than the format allows or announced.
    #[error("{what}: {len} bytes exceeds the limit of {limit}")]
    TooLarge {
        what: &'static str,
        len: usize,
        limit: usize,
    },
    /// The magic number does not match.
    #[error("{what}: bad magic {found:#010x}")]
    BadMagic { what: &'static str, found: u32 },
    /// A format version this build does not understand.
    #[error("{what}: unsupported version {found}")]
    UnsupportedVersion { what: &'static str, found: u16 },
    /// A field holds a value outside its range.
    #[error("{what}: {detail}")]
    OutOfRange { what: &'static str, detail: String },
    /// A treelet's node records are not a well-formed tree.
    #[error("treelet {id}: node {node}: {detail}")]
    MalformedTreelet {
        id: TreeletId,
        node: u32,
        detail: String,
    },
    /// zstd could not compress or decompress.
    #[error("{what}: zstd: {detail}")]
    Compression { what: &'static str, detail: String },
    /// A serialized structure could not be decoded.
    #[error("{what}: {detail}")]
    Serialization { what: &'static str, detail: String },
}
