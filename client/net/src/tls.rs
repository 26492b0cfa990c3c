//! TLS for the client: how the server's certificate is trusted, and the rustls configuration.
//!
//! Two ways (docs/design.md §6): a **pinned fingerprint** for the server's self-signed certificate (the
//! SHA-256 of the leaf certificate's DER, as the server prints it and its admin API shows it), or
//! ordinary **CA** verification (webpki) against the roots given, with the URL's host as the
//! server name. Either way only TLS 1.3 with ALPN [`arbor_proto::wire::ALPN`] is offered, on the
//! ring crypto provider.

use std::fmt;
use std::sync::Arc;

use arbor_proto::wire::ALPN;
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::{CryptoProvider, WebPkiSupportedAlgorithms};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName, UnixTime};
use rustls::{CertificateError, DigitallySignedStruct, SignatureScheme};

use super::error::ClientError;

/// How the client decides the server is the right one.
#[derive(Clone, PartialEq, Eq)]
pub enum Trust {
    /// Accept exactly the leaf certificate whose SHA-256 (over its DER) is this: 64 hex digits
    /// (case and `:` separators are ignored). Host name, issuer and dates are not checked; the
    /// handshake signature is.
    Fingerprint(String),
    /// Verify the chain against these root certificates (PEM, one or more), with the URL's host
    /// as the server name (a DNS name or an IP address in the certificate's SAN).
    CaPem(Vec<u8>),
}

impl fmt::Debug for Trust {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Trust::Fingerprint(s) => f.debug_tuple("Fingerprint").field(s).finish(),
            Trust::CaPem(pem) => write!(f, "CaPem({} bytes)", pem.len()),
        }
    }
}

/// The SHA-256 fingerprint of a DER certificate as the server reports it: 64 lowercase hex
/// digits without separators.
pub fn certificate_fingerprint(der: &[u8]) -> String {
    let digest = ring::digest::digest(&ring::digest::SHA256, der);
    let mut s = String::with_capacity(64);
    for b in digest.as_ref() {
        s.push_str(&format!("{b:02x}"));
    }
    s
}

/// Parses a fingerprint written as 64 hex digits, ignoring case, `:` separators and
/// surrounding whitespace.
pub fn parse_fingerprint(text: &str) -> Result<[u8; 32], ClientError> {
    let digits: Vec<u8> = text.trim().bytes().filter(|&b| b != b':').collect();
    if digits.len() != 64 {
        return Err(ClientError::BadFingerprint(format!(
            "expected 64 hex digits (SHA-256), got {} characters",
            digits.len()
        )));
    }
    let mut out = [0u8; 32];
    for (i, pair) in digits.chunks_exact(2).enumerate() {
        let hex = |c: u8| match c {
            b'0'..=b'9' => Some(c - b'0'),
            b'a'..=b'f' => Some(c - b'a' + 10),
            b'A'..=b'F' => Some(c - b'A' + 10),
            _ => None,
        };
        match (hex(pair[0]), hex(pair[1])) {
            (Some(h), Some(l)) => out[i] = h << 4 | l,
            _ => {
                return Err(ClientError::BadFingerprint(format!(
                    "{:?} is not a hex digit pair",
                    String::from_utf8_lossy(pair)
                )));
            }
        }
    }
    Ok(out)
}

/// Installs rustls's ring provider as the process default, once; a provider installed before
/// (by this or other code) is left as it is. The client's own configurations name the ring
/// provider explicitly and do not depend on the default.
pub fn install_crypto_provider() {
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// A [`ServerCertVerifier`] that accepts exactly one leaf certificate, identified by the SHA-256
/// of its DER, and still checks that the server holds its key (the handshake signature) with the
/// provider's signature algorithms.
#[derive(Debug)]
pub struct PinnedCertVerifier {
    fingerprint: [u8; 32],
    algorithms: WebPkiSupportedAlgorithms,
}

impl PinnedCertVerifier {
    pub fn new(fingerprint: [u8; 32], provider: &CryptoProvider) -> Self {
        Self {
            fingerprint,
            algorithms: provider.signature_verification_algorithms,
        }
    }
}

impl ServerCertVerifier for PinnedCertVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        let digest = ring::digest::digest(&ring::digest::SHA256, end_entity.as_ref());
        if digest.as_ref() == self.fingerprint {
            Ok(ServerCertVerified::assertion())
        } else {
            tracing::warn!(
                got = %certificate_fingerprint(end_entity.as_ref()),
                "server certificate does not match the pinned fingerprint"
            );
            Err(rustls::Error::InvalidCertificate(
                CertificateError::ApplicationVerificationFailure,
            ))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(message, cert, dss, &self.algorithms)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(message, cert, dss, &self.algorithms)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.algorithms.supported_schemes()
    }
}

/// Parses PEM root certificates into a root store; at least one is required.
pub fn root_store(pem: &[u8]) -> Result<rustls::RootCertStore, ClientError> {
    let mut roots = rustls::RootCertStore::empty();
    for cert in CertificateDer::pem_slice_iter(pem) {
        let cert = cert.map_err(|e| ClientError::BadCa(e.to_string()))?;
        roots
            .add(cert)
            .map_err(|e| ClientError::BadCa(format!("unusable certificate: {e}")))?;
    }
    if roots.is_empty() {
        return Err(ClientError::BadCa(
            "no CERTIFICATE block in the PEM data".into(),
        ));
    }
    Ok(roots)
}

/// The rustls client configuration for `trust`: TLS 1.3 only, ALPN `arbor/1`, ring provider.
pub fn rustls_client_config(trust: &Trust) -> Result<rustls::ClientConfig, ClientError> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider.clone())
        .with_protocol_versions(&[&rustls::version::TLS13])?;
    let mut config = match trust {
        Trust::Fingerprint(text) => {
            let pin = parse_fingerprint(text)?;
            builder
                .dangerous()
                .with_custom_certificate_verifier(Arc::new(PinnedCertVerifier::new(pin, &provider)))
                .with_no_client_auth()
        }
        Trust::CaPem(pem) => builder
            .with_root_certificates(root_store(pem)?)
            .with_no_client_auth(),
    };
    config.alpn_protocols = vec![ALPN.to_vec()];
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cert(name: &str) -> rcgen::CertifiedKey<rcgen::KeyPair> {
        rcgen::generate_simple_self_signed(vec![name.to_owned()]).unwrap()
    }

    #[test]
    fn fingerprints_parse_in_any_common_spelling() {
        let c = cert("localhost");
        let fp = certificate_fingerprint(c.cert.der());
        assert_eq!(fp.len(), 64);
        assert!(
            fp.bytes()
                .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
        );
        let raw = parse_fingerprint(&fp).unwrap();
        let colons: Vec<String> = raw.iter().map(|b| format!("{b:02X}")).collect();
        assert_eq!(parse_fingerprint(&colons.join(":")).unwrap(), raw);
        assert_eq!(
            parse_fingerprint(&format!("  {}\n", fp.to_uppercase())).unwrap(),
            raw
        );
        assert!(matches!(
            parse_fingerprint(&fp[..62]),
            Err(ClientError::BadFingerprint(_))
        ));
        let mut bad = fp.clone();
        bad.replace_range(10..12, "zz");
        assert!(
            parse_fingerprint(&bad)
                .unwrap_err()
                .to_string()
                .contains("zz")
        );
    }

    #[test]
    fn pinned_verifier_accepts_only_its_certificate() {
        let provider = rustls::crypto::ring::default_provider();
        let right = cert("localhost");
        let wrong = cert("localhost");
        let pin = parse_fingerprint(&certificate_fingerprint(right.cert.der())).unwrap();
        let v = PinnedCertVerifier::new(pin, &provider);
        let name = ServerName::try_from("example.invalid").unwrap();
        let now = UnixTime::now();
        // The name does not matter for a pin.
        assert!(
            v.verify_server_cert(right.cert.der(), &[], &name, &[], now)
                .is_ok()
        );
        let e = v
            .verify_server_cert(wrong.cert.der(), &[], &name, &[], now)
            .unwrap_err();
        assert_eq!(
            e,
            rustls::Error::InvalidCertificate(CertificateError::ApplicationVerificationFailure)
        );
        // The right leaf offered as an intermediate does not help a wrong leaf.
        assert!(
            v.verify_server_cert(
                wrong.cert.der(),
                &[right.cert.der().clone()],
                &name,
                &[],
                now
            )
            .is_err()
        );
        assert!(!v.supported_verify_schemes().is_empty());
    }

    #[test]
    fn configs_build_for_both_trusts() {
        let c = cert("localhost");
        let fp = certificate_fingerprint(c.cert.der());
        let cfg = rustls_client_config(&Trust::Fingerprint(fp)).unwrap();
        assert_eq!(cfg.alpn_protocols, vec![ALPN.to_vec()]);
        let cfg = rustls_client_config(&Trust::CaPem(c.cert.pem().into_bytes())).unwrap();
        assert_eq!(cfg.alpn_protocols, vec![ALPN.to_vec()]);
        assert!(matches!(
            rustls_client_config(&Trust::CaPem(b"not pem".to_vec())),
            Err(ClientError::BadCa(_))
        ));
        assert!(matches!(
            rustls_client_config(&Trust::Fingerprint("abc".into())),
            Err(ClientError::BadFingerprint(_))
        ));
        install_crypto_provider();
        install_crypto_provider();
    }
}
