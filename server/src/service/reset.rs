//! QUIC stateless resets that outlive the process.
//!
//! A server killed and started again on the same address, or a replica that receives a client's
//! packets after a load balancer moved them, knows nothing of the client's connection. It can
//! still tell the client at once that the connection is gone — a stateless reset — if two things
//! hold: the reset token is derived from a key every such process shares, and the process does
//! not drop the packet first as carrying a connection id it could not have issued. So the reset
//! key is derived from the TLS private key (a restart on the same data dir, and replicas sharing
//! the certificate, share it), and connection ids are plain random bytes that any process
//! accepts as possibly its own. The client then sees `connection reset` within a round trip
//! instead of waiting for its idle timeout.
//!
//! The key is derived once, from the key the process started with: quinn fixes an endpoint's
//! reset key when the endpoint is made, so a certificate renewed by a reload
//! ([`super::certificate`]) leaves it as it was. Replicas that renewed their pair by reloads
//! keep sharing the old key; one restarted since derives the new one, and a client moved from
//! it to a replica still on the old key (or the other way) waits for its idle timeout until
//! those restart too.

use std::time::Duration;

use ring::rand::SecureRandom as _;

use super::tls::TlsIdentity;

/// The key of QUIC stateless-reset tokens, derived from the identity's private key.
pub fn stateless_reset_key(identity: &TlsIdentity) -> ring::hmac::Key {
    let mut input = b"arbor stateless reset key v1".to_vec();
    input.extend_from_slice(identity.key.secret_der());
    let digest = ring::digest::digest(&ring::digest::SHA256, &input);
    ring::hmac::Key::new(ring::hmac::HMAC_SHA256, digest.as_ref())
}

/// Connection ids of [`CID_BYTES`] random bytes; every id is accepted as possibly this
/// process's (quinn's default signs ids with a per-process key and drops the rest unanswered).
#[derive(Debug)]
pub struct RandomCids {
    rng: ring::rand::SystemRandom,
}

/// Length of a connection id.
pub const CID_BYTES: usize = 8;

impl RandomCids {
    pub fn new() -> RandomCids {
        RandomCids {
            rng: ring::rand::SystemRandom::new(),
        }
    }
}

impl Default for RandomCids {
    fn default() -> Self {
        Self::new()
    }
}

impl quinn::ConnectionIdGenerator for RandomCids {
    fn generate_cid(&mut self) -> quinn::ConnectionId {
        let mut bytes = [0u8; CID_BYTES];
        // The system generator does not fail on Linux; zeros would still be unique enough for
        // the endpoint, which checks ids for collisions itself.
        let _ = self.rng.fill(&mut bytes);
        quinn::ConnectionId::new(&bytes)
    }

    fn cid_len(&self) -> usize {
        CID_BYTES
    }

    fn cid_lifetime(&self) -> Option<Duration> {
        None
    }
}

/// The endpoint configuration of a server with `identity`: shared reset key, random ids.
pub fn endpoint_config(identity: &TlsIdentity) -> quinn::EndpointConfig {
    let mut config = quinn::EndpointConfig::default();
    config
        .reset_key(std::sync::Arc::new(stateless_reset_key(identity)))
        .cid_generator(|| Box::new(RandomCids::new()));
    config
}
