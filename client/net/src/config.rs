//! What a [`TreeletClient`](super::TreeletClient) is started with.

use arbor_proto::Channel;
use arbor_proto::limits::{MAX_CHANNELS, MAX_TOKEN_BYTES, MAX_TREELET_MESSAGE_BYTES};

use super::backoff::Backoff;
use super::error::ClientError;
use super::tls::Trust;
use super::url::ServerUrl;

/// Default bound on received treelets the caller has not taken yet: 64 MiB.
pub const DEFAULT_MAX_BUFFERED_BYTES: usize = 64 << 20;

/// Everything a client needs to connect and stay connected.
#[derive(Clone, Debug)]
pub struct ClientConfig {
    /// Server and scene.
    pub url: ServerUrl,
    /// Access token for the scene (empty when it needs none), at most
    /// [`MAX_TOKEN_BYTES`].
    pub token: String,
    /// Attribute channels to receive, each at most once, at most
    /// [`MAX_CHANNELS`]. Any other channel arriving is a
    /// protocol violation.
    pub channels: Vec<Channel>,
    /// How the server's certificate is trusted.
    pub trust: Trust,
    /// Reconnect delays.
    pub backoff: Backoff,
    /// Most bytes of received treelet messages held for the caller (queued events not yet taken,
    /// plus messages being read). When it is reached the client stops reading and accepting
    /// treelet streams, so QUIC flow control pushes back on the server. A single message larger
    /// than the bound (at most [`MAX_TREELET_MESSAGE_BYTES`], about 2.3 MiB) is still read,
    /// alone, so the bound is effectively `max(max_buffered_bytes, largest message)`. Values
    /// above `u32::MAX` are treated as `u32::MAX`.
    pub max_buffered_bytes: usize,
    /// `Hello` flags ([`arbor_proto::wire::HELLO_GRANT_AVAILABLE`],
    /// [`arbor_proto::wire::HELLO_SEND_ROOT`]); 0 by default.
    pub hello_flags: u8,
}

impl ClientConfig {
    /// A configuration with no token, no channels, the default backoff and
    /// [`DEFAULT_MAX_BUFFERED_BYTES`].
    pub fn new(url: ServerUrl, trust: Trust) -> Self {
        Self {
            url,
            token: String::new(),
            channels: Vec::new(),
            trust,
            backoff: Backoff::default(),
            max_buffered_bytes: DEFAULT_MAX_BUFFERED_BYTES,
            hello_flags: 0,
        }
    }

    pub fn with_token(mut self, token: impl Into<String>) -> Self {
        self.token = token.into();
        self
    }

    pub fn with_channels(mut self, channels: impl IntoIterator<Item = Channel>) -> Self {
        self.channels = channels.into_iter().collect();
        self
    }

    pub fn with_backoff(mut self, backoff: Backoff) -> Self {
        self.backoff = backoff;
        self
    }

    pub fn with_max_buffered_bytes(mut self, bytes: usize) -> Self {
        self.max_buffered_bytes = bytes;
        self
    }

    /// Sets the `Hello` flags.
    pub fn with_hello_flags(mut self, flags: u8) -> Self {
        self.hello_flags = flags;
        self
    }

    /// Checks every field the protocol or the client limits.
    pub fn validate(&self) -> Result<(), ClientError> {
        if self.channels.len() > MAX_CHANNELS {
            return Err(ClientError::InvalidConfig(format!(
                "{} channels asked for, at most {MAX_CHANNELS}",
                self.channels.len()
            )));
        }
        for (i, c) in self.channels.iter().enumerate() {
            if self.channels[..i].contains(c) {
                return Err(ClientError::InvalidConfig(format!(
                    "channel {} asked for twice",
                    c.name()
                )));
            }
        }
        if self.token.len() > MAX_TOKEN_BYTES {
            return Err(ClientError::InvalidConfig(format!(
                "access token of {} bytes, at most {MAX_TOKEN_BYTES}",
                self.token.len()
            )));
        }
        if self.hello_flags & !arbor_proto::wire::HELLO_FLAGS != 0 {
            return Err(ClientError::InvalidConfig(format!(
                "unknown Hello flags {:#04x}",
                self.hello_flags
            )));
        }
        if self.max_buffered_bytes == 0 {
            return Err(ClientError::InvalidConfig(
                "max_buffered_bytes must be positive".into(),
            ));
        }
        self.backoff.validate()
    }
}

const _: () = assert!(MAX_TREELET_MESSAGE_BYTES < u32::MAX as usize);
