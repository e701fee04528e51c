//! Which requests are answered at all: the `Host` (against DNS rebinding), `Origin` and `Sec-Fetch-Site` checks
//! every request passes before any route sees it, and the per-page token a request that changes anything needs.

use super::request::Request;
use super::response::Response;

/// A `Host` header's or an origin's authority: `name`, `name:port`, `[v6]` or `[v6]:port`, nothing else.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Authority {
    /// Lower case, without a trailing dot; an IP literal in its canonical form (a v6 one without brackets), so
    /// two spellings of one address compare equal.
    name: String,
    ip: bool,
    port: Option<u16>,
}

impl Authority {
    /// None unless `s` is exactly an authority: after a bracketed address only `:PORT` may follow, a port is
    /// 1–5 ASCII digits, a name is letters, digits, `-`, `_` and dots.
    fn parse(s: &str) -> Option<Self> {
        let (host, port) = match s.strip_prefix('[') {
            Some(rest) => {
                let (v6, after) = rest.split_once(']')?;
                let port = match after {
                    "" => None,
                    _ => Some(parse_port(after.strip_prefix(':')?)?),
                };
                let ip = v6.parse::<std::net::Ipv6Addr>().ok()?;
                return Some(Self { name: ip.to_string(), ip: true, port });
            }
            None => match s.split_once(':') {
                Some((h, p)) => (h, Some(parse_port(p)?)),
                None => (s, None),
            },
        };
        if let Ok(ip) = host.parse::<std::net::Ipv4Addr>() {
            return Some(Self { name: ip.to_string(), ip: true, port });
        }
        let name = host.strip_suffix('.').unwrap_or(host).to_ascii_lowercase();
        let label_ok = |l: &str| !l.is_empty() && l.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
        name.split('.').all(label_ok).then_some(Self { name, ip: false, port })
    }
}

/// `:PORT`'s digits (no sign, no spaces).
fn parse_port(p: &str) -> Option<u16> {
    if p.is_empty() || p.len() > 5 || !p.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    p.parse().ok()
}

/// Which `Host` headers the server answers: against DNS rebinding (a foreign site's name pointed at 127.0.0.1
/// reaches the server with its own name in `Host`, as Vite and webpack-dev-server refuse), only IP literals,
/// `localhost` and `*.localhost`, and the names given with `--allow-host` (a tunnel's or proxy's), each with the
/// server's port or none. An `Origin` must be the page's own: the accepted `Host`'s name and port.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HostPolicy {
    pub port: u16,
    pub allowed: Vec<String>,
}

/// Why a request is refused before its target is looked at.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Refusal {
    /// 400: no `Host`, several, or one that is not exactly an authority.
    BadHost,
    /// 403: a well-formed `Host` this server does not answer to.
    ForeignHost,
    /// 403: `Sec-Fetch-Site: cross-site`.
    CrossSite,
    /// 403: an `Origin` other than the accepted `Host`'s.
    ForeignOrigin,
    /// 403: a method that changes something (anything but GET, HEAD, OPTIONS) without the page's token.
    NoToken,
}

impl Refusal {
    pub(crate) fn response(self) -> Response {
        match self {
            Refusal::BadHost => Response::text(400, "missing, repeated or malformed Host header"),
            Refusal::ForeignHost => Response::text(403, "this Host is not served (start the server with --allow-host NAME for a tunnel or proxy name)"),
            Refusal::CrossSite => Response::text(403, "cross-site request refused"),
            Refusal::ForeignOrigin => Response::text(403, "cross-origin request refused"),
            Refusal::NoToken => Response::text(403, "missing or wrong X-Mvsplat360-Token (reload the page)"),
        }
    }
}

impl HostPolicy {
    /// `Host`'s authority when it is one this server answers to.
    fn host(&self, value: &str) -> std::result::Result<Authority, Refusal> {
        let a = Authority::parse(value.trim()).ok_or(Refusal::BadHost)?;
        if a.port.is_some_and(|p| p != self.port) {
            return Err(Refusal::ForeignHost);
        }
        let served = a.ip
            || a.name == "localhost"
            || a.name.ends_with(".localhost")
            || self.allowed.iter().any(|n| n.trim_end_matches('.').eq_ignore_ascii_case(&a.name));
        if served {
            Ok(a)
        } else {
            Err(Refusal::ForeignHost)
        }
    }

    /// Whether `origin` (`scheme://authority`, as browsers serialise it) is the page's own, served under `host`:
    /// same name and port, a missing port being the scheme's default (80 for http; 443 for https, the scheme a
    /// TLS tunnel or proxy in front of the server gives the page). `null` and any path are refused.
    fn same_origin(origin: &str, host: &Authority) -> bool {
        let origin = origin.trim();
        let Some((scheme, rest)) = origin.split_once("://") else { return false };
        let default = match scheme.to_ascii_lowercase().as_str() {
            "http" => 80,
            "https" => 443,
            _ => return false,
        };
        let Some(o) = Authority::parse(rest) else { return false };
        o.name == host.name && o.port.unwrap_or(default) == host.port.unwrap_or(default)
    }

    /// Ok when `req` may be answered.
    pub(crate) fn check(&self, req: &Request) -> std::result::Result<(), Refusal> {
        let mut hosts = req.headers_named("Host");
        let (Some(host), None) = (hosts.next(), hosts.next()) else { return Err(Refusal::BadHost) };
        let host = self.host(host)?;
        if req.headers_named("Sec-Fetch-Site").any(|v| v.trim().eq_ignore_ascii_case("cross-site")) {
            return Err(Refusal::CrossSite);
        }
        if !req.headers_named("Origin").all(|o| Self::same_origin(o, &host)) {
            return Err(Refusal::ForeignOrigin);
        }
        Ok(())
    }
}

/// The header a request that changes something carries the page's token in.
pub const TOKEN_HEADER: &str = "X-Mvsplat360-Token";

/// A random per-run secret the server embeds in the page it serves (e.g. as
/// `<meta name="mvsplat360-token" content="…">`, see [`PageToken::meta_tag`]) and requires, in the
/// [`TOKEN_HEADER`] header, on every request that is not GET, HEAD or OPTIONS. Another site's page cannot read it
/// (the `Host`/`Origin` checks keep it from reading the page), so it cannot forge such a request — even through a
/// form post, which can set no header.
#[derive(Clone, PartialEq, Eq)]
pub struct PageToken(String);

impl std::fmt::Debug for PageToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("PageToken(…)")
    }
}

impl PageToken {
    /// 128 random bits as 32 hex digits (from the system's random source).
    pub fn random() -> Self {
        let mut b = [0u8; 16];
        let filled = std::fs::File::open("/dev/urandom").and_then(|mut f| std::io::Read::read_exact(&mut f, &mut b)).is_ok();
        if !filled {
            // No /dev/urandom (not Unix): std's randomly keyed hasher, fed the time and the process id.
            use std::hash::{BuildHasher, Hasher};
            for (i, chunk) in b.chunks_mut(8).enumerate() {
                let mut h = std::collections::hash_map::RandomState::new().build_hasher();
                h.write_u128(std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0));
                h.write_u32(std::process::id());
                h.write_usize(i);
                chunk.copy_from_slice(&h.finish().to_le_bytes());
            }
        }
        Self(b.iter().map(|x| format!("{x:02x}")).collect())
    }

    /// A given token (tests; a token of at least 16 characters).
    pub fn from_string(s: impl Into<String>) -> Self {
        Self(s.into())
    }

    /// The token, to embed in the page.
    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// `<meta name="mvsplat360-token" content="TOKEN">`, for the page's `<head>`; the page sends
    /// `document.querySelector('meta[name=mvsplat360-token]').content` as the [`TOKEN_HEADER`] header.
    pub fn meta_tag(&self) -> String {
        format!("<meta name=\"mvsplat360-token\" content=\"{}\">", self.0)
    }

    /// Whether `value` is the token (compared in constant time).
    pub fn matches(&self, value: &str) -> bool {
        let (a, b) = (self.0.as_bytes(), value.trim().as_bytes());
        a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
    }

    /// Ok when `req` needs no token (GET, HEAD, OPTIONS) or carries exactly one header with this token.
    pub(crate) fn check(&self, req: &Request) -> std::result::Result<(), Refusal> {
        if matches!(req.method.as_str(), "GET" | "HEAD" | "OPTIONS") {
            return Ok(());
        }
        let mut v = req.headers_named(TOKEN_HEADER);
        match (v.next(), v.next()) {
            (Some(t), None) if self.matches(t) => Ok(()),
            _ => Err(Refusal::NoToken),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_answered() {
        let p = HostPolicy { port: 8080, allowed: vec!["gpu-box.tail1234.ts.net".into()] };
        for ok in [
            "127.0.0.1:8080",
            "127.0.0.1",
            "localhost:8080",
            "LOCALHOST",
            "localhost.",
            "app.localhost:8080",
            "[::1]:8080",
            "[::1]",
            "[0:0::1]:8080",
            "10.1.2.3:8080",
            "gpu-box.tail1234.ts.net:8080",
            " localhost:8080 ",
        ] {
            assert!(p.host(ok).is_ok(), "{ok}");
        }
        // Well formed, not served: 403.
        for foreign in ["evil.example", "evil.example:8080", "127.0.0.1:9999", "localhost.evil.example:8080", "[::1]:9999", "127.1:8080"] {
            assert_eq!(p.host(foreign), Err(Refusal::ForeignHost), "{foreign}");
        }
        // Not exactly an authority: 400. After `]` only `:PORT` may follow.
        for bad in [
            "[::1]evil.example",
            "[::1]evil.example:8080",
            "[::1]:8080evil.example",
            "[::1]:8080/",
            "[::1]:8080:8080",
            "[::1]:",
            "[::1]]",
            "[::1",
            "[nothost]:8080",
            "[127.0.0.1]:8080",
            "[fe80::1%25eth0]:8080",
            "::1",
            "",
            "127.0.0.1:80:80",
            "127.0.0.1:",
            "127.0.0.1:+8080",
            "127.0.0.1:08080x",
            "127.0.0.1:99999",
            "local host:8080",
            "localhost..:8080",
            "user@localhost:8080",
            "localhost/evil:8080",
        ] {
            assert_eq!(p.host(bad), Err(Refusal::BadHost), "{bad}");
        }
    }

    #[test]
    fn origins_match_the_host() {
        let host = |h: &str| Authority::parse(h).unwrap();
        let same = [
            ("http://127.0.0.1:8080", "127.0.0.1:8080"),
            ("HTTP://LOCALHOST:8080", "localhost:8080"),
            ("http://[::1]:8080", "[0:0::1]:8080"),
            ("http://gpu-box.example", "gpu-box.example"),
            ("http://gpu-box.example:80", "gpu-box.example"),
            ("http://gpu-box.example", "gpu-box.example:80"),
            // A TLS tunnel in front: the page is https, the Host it forwards has no port.
            ("https://gpu-box.example", "gpu-box.example"),
            ("https://gpu-box.example:443", "gpu-box.example"),
        ];
        for (o, h) in same {
            assert!(HostPolicy::same_origin(o, &host(h)), "{o} for {h}");
        }
        let foreign = [
            ("http://203.0.113.5", "127.0.0.1:8080"),
            ("http://127.0.0.1", "127.0.0.1:8080"),
            ("http://127.0.0.1:9999", "127.0.0.1:8080"),
            ("http://localhost:8080", "127.0.0.1:8080"),
            ("http://127.0.0.1:8080", "localhost:8080"),
            ("http://evil.example:8080", "127.0.0.1:8080"),
            ("http://[::1]evil.example", "[::1]"),
            ("http://127.0.0.1:8080/", "127.0.0.1:8080"),
            ("http://127.0.0.1:8080/x", "127.0.0.1:8080"),
            ("http://user@127.0.0.1:8080", "127.0.0.1:8080"),
            ("https://gpu-box.example", "gpu-box.example:80"),
            ("http://gpu-box.example", "gpu-box.example:443"),
            ("ftp://127.0.0.1:8080", "127.0.0.1:8080"),
            ("127.0.0.1:8080", "127.0.0.1:8080"),
            ("null", "127.0.0.1:8080"),
            ("", "127.0.0.1:8080"),
        ];
        for (o, h) in foreign {
            assert!(!HostPolicy::same_origin(o, &host(h)), "{o} for {h}");
        }
    }
}
