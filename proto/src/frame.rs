//! Byte layout of the network protocol: control frames and treelet messages, with every limit
//! enforced (docs/design.md §6). No I/O: callers feed bytes in and take values out.
//!
//! # Control frames
//!
//! `[u32 LE payload length][u8 frame type][payload]`, the payloads described on
//! [`Frame`]: hand-written little endian, strings as `u16` length + UTF-8,
//! except `SceneInfo`, whose payload is [`SceneDescription::encode`]'s bytes.
//!
//! Reading is two steps, as in mini-redis: [`check`] says whether a whole frame sits at the start
//! of a buffer (and rejects an over-limit length as soon as the 4 length bytes are there, before
//! any of the payload is buffered), then [`parse`] decodes exactly that frame. [`FrameDecoder`]
//! wraps both around a buffer that never holds more than one maximal frame.
//!
//! Every decoder error is a [`FrameError`] whose [`FrameError::code`] is the [`ErrorCode`] the
//! server closes the connection with. The encoders refuse to produce anything the decoders would
//! reject, so a bug shows up at the sender.
//!
//! # Treelet messages
//!
//! A server-opened unidirectional stream carries one or more treelet messages back to back:
//!
//! ```text
//! [u32 treelet id][u16 used nodes][u8 channel count]
//! [channel count × (u8 channel id, u32 compressed block length)]
//! [u32 compressed node block length]
//! [node block][channel blocks, in header order]
//! ```
//!
//! Blocks are exactly as stored in the pool (zstd). Channel ids ascend strictly (canonical
//! order, no duplicates). `used_nodes` lets a client size the attribute decompression
//! ([`crate::codec::decode_compressed_attributes`]) before it decompresses the node block; the
//! node block's own header is authoritative and a client must check that they agree.

use crate::attribute::Channel;
use crate::error::ProtoError;
use crate::limits::{
    FRAME_HEADER_BYTES, MAX_CHANNELS, MAX_COMPRESSED_BLOCK, MAX_CONTROL_FRAME_BYTES,
    MAX_FRAME_BYTES, MAX_MESSAGE_BYTES, MAX_REQUEST_ITEMS, MAX_TOKEN_BYTES, MAX_TREELET_BYTES,
    NODE_BYTES,
};
use crate::scene::{SceneDescription, validate_scene_name};
use crate::treelet::TreeletId;
use crate::wire::{
    ErrorCode, Frame, FrameType, HELLO_FLAGS, HELLO_SEND_ROOT, HELLO_VIEW, PROTOCOL_VERSION,
    ViewHint,
};

/// Everything that can be wrong with bytes claiming to be a control frame or a treelet message
/// (and with a value handed to an encoder).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// A frame announced (or an encoder was given) a payload longer than the limit for its type
    /// or for the decoder.
    #[error("frame payload of {len} bytes exceeds the limit of {limit}")]
    TooLarge {
        /// The length found.
        len: usize,
        /// The limit.
        limit: usize,
    },
    /// The frame-type byte is not a known [`FrameType`].
    #[error("unknown frame type {0}")]
    UnknownType(u8),
    /// The bytes end before a field does.
    #[error("{what}: truncated, need {need} bytes, have {have}")]
    Truncated {
        /// What was being read.
        what: &'static str,
        /// Bytes needed.
        need: usize,
        /// Bytes available.
        have: usize,
    },
    /// Bytes are left over after the last field of a frame or message.
    #[error("{what}: {extra} trailing bytes")]
    TrailingBytes {
        /// What was being read.
        what: &'static str,
        /// Bytes left over.
        extra: usize,
    },
    /// `Hello` carries a protocol version other than [`PROTOCOL_VERSION`]. The version is the
    /// first field, so a future layout is still answered with this error.
    #[error("unsupported protocol version {found}, this build speaks {PROTOCOL_VERSION}")]
    UnsupportedVersion {
        /// The value found.
        found: u16,
    },
    /// A string field is not UTF-8.
    #[error("{what} is not valid UTF-8")]
    BadUtf8 {
        /// What was being read.
        what: &'static str,
    },
    /// A string field is longer than its limit.
    #[error("{what}: {len} bytes exceeds the limit of {limit}")]
    FieldTooLong {
        /// What was being read.
        what: &'static str,
        /// The length found.
        len: usize,
        /// The limit.
        limit: usize,
    },
    /// The scene name in `Hello` is not a valid scene name.
    #[error("bad scene name: {0}")]
    BadSceneName(ProtoError),
    /// More channels than [`MAX_CHANNELS`].
    #[error("{count} channels exceeds the limit of {limit}")]
    TooManyChannels {
        /// How many were given.
        count: usize,
        /// The limit.
        limit: usize,
    },
    /// A channel id this build does not know.
    #[error("unknown channel id {0}")]
    UnknownChannel(u8),
    /// A channel named twice (or, in a treelet message, out of ascending order).
    #[error("channel {0:?} repeated or out of order")]
    DuplicateChannel(Channel),
    /// A request list with more than [`MAX_REQUEST_ITEMS`] items.
    #[error("request list of {len} items exceeds the limit of {limit}")]
    ListTooLong {
        /// The length found.
        len: usize,
        /// The limit.
        limit: usize,
    },
    /// A request-list priority is NaN or infinite.
    #[error("request item {index} (treelet {treelet}): priority is not finite")]
    NonFinitePriority {
        /// Position in the list.
        index: usize,
        /// The treelet named there.
        treelet: TreeletId,
    },
    /// A treelet id is [`TreeletId::NONE`], which names no treelet.
    #[error("item {index}: treelet id NONE")]
    NoneTreeletId {
        /// Position in the list.
        index: usize,
    },
    /// A deep request list's prefetch start lies beyond its items.
    #[error("prefetch from item {prefetch_from}, but the list has {count} items")]
    BadPrefetchStart {
        /// The start found.
        prefetch_from: u32,
        /// The list's items.
        count: usize,
    },
    /// An error code this build does not know.
    #[error("unknown error code {0}")]
    UnknownErrorCode(u32),
    /// The `SceneInfo` payload is not a valid scene description (or, encoding, could not be
    /// encoded).
    #[error("scene description: {0}")]
    SceneDescription(ProtoError),
    /// A treelet-message block is empty or longer than [`MAX_COMPRESSED_BLOCK`].
    #[error("{what}: block of {len} bytes, must be 1..={limit}")]
    BadBlockLength {
        /// What was being read.
        what: &'static str,
        /// The length found.
        len: usize,
        /// The limit.
        limit: usize,
    },
    /// `Hello` sets a flag this build does not know.
    #[error("unknown Hello flags {0:#04x}")]
    UnknownFlags(u8),
    /// A deep request list's or a `Hello`'s view hint is unusable (see [`ViewHint::check`]).
    #[error("view hint: {0}")]
    BadView(String),
    /// `Hello`'s [`HELLO_VIEW`] flag without [`HELLO_SEND_ROOT`] (the view refines below the
    /// root), or a view without the flag (encoding only).
    #[error("Hello: {0}")]
    BadHelloView(&'static str),
    /// A deep request list item's error is not finite or beyond ±[`ViewHint::MAX_ERROR`].
    #[error(
        "request item {index} (treelet {treelet}): error {} is not a finite level count within ±64",
        f32::from_bits(*error_bits)
    )]
    BadError {
        /// Position in the list.
        index: usize,
        /// The treelet named there.
        treelet: TreeletId,
        /// The bits of the error given (`f32::to_bits`; a NaN keeps its payload).
        error_bits: u32,
    },
    /// A treelet message's used-node count is 0 or more than a treelet can hold.
    #[error("used nodes {0} outside 1..={max}", max = MAX_TREELET_BYTES / NODE_BYTES)]
    BadUsedNodes(u16),
    /// A ranked request list's id delta is not a varint of at most five bytes.
    #[error("request item {index}: the id delta is not a varint of at most 5 bytes")]
    BadVarint {
        /// Position in the list.
        index: usize,
    },
    /// A ranked request list's id delta leads outside the treelet ids (below 0, or to
    /// [`TreeletId::NONE`] or beyond).
    #[error("request item {index}: id delta {delta} from {previous} leaves the treelet ids")]
    BadIdDelta {
        /// Position in the list.
        index: usize,
        /// The previous item's id (0 before the first).
        previous: u32,
        /// The delta found.
        delta: i64,
    },
}

impl FrameError {
    /// The code a server closes the connection with (and sends in an `Error` frame) when a
    /// client's bytes fail this way.
    pub fn code(&self) -> ErrorCode {
        match self {
            FrameError::TooLarge { .. } => ErrorCode::FrameTooLarge,
            FrameError::UnsupportedVersion { .. } => ErrorCode::UnsupportedVersion,
            FrameError::BadSceneName(_) => ErrorCode::UnknownScene,
            FrameError::TooManyChannels { .. } => ErrorCode::TooManyChannels,
            FrameError::UnknownChannel(_) => ErrorCode::UnknownChannel,
            FrameError::ListTooLong { .. } => ErrorCode::ListTooLong,
            FrameError::UnknownType(_)
            | FrameError::Truncated { .. }
            | FrameError::TrailingBytes { .. }
            | FrameError::BadUtf8 { .. }
            | FrameError::FieldTooLong { .. }
            | FrameError::DuplicateChannel(_)
            | FrameError::NonFinitePriority { .. }
            | FrameError::NoneTreeletId { .. }
            | FrameError::UnknownErrorCode(_)
            | FrameError::SceneDescription(_)
            | FrameError::BadBlockLength { .. }
            | FrameError::BadUsedNodes(_)
            | FrameError::BadView(_)
            | FrameError::BadHelloView(_)
            | FrameError::UnknownFlags(_)
            | FrameError::BadError { .. }
            | FrameError::BadPrefetchStart { .. }
            | FrameError::BadVarint { .. }
            | FrameError::BadIdDelta { .. } => ErrorCode::ProtocolViolation,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Control frames
// ---------------------------------------------------------------------------------------------

/// Whether a complete frame sits at the start of `buf`, with the payload limit of the frame's
/// type ([`FrameType::max_payload`]). See [`check_with_limit`].
pub fn check(buf: &[u8]) -> Result<Option<usize>, FrameError> {
    check_with_limit(buf, MAX_CONTROL_FRAME_BYTES)
}

/// Whether a complete frame sits at the start of `buf`: `Ok(Some(total length))` if so,
/// `Ok(None)` if more bytes are needed, an error as soon as the bytes present prove the frame
/// bad: a payload length over `max_payload` (decided from the 4 length bytes alone), an unknown
/// type byte, or a length over that type's own limit (decided with the 5th byte).
pub fn check_with_limit(buf: &[u8], max_payload: usize) -> Result<Option<usize>, FrameError> {
    let Some(len_bytes) = buf.first_chunk::<4>() else {
        return Ok(None);
    };
    let len = u32::from_le_bytes(*len_bytes) as usize;
    if len > max_payload {
        return Err(FrameError::TooLarge {
            len,
            limit: max_payload,
        });
    }
    let Some(&type_byte) = buf.get(4) else {
        return Ok(None);
    };
    let ty = FrameType::from_u8(type_byte).ok_or(FrameError::UnknownType(type_byte))?;
    if len > ty.max_payload() {
        return Err(FrameError::TooLarge {
            len,
            limit: ty.max_payload(),
        });
    }
    let total = FRAME_HEADER_BYTES + len;
    Ok((buf.len() >= total).then_some(total))
}

/// Decodes exactly one frame; `frame` must be the whole frame (as delimited by [`check`]) and
/// nothing more.
pub fn parse(frame: &[u8]) -> Result<Frame, FrameError> {
    let total = check(frame)?.ok_or(FrameError::Truncated {
        what: "frame",
        need: frame.first_chunk::<4>().map_or(FRAME_HEADER_BYTES, |l| {
            FRAME_HEADER_BYTES + u32::from_le_bytes(*l) as usize
        }),
        have: frame.len(),
    })?;
    if total != frame.len() {
        return Err(FrameError::TrailingBytes {
            what: "frame",
            extra: frame.len() - total,
        });
    }
    let ty = FrameType::from_u8(frame[4]).ok_or(FrameError::UnknownType(frame[4]))?;
    let payload = &frame[FRAME_HEADER_BYTES..];
    if ty == FrameType::SceneInfo {
        let description =
            SceneDescription::decode(payload).map_err(FrameError::SceneDescription)?;
        return Ok(Frame::SceneInfo {
            description: Box::new(description),
        });
    }
    let mut r = Reader::new(payload);
    let out = match ty {
        FrameType::Hello => parse_hello(&mut r)?,
        FrameType::RequestList => parse_request_list(&mut r)?,
        FrameType::DeepRequestList => parse_deep_request_list(&mut r)?,
        FrameType::RankedRequestList => parse_ranked_request_list(&mut r)?,
        FrameType::Error => {
            let code = r.u32("error code")?;
            let code = ErrorCode::from_u32(code).ok_or(FrameError::UnknownErrorCode(code))?;
            let message = r.string("error message", MAX_MESSAGE_BYTES)?.to_owned();
            Frame::Error { code, message }
        }
        FrameType::Goodbye => {
            let code = r.u32("goodbye code")?;
            let code = ErrorCode::from_u32(code).ok_or(FrameError::UnknownErrorCode(code))?;
            Frame::Goodbye { code }
        }
        FrameType::SceneInfo => unreachable!("handled above"),
    };
    r.finish(frame_what(ty))?;
    Ok(out)
}

fn frame_what(ty: FrameType) -> &'static str {
    match ty {
        FrameType::Hello => "Hello frame",
        FrameType::SceneInfo => "SceneInfo frame",
        FrameType::RequestList => "RequestList frame",
        FrameType::DeepRequestList => "DeepRequestList frame",
        FrameType::RankedRequestList => "RankedRequestList frame",
        FrameType::Error => "Error frame",
        FrameType::Goodbye => "Goodbye frame",
    }
}

fn parse_hello(r: &mut Reader<'_>) -> Result<Frame, FrameError> {
    let version = r.u16("protocol version")?;
    if version != PROTOCOL_VERSION {
        return Err(FrameError::UnsupportedVersion { found: version });
    }
    let scene = r.string("scene name", usize::from(u16::MAX))?;
    validate_scene_name(scene).map_err(FrameError::BadSceneName)?;
    let count = usize::from(r.u8("channel count")?);
    if count > MAX_CHANNELS {
        return Err(FrameError::TooManyChannels {
            count,
            limit: MAX_CHANNELS,
        });
    }
    let mut channels = Vec::with_capacity(count);
    for _ in 0..count {
        let id = r.u8("channel id")?;
        let c = Channel::from_id(id).ok_or(FrameError::UnknownChannel(id))?;
        if channels.contains(&c) {
            return Err(FrameError::DuplicateChannel(c));
        }
        channels.push(c);
    }
    let token = r.string("access token", MAX_TOKEN_BYTES)?;
    let flags = if r.remaining() > 0 {
        r.u8("hello flags")?
    } else {
        0
    };
    if flags & !HELLO_FLAGS != 0 {
        return Err(FrameError::UnknownFlags(flags));
    }
    check_hello_flags(flags)?;
    let view = if flags & HELLO_VIEW != 0 {
        Some(parse_view(r)?)
    } else {
        None
    };
    Ok(Frame::Hello {
        version,
        scene: scene.to_owned(),
        channels,
        token: token.to_owned(),
        flags,
        view,
    })
}

fn check_hello_flags(flags: u8) -> Result<(), FrameError> {
    if flags & HELLO_VIEW != 0 && flags & HELLO_SEND_ROOT == 0 {
        return Err(FrameError::BadHelloView(
            "the view flag needs the send-root flag (the view refines below the root)",
        ));
    }
    Ok(())
}

/// A [`ViewHint`] (layout: see [`ViewHint::BYTES`]), checked.
fn parse_view(r: &mut Reader<'_>) -> Result<ViewHint, FrameError> {
    let f64s = |r: &mut Reader<'_>, what| -> Result<[f64; 3], FrameError> {
        Ok([
            f64::from_bits(r.u64(what)?),
            f64::from_bits(r.u64(what)?),
            f64::from_bits(r.u64(what)?),
        ])
    };
    let f32s = |r: &mut Reader<'_>, what| -> Result<[f32; 3], FrameError> {
        Ok([
            f32::from_bits(r.u32(what)?),
            f32::from_bits(r.u32(what)?),
            f32::from_bits(r.u32(what)?),
        ])
    };
    let view = ViewHint {
        eye: f64s(r, "view eye")?,
        forward: f32s(r, "view forward")?,
        up: f32s(r, "view up")?,
        tan_half_fov_y: f32::from_bits(r.u32("view fov")?),
        aspect: f32::from_bits(r.u32("view aspect")?),
        footprint: f32::from_bits(r.u32("view footprint")?),
        free_slots: r.u32("view free slots")?,
    };
    view.check().map_err(FrameError::BadView)?;
    Ok(view)
}

/// Appends `view` (checked) in [`parse_view`]'s layout.
fn put_view(out: &mut Vec<u8>, view: &ViewHint) -> Result<(), FrameError> {
    view.check().map_err(FrameError::BadView)?;
    for c in view.eye {
        out.extend_from_slice(&c.to_bits().to_le_bytes());
    }
    for c in view.forward.iter().chain(&view.up).chain(&[
        view.tan_half_fov_y,
        view.aspect,
        view.footprint,
    ]) {
        out.extend_from_slice(&c.to_bits().to_le_bytes());
    }
    out.extend_from_slice(&view.free_slots.to_le_bytes());
    Ok(())
}

/// Reads a list's item count and checks it against the protocol's limit and against the bytes
/// left for items of `item_bytes` each, before anything is allocated.
fn list_length(
    r: &mut Reader<'_>,
    item_bytes: usize,
    what: &'static str,
) -> Result<usize, FrameError> {
    let count = r.u32("list length")? as usize;
    if count > MAX_REQUEST_ITEMS {
        return Err(FrameError::ListTooLong {
            len: count,
            limit: MAX_REQUEST_ITEMS,
        });
    }
    let need = count * item_bytes;
    if r.remaining() < need {
        return Err(FrameError::Truncated {
            what,
            need,
            have: r.remaining(),
        });
    }
    Ok(count)
}

fn parse_request_list(r: &mut Reader<'_>) -> Result<Frame, FrameError> {
    let seq = r.u64("list seq")?;
    let count = list_length(r, 8, "request list items")?;
    let mut items = Vec::with_capacity(count);
    for index in 0..count {
        let treelet = TreeletId(r.u32("treelet id")?);
        let priority = f32::from_bits(r.u32("priority")?);
        check_item(index, treelet, priority)?;
        items.push((treelet, priority));
    }
    Ok(Frame::RequestList { seq, items })
}

fn parse_deep_request_list(r: &mut Reader<'_>) -> Result<Frame, FrameError> {
    let seq = r.u64("list seq")?;
    let view = parse_view(r)?;
    let prefetch_from = r.u32("prefetch start")?;
    let count = list_length(r, 12, "deep request list items")?;
    check_prefetch_start(prefetch_from, count)?;
    let mut items = Vec::with_capacity(count);
    for index in 0..count {
        let treelet = TreeletId(r.u32("treelet id")?);
        let priority = f32::from_bits(r.u32("priority")?);
        let error = f32::from_bits(r.u32("error")?);
        check_deep_item(index, treelet, priority, error)?;
        items.push((treelet, priority, error));
    }
    Ok(Frame::DeepRequestList {
        seq,
        view,
        items,
        prefetch_from,
    })
}

/// Smallest ranked item: a one-byte id delta and the error.
const MIN_RANKED_ITEM_BYTES: usize = 3;

/// Most bytes of a ranked item's id delta: a zigzag varint of a difference between two `u32`s
/// needs 33 bits.
const MAX_VARINT_BYTES: usize = 5;

fn parse_ranked_request_list(r: &mut Reader<'_>) -> Result<Frame, FrameError> {
    let seq = r.u64("list seq")?;
    let view = parse_view(r)?;
    let prefetch_from = r.u32("prefetch start")?;
    let count = list_length(r, MIN_RANKED_ITEM_BYTES, "ranked request list items")?;
    check_prefetch_start(prefetch_from, count)?;
    let mut items = Vec::with_capacity(count);
    let mut previous = 0u32;
    for index in 0..count {
        let zigzag = read_varint(r, index)?;
        let delta = (zigzag >> 1) as i64 ^ -((zigzag & 1) as i64);
        let id = i64::from(previous) + delta;
        if !(0..i64::from(TreeletId::NONE.0)).contains(&id) {
            return Err(FrameError::BadIdDelta {
                index,
                previous,
                delta,
            });
        }
        previous = id as u32;
        let error = r.u16("error")? as i16;
        items.push((TreeletId(previous), error));
    }
    Ok(Frame::RankedRequestList {
        seq,
        view,
        items,
        prefetch_from,
    })
}

/// An unsigned LEB128 varint of at most [`MAX_VARINT_BYTES`] bytes.
fn read_varint(r: &mut Reader<'_>, index: usize) -> Result<u64, FrameError> {
    let mut value = 0u64;
    for i in 0..MAX_VARINT_BYTES {
        let byte = r.u8("id delta")?;
        value |= u64::from(byte & 0x7f) << (7 * i);
        if byte & 0x80 == 0 {
            return Ok(value);
        }
    }
    Err(FrameError::BadVarint { index })
}

/// What a list with a view starts with: `u64 seq`, the view, `u32 prefetch_from`, `u32 count`
/// (checked: at most [`MAX_REQUEST_ITEMS`], the prefetch start within them), with room reserved
/// for `count` items of about `item_bytes`.
fn put_view_list_head(
    out: &mut Vec<u8>,
    seq: u64,
    view: &ViewHint,
    prefetch_from: u32,
    count: usize,
    item_bytes: usize,
) -> Result<(), FrameError> {
    if count > MAX_REQUEST_ITEMS {
        return Err(FrameError::ListTooLong {
            len: count,
            limit: MAX_REQUEST_ITEMS,
        });
    }
    check_prefetch_start(prefetch_from, count)?;
    out.reserve(16 + ViewHint::BYTES + item_bytes * count);
    out.extend_from_slice(&seq.to_le_bytes());
    put_view(out, view)?;
    out.extend_from_slice(&prefetch_from.to_le_bytes());
    out.extend_from_slice(&(count as u32).to_le_bytes());
    Ok(())
}

fn put_varint(out: &mut Vec<u8>, mut value: u64) {
    while value >= 0x80 {
        out.push((value as u8) | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
}

fn check_prefetch_start(prefetch_from: u32, count: usize) -> Result<(), FrameError> {
    if prefetch_from as usize > count {
        return Err(FrameError::BadPrefetchStart {
            prefetch_from,
            count,
        });
    }
    Ok(())
}

fn check_deep_item(
    index: usize,
    treelet: TreeletId,
    priority: f32,
    error: f32,
) -> Result<(), FrameError> {
    check_item(index, treelet, priority)?;
    if !(error.is_finite() && error.abs() <= ViewHint::MAX_ERROR) {
        return Err(FrameError::BadError {
            index,
            treelet,
            error_bits: error.to_bits(),
        });
    }
    Ok(())
}

fn check_item(index: usize, treelet: TreeletId, priority: f32) -> Result<(), FrameError> {
    if treelet.is_none() {
        return Err(FrameError::NoneTreeletId { index });
    }
    if !priority.is_finite() {
        return Err(FrameError::NonFinitePriority { index, treelet });
    }
    Ok(())
}

/// Encodes a frame. Fails, rather than produce bytes the peer would reject, on any value outside
/// the protocol's limits (the same checks as [`parse`]).
pub fn encode(frame: &Frame) -> Result<Vec<u8>, FrameError> {
    let mut out = vec![0u8; FRAME_HEADER_BYTES];
    out[4] = frame.frame_type() as u8;
    match frame {
        Frame::Hello {
            version,
            scene,
            channels,
            token,
            flags,
            view,
        } => {
            if flags & !HELLO_FLAGS != 0 {
                return Err(FrameError::UnknownFlags(*flags));
            }
            check_hello_flags(*flags)?;
            if view.is_some() != (flags & HELLO_VIEW != 0) {
                return Err(FrameError::BadHelloView(
                    "a view is sent exactly when the view flag is set",
                ));
            }
            if *version != PROTOCOL_VERSION {
                return Err(FrameError::UnsupportedVersion { found: *version });
            }
            validate_scene_name(scene).map_err(FrameError::BadSceneName)?;
            if channels.len() > MAX_CHANNELS {
                return Err(FrameError::TooManyChannels {
                    count: channels.len(),
                    limit: MAX_CHANNELS,
                });
            }
            out.extend_from_slice(&version.to_le_bytes());
            put_string(&mut out, "scene name", scene, usize::from(u16::MAX))?;
            out.push(channels.len() as u8);
            for (i, c) in channels.iter().enumerate() {
                if channels[..i].contains(c) {
                    return Err(FrameError::DuplicateChannel(*c));
                }
                out.push(c.id());
            }
            put_string(&mut out, "access token", token, MAX_TOKEN_BYTES)?;
            if *flags != 0 {
                out.push(*flags);
            }
            if let Some(view) = view {
                put_view(&mut out, view)?;
            }
        }
        Frame::SceneInfo { description } => {
            description
                .validate()
                .map_err(FrameError::SceneDescription)?;
            out.extend_from_slice(&description.encode().map_err(FrameError::SceneDescription)?);
        }
        Frame::RequestList { seq, items } => {
            if items.len() > MAX_REQUEST_ITEMS {
                return Err(FrameError::ListTooLong {
                    len: items.len(),
                    limit: MAX_REQUEST_ITEMS,
                });
            }
            out.reserve(12 + 8 * items.len());
            out.extend_from_slice(&seq.to_le_bytes());
            out.extend_from_slice(&(items.len() as u32).to_le_bytes());
            for (index, &(treelet, priority)) in items.iter().enumerate() {
                check_item(index, treelet, priority)?;
                out.extend_from_slice(&treelet.0.to_le_bytes());
                out.extend_from_slice(&priority.to_bits().to_le_bytes());
            }
        }
        Frame::DeepRequestList {
            seq,
            view,
            items,
            prefetch_from,
        } => {
            put_view_list_head(&mut out, *seq, view, *prefetch_from, items.len(), 12)?;
            for (index, &(treelet, priority, error)) in items.iter().enumerate() {
                check_deep_item(index, treelet, priority, error)?;
                out.extend_from_slice(&treelet.0.to_le_bytes());
                out.extend_from_slice(&priority.to_bits().to_le_bytes());
                out.extend_from_slice(&error.to_bits().to_le_bytes());
            }
        }
        Frame::RankedRequestList {
            seq,
            view,
            items,
            prefetch_from,
        } => {
            put_view_list_head(&mut out, *seq, view, *prefetch_from, items.len(), 4)?;
            let mut previous = 0i64;
            for (index, &(treelet, error)) in items.iter().enumerate() {
                if treelet.is_none() {
                    return Err(FrameError::NoneTreeletId { index });
                }
                let delta = i64::from(treelet.0) - previous;
                previous = i64::from(treelet.0);
                put_varint(&mut out, ((delta << 1) ^ (delta >> 63)) as u64);
                out.extend_from_slice(&error.to_le_bytes());
            }
        }
        Frame::Error { code, message } => {
            out.extend_from_slice(&code.to_u32().to_le_bytes());
            put_string(&mut out, "error message", message, MAX_MESSAGE_BYTES)?;
        }
        Frame::Goodbye { code } => out.extend_from_slice(&code.to_u32().to_le_bytes()),
    }
    let len = out.len() - FRAME_HEADER_BYTES;
    let limit = frame.frame_type().max_payload();
    if len > limit {
        return Err(FrameError::TooLarge { len, limit });
    }
    out[..4].copy_from_slice(&(len as u32).to_le_bytes());
    Ok(out)
}

fn put_string(
    out: &mut Vec<u8>,
    what: &'static str,
    s: &str,
    limit: usize,
) -> Result<(), FrameError> {
    let limit = limit.min(usize::from(u16::MAX));
    if s.len() > limit {
        return Err(FrameError::FieldTooLong {
            what,
            len: s.len(),
            limit,
        });
    }
    out.extend_from_slice(&(s.len() as u16).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
    Ok(())
}

/// A bounds-checked little-endian reader over a payload.
struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn new(b: &'a [u8]) -> Self {
        Self { b, at: 0 }
    }

    fn remaining(&self) -> usize {
        self.b.len() - self.at
    }

    fn bytes(&mut self, what: &'static str, n: usize) -> Result<&'a [u8], FrameError> {
        if self.remaining() < n {
            return Err(FrameError::Truncated {
                what,
                need: n,
                have: self.remaining(),
            });
        }
        let s = &self.b[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }

    fn array<const K: usize>(&mut self, what: &'static str) -> Result<[u8; K], FrameError> {
        let mut a = [0u8; K];
        a.copy_from_slice(self.bytes(what, K)?);
        Ok(a)
    }

    fn u8(&mut self, what: &'static str) -> Result<u8, FrameError> {
        Ok(self.array::<1>(what)?[0])
    }

    fn u16(&mut self, what: &'static str) -> Result<u16, FrameError> {
        Ok(u16::from_le_bytes(self.array(what)?))
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, FrameError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    fn u64(&mut self, what: &'static str) -> Result<u64, FrameError> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }

    /// A `u16`-length-prefixed UTF-8 string of at most `limit` bytes; the limit is checked
    /// before the bytes are read.
    fn string(&mut self, what: &'static str, limit: usize) -> Result<&'a str, FrameError> {
        let len = usize::from(self.u16(what)?);
        if len > limit {
            return Err(FrameError::FieldTooLong { what, len, limit });
        }
        std::str::from_utf8(self.bytes(what, len)?).map_err(|_| FrameError::BadUtf8 { what })
    }

    fn finish(&self, what: &'static str) -> Result<(), FrameError> {
        match self.remaining() {
            0 => Ok(()),
            extra => Err(FrameError::TrailingBytes { what, extra }),
        }
    }
}

/// Accumulates control-stream bytes and yields whole frames.
///
/// The buffer never holds more than [`FrameDecoder::capacity`] bytes (one frame of the largest
/// payload the decoder accepts plus its header): [`FrameDecoder::push`] takes only what fits and
/// says how much it took. Because any frame the decoder accepts fits the buffer whole, a full
/// buffer always yields a frame or an error, so a caller that alternates `push` and `next` always
/// makes progress:
///
/// ```
/// # use arbor_proto::frame::FrameDecoder;
/// # fn handle(_: arbor_proto::wire::Frame) {}
/// let mut decoder = FrameDecoder::for_server();
/// let mut chunk: &[u8] = &[]; // bytes read from the control stream
/// while !chunk.is_empty() {
///     let taken = decoder.push(chunk);
///     chunk = &chunk[taken..];
///     while let Some(frame) = decoder.next()? {
///         handle(frame);
///     }
/// }
/// # Ok::<(), arbor_proto::frame::FrameError>(())
/// ```
///
/// After an error the decoder is poisoned: `next` returns the same error again and `push`
/// takes nothing (the stream cannot be resynchronised; the connection ends).
#[derive(Debug, Clone)]
pub struct FrameDecoder {
    buf: Vec<u8>,
    /// Start of the unconsumed bytes in `buf`.
    start: usize,
    max_payload: usize,
    failed: Option<FrameError>,
}

impl FrameDecoder {
    /// A decoder accepting payloads up to `max_payload` (further capped per frame type by
    /// [`FrameType::max_payload`]).
    pub fn new(max_payload: usize) -> Self {
        Self {
            buf: Vec::new(),
            start: 0,
            max_payload: max_payload.min(MAX_CONTROL_FRAME_BYTES),
            failed: None,
        }
    }

    /// The decoder a server uses for a client's control stream: payloads up to
    /// [`MAX_FRAME_BYTES`], so a client can make the server buffer at most about 1 MiB.
    pub fn for_server() -> Self {
        Self::new(MAX_FRAME_BYTES)
    }

    /// The decoder a client uses for the server's control stream: payloads up to
    /// [`MAX_CONTROL_FRAME_BYTES`] (a `SceneInfo` with dictionaries).
    pub fn for_client() -> Self {
        Self::new(MAX_CONTROL_FRAME_BYTES)
    }

    /// Most bytes the decoder ever buffers.
    pub fn capacity(&self) -> usize {
        FRAME_HEADER_BYTES + self.max_payload
    }

    /// Bytes buffered and not yet returned as frames.
    pub fn buffered(&self) -> usize {
        self.buf.len() - self.start
    }

    /// Appends as much of `data` as fits in the buffer and returns how many bytes it took. It
    /// takes nothing once the decoder has failed.
    pub fn push(&mut self, data: &[u8]) -> usize {
        if self.failed.is_some() {
            return 0;
        }
        if self.start > 0 {
            self.buf.drain(..self.start);
            self.start = 0;
        }
        let n = data.len().min(self.capacity() - self.buf.len());
        self.buf.extend_from_slice(&data[..n]);
        n
    }

    /// The next whole frame, `Ok(None)` if more bytes are needed, or the error that ends the
    /// stream. Over-limit lengths and unknown types are reported as soon as their bytes are in.
    #[allow(
        clippy::should_implement_trait,
        reason = "fallible and poisoning: not an Iterator"
    )]
    pub fn next(&mut self) -> Result<Option<Frame>, FrameError> {
        if let Some(e) = &self.failed {
            return Err(e.clone());
        }
        let pending = &self.buf[self.start..];
        let result = match check_with_limit(pending, self.max_payload) {
            Ok(None) => return Ok(None),
            Ok(Some(len)) => parse(&pending[..len]).map(|f| (f, len)),
            Err(e) => Err(e),
        };
        match result {
            Ok((frame, len)) => {
                self.start += len;
                if self.start == self.buf.len() {
                    self.buf.clear();
                    self.start = 0;
                }
                Ok(Some(frame))
            }
            Err(e) => {
                self.buf = Vec::new();
                self.start = 0;
                self.failed = Some(e.clone());
                Err(e)
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Treelet messages
// ---------------------------------------------------------------------------------------------

/// A decoded treelet message, borrowing its blocks from the input.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TreeletMessage<'a> {
    /// The treelet.
    pub id: TreeletId,
    /// Node records in use, as announced; must match the decompressed node header.
    pub used_nodes: u16,
    /// The compressed node block, as stored.
    pub nodes: &'a [u8],
    /// The compressed attribute blocks sent, in ascending channel id order.
    pub channels: Vec<(Channel, &'a [u8])>,
}

/// The parsed fixed part of a treelet message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TreeletMessageHeader {
    /// The treelet.
    pub id: TreeletId,
    /// Node records in use, as announced.
    pub used_nodes: u16,
    /// Compressed node block length.
    pub node_len: usize,
    /// `(channel, compressed block length)` in ascending channel id order.
    pub channels: ChannelBlocks,
    /// Bytes of the header itself.
    pub header_len: usize,
}

/// A message's `(channel, compressed block length)` pairs, held inline: a client parses a
/// header per treelet (twice: the fixed part first), and a vector there was an allocation and a
/// free per parse. Lengths are `u32` (a block is at most [`MAX_COMPRESSED_BLOCK`]), which keeps
/// the table at 68 bytes instead of 136: a received treelet carries it and is moved several
/// times on its way to the caller. Dereferences to the pairs as a slice.
#[derive(Clone, Copy)]
pub struct ChannelBlocks {
    len: u8,
    items: [(Channel, u32); MAX_CHANNELS],
}

impl ChannelBlocks {
    fn new() -> Self {
        ChannelBlocks {
            len: 0,
            items: [(Channel::Color, 0); MAX_CHANNELS],
        }
    }

    /// Appends a pair; the parser checks the count against [`MAX_CHANNELS`] and the length
    /// against [`MAX_COMPRESSED_BLOCK`] first.
    fn push(&mut self, (channel, len): (Channel, usize)) {
        self.items[usize::from(self.len)] = (channel, len as u32);
        self.len += 1;
    }
}

impl std::ops::Deref for ChannelBlocks {
    type Target = [(Channel, u32)];
    fn deref(&self) -> &Self::Target {
        &self.items[..usize::from(self.len)]
    }
}

impl std::fmt::Debug for ChannelBlocks {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.iter()).finish()
    }
}

impl PartialEq for ChannelBlocks {
    fn eq(&self, other: &Self) -> bool {
        **self == **other
    }
}

impl Eq for ChannelBlocks {}

impl TreeletMessageHeader {
    /// Header plus all blocks.
    pub fn total_len(&self) -> usize {
        self.header_len + self.node_len + self.channels.iter().map(|c| c.1 as usize).sum::<usize>()
    }
}

fn check_block(what: &'static str, len: usize) -> Result<(), FrameError> {
    if len == 0 || len > MAX_COMPRESSED_BLOCK {
        return Err(FrameError::BadBlockLength {
            what,
            len,
            limit: MAX_COMPRESSED_BLOCK,
        });
    }
    Ok(())
}

fn check_used_nodes(used_nodes: u16) -> Result<(), FrameError> {
    if used_nodes == 0 || u32::from(used_nodes) > MAX_TREELET_BYTES / NODE_BYTES {
        return Err(FrameError::BadUsedNodes(used_nodes));
    }
    Ok(())
}

/// Parses the header of a treelet message at the start of `buf`: `Ok(None)` if the header is not
/// complete yet, an error as soon as a field present is out of range (so a reader never buffers
/// the blocks of a bad message).
pub fn parse_treelet_header(buf: &[u8]) -> Result<Option<TreeletMessageHeader>, FrameError> {
    let mut r = Reader::new(buf);
    let incomplete = |e: FrameError| match e {
        FrameError::Truncated { .. } => Ok(None),
        e => Err(e),
    };
    let id = match r.u32("treelet id") {
        Ok(v) => TreeletId(v),
        Err(e) => return incomplete(e),
    };
    if id.is_none() {
        return Err(FrameError::NoneTreeletId { index: 0 });
    }
    let used_nodes = match r.u16("used nodes") {
        Ok(v) => v,
        Err(e) => return incomplete(e),
    };
    check_used_nodes(used_nodes)?;
    let count = match r.u8("channel count") {
        Ok(v) => usize::from(v),
        Err(e) => return incomplete(e),
    };
    if count > MAX_CHANNELS {
        return Err(FrameError::TooManyChannels {
            count,
            limit: MAX_CHANNELS,
        });
    }
    let mut channels = ChannelBlocks::new();
    for _ in 0..count {
        let id = match r.u8("channel id") {
            Ok(v) => v,
            Err(e) => return incomplete(e),
        };
        let c = Channel::from_id(id).ok_or(FrameError::UnknownChannel(id))?;
        if channels.last().is_some_and(|&(prev, _)| prev.id() >= id) {
            return Err(FrameError::DuplicateChannel(c));
        }
        let len = match r.u32("channel block length") {
            Ok(v) => v as usize,
            Err(e) => return incomplete(e),
        };
        check_block("channel block", len)?;
        channels.push((c, len));
    }
    let node_len = match r.u32("node block length") {
        Ok(v) => v as usize,
        Err(e) => return incomplete(e),
    };
    check_block("node block", node_len)?;
    Ok(Some(TreeletMessageHeader {
        id,
        used_nodes,
        node_len,
        channels,
        header_len: r.at,
    }))
}

/// Whether a complete treelet message sits at the start of `buf` (for streams carrying several):
/// `Ok(Some(total length))`, `Ok(None)` if more bytes are needed, or an error as soon as the
/// header is bad. The total is at most [`crate::limits::MAX_TREELET_MESSAGE_BYTES`].
pub fn check_treelet_message(buf: &[u8]) -> Result<Option<usize>, FrameError> {
    Ok(parse_treelet_header(buf)?
        .map(|h| h.total_len())
        .filter(|&total| buf.len() >= total))
}

/// Decodes one treelet message; `buf` must hold exactly the message.
pub fn decode_treelet_message(buf: &[u8]) -> Result<TreeletMessage<'_>, FrameError> {
    let Some(h) = parse_treelet_header(buf)? else {
        return Err(FrameError::Truncated {
            what: "treelet message header",
            need: buf.len() + 1,
            have: buf.len(),
        });
    };
    let total = h.total_len();
    if buf.len() < total {
        return Err(FrameError::Truncated {
            what: "treelet message",
            need: total,
            have: buf.len(),
        });
    }
    if buf.len() > total {
        return Err(FrameError::TrailingBytes {
            what: "treelet message",
            extra: buf.len() - total,
        });
    }
    let mut at = h.header_len;
    let nodes = &buf[at..at + h.node_len];
    at += h.node_len;
    let mut channels = Vec::with_capacity(h.channels.len());
    for &(c, len) in h.channels.iter() {
        let len = len as usize;
        channels.push((c, &buf[at..at + len]));
        at += len;
    }
    Ok(TreeletMessage {
        id: h.id,
        used_nodes: h.used_nodes,
        nodes,
        channels,
    })
}

/// Encodes only the header of a treelet message, for a sender that writes the blocks itself
/// (node block, then the channel blocks in the order given) without copying them. Channels must
/// ascend strictly by id; every block must be 1..=[`MAX_COMPRESSED_BLOCK`] bytes.
pub fn encode_treelet_header(
    id: TreeletId,
    used_nodes: u16,
    node_len: usize,
    channels: &[(Channel, usize)],
) -> Result<Vec<u8>, FrameError> {
    if id.is_none() {
        return Err(FrameError::NoneTreeletId { index: 0 });
    }
    check_used_nodes(used_nodes)?;
    if channels.len() > MAX_CHANNELS {
        return Err(FrameError::TooManyChannels {
            count: channels.len(),
            limit: MAX_CHANNELS,
        });
    }
    check_block("node block", node_len)?;
    let mut out = Vec::with_capacity(11 + 5 * channels.len());
    out.extend_from_slice(&id.0.to_le_bytes());
    out.extend_from_slice(&used_nodes.to_le_bytes());
    out.push(channels.len() as u8);
    for (i, &(c, len)) in channels.iter().enumerate() {
        if i > 0 && channels[i - 1].0.id() >= c.id() {
            return Err(FrameError::DuplicateChannel(c));
        }
        check_block("channel block", len)?;
        out.push(c.id());
        out.extend_from_slice(&(len as u32).to_le_bytes());
    }
    out.extend_from_slice(&(node_len as u32).to_le_bytes());
    Ok(out)
}

/// Encodes a whole treelet message: header, node block, channel blocks (see
/// [`encode_treelet_header`] for the rules).
pub fn encode_treelet_message(
    id: TreeletId,
    used_nodes: u16,
    nodes: &[u8],
    channels: &[(Channel, &[u8])],
) -> Result<Vec<u8>, FrameError> {
    let lens: Vec<(Channel, usize)> = channels.iter().map(|&(c, b)| (c, b.len())).collect();
    let mut out = encode_treelet_header(id, used_nodes, nodes.len(), &lens)?;
    out.reserve(nodes.len() + lens.iter().map(|l| l.1).sum::<usize>());
    out.extend_from_slice(nodes);
    for (_, b) in channels {
        out.extend_from_slice(b);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::attribute::AttributeLayout;
    use crate::limits::MAX_TREELET_MESSAGE_BYTES;
    use crate::scene::{BuildParameters, SceneStats, SourceKind};
    use proptest::prelude::*;

    fn scene() -> SceneDescription {
        SceneDescription {
            name: "lion".into(),
            origin: [1.5, -2.25, 1e6],
            edge: 3.0,
            treelet_nodes: 512,
            max_depth: 12,
            layout: AttributeLayout::new([Channel::Color, Channel::Normal]),
            treelet_count: 3658,
            root_treelet: TreeletId::ROOT,
            source_kind: SourceKind::Points,
            source: "lion.las".into(),
            primitives: 1_000_000,
            build: BuildParameters {
                requested_depth: Some(12),
                data_resolution: 0.001,
                treelet_bytes: 4096,
                iso: None,
                zstd_level: 9,
                dictionary: true,
            },
            stats: SceneStats::default(),
            node_dictionary: Some(vec![7; 3000]),
            channel_dictionaries: vec![None, None],
        }
    }

    fn hello() -> Frame {
        Frame::Hello {
            version: PROTOCOL_VERSION,
            scene: "lion".into(),
            channels: vec![Channel::Normal, Channel::Color],
            token: "s3cret-ü".into(),
            flags: 0,
            view: None,
        }
    }

    fn all_frames() -> Vec<Frame> {
        vec![
            hello(),
            Frame::Hello {
                version: PROTOCOL_VERSION,
                scene: "a".into(),
                channels: vec![],
                token: String::new(),
                flags: 0,
                view: None,
            },
            Frame::Hello {
                version: PROTOCOL_VERSION,
                scene: "b".into(),
                channels: vec![Channel::Color],
                token: String::new(),
                flags: crate::wire::HELLO_GRANT_AVAILABLE | crate::wire::HELLO_SEND_ROOT,
                view: None,
            },
            Frame::Hello {
                version: PROTOCOL_VERSION,
                scene: "c".into(),
                channels: vec![],
                token: String::new(),
                flags: HELLO_SEND_ROOT | HELLO_VIEW,
                view: Some(view()),
            },
            Frame::SceneInfo {
                description: Box::new(scene()),
            },
            Frame::RequestList {
                seq: u64::MAX,
                items: vec![
                    (TreeletId(0), 1.5),
                    (TreeletId(7), -3.25),
                    (TreeletId(7), f32::MAX),
                    (TreeletId(u32::MAX - 1), -0.0),
                ],
            },
            Frame::RequestList {
                seq: 0,
                items: vec![],
            },
            Frame::error(ErrorCode::UnknownScene, "no scene \"x\""),
            Frame::Goodbye {
                code: ErrorCode::ShuttingDown,
            },
        ]
    }

    /// A raw frame with a correct length prefix.
    fn raw(ty: u8, payload: &[u8]) -> Vec<u8> {
        let mut v = (payload.len() as u32).to_le_bytes().to_vec();
        v.push(ty);
        v.extend_from_slice(payload);
        v
    }

    fn list_payload(seq: u64, items: &[(u32, f32)]) -> Vec<u8> {
        let mut p = seq.to_le_bytes().to_vec();
        p.extend_from_slice(&(items.len() as u32).to_le_bytes());
        for (id, pr) in items {
            p.extend_from_slice(&id.to_le_bytes());
            p.extend_from_slice(&pr.to_bits().to_le_bytes());
        }
        p
    }

    fn hello_payload(version: u16, scene: &[u8], channels: &[u8], token: &[u8]) -> Vec<u8> {
        let mut p = version.to_le_bytes().to_vec();
        p.extend_from_slice(&(scene.len() as u16).to_le_bytes());
        p.extend_from_slice(scene);
        p.push(channels.len() as u8);
        p.extend_from_slice(channels);
        p.extend_from_slice(&(token.len() as u16).to_le_bytes());
        p.extend_from_slice(token);
        p
    }

    #[test]
    fn every_frame_round_trips() {
        for f in all_frames() {
            let bytes = encode(&f).unwrap();
            assert_eq!(check(&bytes).unwrap(), Some(bytes.len()), "{f:?}");
            assert_eq!(parse(&bytes).unwrap(), f);
            // Every strict prefix is incomplete, never an error.
            for cut in 0..bytes.len().min(64) {
                assert_eq!(check(&bytes[..cut]).unwrap(), None);
            }
            assert_eq!(check(&bytes[..bytes.len() - 1]).unwrap(), None);
        }
    }

    fn view() -> ViewHint {
        ViewHint {
            eye: [1.0, -2.0, 3e5],
            forward: [0.0, 0.0, -1.0],
            up: [0.0, 1.0, 0.0],
            tan_half_fov_y: 0.5,
            aspect: 1.5,
            footprint: 0.002,
            free_slots: 900,
        }
    }

    #[test]
    fn hello_views_go_with_their_flag_and_hostile_ones_are_refused() {
        let with_view = |flags: u8, view: Option<ViewHint>| Frame::Hello {
            version: PROTOCOL_VERSION,
            scene: "lion".into(),
            channels: vec![Channel::Color],
            token: String::new(),
            flags,
            view,
        };
        let f = with_view(HELLO_SEND_ROOT | HELLO_VIEW, Some(view()));
        let bytes = encode(&f).unwrap();
        assert_eq!(parse(&bytes).unwrap(), f);
        // The view is the last field: cut it short and the frame is truncated.
        let len = bytes.len() - FRAME_HEADER_BYTES - 1;
        let mut short = bytes[..bytes.len() - 1].to_vec();
        short[..4].copy_from_slice(&(len as u32).to_le_bytes());
        assert!(matches!(
            parse(&short).unwrap_err(),
            FrameError::Truncated { .. }
        ));
        // Flag and view go together; the view needs the root sent.
        for bad in [
            with_view(HELLO_SEND_ROOT, Some(view())),
            with_view(HELLO_SEND_ROOT | HELLO_VIEW, None),
            with_view(HELLO_VIEW, Some(view())),
        ] {
            let e = encode(&bad).unwrap_err();
            assert!(matches!(e, FrameError::BadHelloView(_)), "{e}");
        }
        let mut forged = bytes.clone();
        let flags_at = forged.len() - ViewHint::BYTES - 1;
        forged[flags_at] = HELLO_VIEW;
        let e = parse(&forged).unwrap_err();
        assert!(matches!(e, FrameError::BadHelloView(_)), "{e}");
        assert_eq!(e.code(), ErrorCode::ProtocolViolation);
        // A hostile view (NaN eye) is refused by the decoder as in a deep list.
        let mut forged = bytes.clone();
        let eye_at = forged.len() - ViewHint::BYTES;
        forged[eye_at..eye_at + 8].copy_from_slice(&f64::NAN.to_bits().to_le_bytes());
        let e = parse(&forged).unwrap_err();
        assert!(matches!(e, FrameError::BadView(_)), "{e}");
        let mut hostile = view();
        hostile.free_slots = u32::MAX;
        let e = encode(&with_view(HELLO_SEND_ROOT | HELLO_VIEW, Some(hostile))).unwrap_err();
        assert!(matches!(e, FrameError::BadView(_)), "{e}");
    }

    /// A ranked list as its payload would be laid out by hand, for forging.
    fn ranked_bytes(count: u32, items: &[u8]) -> Vec<u8> {
        let good = encode(&Frame::RankedRequestList {
            seq: 4,
            view: view(),
            items: vec![],
            prefetch_from: 0,
        })
        .unwrap();
        let mut out = good[..good.len() - 4].to_vec();
        out.extend_from_slice(&count.to_le_bytes());
        out.extend_from_slice(items);
        let len = (out.len() - FRAME_HEADER_BYTES) as u32;
        out[..4].copy_from_slice(&len.to_le_bytes());
        out
    }

    #[test]
    fn ranked_request_lists_round_trip_in_a_third_of_a_deep_lists_bytes() {
        // Ids going up and down, near and far apart, the largest and the smallest.
        let ids = [5u32, 6, 7, 4, 1_000_000, 999_990, 0, u32::MAX - 1, 3, 3];
        let items: Vec<(TreeletId, i16)> = ids
            .iter()
            .enumerate()
            .map(|(i, &id)| (TreeletId(id), (i as i16 - 5) * 3001))
            .collect();
        let f = Frame::RankedRequestList {
            seq: 77,
            view: view(),
            items: items.clone(),
            prefetch_from: 6,
        };
        let bytes = encode(&f).unwrap();
        assert_eq!(parse(&bytes).unwrap(), f);
        let mut d = FrameDecoder::for_server();
        assert_eq!(d.push(&bytes), bytes.len());
        assert_eq!(d.next().unwrap(), Some(f));

        // The deep list it stands for: rank as priority, errors in levels.
        let deep = crate::wire::ranked_as_deep(&items);
        assert_eq!(deep.len(), items.len());
        assert!(deep.windows(2).all(|w| w[0].1 > w[1].1 && w[1].1 >= 1.0));
        assert_eq!((deep[0].0, deep[0].2), (TreeletId(5), -15005.0 / 512.0));

        // A list as a view's: runs of siblings, a few jumps. About 4 bytes an item, against 12.
        let view_list: Vec<(TreeletId, i16)> = (0..4000u32)
            .map(|i| (TreeletId(50_000 + (i / 8) * 37 + i % 8), (i % 300) as i16))
            .collect();
        let ranked = encode(&Frame::RankedRequestList {
            seq: 1,
            view: view(),
            items: view_list.clone(),
            prefetch_from: 0,
        })
        .unwrap();
        let deep = encode(&Frame::DeepRequestList {
            seq: 1,
            view: view(),
            items: crate::wire::ranked_as_deep(&view_list),
            prefetch_from: 0,
        })
        .unwrap();
        assert!(
            ranked.len() * 3 < deep.len(),
            "{} against {} bytes",
            ranked.len(),
            deep.len()
        );

        let e = encode(&Frame::RankedRequestList {
            seq: 1,
            view: view(),
            items: vec![(TreeletId::NONE, 0)],
            prefetch_from: 0,
        })
        .unwrap_err();
        assert_eq!(e, FrameError::NoneTreeletId { index: 0 });
        let e = encode(&Frame::RankedRequestList {
            seq: 1,
            view: view(),
            items: vec![(TreeletId(1), 0)],
            prefetch_from: 2,
        })
        .unwrap_err();
        assert!(matches!(e, FrameError::BadPrefetchStart { .. }), "{e}");
    }

    #[test]
    fn hostile_ranked_request_lists_are_refused_before_anything_is_allocated() {
        // A varint of six bytes.
        let e = parse(&ranked_bytes(
            1,
            &[0x80, 0x80, 0x80, 0x80, 0x80, 0x01, 0, 0],
        ))
        .unwrap_err();
        assert_eq!(e, FrameError::BadVarint { index: 0 });
        assert_eq!(e.code(), ErrorCode::ProtocolViolation);
        // Below id 0: zigzag 1 is -1.
        let e = parse(&ranked_bytes(1, &[0x01, 0, 0])).unwrap_err();
        assert_eq!(
            e,
            FrameError::BadIdDelta {
                index: 0,
                previous: 0,
                delta: -1
            }
        );
        // To NONE and beyond: 2 × (2³² − 1) and 2 × 2³² as five-byte varints.
        for (zigzag, delta) in [(0x1_FFFF_FFFEu64, 0xFFFF_FFFFi64), (0x2_0000_0000, 1 << 32)] {
            let mut v = Vec::new();
            put_varint(&mut v, zigzag);
            assert_eq!(v.len(), 5);
            v.extend_from_slice(&[0, 0]);
            let e = parse(&ranked_bytes(1, &v)).unwrap_err();
            assert_eq!(
                e,
                FrameError::BadIdDelta {
                    index: 0,
                    previous: 0,
                    delta
                }
            );
        }
        // A count the bytes cannot hold, refused before the items are read or allocated.
        let e = parse(&ranked_bytes(65_536, &[2, 0, 0])).unwrap_err();
        assert!(
            matches!(e, FrameError::Truncated { need, .. } if need == 3 * 65_536),
            "{e}"
        );
        let e = parse(&ranked_bytes(65_537, &[])).unwrap_err();
        assert!(matches!(e, FrameError::ListTooLong { .. }), "{e}");
        // An item cut in its error, and an item too many.
        let e = parse(&ranked_bytes(1, &[0x82, 0x01, 0])).unwrap_err();
        assert!(matches!(e, FrameError::Truncated { .. }), "{e}");
        let e = parse(&ranked_bytes(1, &[2, 0, 0, 9])).unwrap_err();
        assert!(matches!(e, FrameError::TrailingBytes { .. }), "{e}");
        // Every i16 is an error within ±64 levels.
        assert_eq!(crate::wire::error_levels(i16::MIN), -ViewHint::MAX_ERROR);
        assert!(crate::wire::error_levels(i16::MAX) < ViewHint::MAX_ERROR);
    }

    #[test]
    fn errors_become_steps_to_the_nearest_and_within_the_limit() {
        use crate::wire::{ERROR_STEPS_PER_LEVEL, error_levels, error_steps};
        for levels in [0.0f32, 1.0, -2.5, 0.001, 63.99, -63.99, 17.123_456] {
            let back = error_levels(error_steps(levels));
            assert!(
                (back - levels).abs() <= 0.5 / ERROR_STEPS_PER_LEVEL,
                "{levels} → {back}"
            );
        }
        assert_eq!(error_steps(64.0), i16::MAX);
        assert_eq!(error_steps(1e30), i16::MAX);
        assert_eq!(error_steps(-1e30), -i16::MAX);
        assert_eq!(error_steps(f32::INFINITY), i16::MAX);
        assert_eq!(error_steps(f32::NAN), 0);
        assert_eq!(crate::wire::ranked_priority(0, 3), 3.0);
        assert_eq!(crate::wire::ranked_priority(2, 3), 1.0);
        assert_eq!(
            crate::wire::ranked_priority(0, crate::limits::MAX_REQUEST_ITEMS),
            65_536.0
        );
    }

    #[test]
    fn deep_request_lists_round_trip_and_hostile_views_are_refused() {
        let f = Frame::DeepRequestList {
            seq: 9,
            view: view(),
            items: vec![(TreeletId(5), 3.0, 2.5), (TreeletId(7), 1.0, -64.0)],
            prefetch_from: 1,
        };
        let bytes = encode(&f).unwrap();
        assert_eq!(bytes.len(), 5 + 8 + ViewHint::BYTES + 4 + 4 + 2 * 12);
        assert_eq!(parse(&bytes).unwrap(), f);
        let mut d = FrameDecoder::for_server();
        assert_eq!(d.push(&bytes), bytes.len());
        assert_eq!(d.next().unwrap(), Some(f));
        type Damage = fn(&mut ViewHint);
        let bad_views: [(&str, Damage); 8] = [
            ("NaN eye", |v| v.eye[1] = f64::NAN),
            ("eye too far", |v| v.eye[0] = 1e300),
            ("zero forward", |v| v.forward = [0.0; 3]),
            ("not orthogonal", |v| v.up = [0.0, 0.0, -1.0]),
            ("fov", |v| v.tan_half_fov_y = f32::INFINITY),
            ("aspect", |v| v.aspect = 0.0),
            ("footprint", |v| v.footprint = f32::NAN),
            ("free slots", |v| v.free_slots = u32::MAX),
        ];
        for (what, damage) in bad_views {
            let mut v = view();
            damage(&mut v);
            assert!(v.check().is_err(), "{what}");
            // Encode refuses it, and so does the decoder when forged.
            let good = encode(&Frame::DeepRequestList {
                seq: 1,
                view: view(),
                items: vec![],
                prefetch_from: 0,
            })
            .unwrap();
            assert!(
                encode(&Frame::DeepRequestList {
                    seq: 1,
                    view: v,
                    items: vec![],
                    prefetch_from: 0,
                })
                .is_err(),
                "{what}"
            );
            let mut forged = good.clone();
            let mut payload = Vec::new();
            for c in v.eye {
                payload.extend_from_slice(&c.to_bits().to_le_bytes());
            }
            for c in v
                .forward
                .iter()
                .chain(&v.up)
                .chain(&[v.tan_half_fov_y, v.aspect, v.footprint])
            {
                payload.extend_from_slice(&c.to_bits().to_le_bytes());
            }
            payload.extend_from_slice(&v.free_slots.to_le_bytes());
            forged[13..13 + ViewHint::BYTES].copy_from_slice(&payload);
            let e = parse(&forged).unwrap_err();
            assert!(matches!(e, FrameError::BadView(_)), "{what}: {e}");
            assert_eq!(e.code(), ErrorCode::ProtocolViolation);
        }
        for error in [f32::NAN, f32::INFINITY, 65.0, -1e9] {
            let f = Frame::DeepRequestList {
                seq: 1,
                view: view(),
                items: vec![(TreeletId(1), 1.0, error)],
                prefetch_from: 1,
            };
            assert!(encode(&f).is_err());
            let mut forged = encode(&Frame::DeepRequestList {
                seq: 1,
                view: view(),
                items: vec![(TreeletId(1), 1.0, 0.0)],
                prefetch_from: 1,
            })
            .unwrap();
            let at = forged.len() - 4;
            forged[at..].copy_from_slice(&error.to_bits().to_le_bytes());
            let e = parse(&forged).unwrap_err();
            assert!(matches!(e, FrameError::BadError { index: 0, .. }), "{e}");
        }
        // A prefetch start beyond the items: refused by the encoder, and forged, by the decoder.
        let two = |prefetch_from| Frame::DeepRequestList {
            seq: 1,
            view: view(),
            items: vec![(TreeletId(1), 2.0, 0.0), (TreeletId(2), 1.0, 0.0)],
            prefetch_from,
        };
        assert!(encode(&two(2)).is_ok());
        let e = encode(&two(3)).unwrap_err();
        assert!(
            matches!(
                e,
                FrameError::BadPrefetchStart {
                    prefetch_from: 3,
                    count: 2
                }
            ),
            "{e}"
        );
        for start in [3, u32::MAX] {
            let mut forged = encode(&two(0)).unwrap();
            let at = 5 + 8 + ViewHint::BYTES;
            forged[at..at + 4].copy_from_slice(&start.to_le_bytes());
            let e = parse(&forged).unwrap_err();
            assert!(matches!(e, FrameError::BadPrefetchStart { .. }), "{e}");
            assert_eq!(e.code(), ErrorCode::ProtocolViolation);
        }
    }

    #[test]
    fn request_list_layout_is_as_documented() {
        let f = Frame::RequestList {
            seq: 2,
            items: vec![(TreeletId(5), 1.0)],
        };
        let bytes = encode(&f).unwrap();
        assert_eq!(bytes, raw(3, &list_payload(2, &[(5, 1.0)])));
        assert_eq!(&bytes[..5], &[20, 0, 0, 0, 3]);
    }

    #[test]
    fn decoder_yields_frames_across_arbitrary_splits() {
        let frames = all_frames();
        let stream: Vec<u8> = frames.iter().flat_map(|f| encode(f).unwrap()).collect();
        for step in [1, 2, 3, 5, 7, 64, 4096, stream.len()] {
            let mut d = FrameDecoder::for_client();
            let mut got = vec![];
            for chunk in stream.chunks(step) {
                let mut rest = chunk;
                loop {
                    let n = d.push(rest);
                    rest = &rest[n..];
                    while let Some(f) = d.next().unwrap() {
                        got.push(f);
                    }
                    if rest.is_empty() {
                        break;
                    }
                }
            }
            assert_eq!(got, frames, "step {step}");
            assert_eq!(d.buffered(), 0);
        }
    }

    #[test]
    fn push_takes_only_what_fits() {
        let mut d = FrameDecoder::new(100);
        assert_eq!(d.capacity(), 105);
        let f = encode(&Frame::Goodbye {
            code: ErrorCode::NoError,
        })
        .unwrap();
        let stream: Vec<u8> = f.iter().copied().cycle().take(f.len() * 100).collect();
        let mut rest = &stream[..];
        let mut frames = 0;
        while !rest.is_empty() {
            let n = d.push(rest);
            assert!(d.buffered() <= d.capacity());
            rest = &rest[n..];
            while d.next().unwrap().is_some() {
                frames += 1;
            }
        }
        assert_eq!(frames, 100);
    }

    #[test]
    fn truncated_length_prefix_is_incomplete_not_an_error() {
        let bytes = encode(&hello()).unwrap();
        for cut in 0..4 {
            assert_eq!(check(&bytes[..cut]), Ok(None));
            assert!(matches!(
                parse(&bytes[..cut]),
                Err(FrameError::Truncated { .. })
            ));
        }
        let mut d = FrameDecoder::for_server();
        d.push(&bytes[..3]);
        assert_eq!(d.next(), Ok(None));
    }

    #[test]
    fn over_limit_length_is_rejected_before_the_payload() {
        let len = (MAX_FRAME_BYTES as u32 + 1).to_le_bytes();
        let e = check_with_limit(&len, MAX_FRAME_BYTES).unwrap_err();
        assert_eq!(
            e,
            FrameError::TooLarge {
                len: MAX_FRAME_BYTES + 1,
                limit: MAX_FRAME_BYTES
            }
        );
        assert_eq!(e.code(), ErrorCode::FrameTooLarge);
        // The decoder of a server says so with 4 bytes in and has buffered nothing more.
        let mut d = FrameDecoder::for_server();
        assert_eq!(d.push(&len), 4);
        assert_eq!(d.next().unwrap_err().code(), ErrorCode::FrameTooLarge);
        assert_eq!(d.buffered(), 0);
        assert_eq!(d.push(&[0; 100]), 0, "poisoned decoder takes nothing");
        assert_eq!(d.next().unwrap_err().code(), ErrorCode::FrameTooLarge);
        // The largest length overall is refused even by a client, from the prefix alone.
        let huge = u32::MAX.to_le_bytes();
        assert!(matches!(check(&huge), Err(FrameError::TooLarge { .. })));
        // A non-SceneInfo type with a SceneInfo-sized length is refused at the type byte.
        let mut b = ((MAX_FRAME_BYTES + 1) as u32).to_le_bytes().to_vec();
        assert_eq!(check(&b), Ok(None));
        b.push(FrameType::RequestList as u8);
        assert!(matches!(check(&b), Err(FrameError::TooLarge { .. })));
        b[4] = FrameType::SceneInfo as u8;
        assert_eq!(check(&b), Ok(None));
    }

    #[test]
    fn unknown_type_is_rejected() {
        for t in [0u8, 8, 0xff] {
            let b = raw(t, &[]);
            assert_eq!(check(&b), Err(FrameError::UnknownType(t)));
            assert_eq!(parse(&b), Err(FrameError::UnknownType(t)));
            assert_eq!(
                FrameError::UnknownType(t).code(),
                ErrorCode::ProtocolViolation
            );
        }
    }

    #[test]
    fn trailing_bytes_are_rejected() {
        // Inside the payload.
        let mut p = 0u32.to_le_bytes().to_vec();
        p.push(0);
        let e = parse(&raw(FrameType::Goodbye as u8, &p)).unwrap_err();
        assert_eq!(
            e,
            FrameError::TrailingBytes {
                what: "Goodbye frame",
                extra: 1
            }
        );
        let mut p = list_payload(1, &[(1, 1.0)]);
        p.extend_from_slice(&[0; 8]);
        assert!(matches!(
            parse(&raw(3, &p)),
            Err(FrameError::TrailingBytes { .. })
        ));
        let mut p = hello_payload(PROTOCOL_VERSION, b"lion", &[0], b"");
        // One byte after the token is the flags; unknown flags are refused, and a second byte
        // is trailing.
        p.push(9);
        assert_eq!(parse(&raw(1, &p)), Err(FrameError::UnknownFlags(9)));
        p.pop();
        p.extend_from_slice(&[1, 9]);
        assert!(matches!(
            parse(&raw(1, &p)),
            Err(FrameError::TrailingBytes { .. })
        ));
        // After the frame.
        let mut b = encode(&hello()).unwrap();
        b.push(0);
        assert!(matches!(
            parse(&b),
            Err(FrameError::TrailingBytes { what: "frame", .. })
        ));
        // Fields running past the payload.
        let p = list_payload(1, &[(1, 1.0), (2, 2.0)]);
        assert!(matches!(
            parse(&raw(3, &p[..p.len() - 1])),
            Err(FrameError::Truncated { .. })
        ));
    }

    #[test]
    fn non_finite_priorities_and_none_ids_are_rejected() {
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let e = parse(&raw(3, &list_payload(1, &[(1, 0.5), (2, bad)]))).unwrap_err();
            assert_eq!(
                e,
                FrameError::NonFinitePriority {
                    index: 1,
                    treelet: TreeletId(2)
                }
            );
            assert_eq!(e.code(), ErrorCode::ProtocolViolation);
            let f = Frame::RequestList {
                seq: 1,
                items: vec![(TreeletId(2), bad)],
            };
            assert!(encode(&f).is_err());
        }
        assert_eq!(
            parse(&raw(3, &list_payload(1, &[(u32::MAX, 0.5)]))),
            Err(FrameError::NoneTreeletId { index: 0 })
        );
    }

    #[test]
    fn list_over_the_limit_is_rejected() {
        // The count alone decides; the items need not be there.
        let mut p = 1u64.to_le_bytes().to_vec();
        p.extend_from_slice(&(MAX_REQUEST_ITEMS as u32 + 1).to_le_bytes());
        let e = parse(&raw(3, &p)).unwrap_err();
        assert_eq!(e.code(), ErrorCode::ListTooLong);
        // A full over-limit list fits the frame limit and is still refused.
        let items: Vec<(u32, f32)> = (0..=MAX_REQUEST_ITEMS as u32).map(|i| (i, 1.0)).collect();
        let b = raw(3, &list_payload(1, &items));
        assert!(b.len() - FRAME_HEADER_BYTES <= MAX_FRAME_BYTES);
        assert_eq!(parse(&b).unwrap_err().code(), ErrorCode::ListTooLong);
        let f = Frame::RequestList {
            seq: 1,
            items: items.iter().map(|&(i, p)| (TreeletId(i), p)).collect(),
        };
        assert_eq!(encode(&f).unwrap_err().code(), ErrorCode::ListTooLong);
        // Exactly the limit is fine.
        let f = Frame::RequestList {
            seq: 1,
            items: (0..MAX_REQUEST_ITEMS as u32)
                .map(|i| (TreeletId(i), 1.0))
                .collect(),
        };
        assert_eq!(parse(&encode(&f).unwrap()).unwrap(), f);
        // A count larger than the bytes present is truncation, not an allocation.
        let mut p = 1u64.to_le_bytes().to_vec();
        p.extend_from_slice(&1000u32.to_le_bytes());
        assert!(matches!(
            parse(&raw(3, &p)),
            Err(FrameError::Truncated { .. })
        ));
    }

    #[test]
    fn bad_strings_are_rejected() {
        let e = parse(&raw(
            1,
            &hello_payload(PROTOCOL_VERSION, b"li\xffon", &[], b""),
        ))
        .unwrap_err();
        assert_eq!(e, FrameError::BadUtf8 { what: "scene name" });
        let e = parse(&raw(
            1,
            &hello_payload(PROTOCOL_VERSION, b"lion", &[], b"\xc3"),
        ))
        .unwrap_err();
        assert_eq!(
            e,
            FrameError::BadUtf8 {
                what: "access token"
            }
        );
        let mut p = 4u32.to_le_bytes().to_vec();
        p.extend_from_slice(&2u16.to_le_bytes());
        p.extend_from_slice(b"\xc0\x80");
        assert!(matches!(
            parse(&raw(4, &p)),
            Err(FrameError::BadUtf8 { .. })
        ));
        // Over-long token: decided by its length field.
        let token = vec![b'a'; MAX_TOKEN_BYTES + 1];
        let e = parse(&raw(
            1,
            &hello_payload(PROTOCOL_VERSION, b"lion", &[], &token),
        ))
        .unwrap_err();
        assert!(matches!(
            e,
            FrameError::FieldTooLong {
                what: "access token",
                ..
            }
        ));
        let f = Frame::Hello {
            version: PROTOCOL_VERSION,
            scene: "lion".into(),
            channels: vec![],
            token: "a".repeat(MAX_TOKEN_BYTES + 1),
            flags: 0,
            view: None,
        };
        assert!(encode(&f).is_err());
        // Over-long error message.
        let f = Frame::Error {
            code: ErrorCode::Internal,
            message: "x".repeat(MAX_MESSAGE_BYTES + 1),
        };
        assert!(encode(&f).is_err());
    }

    #[test]
    fn bad_scene_names_are_rejected() {
        for name in [&b""[..], b".hidden", b"a b", b"../etc", &[b'a'; 129]] {
            let e = parse(&raw(1, &hello_payload(PROTOCOL_VERSION, name, &[], b""))).unwrap_err();
            assert!(matches!(e, FrameError::BadSceneName(_)), "{name:?}: {e}");
            assert_eq!(e.code(), ErrorCode::UnknownScene);
        }
    }

    #[test]
    fn hello_channel_and_version_errors() {
        let e = parse(&raw(
            1,
            &hello_payload(PROTOCOL_VERSION, b"lion", &[0; 9], b""),
        ))
        .unwrap_err();
        assert_eq!(
            e,
            FrameError::TooManyChannels {
                count: 9,
                limit: MAX_CHANNELS
            }
        );
        assert_eq!(e.code(), ErrorCode::TooManyChannels);
        let e = parse(&raw(
            1,
            &hello_payload(PROTOCOL_VERSION, b"lion", &[1, 7], b""),
        ))
        .unwrap_err();
        assert_eq!(e, FrameError::UnknownChannel(7));
        assert_eq!(e.code(), ErrorCode::UnknownChannel);
        let e = parse(&raw(
            1,
            &hello_payload(PROTOCOL_VERSION, b"lion", &[1, 1], b""),
        ))
        .unwrap_err();
        assert_eq!(e, FrameError::DuplicateChannel(Channel::Normal));
        // A future version is answered with UnsupportedVersion whatever follows it.
        let future = PROTOCOL_VERSION + 1;
        let mut p = future.to_le_bytes().to_vec();
        p.extend_from_slice(b"anything at all");
        let e = parse(&raw(1, &p)).unwrap_err();
        assert_eq!(e, FrameError::UnsupportedVersion { found: future });
        assert_eq!(e.code(), ErrorCode::UnsupportedVersion);
        let f = Frame::Hello {
            version: PROTOCOL_VERSION,
            scene: "lion".into(),
            channels: vec![Channel::Color; 9],
            token: String::new(),
            flags: 0,
            view: None,
        };
        assert_eq!(encode(&f).unwrap_err().code(), ErrorCode::TooManyChannels);
    }

    #[test]
    fn bad_codes_and_scene_info_are_rejected() {
        assert_eq!(
            parse(&raw(5, &99u32.to_le_bytes())),
            Err(FrameError::UnknownErrorCode(99))
        );
        let e = parse(&raw(2, b"not a scene")).unwrap_err();
        assert!(matches!(e, FrameError::SceneDescription(_)));
        let mut s = scene();
        s.edge = -1.0;
        assert!(
            encode(&Frame::SceneInfo {
                description: Box::new(s)
            })
            .is_err()
        );
    }

    fn message_parts() -> (Vec<u8>, Vec<u8>, Vec<u8>) {
        (vec![1; 300], vec![2; 20], vec![3; 7])
    }

    #[test]
    fn treelet_message_round_trips() {
        let (n, c, d) = message_parts();
        let chans = [(Channel::Color, &c[..]), (Channel::Density, &d[..])];
        let m = encode_treelet_message(TreeletId(42), 77, &n, &chans).unwrap();
        assert_eq!(m.len(), 4 + 2 + 1 + 2 * 5 + 4 + 300 + 20 + 7);
        assert_eq!(check_treelet_message(&m), Ok(Some(m.len())));
        for cut in 0..m.len() {
            assert_eq!(check_treelet_message(&m[..cut]), Ok(None));
            assert!(decode_treelet_message(&m[..cut]).is_err());
        }
        let t = decode_treelet_message(&m).unwrap();
        assert_eq!(t.id, TreeletId(42));
        assert_eq!(t.used_nodes, 77);
        assert_eq!(t.nodes, &n[..]);
        assert_eq!(t.channels, chans.to_vec());
        // Two messages back to back: the first is delimited exactly.
        let mut two = m.clone();
        two.extend_from_slice(&m);
        assert_eq!(check_treelet_message(&two), Ok(Some(m.len())));
        assert!(matches!(
            decode_treelet_message(&two),
            Err(FrameError::TrailingBytes { .. })
        ));
        // No channels.
        let m = encode_treelet_message(TreeletId(0), 1, &n, &[]).unwrap();
        assert_eq!(decode_treelet_message(&m).unwrap().channels, vec![]);
    }

    #[test]
    fn hostile_treelet_messages_are_rejected() {
        let (n, c, _) = message_parts();
        let good = encode_treelet_message(TreeletId(1), 5, &n, &[(Channel::Normal, &c)]).unwrap();
        let patch = |at: usize, bytes: &[u8]| {
            let mut m = good.clone();
            m[at..at + bytes.len()].copy_from_slice(bytes);
            m
        };
        // Header decided before the blocks arrive.
        let e = check_treelet_message(&patch(0, &u32::MAX.to_le_bytes())[..4]).unwrap_err();
        assert_eq!(e, FrameError::NoneTreeletId { index: 0 });
        let e = check_treelet_message(&patch(4, &0u16.to_le_bytes())[..6]).unwrap_err();
        assert_eq!(e, FrameError::BadUsedNodes(0));
        let e = check_treelet_message(&patch(4, &2049u16.to_le_bytes())).unwrap_err();
        assert_eq!(e, FrameError::BadUsedNodes(2049));
        let e = check_treelet_message(&patch(6, &[9])[..7]).unwrap_err();
        assert_eq!(e.code(), ErrorCode::TooManyChannels);
        let e = check_treelet_message(&patch(7, &[5])[..8]).unwrap_err();
        assert_eq!(e, FrameError::UnknownChannel(5));
        let big = (MAX_COMPRESSED_BLOCK as u32 + 1).to_le_bytes();
        let e = check_treelet_message(&patch(8, &big)[..12]).unwrap_err();
        assert!(matches!(e, FrameError::BadBlockLength { .. }));
        let e = check_treelet_message(&patch(12, &0u32.to_le_bytes())[..16]).unwrap_err();
        assert!(matches!(
            e,
            FrameError::BadBlockLength {
                what: "node block",
                len: 0,
                ..
            }
        ));
        // Wrong total length.
        let mut long = good.clone();
        long.push(0);
        assert!(matches!(
            decode_treelet_message(&long),
            Err(FrameError::TrailingBytes { extra: 1, .. })
        ));
        // Channels out of order or repeated.
        for chans in [
            [(Channel::Normal, &c[..]), (Channel::Color, &c[..])],
            [(Channel::Normal, &c[..]), (Channel::Normal, &c[..])],
        ] {
            assert!(encode_treelet_message(TreeletId(1), 5, &n, &chans).is_err());
            let mut m = encode_treelet_message(
                TreeletId(1),
                5,
                &n,
                &[(Channel::Color, &c[..]), (Channel::Density, &c[..])],
            )
            .unwrap();
            m[7] = chans[0].0.id();
            m[12] = chans[1].0.id();
            assert!(matches!(
                decode_treelet_message(&m),
                Err(FrameError::DuplicateChannel(_))
            ));
        }
        assert!(encode_treelet_message(TreeletId(1), 5, &[], &[]).is_err());
        assert!(encode_treelet_message(TreeletId(1), 0, &n, &[]).is_err());
    }

    #[test]
    fn limits_are_consistent() {
        let h = TreeletMessageHeader {
            id: TreeletId(0),
            used_nodes: 1,
            node_len: MAX_COMPRESSED_BLOCK,
            channels: {
                let mut c = ChannelBlocks::new();
                for _ in 0..MAX_CHANNELS {
                    c.push((Channel::Color, MAX_COMPRESSED_BLOCK));
                }
                c
            },
            header_len: crate::limits::MAX_TREELET_MESSAGE_HEADER,
        };
        assert_eq!(h.total_len(), MAX_TREELET_MESSAGE_BYTES);
        assert_eq!(FrameDecoder::for_server().capacity(), 5 + MAX_FRAME_BYTES);
        assert_eq!(
            FrameDecoder::for_client().capacity(),
            5 + MAX_CONTROL_FRAME_BYTES
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

        /// Arbitrary bytes in arbitrary pieces: no panic, the buffer stays within its bound, and
        /// the decoder never stalls (a full buffer yields a frame or an error).
        #[test]
        fn decoder_never_panics_or_overbuffers(
            data in proptest::collection::vec(any::<u8>(), 0..4096),
            pieces in proptest::collection::vec(1usize..300, 1..64),
            limit in prop_oneof![Just(MAX_FRAME_BYTES), 0usize..200],
        ) {
            let mut d = FrameDecoder::new(limit);
            let mut rest = &data[..];
            let mut i = 0;
            'feed: while !rest.is_empty() {
                let piece = pieces[i % pieces.len()].min(rest.len());
                i += 1;
                let mut chunk = &rest[..piece];
                rest = &rest[piece..];
                while !chunk.is_empty() {
                    let n = d.push(chunk);
                    prop_assert!(d.buffered() <= d.capacity());
                    chunk = &chunk[n..];
                    let mut progressed = n > 0;
                    loop {
                        match d.next() {
                            Ok(Some(f)) => {
                                progressed = true;
                                // Whatever decodes re-encodes to a frame that decodes the same.
                                prop_assert_eq!(parse(&encode(&f).unwrap()).unwrap(), f);
                            }
                            Ok(None) => break,
                            Err(_) => break 'feed,
                        }
                    }
                    prop_assert!(progressed, "decoder stalled");
                }
            }
        }

        /// Valid frames with garbage around them decode, through the decoder, to themselves.
        #[test]
        fn random_request_lists_round_trip(
            seq in any::<u64>(),
            items in proptest::collection::vec((0u32..u32::MAX, -1e30f32..1e30), 0..200),
            step in 1usize..100,
        ) {
            let f = Frame::RequestList {
                seq,
                items: items.into_iter().map(|(i, p)| (TreeletId(i), p)).collect(),
            };
            let bytes = encode(&f).unwrap();
            let mut d = FrameDecoder::for_server();
            let mut got = None;
            for chunk in bytes.chunks(step) {
                prop_assert_eq!(d.push(chunk), chunk.len());
                if let Some(g) = d.next().unwrap() {
                    got = Some(g);
                }
            }
            prop_assert_eq!(got, Some(f));
        }

        #[test]
        fn parse_never_panics(data in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = parse(&data);
            let _ = check(&data);
        }

        #[test]
        fn treelet_decoder_never_panics(data in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = check_treelet_message(&data);
            if let Ok(m) = decode_treelet_message(&data) {
                let chans: Vec<_> = m.channels.clone();
                let again = encode_treelet_message(m.id, m.used_nodes, m.nodes, &chans).unwrap();
                prop_assert_eq!(again, data);
            }
        }

        /// Mostly well-formed headers with small blocks, so decoding gets past the header.
        #[test]
        fn treelet_decoder_on_near_valid_input(
            id in 0u32..10,
            used in 0u16..3000,
            chans in proptest::collection::vec((0u8..4, 0u32..40), 0..4),
            node_len in 0u32..40,
            body in proptest::collection::vec(any::<u8>(), 0..200),
        ) {
            let mut m = id.to_le_bytes().to_vec();
            m.extend_from_slice(&used.to_le_bytes());
            m.push(chans.len() as u8);
            for (c, l) in &chans {
                m.push(*c);
                m.extend_from_slice(&l.to_le_bytes());
            }
            m.extend_from_slice(&node_len.to_le_bytes());
            m.extend_from_slice(&body);
            let _ = check_treelet_message(&m);
            if let Ok(t) = decode_treelet_message(&m) {
                prop_assert_eq!(t.id, TreeletId(id));
                prop_assert_eq!(t.nodes.len() as u32, node_len);
            }
        }
    }
}
