//! The Arbor network protocol's vocabulary (docs/design.md §6): ALPN, version, control frames and error
//! codes. The byte layout and its checks live in [`crate::frame`].
//!
//! A connection is QUIC with ALPN [`ALPN`]. The client opens one bidirectional **control
//! stream** and sends [`Frame::Hello`]; the server answers [`Frame::SceneInfo`] or
//! [`Frame::Error`] (then closes the connection with the same [`ErrorCode`]). From then on the
//! client sends a [`Frame::RequestList`] (or a [`Frame::DeepRequestList`], or its compact form
//! [`Frame::RankedRequestList`]) whenever its wishes change (every cycle); each list
//! **replaces** the previous one. Treelets come back on server-opened unidirectional streams as
//! treelet messages ([`crate::frame::encode_treelet_message`]). Either side may end with
//! [`Frame::Goodbye`] before closing.
//!
//! # Request-list semantics
//!
//! * Items are `(treelet id, priority)`; a higher priority is served first, ties by lower id.
//!   Priorities are any finite `f32` (the client's log-domain screen-space error may be negative);
//!   NaN and infinities are rejected by the decoder.
//! * An id may appear more than once; the server treats it as one request with the **largest** of
//!   its priorities. The decoder keeps the list exactly as sent; the collapse happens in the
//!   server's scheduler.
//! * A list whose `seq` is not larger than the last accepted one is stale and ignored (QUIC keeps
//!   one stream's frames in order, so this only guards against client bugs and future
//!   multi-stream clients).

use std::fmt;

use crate::attribute::Channel;
use crate::scene::SceneDescription;
use crate::treelet::TreeletId;

/// `Hello` flag: of the channels asked for, send those the scene stores instead of refusing
/// the others with [`ErrorCode::UnknownChannel`] (the client learns which from `SceneInfo`; it
/// need not ask the scene's channels on a connection of its own first).
pub const HELLO_GRANT_AVAILABLE: u8 = 1;
/// `Hello` flag: send the root treelet right after `SceneInfo`, unasked (saves the client the
/// round trip of requesting it).
pub const HELLO_SEND_ROOT: u8 = 2;
/// `Hello` flag: a [`ViewHint`] follows the flags, and the server sends along with the root
/// the descendants that view would refine ([`Frame::DeepRequestList`]'s pushes below the root,
/// as deep as the view refines, within the hint's free slots). Only with [`HELLO_SEND_ROOT`].
/// Bytes then flow while the client still builds its first list, one round trip earlier. The
/// client does not know where the scene lies before `SceneInfo`, so this view's eye is in
/// units of the scene's root cube: world = origin + eye × edge (directions and angles are the
/// same in both).
pub const HELLO_VIEW: u8 = 4;
/// Every `Hello` flag this build knows.
pub const HELLO_FLAGS: u8 = HELLO_GRANT_AVAILABLE | HELLO_SEND_ROOT | HELLO_VIEW;

/// QUIC ALPN of this protocol. A connection that negotiates anything else is refused by the TLS
/// handshake.
pub const ALPN: &[u8] = b"arbor/1";

/// Version carried in [`Frame::Hello`]. A server answers any other version with
/// [`ErrorCode::UnsupportedVersion`].
pub const PROTOCOL_VERSION: u16 = 3;

/// Why a connection, a stream or a request ended. Sent in [`Frame::Error`] and
/// [`Frame::Goodbye`], and used unchanged as the QUIC application close code (and stream reset
/// code), so a client sees the same number whichever way the news reaches it.
///
/// The numbers are part of the protocol and never reused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u32)]
pub enum ErrorCode {
    /// Orderly end; nothing went wrong.
    NoError = 0,
    /// The peer broke the protocol: garbage bytes, a malformed or unexpected frame, a field out of
    /// range, a frame other than `Hello` first.
    ProtocolViolation = 1,
    /// A control frame announced a payload over the limit
    /// ([`crate::limits::MAX_FRAME_BYTES`] for client frames).
    FrameTooLarge = 2,
    /// A request list over [`crate::limits::MAX_REQUEST_ITEMS`] items.
    ListTooLong = 3,
    /// The scene named in `Hello` does not exist (or its name is not a valid scene name).
    UnknownScene = 4,
    /// The access token is missing or wrong for the scene.
    Unauthorized = 5,
    /// The client speaks a protocol version this server does not.
    UnsupportedVersion = 6,
    /// `Hello` asked for more channels than [`crate::limits::MAX_CHANNELS`].
    TooManyChannels = 7,
    /// `Hello` asked for a channel that does not exist or that the scene does not store.
    UnknownChannel = 8,
    /// The server is at its connection cap; try again later.
    ServerBusy = 9,
    /// The server is shutting down; reconnect later (possibly to another replica).
    ShuttingDown = 10,
    /// The client did not read its treelet streams and exceeded its memory bound on the server.
    SlowReader = 11,
    /// The server failed internally (pool read error, bug). Not the client's fault.
    Internal = 12,
    /// A request list named a treelet id the scene does not have.
    UnknownTreelet = 13,
}

impl ErrorCode {
    /// Every code, in numeric order.
    pub const ALL: [ErrorCode; 14] = [
        ErrorCode::NoError,
        ErrorCode::ProtocolViolation,
        ErrorCode::FrameTooLarge,
        ErrorCode::ListTooLong,
        ErrorCode::UnknownScene,
        ErrorCode::Unauthorized,
        ErrorCode::UnsupportedVersion,
        ErrorCode::TooManyChannels,
        ErrorCode::UnknownChannel,
        ErrorCode::ServerBusy,
        ErrorCode::ShuttingDown,
        ErrorCode::SlowReader,
        ErrorCode::Internal,
        ErrorCode::UnknownTreelet,
    ];

    /// The code's number on the wire.
    pub const fn to_u32(self) -> u32 {
        self as u32
    }

    /// The code of a number, `None` for a number this build does not know.
    pub fn from_u32(code: u32) -> Option<ErrorCode> {
        ErrorCode::ALL.get(usize::try_from(code).ok()?).copied()
    }

    /// Stable snake_case name, for logs and metric labels.
    pub const fn name(self) -> &'static str {
        match self {
            ErrorCode::NoError => "no_error",
            ErrorCode::ProtocolViolation => "protocol_violation",
            ErrorCode::FrameTooLarge => "frame_too_large",
            ErrorCode::ListTooLong => "list_too_long",
            ErrorCode::UnknownScene => "unknown_scene",
            ErrorCode::Unauthorized => "unauthorized",
            ErrorCode::UnsupportedVersion => "unsupported_version",
            ErrorCode::TooManyChannels => "too_many_channels",
            ErrorCode::UnknownChannel => "unknown_channel",
            ErrorCode::ServerBusy => "server_busy",
            ErrorCode::ShuttingDown => "shutting_down",
            ErrorCode::SlowReader => "slow_reader",
            ErrorCode::Internal => "internal",
            ErrorCode::UnknownTreelet => "unknown_treelet",
        }
    }
}

impl fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({})", self.name(), self.to_u32())
    }
}

/// The one-byte type of a control frame. The numbers are part of the protocol.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum FrameType {
    /// [`Frame::Hello`].
    Hello = 1,
    /// [`Frame::SceneInfo`].
    SceneInfo = 2,
    /// [`Frame::RequestList`].
    RequestList = 3,
    /// [`Frame::Error`].
    Error = 4,
    /// [`Frame::Goodbye`].
    Goodbye = 5,
    /// [`Frame::DeepRequestList`].
    DeepRequestList = 6,
    /// [`Frame::RankedRequestList`].
    RankedRequestList = 7,
}

impl FrameType {
    /// The type of a frame-type byte, `None` for an unknown one.
    pub const fn from_u8(b: u8) -> Option<FrameType> {
        match b {
            1 => Some(FrameType::Hello),
            2 => Some(FrameType::SceneInfo),
            3 => Some(FrameType::RequestList),
            4 => Some(FrameType::Error),
            5 => Some(FrameType::Goodbye),
            6 => Some(FrameType::DeepRequestList),
            7 => Some(FrameType::RankedRequestList),
            _ => None,
        }
    }

    /// Largest payload of a frame of this type: [`crate::limits::MAX_CONTROL_FRAME_BYTES`] for
    /// `SceneInfo`, [`crate::limits::MAX_FRAME_BYTES`] for every other type.
    pub const fn max_payload(self) -> usize {
        match self {
            FrameType::SceneInfo => crate::limits::MAX_CONTROL_FRAME_BYTES,
            _ => crate::limits::MAX_FRAME_BYTES,
        }
    }
}

/// One control-stream frame.
#[derive(Clone, Debug, PartialEq)]
pub enum Frame {
    /// Client → server, first frame. Layout: `u16 version`, `u16 len + scene name`,
    /// `u8 count + channel ids`, `u16 len + token`, then `u8 flags` when any flag is set (a
    /// Hello without the byte has no flags), then the [`ViewHint`] when the flags have
    /// [`HELLO_VIEW`].
    Hello {
        /// Must be [`PROTOCOL_VERSION`].
        version: u16,
        /// Scene name (checked with [`crate::scene::validate_scene_name`]).
        scene: String,
        /// Channels the client draws; each at most once, at most
        /// [`crate::limits::MAX_CHANNELS`]. Only these are sent.
        channels: Vec<Channel>,
        /// Access token for the scene (empty when the scene needs none), at most
        /// [`crate::limits::MAX_TOKEN_BYTES`].
        token: String,
        /// [`HELLO_GRANT_AVAILABLE`], [`HELLO_SEND_ROOT`] and [`HELLO_VIEW`]; other bits must
        /// be zero.
        flags: u8,
        /// The view to push the root's refinement for, its eye in root-cube units: present
        /// exactly when `flags` has [`HELLO_VIEW`].
        view: Option<ViewHint>,
    },
    /// Server → client answer to `Hello`: the scene as stored. Payload: the bytes of
    /// [`SceneDescription::encode`].
    SceneInfo {
        /// The scene as stored.
        description: Box<SceneDescription>,
    },
    /// Client → server: the treelets it wants now, replacing the previous list. Layout:
    /// `u64 seq`, `u32 count`, `count × (u32 id, f32 priority)`.
    RequestList {
        /// Increases with every list the client sends.
        seq: u64,
        /// `(treelet, priority)`, at most [`crate::limits::MAX_REQUEST_ITEMS`], priorities
        /// finite; see the module docs for duplicates.
        items: Vec<(TreeletId, f32)>,
    },
    /// Either direction: what went wrong, just before the connection is closed with `code`.
    /// Layout: `u32 code`, `u16 len + message` (at most [`crate::limits::MAX_MESSAGE_BYTES`]).
    Error {
        /// Why.
        code: ErrorCode,
        /// What happened, for people (bounded by [`crate::limits::MAX_MESSAGE_BYTES`]).
        message: String,
    },
    /// Client → server: a request list as [`Frame::RequestList`] (it replaces the previous list
    /// of either kind, `seq` counts both), plus what the server needs to send the descendants
    /// this view would refine without waiting to be asked (docs/design.md §10, server-assisted
    /// deep requests): the camera, the slots the client has free, and per item the screen-space
    /// error the client measured at the leaf it refines. Layout: `u64 seq`, the [`ViewHint`]
    /// (see [`ViewHint::BYTES`]), `u32 prefetch_from`, `u32 count`, `count × (u32 id, f32
    /// priority, f32 error)`.
    DeepRequestList {
        /// Increases with every list the client sends.
        seq: u64,
        /// The view the errors were measured in.
        view: ViewHint,
        /// `(treelet, priority, error in levels)`, at most
        /// [`crate::limits::MAX_REQUEST_ITEMS`]; priorities finite, errors within
        /// ±[`ViewHint::MAX_ERROR`].
        items: Vec<(TreeletId, f32, f32)>,
        /// Items from this index on are **prefetch**: the client's guesses from the frustum at
        /// what this view or the next camera move may need, not what its samples or rays
        /// found. A server that knows the view's visible cut sends them after the cut's
        /// pushes and keeps only a few in flight, so a new view's list does not queue behind
        /// them on the link. At most `items.len()` (then nothing is prefetch).
        prefetch_from: u32,
    },
    /// Client → server: a [`Frame::DeepRequestList`] in about a third of its bytes (protocol 3),
    /// what a client sends every cycle over an uplink that may be a fraction of its downlink.
    /// Items come in the order they are to be served: the list's rank is its priority
    /// ([`ranked_priority`]), so no priority travels; the ids are zigzag varints of the
    /// difference to the previous item's id (the first to 0), and the errors are fixed point
    /// ([`ERROR_STEPS_PER_LEVEL`]). Layout: `u64 seq`, the [`ViewHint`], `u32 prefetch_from`,
    /// `u32 count`, `count × (varint id delta, i16 error steps)`.
    RankedRequestList {
        /// Increases with every list the client sends.
        seq: u64,
        /// The view the errors were measured in.
        view: ViewHint,
        /// `(treelet, error in 1/[`ERROR_STEPS_PER_LEVEL`] levels)`, highest priority first,
        /// at most [`crate::limits::MAX_REQUEST_ITEMS`]; errors within
        /// ±[`ViewHint::MAX_ERROR`] levels.
        items: Vec<(TreeletId, i16)>,
        /// As [`Frame::DeepRequestList`]'s: items from this index on are prefetch.
        prefetch_from: u32,
    },
    /// Either direction: orderly end. Layout: `u32 code`.
    Goodbye {
        /// Why the peer is leaving ([`ErrorCode::NoError`] or [`ErrorCode::ShuttingDown`]).
        code: ErrorCode,
    },
}

impl Frame {
    /// This frame's type.
    pub fn frame_type(&self) -> FrameType {
        match self {
            Frame::Hello { .. } => FrameType::Hello,
            Frame::SceneInfo { .. } => FrameType::SceneInfo,
            Frame::RequestList { .. } => FrameType::RequestList,
            Frame::Error { .. } => FrameType::Error,
            Frame::Goodbye { .. } => FrameType::Goodbye,
            Frame::DeepRequestList { .. } => FrameType::DeepRequestList,
            Frame::RankedRequestList { .. } => FrameType::RankedRequestList,
        }
    }

    /// An `Error` frame whose message is cut (at a character boundary) to
    /// [`crate::limits::MAX_MESSAGE_BYTES`], so that any error text can be sent.
    pub fn error(code: ErrorCode, message: impl Into<String>) -> Frame {
        Frame::Error {
            code,
            message: error_message(message),
        }
    }
}

/// `message` cut (at a character boundary) to [`crate::limits::MAX_MESSAGE_BYTES`]: what an
/// `Error` frame, or the close frame that follows it, says.
pub fn error_message(message: impl Into<String>) -> String {
    let mut message = message.into();
    if message.len() > crate::limits::MAX_MESSAGE_BYTES {
        let mut cut = crate::limits::MAX_MESSAGE_BYTES;
        while !message.is_char_boundary(cut) {
            cut -= 1;
        }
        message.truncate(cut);
    }
    message
}

/// Steps per level of a [`Frame::RankedRequestList`] item's error: 1/512 level, so ±64 levels
/// fit an `i16`.
pub const ERROR_STEPS_PER_LEVEL: f32 = 512.0;

/// An error in levels as a [`Frame::RankedRequestList`] carries it: to the nearest step, within
/// ±[`ViewHint::MAX_ERROR`] levels (what an `i16` holds of them); NaN as 0.
pub fn error_steps(levels: f32) -> i16 {
    let limit = f32::from(i16::MAX);
    let steps = (levels * ERROR_STEPS_PER_LEVEL).round();
    if steps.is_nan() {
        0
    } else {
        steps.clamp(-limit, limit) as i16
    }
}

/// The error in levels of `steps` ([`error_steps`]).
pub fn error_levels(steps: i16) -> f32 {
    f32::from(steps) / ERROR_STEPS_PER_LEVEL
}

/// The priority of item `index` of a ranked list of `count` items: `count - index`, so the
/// first item is served first and every item ranks above the server's pushes (which go below
/// a list's lowest priority). Exact in an `f32` for every list length the protocol allows.
pub fn ranked_priority(index: usize, count: usize) -> f32 {
    count.saturating_sub(index) as f32
}

/// A ranked list's items as a deep list's: `(treelet, priority, error in levels)`.
pub fn ranked_as_deep(items: &[(TreeletId, i16)]) -> Vec<(TreeletId, f32, f32)> {
    items
        .iter()
        .enumerate()
        .map(|(i, &(id, steps))| (id, ranked_priority(i, items.len()), error_levels(steps)))
        .collect()
}

/// The client's view, as a [`Frame::DeepRequestList`] carries it: enough for the server to
/// test a voxel against the view frustum and its projected size against a pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewHint {
    /// Camera position, world units.
    pub eye: [f64; 3],
    /// Unit view direction.
    pub forward: [f32; 3],
    /// Unit up direction, orthogonal to `forward`.
    pub up: [f32; 3],
    /// `tan(fov_y / 2)`.
    pub tan_half_fov_y: f32,
    /// Frame width / height.
    pub aspect: f32,
    /// Pixel angle × LOD bias, radians: a voxel of size `s` at distance `t` is coarser than a
    /// pixel when `s > t · footprint`.
    pub footprint: f32,
    /// Slots the client has free for pushed treelets (beyond the listed ones).
    pub free_slots: u32,
}

impl ViewHint {
    /// Bytes on the wire.
    pub const BYTES: usize = 3 * 8 + 6 * 4 + 4 * 4;
    /// Largest free-slot count accepted.
    pub const MAX_FREE_SLOTS: u32 = 1 << 22;
    /// Largest accepted error magnitude, levels (the client clamps its errors to this).
    pub const MAX_ERROR: f32 = 64.0;
    /// Largest accepted eye coordinate magnitude.
    pub const MAX_COORDINATE: f64 = 1e15;

    /// Why the hint is unusable, if it is: every value finite and in range, the directions
    /// unit length and orthogonal.
    pub fn check(&self) -> Result<(), String> {
        if !self
            .eye
            .iter()
            .all(|c| c.is_finite() && c.abs() <= Self::MAX_COORDINATE)
        {
            return Err(format!(
                "eye {:?} not finite or beyond ±{:e}",
                self.eye,
                Self::MAX_COORDINATE
            ));
        }
        let len = |v: [f32; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        for (what, v) in [("forward", self.forward), ("up", self.up)] {
            let l = len(v);
            if !(l.is_finite() && (0.99..=1.01).contains(&l)) {
                return Err(format!("{what} {v:?} is not a unit vector"));
            }
        }
        if !(dot(self.forward, self.up).abs() <= 0.01) {
            return Err("forward and up are not orthogonal".into());
        }
        if !(self.tan_half_fov_y > 0.0 && self.tan_half_fov_y <= 1e4) {
            return Err(format!(
                "tan(fov/2) {} not in (0, 1e4]",
                self.tan_half_fov_y
            ));
        }
        if !(self.aspect >= 1e-4 && self.aspect <= 1e4) {
            return Err(format!("aspect {} not in [1e-4, 1e4]", self.aspect));
        }
        if !(self.footprint > 1e-9 && self.footprint <= 1.0) {
            return Err(format!("footprint {} not in (1e-9, 1]", self.footprint));
        }
        if self.free_slots > Self::MAX_FREE_SLOTS {
            return Err(format!(
                "free slots {} above {}",
                self.free_slots,
                Self::MAX_FREE_SLOTS
            ));
        }
        Ok(())
    }

    /// How many octree levels the box `[min, max]` (world units, a cube) is coarser than a pixel
    /// of this view — `log2(edge / (distance · footprint))` with the distance from the eye to the
    /// nearest point of the box — or `None` when the box lies outside the view frustum. The
    /// frustum test is conservative (a box is out only when wholly outside one side plane or
    /// behind the eye); the distance is 0 inside the box, which makes the box infinitely coarse.
    /// Testing many boxes against one view: [`ViewHint::frustum`] once, then
    /// [`ViewFrustum::box_error`].
    pub fn box_error(&self, min: [f64; 3], max: [f64; 3]) -> Option<f64> {
        self.frustum().box_error(min, max)
    }

    /// The view's frustum planes, computed once for many [`ViewFrustum::box_error`] tests.
    pub fn frustum(&self) -> ViewFrustum {
        let v = |a: [f32; 3]| [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])];
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let add =
            |a: [f64; 3], b: [f64; 3], k: f64| [a[0] + b[0] * k, a[1] + b[1] * k, a[2] + b[2] * k];
        let (f, up) = (v(self.forward), v(self.up));
        let right = cross(f, up);
        let h = f64::from(self.tan_half_fov_y);
        let w = h * f64::from(self.aspect);
        ViewFrustum {
            eye: self.eye,
            // Inward normals of the four side planes through the eye, and the forward
            // half-space.
            planes: [
                cross(add(f, right, -w), up),
                cross(up, add(f, right, w)),
                cross(right, add(f, up, -h)),
                cross(add(f, up, h), right),
                f,
            ],
            footprint: f64::from(self.footprint),
        }
    }
}

/// A [`ViewHint`]'s frustum planes and footprint, for testing many boxes against one view
/// ([`ViewHint::frustum`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewFrustum {
    eye: [f64; 3],
    planes: [[f64; 3]; 5],
    footprint: f64,
}

impl ViewFrustum {
    /// [`ViewHint::box_error`] of the view this was made from.
    pub fn box_error(&self, min: [f64; 3], max: [f64; 3]) -> Option<f64> {
        let ratio = self.coarseness(min, max)?;
        let error = ratio.log2();
        Some(if error.is_nan() { f64::INFINITY } else { error })
    }

    /// The box's edge over a pixel's footprint at its nearest point (`None` out of view):
    /// what [`ViewFrustum::box_error`] takes the logarithm of.
    fn coarseness(&self, min: [f64; 3], max: [f64; 3]) -> Option<f64> {
        let outside = |n: &[f64; 3]| {
            let p = [0, 1, 2].map(|a| if n[a] >= 0.0 { max[a] } else { min[a] });
            (0..3).map(|a| n[a] * (p[a] - self.eye[a])).sum::<f64>() < 0.0
        };
        if self.planes.iter().any(outside) {
            return None;
        }
        let d2: f64 = (0..3)
            .map(|a| {
                (min[a] - self.eye[a])
                    .max(self.eye[a] - max[a])
                    .max(0.0)
                    .powi(2)
            })
            .sum();
        let edge = max[0] - min[0];
        Some(edge / (d2.sqrt() * self.footprint))
    }

    /// Whether a box is in view and coarser than a pixel: [`ViewFrustum::box_error`] > 0.
    /// The same as testing the error, without the logarithm: `log2(r) > 0` exactly when
    /// `r > 1`, and a NaN ratio counts as infinitely coarse.
    pub fn refines(&self, min: [f64; 3], max: [f64; 3]) -> bool {
        self.coarseness(min, max)
            .is_some_and(|r| r.is_nan() || r > 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_codes_round_trip_and_are_dense() {
        for (i, c) in ErrorCode::ALL.iter().enumerate() {
            assert_eq!(c.to_u32() as usize, i);
            assert_eq!(ErrorCode::from_u32(c.to_u32()), Some(*c));
        }
        assert_eq!(ErrorCode::from_u32(ErrorCode::ALL.len() as u32), None);
        assert_eq!(ErrorCode::from_u32(u32::MAX), None);
        assert_eq!(ErrorCode::SlowReader.to_string(), "slow_reader (11)");
    }

    #[test]
    fn frame_types_round_trip() {
        for t in [
            FrameType::Hello,
            FrameType::SceneInfo,
            FrameType::RequestList,
            FrameType::Error,
            FrameType::Goodbye,
            FrameType::DeepRequestList,
            FrameType::RankedRequestList,
        ] {
            assert_eq!(FrameType::from_u8(t as u8), Some(t));
        }
        assert_eq!(FrameType::from_u8(0), None);
        assert_eq!(FrameType::from_u8(8), None);
    }

    /// An eye at z = 5 looking down −z at the unit cube, a pixel of 0.01 radians.
    fn looking_down_z(aspect: f32) -> ViewHint {
        ViewHint {
            eye: [0.5, 0.5, 5.0],
            forward: [0.0, 0.0, -1.0],
            up: [0.0, 1.0, 0.0],
            tan_half_fov_y: 0.5,
            aspect,
            footprint: 0.01,
            free_slots: 10,
        }
    }

    #[test]
    fn box_error_tests_the_frustum_and_the_projected_size() {
        let v = looking_down_z(1.0);
        // A unit cube 4 units ahead: 1 / (4 · 0.01) = 25 pixels, log2 ≈ 4.64 levels.
        let e = v.box_error([0.0; 3], [1.0; 3]).unwrap();
        assert!((e - 25f64.log2()).abs() < 1e-6, "{e}");
        // Behind the eye, far to the side, above: out.
        assert_eq!(v.box_error([0.0, 0.0, 6.0], [1.0, 1.0, 7.0]), None);
        assert_eq!(v.box_error([50.0, 0.0, 0.0], [51.0, 1.0, 1.0]), None);
        assert_eq!(v.box_error([0.0, 50.0, 0.0], [1.0, 51.0, 1.0]), None);
        // Around the eye: infinitely coarse.
        assert_eq!(v.box_error([0.0; 3], [10.0; 3]), Some(f64::INFINITY));
        // Tiny and far: finer than a pixel.
        assert!(
            v.box_error([0.5, 0.5, -995.0], [0.501, 0.501, -994.999])
                .unwrap()
                < 0.0
        );
    }

    #[test]
    fn refines_is_a_positive_box_error_without_the_logarithm() {
        // A wider frame, so the side planes are not symmetric in x and y.
        let v = looking_down_z(1.25);
        let f = v.frustum();
        let agree = |min: [f64; 3], max: [f64; 3]| {
            assert_eq!(
                f.refines(min, max),
                v.box_error(min, max).is_some_and(|e| e > 0.0),
                "{min:?} {max:?}"
            );
            assert_eq!(f.box_error(min, max), v.box_error(min, max));
        };
        // Boxes right at one pixel: edge = distance · footprint, and one ulp either side.
        for d in [0.5f64, 1.0, 3.0, 4.0, 7.5, 1e3] {
            let edge = d * 0.01;
            for e in [edge, edge.next_up(), edge.next_down()] {
                agree([0.5, 0.5, 5.0 - d - e], [0.5 + e, 0.5 + e, 5.0 - d]);
            }
        }
        // The eye inside (infinitely coarse), a point box at the eye (0 / 0), out of view.
        agree([0.0; 3], [10.0; 3]);
        agree([0.5, 0.5, 5.0], [0.5, 0.5, 5.0]);
        agree([0.0, 0.0, 6.0], [1.0, 1.0, 7.0]);
        // A spread of boxes in and around the frustum (a fixed LCG, so the test is exact).
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..20_000 {
            let min = [next() * 8.0 - 3.5, next() * 8.0 - 3.5, next() * 12.0 - 8.0];
            let edge = 10f64.powf(next() * 4.0 - 3.0);
            agree(min, [min[0] + edge, min[1] + edge, min[2] + edge]);
        }
    }

    #[test]
    fn error_frame_message_is_cut_at_a_char_boundary() {
        let long = "é".repeat(crate::limits::MAX_MESSAGE_BYTES);
        let Frame::Error { message, .. } = Frame::error(ErrorCode::Internal, long) else {
            unreachable!()
        };
        assert!(message.len() <= crate::limits::MAX_MESSAGE_BYTES);
        assert!(message.len() >= crate::limits::MAX_MESSAGE_BYTES - 1);
        assert!(message.chars().all(|c| c == 'é'));
    }
}
