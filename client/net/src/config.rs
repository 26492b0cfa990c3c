//! What a [`TreeletClient`](super::TreeletClient) is started with.

use std::time::Duration;

use arbor_proto::Channel;
use arbor_proto::limits::{MAX_CHANNELS, MAX_TOKEN_BYTES, MAX_TREELET_MESSAGE_BYTES};
use arbor_proto::wire::{HELLO_SEND_ROOT, HELLO_VIEW, ViewHint};

use super::backoff::Backoff;
use super::error::ClientError;
use super::tls::Trust;
use super::url::ServerUrl;

/// Default bound on received treelets the caller has not taken yet: 64 MiB.
pub const DEFAULT_MAX_BUFFERED_BYTES: usize = 64 << 20;
/// Default [`ClientConfig::failover_after`]: 750 ms.
pub const DEFAULT_FAILOVER_AFTER: Duration = Duration::from_millis(750);
/// Shortest [`ClientConfig::failover_after`]: keep-alives every third of it must stay cheap.
pub const MIN_FAILOVER_AFTER: Duration = Duration::from_millis(100);
/// Most replicas besides the URL.
pub const MAX_REPLICAS: usize = 64;
/// Smallest [`ClientConfig::list_send_window`]: a list larger than the window still goes out,
/// a window at a time, but one of a few bytes would take a round trip per item.
pub const MIN_LIST_SEND_WINDOW: u64 = 1 << 10;

/// Everything a client needs to connect and stay connected.
#[derive(Clone, Debug)]
pub struct ClientConfig {
    /// Server and scene.
    pub url: ServerUrl,
    /// Other servers of the same pool (the same scene description), tried in order after `url`
    /// when a connection is lost or an attempt fails. Same scene name as `url`; a server that
    /// describes the scene differently from the first one connected to is refused.
    pub replicas: Vec<ServerUrl>,
    /// With replicas, a connection on which nothing arrives for this long is lost (the QUIC idle
    /// timeout, with keep-alives every third of it) and the client moves to the next server.
    /// Without replicas the client waits [`crate::transport::IDLE_TIMEOUT`] instead.
    pub failover_after: Duration,
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
    /// The view to send in the first connection's `Hello` ([`arbor_proto::wire::HELLO_VIEW`],
    /// needs [`arbor_proto::wire::HELLO_SEND_ROOT`]): the server then pushes the root's
    /// refinement for it right away. A reconnection (the slot buffer is kept) sends none.
    pub hello_view: Option<ViewHint>,
    /// Most request-list bytes written and not yet acknowledged
    /// ([`crate::transport::LIST_SEND_WINDOW`] by default, at least
    /// [`MIN_LIST_SEND_WINDOW`]): a newer list waits for the window, and only the latest is
    /// sent then.
    pub list_send_window: u64,
    /// Send fewer of a ranked list's items while lists wait for the uplink
    /// ([`crate::list_cap`]); on by default.
    pub adaptive_list_cap: bool,
}

impl ClientConfig {
    /// A configuration with no token, no channels, the default backoff and
    /// [`DEFAULT_MAX_BUFFERED_BYTES`].
    pub fn new(url: ServerUrl, trust: Trust) -> Self {
        Self {
            url,
            replicas: Vec::new(),
            failover_after: DEFAULT_FAILOVER_AFTER,
            token: String::new(),
            channels: Vec::new(),
            trust,
            backoff: Backoff::default(),
            max_buffered_bytes: DEFAULT_MAX_BUFFERED_BYTES,
            hello_flags: 0,
            hello_view: None,
            list_send_window: crate::transport::LIST_SEND_WINDOW,
            adaptive_list_cap: true,
        }
    }

    /// Sets the replicas of the same pool to fail over to.
    pub fn with_replicas(mut self, replicas: impl IntoIterator<Item = ServerUrl>) -> Self {
        self.replicas = replicas.into_iter().collect();
        self
    }

    pub fn with_failover_after(mut self, after: Duration) -> Self {
        self.failover_after = after;
        self
    }

    /// The URL and then the replicas, in order of preference.
    pub fn servers(&self) -> Vec<ServerUrl> {
        std::iter::once(self.url.clone())
            .chain(self.replicas.iter().cloned())
            .collect()
    }

    /// The QUIC idle timeout the client offers: [`Self::failover_after`] with replicas, the
    /// long [`crate::transport::IDLE_TIMEOUT`] without.
    pub fn idle_timeout(&self) -> Duration {
        if self.replicas.is_empty() {
            crate::transport::IDLE_TIMEOUT
        } else {
            self.failover_after
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

    /// Sets [`Self::adaptive_list_cap`].
    pub fn with_adaptive_list_cap(mut self, on: bool) -> Self {
        self.adaptive_list_cap = on;
        self
    }

    /// Sets [`Self::list_send_window`].
    pub fn with_list_send_window(mut self, bytes: u64) -> Self {
        self.list_send_window = bytes;
        self
    }

    /// Sets the first connection's `Hello` view ([`Self::hello_view`]).
    pub fn with_hello_view(mut self, view: Option<ViewHint>) -> Self {
        self.hello_view = view;
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
        if self.hello_flags & HELLO_VIEW != 0 {
            return Err(ClientError::InvalidConfig(
                "the Hello view flag is set by with_hello_view, not by the flags".into(),
            ));
        }
        if let Some(view) = &self.hello_view {
            if self.hello_flags & HELLO_SEND_ROOT == 0 {
                return Err(ClientError::InvalidConfig(
                    "a Hello view needs the send-root flag (it refines below the root)".into(),
                ));
            }
            view.check()
                .map_err(|e| ClientError::InvalidConfig(format!("Hello view: {e}")))?;
        }
        self.validate_replicas()?;
        if self.max_buffered_bytes == 0 {
            return Err(ClientError::InvalidConfig(
                "max_buffered_bytes must be positive".into(),
            ));
        }
        if self.list_send_window < MIN_LIST_SEND_WINDOW {
            return Err(ClientError::InvalidConfig(format!(
                "list_send_window of {} bytes, at least {MIN_LIST_SEND_WINDOW}",
                self.list_send_window
            )));
        }
        self.backoff.validate()
    }
}

impl ClientConfig {
    fn validate_replicas(&self) -> Result<(), ClientError> {
        if self.replicas.len() > MAX_REPLICAS {
            return Err(ClientError::InvalidConfig(format!(
                "{} replicas, at most {MAX_REPLICAS}",
                self.replicas.len()
            )));
        }
        let servers = self.servers();
        for (i, r) in servers.iter().enumerate().skip(1) {
            if r.scene != self.url.scene {
                return Err(ClientError::InvalidConfig(format!(
                    "replica {r} names scene {:?}, the URL {:?}: replicas serve the same scene",
                    r.scene, self.url.scene
                )));
            }
            if servers[..i].contains(r) {
                return Err(ClientError::InvalidConfig(format!(
                    "server {r} given twice"
                )));
            }
        }
        if !(MIN_FAILOVER_AFTER..=crate::transport::IDLE_TIMEOUT).contains(&self.failover_after) {
            return Err(ClientError::InvalidConfig(format!(
                "failover_after {:?} outside {MIN_FAILOVER_AFTER:?}..={:?}",
                self.failover_after,
                crate::transport::IDLE_TIMEOUT
            )));
        }
        Ok(())
    }
}

const _: () = assert!(MAX_TREELET_MESSAGE_BYTES < u32::MAX as usize);
