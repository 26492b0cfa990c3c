//! The errors the connection library reports to its caller.
//!
//! Only configuration and request mistakes are errors: everything that happens on the network
//! (a refused handshake, a lost connection, a server's close code) arrives as a
//! [`ClientEvent::Disconnected`](super::ClientEvent::Disconnected) event instead, because the
//! client deals with it itself (reconnect or give up) and the caller only needs to know.

/// A mistake in what the caller gave the client.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The server URL is not of the form `quic://HOST:PORT/SCENE`.
    #[error("bad server URL {url:?}: {reason}")]
    BadUrl {
        /// The URL as given.
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A pinned certificate fingerprint is not a SHA-256 digest written as 64 hex digits.
    #[error("bad certificate fingerprint: {0}")]
    BadFingerprint(String),
    /// The CA certificates (PEM) could not be parsed or contain no certificate.
    #[error("bad CA certificates: {0}")]
    BadCa(String),
    /// rustls refused the TLS configuration.
    #[error("TLS configuration: {0}")]
    Tls(#[from] rustls::Error),
    /// A field of [`ClientConfig`](super::ClientConfig) is out of range (channels, backoff,
    /// buffer bound, token length).
    #[error("invalid client configuration: {0}")]
    InvalidConfig(String),
    /// A request list the protocol cannot carry (too long, a non-finite priority, the "none"
    /// treelet id).
    #[error("invalid request list: {0}")]
    InvalidRequest(String),
    /// [`TreeletClient::start`](super::TreeletClient::start) was called outside a tokio runtime.
    #[error("TreeletClient::start must be called inside a tokio runtime")]
    NoRuntime,
}
