//! Credentials of the admin API: `Authorization: Bearer <token>` or the `arbor_admin` cookie.
//!
//! The configured token is kept only as its SHA-256; a presented token is hashed and the two
//! digests compared with a branch-free fold, so neither the comparison's time nor an early exit
//! tells how much of a guess was right, and the comparison does not depend on the token's length.
//!
//! The cookie holds the token itself, percent-encoding the bytes a cookie value may not hold
//! (RFC 6265 `cookie-octet`, and `%`), so `arbor_admin=<token>` set by hand works for usual tokens.

use std::sync::{Arc, PoisonError, RwLock};

use axum::http::{HeaderMap, header};
use ring::digest;

/// Name of the cookie `POST /login` sets.
pub const COOKIE: &str = "arbor_admin";

/// The configured token, as its digest.
pub(super) struct Secret {
    digest: [u8; 32],
    /// False for an empty token: nothing is accepted then.
    enabled: bool,
}

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Secret")
            .field("enabled", &self.enabled)
            .finish_non_exhaustive()
    }
}

fn sha256(b: &[u8]) -> [u8; 32] {
    let d = digest::digest(&digest::SHA256, b);
    let mut out = [0; 32];
    out.copy_from_slice(d.as_ref());
    out
}

impl Secret {
    pub(super) fn new(token: &str) -> Self {
        Self {
            digest: sha256(token.as_bytes()),
            enabled: !token.is_empty(),
        }
    }

    /// Whether `presented` is the token, in time independent of where they differ.
    pub(super) fn matches(&self, presented: &[u8]) -> bool {
        let d = sha256(presented);
        let mut diff = 0u8;
        for (a, b) in d.iter().zip(&self.digest) {
            diff |= a ^ b;
        }
        std::hint::black_box(diff) == 0 && self.enabled && !presented.is_empty()
    }
}

/// The admin token and the probe token in force; [`AdminCredentials::replace`] puts new ones
/// in force for the next request (SIGHUP, [`crate::daemon::Reloader`]). A login cookie holds
/// the token itself, so a replaced token logs its browsers out.
pub struct AdminCredentials {
    current: RwLock<Arc<Tokens>>,
}

/// One generation of [`AdminCredentials`].
#[derive(Debug)]
pub(super) struct Tokens {
    pub(super) admin: Secret,
    pub(super) probe: Option<Secret>,
}

impl Tokens {
    fn new(admin: &str, probe: Option<&str>) -> Self {
        if admin.is_empty() {
            tracing::error!(
                "the admin token is empty: every authenticated admin route will answer 401"
            );
        }
        Self {
            admin: Secret::new(admin),
            probe: probe.map(Secret::new),
        }
    }
}

impl std::fmt::Debug for AdminCredentials {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AdminCredentials").finish_non_exhaustive()
    }
}

impl AdminCredentials {
    /// The bearer token of every route but `/healthz` and the login form (empty: nobody is
    /// admitted), and a low-privilege one accepted by `/readyz` only (orchestrator probes).
    pub fn new(admin: &str, probe: Option<&str>) -> Arc<Self> {
        Arc::new(Self {
            current: RwLock::new(Arc::new(Tokens::new(admin, probe))),
        })
    }

    /// Puts `admin` and `probe` in force; true when the admin token changed.
    pub fn replace(&self, admin: &str, probe: Option<&str>) -> bool {
        let next = Arc::new(Tokens::new(admin, probe));
        let mut current = self.current.write().unwrap_or_else(PoisonError::into_inner);
        let changed = current.admin.digest != next.admin.digest;
        *current = next;
        changed
    }

    /// The tokens in force.
    pub(super) fn current(&self) -> Arc<Tokens> {
        self.current
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

/// What a request presented.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Credentials {
    /// No bearer token and no admin cookie.
    None,
    /// Something was presented, and none of it is the token.
    Invalid,
    /// A bearer token or the cookie is the token.
    Valid,
}

/// Checks every `Authorization: Bearer` header and every `arbor_admin` cookie of a request.
pub(super) fn check(headers: &HeaderMap, secret: &Secret) -> Credentials {
    let mut presented = false;
    for v in headers.get_all(header::AUTHORIZATION) {
        let Some(token) = bearer(v.as_bytes()) else {
            presented = true;
            continue;
        };
        presented = true;
        if secret.matches(token) {
            return Credentials::Valid;
        }
    }
    for v in headers.get_all(header::COOKIE) {
        for value in cookie_values(v.as_bytes()) {
            presented = true;
            if let Some(token) = decode_cookie(value)
                && secret.matches(&token)
            {
                return Credentials::Valid;
            }
        }
    }
    if presented {
        Credentials::Invalid
    } else {
        Credentials::None
    }
}

/// The token of `Bearer <token>` (scheme case-insensitive, RFC 7235), `None` for another scheme.
fn bearer(v: &[u8]) -> Option<&[u8]> {
    let v = v.trim_ascii();
    let (scheme, rest) = v.split_at_checked(6)?;
    if !scheme.eq_ignore_ascii_case(b"bearer") || !rest.first()?.is_ascii_whitespace() {
        return None;
    }
    Some(rest.trim_ascii())
}

/// Values of the admin cookie in one `Cookie` header (`a=1; arbor_admin=...; b=2`).
fn cookie_values(v: &[u8]) -> impl Iterator<Item = &[u8]> {
    v.split(|&b| b == b';').filter_map(|pair| {
        let pair = pair.trim_ascii();
        let eq = pair.iter().position(|&b| b == b'=')?;
        let (name, value) = (&pair[..eq], &pair[eq + 1..]);
        (name.trim_ascii() == COOKIE.as_bytes()).then(|| {
            let v = value.trim_ascii();
            // RFC 6265 allows the value to be quoted.
            v.strip_prefix(b"\"")
                .and_then(|x| x.strip_suffix(b"\""))
                .unwrap_or(v)
        })
    })
}

/// RFC 6265 `cookie-octet`, less `%` which escapes the others.
fn plain_cookie_octet(b: u8) -> bool {
    matches!(b, 0x21 | 0x23..=0x24 | 0x26..=0x2B | 0x2D..=0x3A | 0x3C..=0x5B | 0x5D..=0x7E)
}

fn encode_cookie(token: &str) -> String {
    let mut out = String::with_capacity(token.len());
    for &b in token.as_bytes() {
        if plain_cookie_octet(b) {
            out.push(char::from(b));
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

fn decode_cookie(v: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::with_capacity(v.len());
    let mut i = 0;
    while i < v.len() {
        if v[i] == b'%' {
            let hex = v.get(i + 1..i + 3)?;
            if !hex.iter().all(u8::is_ascii_hexdigit) {
                return None;
            }
            out.push(u8::from_str_radix(std::str::from_utf8(hex).ok()?, 16).ok()?);
            i += 3;
        } else {
            out.push(v[i]);
            i += 1;
        }
    }
    Some(out)
}

/// `Set-Cookie` value that logs a browser in. Not `Secure`: the admin API speaks plain HTTP on
/// loopback (put a TLS proxy in front to reach it from elsewhere).
pub(super) fn set_cookie(token: &str) -> String {
    format!(
        "{COOKIE}={}; Path=/; HttpOnly; SameSite=Strict",
        encode_cookie(token)
    )
}

/// `Set-Cookie` value that logs a browser out.
pub(super) fn clear_cookie() -> String {
    format!("{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0")
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn headers(pairs: &[(header::HeaderName, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.append(k.clone(), HeaderValue::from_str(v).unwrap());
        }
        h
    }

    #[test]
    fn bearer_and_cookie() {
        let s = Secret::new("t0k/en+=");
        let check = |p: &[(header::HeaderName, &str)]| check(&headers(p), &s);
        assert_eq!(check(&[]), Credentials::None);
        assert_eq!(
            check(&[(header::AUTHORIZATION, "Bearer t0k/en+=")]),
            Credentials::Valid
        );
        assert_eq!(
            check(&[(header::AUTHORIZATION, "bearer   t0k/en+= ")]),
            Credentials::Valid
        );
        assert_eq!(
            check(&[(header::AUTHORIZATION, "Bearer t0k/en+")]),
            Credentials::Invalid
        );
        assert_eq!(
            check(&[(header::AUTHORIZATION, "Basic t0k/en+=")]),
            Credentials::Invalid
        );
        assert_eq!(
            check(&[(header::AUTHORIZATION, "Bearert0k/en+=")]),
            Credentials::Invalid
        );
        assert_eq!(
            check(&[(header::COOKIE, "a=1; arbor_admin=t0k/en+=; b=2")]),
            Credentials::Valid
        );
        assert_eq!(
            check(&[(header::COOKIE, "arbor_admin=\"t0k/en+=\"")]),
            Credentials::Valid
        );
        assert_eq!(
            check(&[(header::COOKIE, "arbor_admin=nope")]),
            Credentials::Invalid
        );
        assert_eq!(check(&[(header::COOKIE, "other=1")]), Credentials::None);
    }

    #[test]
    fn cookie_encoding_round_trips_any_token() {
        for t in ["plain", "a b;c%d\"e,f\\g", "ünïcödé", "%41"] {
            let c = set_cookie(t);
            assert!(HeaderValue::from_str(&c).is_ok(), "{c}");
            let value = c
                .strip_prefix("arbor_admin=")
                .unwrap()
                .split(';')
                .next()
                .unwrap();
            assert_eq!(decode_cookie(value.as_bytes()).unwrap(), t.as_bytes());
        }
        assert_eq!(decode_cookie(b"%4"), None);
        assert_eq!(decode_cookie(b"%zz"), None);
        assert_eq!(decode_cookie(b"%+4"), None);
    }

    #[test]
    fn empty_token_admits_nobody() {
        let s = Secret::new("");
        assert!(!s.matches(b""));
        assert_eq!(
            check(&headers(&[(header::AUTHORIZATION, "Bearer ")]), &s),
            Credentials::Invalid
        );
    }

    #[test]
    fn replaced_tokens_admit_from_the_next_request() {
        let credentials = AdminCredentials::new("first", Some("probe-1"));
        let bearer = |t: &str| headers(&[(header::AUTHORIZATION, &format!("Bearer {t}"))]);
        let tokens = credentials.current();
        assert_eq!(check(&bearer("first"), &tokens.admin), Credentials::Valid);
        let probe = tokens.probe.as_ref().unwrap();
        assert_eq!(check(&bearer("probe-1"), probe), Credentials::Valid);

        assert!(credentials.replace("second", None));
        let tokens = credentials.current();
        assert_eq!(check(&bearer("first"), &tokens.admin), Credentials::Invalid);
        assert_eq!(check(&bearer("second"), &tokens.admin), Credentials::Valid);
        assert!(tokens.probe.is_none(), "the probe token taken out");
        assert!(
            !credentials.replace("second", Some("probe-2")),
            "the admin token is the same"
        );
        let probe = credentials
            .current()
            .probe
            .as_ref()
            .map(|p| p.matches(b"probe-2"));
        assert_eq!(probe, Some(true));
    }
}
