//! The server's TLS identity and its QUIC crypto configuration (docs/design.md §6: TLS always).
//!
//! * Without a configured certificate, a self-signed pair (rcgen, ECDSA P-256) is created on
//!   first start in the data dir as `cert.pem` and `key.pem` (mode 0600, written to temporary
//!   files and renamed, key first) and reused on every later start, so the fingerprint clients
//!   pin stays the same. SANs: `localhost`, `127.0.0.1`, `::1` and the host name when it can be
//!   read.
//! * Or a given PEM chain + key.
//!
//! The fingerprint clients pin is the SHA-256 of the leaf certificate's DER, lowercase hex, 64
//! characters, no separators ([`fingerprint`]).
//!
//! Only TLS 1.3 (QUIC requires it) and only ALPN [`arbor_proto::wire::ALPN`]: a client offering
//! any other protocol, or none, fails the handshake (rustls answers `no_application_protocol`,
//! QUIC transport error 0x178).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

use super::certificate::LiveCertificate;
use super::config::TlsSource;

/// Errors setting up TLS.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A certificate or key file could not be read, created or written.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A PEM file holds no certificate / no key, or is malformed.
    #[error("{}: {reason}", path.display())]
    Pem { path: PathBuf, reason: String },
    /// The data dir holds only one half of a self-signed pair.
    #[error("{} exists but {} does not; remove it to generate a new pair", present.display(), missing.display())]
    HalfPair { present: PathBuf, missing: PathBuf },
    /// rcgen could not generate the self-signed certificate.
    #[error("generating the self-signed certificate: {0}")]
    Generate(#[from] rcgen::Error),
    /// rustls rejected the certificate/key or the configuration.
    #[error("TLS configuration: {0}")]
    Rustls(#[from] rustls::Error),
    /// quinn rejected the rustls configuration (not TLS 1.3 capable).
    #[error("QUIC crypto configuration: {0}")]
    Quic(String),
    /// The key is not the one the certificate was issued for.
    #[error("{}: not the key of the certificate in {}", key.display(), cert.display())]
    KeyMismatch { cert: PathBuf, key: PathBuf },
}

/// The certificate chain and key the server presents.
#[derive(Debug)]
pub struct TlsIdentity {
    pub certs: Vec<CertificateDer<'static>>,
    pub key: PrivateKeyDer<'static>,
    /// SHA-256 of `certs[0]`, lowercase hex.
    pub fingerprint: String,
    /// Where it came from.
    pub origin: IdentityOrigin,
}

/// How the identity was obtained.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum IdentityOrigin {
    /// Self-signed pair created now in the data dir.
    Created { cert: PathBuf, key: PathBuf },
    /// Self-signed pair from an earlier start, reused.
    Reused { cert: PathBuf, key: PathBuf },
    /// Configured PEM files.
    Files { cert: PathBuf, key: PathBuf },
}

impl IdentityOrigin {
    /// The certificate and key files.
    pub fn paths(&self) -> (&Path, &Path) {
        match self {
            IdentityOrigin::Created { cert, key }
            | IdentityOrigin::Reused { cert, key }
            | IdentityOrigin::Files { cert, key } => (cert, key),
        }
    }
}

/// SHA-256 of a certificate's DER, lowercase hex, 64 characters, no separators.
pub fn fingerprint(der: &[u8]) -> String {
    let d = ring::digest::digest(&ring::digest::SHA256, der);
    let mut s = String::with_capacity(64);
    for b in d.as_ref() {
        s.push_str(&format!("{b:02x}"));
    }
    s
}

/// Installs the ring crypto provider as rustls' process default (once; "already installed" is
/// fine).
pub fn install_crypto_provider() {
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// File names of the self-signed pair in the data dir.
pub const CERT_FILE: &str = "cert.pem";
pub const KEY_FILE: &str = "key.pem";

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> TlsError + '_ {
    move |source| TlsError::Io {
        path: path.to_owned(),
        source,
    }
}

/// The host name, when the system tells it without extra dependencies.
fn hostname() -> Option<String> {
    let raw = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .or_else(|_| std::fs::read_to_string("/etc/hostname"))
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())?;
    let h = raw.trim().to_owned();
    let ok = !h.is_empty()
        && h.len() <= 253
        && h != "localhost"
        && h.split('.').all(|l| {
            !l.is_empty()
                && l.len() <= 63
                && l.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
                && !l.starts_with('-')
                && !l.ends_with('-')
        });
    ok.then_some(h)
}

/// Writes `data` to `path` through a temporary file in the same directory, with `mode`.
fn write_atomically(path: &Path, data: &[u8], mode: u32) -> Result<(), TlsError> {
    use std::os::unix::fs::OpenOptionsExt as _;
    let tmp = path.with_extension("pem.tmp");
    let _ = std::fs::remove_file(&tmp);
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(mode)
        .open(&tmp)
        .map_err(io_err(&tmp))?;
    f.write_all(data).map_err(io_err(&tmp))?;
    f.sync_all().map_err(io_err(&tmp))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

/// Reads a PEM chain and key.
pub(crate) fn read_pem(cert: &Path, key: &Path) -> Result<TlsIdentity, TlsError> {
    let cert_bytes = std::fs::read(cert).map_err(io_err(cert))?;
    let certs = CertificateDer::pem_slice_iter(&cert_bytes)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| TlsError::Pem {
            path: cert.to_owned(),
            reason: e.to_string(),
        })?;
    let Some(leaf) = certs.first() else {
        return Err(TlsError::Pem {
            path: cert.to_owned(),
            reason: "no CERTIFICATE section".into(),
        });
    };
    let fingerprint = fingerprint(leaf);
    let key_bytes = std::fs::read(key).map_err(io_err(key))?;
    let key_der = PrivateKeyDer::from_pem_slice(&key_bytes).map_err(|e| TlsError::Pem {
        path: key.to_owned(),
        reason: format!("no usable private key: {e}"),
    })?;
    Ok(TlsIdentity {
        certs,
        key: key_der,
        fingerprint,
        origin: IdentityOrigin::Files {
            cert: cert.to_owned(),
            key: key.to_owned(),
        },
    })
}

/// Loads the identity: the configured files, or the self-signed pair in `data_dir` (created on
/// first start).
pub fn load_or_create(source: &TlsSource, data_dir: &Path) -> Result<TlsIdentity, TlsError> {
    match source {
        TlsSource::Files { cert, key } => read_pem(cert, key),
        TlsSource::SelfSigned => {
            let cert = data_dir.join(CERT_FILE);
            let key = data_dir.join(KEY_FILE);
            match (cert.exists(), key.exists()) {
                (true, true) => load_existing(source, data_dir),
                (false, false) => create_self_signed(data_dir, cert, key),
                (true, false) => Err(TlsError::HalfPair {
                    present: cert,
                    missing: key,
                }),
                (false, true) => Err(TlsError::HalfPair {
                    present: key,
                    missing: cert,
                }),
            }
        }
    }
}

/// Loads the identity as [`load_or_create`] but never creates one: what a reload reads (a
/// missing self-signed pair is an error, not a new fingerprint).
pub fn load_existing(source: &TlsSource, data_dir: &Path) -> Result<TlsIdentity, TlsError> {
    match source {
        TlsSource::Files { cert, key } => read_pem(cert, key),
        TlsSource::SelfSigned => {
            let (cert, key) = (data_dir.join(CERT_FILE), data_dir.join(KEY_FILE));
            let mut id = read_pem(&cert, &key)?;
            id.origin = IdentityOrigin::Reused { cert, key };
            Ok(id)
        }
    }
}

fn create_self_signed(
    data_dir: &Path,
    cert_path: PathBuf,
    key_path: PathBuf,
) -> Result<TlsIdentity, TlsError> {
    std::fs::create_dir_all(data_dir).map_err(io_err(data_dir))?;
    let mut names = vec!["localhost".to_owned(), "127.0.0.1".into(), "::1".into()];
    names.extend(hostname());
    let rcgen::CertifiedKey { cert, signing_key } = rcgen::generate_simple_self_signed(names)?;
    // Key first: a crash between the renames leaves a lone key.pem, reported as a half pair,
    // never a certificate whose key is lost.
    write_atomically(&key_path, signing_key.serialize_pem().as_bytes(), 0o600)?;
    write_atomically(&cert_path, cert.pem().as_bytes(), 0o644)?;
    let der: CertificateDer<'static> = cert.der().clone();
    Ok(TlsIdentity {
        fingerprint: fingerprint(&der),
        certs: vec![der],
        key: PrivatePkcs8KeyDer::from(signing_key.serialize_der()).into(),
        origin: IdentityOrigin::Created {
            cert: cert_path,
            key: key_path,
        },
    })
}

/// The rustls server configuration: TLS 1.3 only, ring provider, ALPN `arbor/1` only, the
/// certificate `certificate` holds at each handshake.
pub fn rustls_server_config(
    certificate: Arc<LiveCertificate>,
) -> Result<rustls::ServerConfig, TlsError> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut cfg = rustls::ServerConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .with_no_client_auth()
        .with_cert_resolver(certificate);
    cfg.alpn_protocols = vec![arbor_proto::wire::ALPN.to_vec()];
    Ok(cfg)
}

/// quinn's server configuration around [`rustls_server_config`] with the given transport.
pub fn quic_server_config(
    certificate: Arc<LiveCertificate>,
    transport: quinn::TransportConfig,
) -> Result<quinn::ServerConfig, TlsError> {
    let crypto =
        quinn::crypto::rustls::QuicServerConfig::try_from(rustls_server_config(certificate)?)
            .map_err(|e| TlsError::Quic(e.to_string()))?;
    let mut cfg = quinn::ServerConfig::with_crypto(Arc::new(crypto));
    cfg.transport_config(Arc::new(transport));
    Ok(cfg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::certificate::PresentedCertificate;
    use std::os::unix::fs::PermissionsExt as _;

    #[test]
    fn created_once_and_reused() {
        install_crypto_provider();
        install_crypto_provider();
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("state");
        let a = load_or_create(&TlsSource::SelfSigned, &data).unwrap();
        assert!(matches!(a.origin, IdentityOrigin::Created { .. }));
        assert_eq!(a.fingerprint.len(), 64);
        assert!(
            a.fingerprint
                .bytes()
                .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
        );
        assert_eq!(a.fingerprint, fingerprint(&a.certs[0]));
        let mode = std::fs::metadata(data.join(KEY_FILE))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600, "key.pem mode {mode:o}");
        let b = load_or_create(&TlsSource::SelfSigned, &data).unwrap();
        assert!(matches!(b.origin, IdentityOrigin::Reused { .. }));
        assert_eq!(a.fingerprint, b.fingerprint);
        assert_eq!(a.certs, b.certs);
        assert_eq!(a.key.secret_der(), b.key.secret_der());
        // The same files given explicitly give the same fingerprint.
        let c = load_or_create(
            &TlsSource::Files {
                cert: data.join(CERT_FILE),
                key: data.join(KEY_FILE),
            },
            Path::new("/nonexistent"),
        )
        .unwrap();
        assert_eq!(c.fingerprint, a.fingerprint);
        // Usable by rustls and quinn.
        let live = LiveCertificate::new(Arc::new(PresentedCertificate::of(&a).unwrap()));
        let live = Arc::new(live);
        quic_server_config(live, quinn::TransportConfig::default()).unwrap();
        // No temporary files left behind.
        let names: Vec<_> = std::fs::read_dir(&data)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert_eq!(names.len(), 2, "{names:?}");
    }

    #[test]
    fn the_certificate_names_loopback() {
        let dir = tempfile::tempdir().unwrap();
        let a = load_or_create(&TlsSource::SelfSigned, dir.path()).unwrap();
        let verifier = rustls::client::WebPkiServerVerifier::builder_with_provider(
            Arc::new({
                let mut roots = rustls::RootCertStore::empty();
                roots.add(a.certs[0].clone()).unwrap();
                roots
            }),
            Arc::new(rustls::crypto::ring::default_provider()),
        )
        .build()
        .unwrap();
        use rustls::client::danger::ServerCertVerifier as _;
        for name in ["localhost", "127.0.0.1", "::1"] {
            let sn = rustls::pki_types::ServerName::try_from(name).unwrap();
            verifier
                .verify_server_cert(
                    &a.certs[0],
                    &[],
                    &sn,
                    &[],
                    rustls::pki_types::UnixTime::now(),
                )
                .unwrap_or_else(|e| panic!("{name}: {e}"));
        }
    }

    #[test]
    fn bad_files_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::write(d.join(KEY_FILE), "x").unwrap();
        assert!(matches!(
            load_or_create(&TlsSource::SelfSigned, d),
            Err(TlsError::HalfPair { .. })
        ));
        std::fs::write(d.join("c.pem"), "not pem").unwrap();
        let e = load_or_create(
            &TlsSource::Files {
                cert: d.join("c.pem"),
                key: d.join(KEY_FILE),
            },
            d,
        )
        .unwrap_err();
        assert!(matches!(e, TlsError::Pem { .. }), "{e}");
        let e = load_or_create(
            &TlsSource::Files {
                cert: d.join("missing.pem"),
                key: d.join(KEY_FILE),
            },
            d,
        )
        .unwrap_err();
        assert!(e.to_string().contains("missing.pem"), "{e}");
    }

    #[test]
    fn a_reload_reads_the_pair_and_never_creates_one() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let e = load_existing(&TlsSource::SelfSigned, d).unwrap_err();
        assert!(e.to_string().contains(CERT_FILE), "{e}");
        assert!(
            std::fs::read_dir(d).unwrap().next().is_none(),
            "nothing created"
        );
        let made = load_or_create(&TlsSource::SelfSigned, d).unwrap();
        let read = load_existing(&TlsSource::SelfSigned, d).unwrap();
        assert_eq!(read.fingerprint, made.fingerprint);
        assert!(matches!(read.origin, IdentityOrigin::Reused { .. }));
    }
}
