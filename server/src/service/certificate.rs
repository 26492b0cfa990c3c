//! The certificate a listener presents, replaceable while it listens.
//!
//! rustls asks its [`ResolvesServerCert`] for the chain and key at every handshake. A
//! [`LiveCertificate`] answers with the one in force, so a renewed certificate (SIGHUP,
//! [`crate::daemon::Reloader`]) is presented to the next client, while every session already
//! open goes on: its keys were agreed at its handshake and nothing of the certificate is needed
//! again. The QUIC endpoint and the admin listener each hold one.
//!
//! A pair is checked before it is put in force ([`PresentedCertificate::of`]): a key that is
//! not the certificate's is refused, naming both files, and the one in force stays. rustls does
//! that check itself only for `with_single_cert`, not for a resolver.
//!
//! [`not_after`] reads the leaf's expiry for `/metrics`
//! (`arbor_tls_certificate_expiry_timestamp_seconds`, and the alert on it): a few lines of DER
//! walking rather than an X.509 crate, since the certificate has been parsed by rustls already
//! and only one field is wanted.

use std::sync::{Arc, PoisonError, RwLock};

use rustls::server::{ClientHello, ResolvesServerCert};
use rustls::sign::CertifiedKey;

use super::tls::{IdentityOrigin, TlsError, TlsIdentity};

/// A chain and key checked to belong together, with what `/metrics` and the admin API show.
#[derive(Debug)]
pub struct PresentedCertificate {
    certified: Arc<CertifiedKey>,
    /// SHA-256 of the leaf certificate (DER), lowercase hex: what clients pin.
    pub fingerprint: String,
    /// The leaf's `notAfter`, seconds since the Unix epoch; `None` when it could not be read.
    pub not_after_unix: Option<i64>,
    /// Where the pair was read from.
    pub origin: IdentityOrigin,
}

impl PresentedCertificate {
    /// The pair of `identity`, once its key is found to be the leaf certificate's.
    pub fn of(identity: &TlsIdentity) -> Result<Self, TlsError> {
        let provider = rustls::crypto::ring::default_provider();
        let certified =
            CertifiedKey::from_der(identity.certs.clone(), identity.key.clone_key(), &provider)
                .map_err(|e| match e {
                    rustls::Error::InconsistentKeys(_) => {
                        let (cert, key) = identity.origin.paths();
                        TlsError::KeyMismatch {
                            cert: cert.to_owned(),
                            key: key.to_owned(),
                        }
                    }
                    e => TlsError::Rustls(e),
                })?;
        Ok(Self {
            certified: Arc::new(certified),
            fingerprint: identity.fingerprint.clone(),
            not_after_unix: identity.certs.first().and_then(|c| not_after(c)),
            origin: identity.origin.clone(),
        })
    }
}

/// The certificate a listener presents now; [`LiveCertificate::replace`] changes it for the
/// handshakes that follow.
#[derive(Debug)]
pub struct LiveCertificate {
    current: RwLock<Arc<PresentedCertificate>>,
}

impl LiveCertificate {
    /// A listener's certificate, `first` until replaced.
    pub fn new(first: Arc<PresentedCertificate>) -> Self {
        Self {
            current: RwLock::new(first),
        }
    }

    /// The certificate in force.
    pub fn current(&self) -> Arc<PresentedCertificate> {
        self.current
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Puts `next` in force for the next handshakes; true when its leaf differs from the one it
    /// replaces.
    pub fn replace(&self, next: Arc<PresentedCertificate>) -> bool {
        let mut current = self.current.write().unwrap_or_else(PoisonError::into_inner);
        let changed = current.fingerprint != next.fingerprint;
        *current = next;
        changed
    }
}

impl ResolvesServerCert for LiveCertificate {
    fn resolve(&self, _client_hello: ClientHello<'_>) -> Option<Arc<CertifiedKey>> {
        Some(self.current().certified.clone())
    }
}

/// One DER element: its tag, its contents, and what follows it. Single-byte tags only (all an
/// X.509 certificate uses up to its validity); `None` for a truncated or over-long length.
fn element(der: &[u8]) -> Option<(u8, &[u8], &[u8])> {
    let (&tag, rest) = der.split_first()?;
    let (&first, rest) = rest.split_first()?;
    let (len, rest) = if first < 0x80 {
        (usize::from(first), rest)
    } else {
        let n = usize::from(first & 0x7f);
        if n == 0 || n > 4 || rest.len() < n {
            return None;
        }
        let len = rest[..n]
            .iter()
            .fold(0usize, |acc, &b| (acc << 8) | usize::from(b));
        (len, &rest[n..])
    };
    (rest.len() >= len).then(|| (tag, &rest[..len], &rest[len..]))
}

const SEQUENCE: u8 = 0x30;
const VERSION: u8 = 0xa0;
const UTC_TIME: u8 = 0x17;
const GENERALIZED_TIME: u8 = 0x18;

/// The `notAfter` of an X.509 certificate (DER), seconds since the Unix epoch; `None` for
/// anything that is not a certificate with a `Z`-terminated time there.
pub fn not_after(der: &[u8]) -> Option<i64> {
    // Certificate ::= SEQUENCE { tbsCertificate SEQUENCE { [0] version OPTIONAL, serialNumber,
    // signature, issuer, validity SEQUENCE { notBefore, notAfter }, ... }, ... }
    let (SEQUENCE, certificate, _) = element(der)? else {
        return None;
    };
    let (SEQUENCE, mut tbs, _) = element(certificate)? else {
        return None;
    };
    if tbs.first() == Some(&VERSION) {
        tbs = element(tbs)?.2;
    }
    for _ in 0..3 {
        tbs = element(tbs)?.2; // serialNumber, signature, issuer
    }
    let (SEQUENCE, validity, _) = element(tbs)? else {
        return None;
    };
    let (_, _, after) = element(validity)?; // notBefore
    let (tag, time, _) = element(after)?;
    asn1_time(tag, time)
}

/// A UTCTime (`YYMMDDHHMMSSZ`, years 1950–2049) or GeneralizedTime (`YYYYMMDDHHMMSSZ`).
fn asn1_time(tag: u8, text: &[u8]) -> Option<i64> {
    let text = std::str::from_utf8(text).ok()?.strip_suffix('Z')?;
    if !text.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let (year, rest) = match (tag, text.len()) {
        (UTC_TIME, 12) => {
            let yy: i16 = text[..2].parse().ok()?;
            (if yy >= 50 { 1900 + yy } else { 2000 + yy }, &text[2..])
        }
        (GENERALIZED_TIME, 14) => (text[..4].parse().ok()?, &text[4..]),
        _ => return None,
    };
    let field = |i: usize| rest[i..i + 2].parse::<i8>().ok();
    let at = jiff::civil::DateTime::new(
        year,
        field(0)?,
        field(2)?,
        field(4)?,
        field(6)?,
        field(8)?,
        0,
    )
    .ok()?;
    let at = jiff::tz::TimeZone::UTC.to_timestamp(at).ok()?;
    Some(at.as_second())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::tls::fingerprint;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};
    use std::path::PathBuf;

    /// A self-signed certificate for `localhost` valid until `until`, and its key.
    fn certificate(until: Option<(i32, u8, u8)>) -> (CertificateDer<'static>, rcgen::KeyPair) {
        let key = rcgen::KeyPair::generate().unwrap();
        let mut params = rcgen::CertificateParams::new(vec!["localhost".into()]).unwrap();
        if let Some((y, m, d)) = until {
            params.not_after = rcgen::date_time_ymd(y, m, d);
        }
        (params.self_signed(&key).unwrap().der().clone(), key)
    }

    fn identity(cert: CertificateDer<'static>, key: &rcgen::KeyPair) -> TlsIdentity {
        TlsIdentity {
            fingerprint: fingerprint(&cert),
            certs: vec![cert],
            key: PrivateKeyDer::from(PrivatePkcs8KeyDer::from(key.serialize_der())),
            origin: IdentityOrigin::Files {
                cert: PathBuf::from("/etc/arbor/cert.pem"),
                key: PathBuf::from("/etc/arbor/key.pem"),
            },
        }
    }

    fn unix(y: i16, m: i8, d: i8) -> i64 {
        let midnight = jiff::civil::DateTime::new(y, m, d, 0, 0, 0, 0).unwrap();
        let t = jiff::tz::TimeZone::UTC.to_timestamp(midnight).unwrap();
        t.as_second()
    }

    #[test]
    fn the_expiry_is_read_in_both_time_forms() {
        // rcgen writes UTCTime before 2050 and GeneralizedTime from 2050 on (RFC 5280), and
        // 4096-01-01 when not told.
        for (until, expected) in [
            (Some((2031, 5, 6)), unix(2031, 5, 6)),
            (Some((1999, 12, 31)), unix(1999, 12, 31)),
            (Some((2049, 12, 31)), unix(2049, 12, 31)),
            (Some((2061, 1, 2)), unix(2061, 1, 2)),
            (None, unix(4096, 1, 1)),
        ] {
            let (cert, _) = certificate(until);
            assert_eq!(not_after(&cert), Some(expected), "{until:?}");
        }
    }

    #[test]
    fn a_broken_certificate_has_no_expiry_and_no_panic() {
        let (cert, _) = certificate(Some((2031, 5, 6)));
        for end in 0..cert.len() {
            assert_eq!(not_after(&cert[..end]), None, "a prefix of {end} bytes");
        }
        let mut flipped = cert.to_vec();
        for i in 0..flipped.len() {
            flipped[i] ^= 0xff;
            let _ = not_after(&flipped);
            flipped[i] ^= 0xff;
        }
        assert_eq!(not_after(b"\x30\x84\xff\xff\xff\xff"), None);
        assert_eq!(not_after(b"\x30\x85\x01\x01\x01\x01\x01"), None);
        assert_eq!(asn1_time(UTC_TIME, b"3105060000Z"), None);
        assert_eq!(asn1_time(UTC_TIME, b"310506000000+0100"), None);
        assert_eq!(asn1_time(GENERALIZED_TIME, b"20311306000000Z"), None);
        assert_eq!(asn1_time(GENERALIZED_TIME, b"2031-5-06000000Z"), None);
    }

    #[test]
    fn the_replaced_certificate_is_what_the_next_handshake_gets() {
        let (a, a_key) = certificate(Some((2030, 1, 1)));
        let (b, b_key) = certificate(Some((2031, 1, 1)));
        let first = PresentedCertificate::of(&identity(a.clone(), &a_key)).unwrap();
        let live = LiveCertificate::new(Arc::new(first));
        assert_eq!(live.current().certified.cert[0], a);
        assert_eq!(live.current().not_after_unix, Some(unix(2030, 1, 1)));
        let next = Arc::new(PresentedCertificate::of(&identity(b.clone(), &b_key)).unwrap());
        assert!(live.replace(next.clone()));
        assert_eq!(live.current().certified.cert[0], b);
        assert_eq!(live.current().fingerprint, fingerprint(&b));
        assert!(!live.replace(next), "the same leaf again is no change");
    }

    #[test]
    fn a_key_that_is_not_the_certificates_is_refused_naming_both_files() {
        let (a, _) = certificate(None);
        let (_, other_key) = certificate(None);
        let e = PresentedCertificate::of(&identity(a, &other_key)).unwrap_err();
        assert!(matches!(e, TlsError::KeyMismatch { .. }), "{e:?}");
        let text = e.to_string();
        assert!(
            text.contains("/etc/arbor/cert.pem") && text.contains("/etc/arbor/key.pem"),
            "{text}"
        );
    }
}
