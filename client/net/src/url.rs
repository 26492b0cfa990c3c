//! Server URLs: `quic://HOST:PORT/SCENE`.

use std::fmt;
use std::net::{Ipv4Addr, Ipv6Addr};
use std::str::FromStr;

use arbor_proto::scene::validate_scene_name;

use super::error::ClientError;

/// The URL scheme of an Arbor treelet server.
pub const SCHEME: &str = "quic";

/// Where a scene is served: `quic://HOST:PORT/SCENE`.
///
/// `HOST` is a DNS name, an IPv4 address, or an IPv6 address in brackets (`[::1]`); the port is
/// required (there is no default port); `SCENE` is one scene name (see
/// [`validate_scene_name`]). User info, queries, fragments and further path segments are
/// refused.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct ServerUrl {
    /// Host name or address, without brackets for IPv6. It is also the TLS server name.
    pub host: String,
    pub port: u16,
    pub scene: String,
}

impl ServerUrl {
    /// Whether the host is an IPv6 address literal.
    pub fn is_ipv6_literal(&self) -> bool {
        self.host.parse::<Ipv6Addr>().is_ok()
    }
}

impl fmt::Display for ServerUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.host.contains(':') {
            write!(f, "{SCHEME}://[{}]:{}/{}", self.host, self.port, self.scene)
        } else {
            write!(f, "{SCHEME}://{}:{}/{}", self.host, self.port, self.scene)
        }
    }
}

impl FromStr for ServerUrl {
    type Err = ClientError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        parse_server_url(s)
    }
}

/// Parses `quic://HOST:PORT/SCENE`.
pub fn parse_server_url(url: &str) -> Result<ServerUrl, ClientError> {
    let bad = |reason: String| ClientError::BadUrl {
        url: url.to_owned(),
        reason,
    };
    let Some((scheme, rest)) = url.split_once("://") else {
        return Err(bad(format!("expected {SCHEME}://HOST:PORT/SCENE")));
    };
    if !scheme.eq_ignore_ascii_case(SCHEME) {
        return Err(bad(format!(
            "scheme {scheme:?} is not {SCHEME:?} (expected {SCHEME}://HOST:PORT/SCENE)"
        )));
    }
    if let Some(c) = rest
        .chars()
        .find(|c| c.is_whitespace() || c.is_control() || matches!(c, '?' | '#' | '@' | '%'))
    {
        return Err(bad(format!(
            "character {c:?} is not allowed (no user info, query, fragment or escapes)"
        )));
    }
    let Some((authority, scene)) = rest.split_once('/') else {
        return Err(bad("missing /SCENE after the port".into()));
    };
    let (host, port) = if let Some(after_bracket) = authority.strip_prefix('[') {
        let Some((host, after)) = after_bracket.split_once(']') else {
            return Err(bad("IPv6 address without closing ']'".into()));
        };
        if host.parse::<Ipv6Addr>().is_err() {
            return Err(bad(format!("{host:?} is not an IPv6 address")));
        }
        let Some(port) = after.strip_prefix(':') else {
            return Err(bad("missing :PORT after the host".into()));
        };
        (host, port)
    } else {
        let Some((host, port)) = authority.split_once(':') else {
            return Err(bad("missing :PORT after the host".into()));
        };
        if host.contains(':') || port.contains(':') {
            return Err(bad(
                "IPv6 addresses must be written in brackets, e.g. quic://[::1]:4433/scene".into(),
            ));
        }
        check_host_name(host).map_err(bad)?;
        (host, port)
    };
    if port.is_empty() {
        return Err(bad("missing port number".into()));
    }
    let port: u16 = match port.parse() {
        Ok(p) if p != 0 && port.bytes().all(|b| b.is_ascii_digit()) => p,
        _ => return Err(bad(format!("port {port:?} is not a number in 1..=65535"))),
    };
    if scene.is_empty() {
        return Err(bad("missing scene name after the '/'".into()));
    }
    if scene.contains('/') {
        return Err(bad(format!(
            "{scene:?}: expected one scene name, not a path"
        )));
    }
    validate_scene_name(scene).map_err(|e| bad(e.to_string()))?;
    Ok(ServerUrl {
        host: host.to_owned(),
        port,
        scene: scene.to_owned(),
    })
}

/// A DNS name (labels of letters, digits and hyphens, not starting or ending with a hyphen) or
/// an IPv4 address.
fn check_host_name(host: &str) -> Result<(), String> {
    if host.is_empty() {
        return Err("missing host".into());
    }
    if host.parse::<Ipv4Addr>().is_ok() {
        return Ok(());
    }
    if host.len() > 253 {
        return Err(format!("host name of {} bytes is too long", host.len()));
    }
    let name = host.strip_suffix('.').unwrap_or(host);
    for label in name.split('.') {
        let ok = !label.is_empty()
            && label.len() <= 63
            && !label.starts_with('-')
            && !label.ends_with('-')
            && label
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
        if !ok {
            return Err(format!("{host:?} is not a valid host name or address"));
        }
    }
    if name
        .split('.')
        .all(|l| l.bytes().all(|b| b.is_ascii_digit()))
    {
        return Err(format!("{host:?} is not a valid IPv4 address"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ok(s: &str) -> ServerUrl {
        parse_server_url(s).unwrap_or_else(|e| panic!("{s}: {e}"))
    }

    fn err(s: &str) -> String {
        match parse_server_url(s) {
            Ok(u) => panic!("{s} parsed as {u:?}"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn parses_names_and_addresses() {
        let u = ok("quic://example.org:4433/lion");
        assert_eq!(
            u,
            ServerUrl {
                host: "example.org".into(),
                port: 4433,
                scene: "lion".into()
            }
        );
        assert!(!u.is_ipv6_literal());
        assert_eq!(u.to_string(), "quic://example.org:4433/lion");
        let u = ok("quic://127.0.0.1:1/a.b_c-d");
        assert_eq!(
            (u.host.as_str(), u.port, u.scene.as_str()),
            ("127.0.0.1", 1, "a.b_c-d")
        );
        let u = ok("QUIC://localhost:65535/x");
        assert_eq!(u.host, "localhost");
        assert_eq!(u.port, 65535);
    }

    #[test]
    fn parses_ipv6_in_brackets() {
        let u = ok("quic://[::1]:4433/bunny");
        assert_eq!(u.host, "::1");
        assert!(u.is_ipv6_literal());
        assert_eq!(u.to_string(), "quic://[::1]:4433/bunny");
        assert_eq!(ok(&u.to_string()), u);
        let u = ok("quic://[2001:db8::7]:9/s");
        assert_eq!(u.host, "2001:db8::7");
        assert_eq!("quic://[2001:db8::7]:9/s".parse::<ServerUrl>().unwrap(), u);
    }

    #[test]
    fn rejects_with_clear_reasons() {
        assert!(err("example.org:4433/lion").contains("expected quic://"));
        assert!(err("https://example.org:4433/lion").contains("scheme"));
        assert!(err("quic://example.org/lion").contains("missing :PORT"));
        assert!(err("quic://example.org:4433").contains("missing /SCENE"));
        assert!(err("quic://example.org:4433/").contains("missing scene"));
        assert!(err("quic://example.org:/lion").contains("missing port"));
        assert!(err("quic://example.org:0/lion").contains("1..=65535"));
        assert!(err("quic://example.org:65536/lion").contains("1..=65535"));
        assert!(err("quic://example.org:+80/lion").contains("1..=65535"));
        assert!(err("quic://example.org:44x/lion").contains("1..=65535"));
        assert!(err("quic://:4433/lion").contains("missing host"));
        assert!(err("quic://::1:4433/lion").contains("brackets"));
        assert!(err("quic://[::1/lion").contains("closing"));
        assert!(err("quic://[::1]/lion").contains("missing :PORT"));
        assert!(err("quic://[nope]:1/lion").contains("not an IPv6"));
        assert!(err("quic://user@host:1/lion").contains("user info"));
        assert!(err("quic://host:1/lion?x=1").contains("query"));
        assert!(err("quic://host:1/lion#f").contains("fragment"));
        assert!(err("quic://ho st:1/lion").contains("not allowed"));
        assert!(err("quic://host:1/a/b").contains("not a path"));
        assert!(err("quic://host:1/.hidden").contains("scene name"));
        assert!(err("quic://-bad-.org:1/lion").contains("not a valid host"));
        assert!(err("quic://a..b:1/lion").contains("not a valid host"));
        assert!(err("quic://300.1.1.1:1/lion").contains("IPv4"));
    }
}
