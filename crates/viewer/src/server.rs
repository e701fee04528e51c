//! The local server: GET/HEAD only, bound to 127.0.0.1, the page's assets from the binary and the render's files
//! from an allow-list (the manifest) — a request can reach nothing else, whatever its encoding.

use std::io::{Read, Seek, SeekFrom};
use std::path::PathBuf;
use std::sync::Arc;

use tiny_http::{Header, Method, Request, Response, StatusCode};

use crate::error::{Result, ViewerError};
use crate::outdir::OutDir;
use crate::site::asset;

/// What a request path refers to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Resolved {
    /// A page asset compiled into the binary (its name).
    Asset(&'static str),
    /// The manifest, generated per request.
    Manifest,
    /// A file of the output folder (canonical path inside it).
    File(PathBuf),
    /// Refused: status code and a short reason.
    Refused(u16, &'static str),
}

/// Map a raw request target (as sent, still percent-encoded) to what it may serve.
///
/// Data paths are decoded once and must then be plain relative paths (no `..`, `.`, empty segments, backslashes,
/// NUL or leading `/`) listed in the folder's manifest, and must still lie inside the folder once symlinks are
/// resolved; anything else is refused.
pub fn resolve(out: &OutDir, target: &str) -> Resolved {
    let path = target.split(['?', '#']).next().unwrap_or("");
    if !path.starts_with('/') {
        return Resolved::Refused(400, "bad request target");
    }
    match path {
        "/" | "/index.html" => return Resolved::Asset("index.html"),
        "/manifest.json" => return Resolved::Manifest,
        _ => {}
    }
    let Some(raw) = path.strip_prefix("/data/") else {
        return match asset(&path[1..]) {
            Some((name, _)) => Resolved::Asset(name),
            None => Resolved::Refused(404, "not found"),
        };
    };
    let Ok(rel) = percent_encoding::percent_decode_str(raw).decode_utf8() else {
        return Resolved::Refused(400, "bad path encoding");
    };
    let bad = rel.is_empty() || rel.starts_with('/') || rel.contains(['\\', '\0', ':']) || rel.split('/').any(|s| s.is_empty() || s == "." || s == "..");
    if bad {
        return Resolved::Refused(400, "bad path");
    }
    if !out.manifest().contains(&rel) {
        return Resolved::Refused(404, "not found");
    }
    match out.root.join(&*rel).canonicalize() {
        Ok(p) if p.starts_with(&out.root) && p.is_file() => Resolved::File(p),
        Ok(_) => Resolved::Refused(403, "outside the output folder"),
        Err(_) => Resolved::Refused(404, "not found"),
    }
}

fn content_type(name: &str) -> &'static str {
    match name.rsplit('.').next().unwrap_or("") {
        "html" => "text/html; charset=utf-8",
        "js" => "text/javascript; charset=utf-8",
        "json" => "application/json",
        "txt" => "text/plain; charset=utf-8",
        "png" => "image/png",
        "mp4" => "video/mp4",
        _ => "application/octet-stream",
    }
}

fn header(k: &str, v: &str) -> Header {
    Header::from_bytes(k.as_bytes(), v.as_bytes()).expect("header names and values built here are ASCII")
}

type Reply = Response<Box<dyn Read + Send>>;

fn reply(status: u16, ctype: &str, body: Box<dyn Read + Send>, len: u64, extra: Vec<Header>) -> Reply {
    let mut headers = vec![
        header("Content-Type", ctype),
        header("Cache-Control", "no-cache"),
        header("X-Content-Type-Options", "nosniff"),
        header("Referrer-Policy", "no-referrer"),
    ];
    headers.extend(extra);
    // The length is always known: send it as Content-Length (tiny_http would switch bodies over 32 KiB to chunked
    // transfer), so the page can show how much of the Gaussians has arrived.
    Response::new(StatusCode(status), headers, body, Some(len as usize), None).with_chunked_threshold(usize::MAX)
}

fn text(status: u16, msg: &str) -> Reply {
    let b = format!("{status} {msg}\n").into_bytes();
    let n = b.len() as u64;
    reply(status, "text/plain; charset=utf-8", Box::new(std::io::Cursor::new(b)), n, vec![])
}

/// `bytes=a-b`, `bytes=a-`, `bytes=-n` (one range; browsers ask for one when seeking in a video).
fn parse_range(v: &str, len: u64) -> Option<(u64, u64)> {
    let spec = v.trim().strip_prefix("bytes=")?;
    if spec.contains(',') || len == 0 {
        return None;
    }
    let (a, b) = spec.split_once('-')?;
    let (start, end) = match (a.trim(), b.trim()) {
        ("", n) => {
            let n: u64 = n.parse().ok()?;
            (len.saturating_sub(n), len - 1)
        }
        (s, "") => (s.parse().ok()?, len - 1),
        (s, e) => (s.parse().ok()?, e.parse::<u64>().ok()?.min(len - 1)),
    };
    (start <= end && start < len).then_some((start, end))
}

fn serve_file(path: &std::path::Path, range: Option<&str>) -> Reply {
    let ctype = content_type(&path.to_string_lossy());
    let Ok(mut f) = std::fs::File::open(path) else { return text(404, "not found") };
    let Ok(len) = f.metadata().map(|m| m.len()) else { return text(500, "cannot read file") };
    let accept = header("Accept-Ranges", "bytes");
    if let Some(r) = range {
        let Some((s, e)) = parse_range(r, len) else {
            return reply(416, "text/plain", Box::new(std::io::empty()), 0, vec![header("Content-Range", &format!("bytes */{len}"))]);
        };
        if f.seek(SeekFrom::Start(s)).is_err() {
            return text(500, "cannot read file");
        }
        let n = e - s + 1;
        return reply(206, ctype, Box::new(f.take(n)), n, vec![accept, header("Content-Range", &format!("bytes {s}-{e}/{len}"))]);
    }
    reply(200, ctype, Box::new(f), len, vec![accept])
}

/// Which `Host` headers the server answers: against DNS rebinding (a foreign site's name pointed at 127.0.0.1
/// reaches the server with its own name in `Host`, as Vite and webpack-dev-server refuse), only IP literals,
/// `localhost` and `*.localhost`, and the names given with `--allow-host` (a tunnel's or proxy's), each with the
/// server's port or none.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HostPolicy {
    pub port: u16,
    pub allowed: Vec<String>,
}

impl HostPolicy {
    /// `Host`'s name when it is one this server answers to.
    fn accepts(&self, host: &str) -> bool {
        let host = host.trim().to_ascii_lowercase();
        // `[v6]:port`, `[v6]`, `name:port`, `name`.
        let (name, port) = if let Some(rest) = host.strip_prefix('[') {
            let Some((v6, after)) = rest.split_once(']') else { return false };
            if v6.parse::<std::net::Ipv6Addr>().is_err() {
                return false;
            }
            (v6.to_string(), after.strip_prefix(':'))
        } else {
            match host.rsplit_once(':') {
                Some((n, p)) => (n.to_string(), Some(p)),
                None => (host.clone(), None),
            }
        };
        if port.is_some_and(|p| p.parse::<u16>().ok() != Some(self.port)) {
            return false;
        }
        let name = name.trim_end_matches('.');
        name.parse::<std::net::IpAddr>().is_ok()
            || host.starts_with('[')
            || name == "localhost"
            || name.ends_with(".localhost")
            || self.allowed.iter().any(|a| a.eq_ignore_ascii_case(name))
    }

    /// None when `req` may be answered, else the refusal.
    fn check(&self, req: &Request) -> Option<Reply> {
        let get = |name: &str| req.headers().iter().find(|h| h.field.as_str().as_str().eq_ignore_ascii_case(name)).map(|h| h.value.as_str().to_string());
        let Some(host) = get("Host") else { return Some(text(400, "no Host header")) };
        if !self.accepts(&host) {
            return Some(text(403, "this Host is not served (start `mvsplat360 view` with --allow-host NAME for a tunnel or proxy name)"));
        }
        if get("Sec-Fetch-Site").is_some_and(|v| v.eq_ignore_ascii_case("cross-site")) {
            return Some(text(403, "cross-site request refused"));
        }
        if let Some(origin) = get("Origin") {
            let o = origin.trim();
            let hostpart = o.strip_prefix("http://").or_else(|| o.strip_prefix("https://"));
            if !hostpart.is_some_and(|h| self.accepts(h.trim_end_matches('/'))) {
                return Some(text(403, "cross-origin request refused"));
            }
        }
        None
    }
}

fn respond(out: &OutDir, policy: &HostPolicy, req: &Request) -> Reply {
    if let Some(refusal) = policy.check(req) {
        return refusal;
    }
    if !matches!(req.method(), Method::Get | Method::Head) {
        return text(405, "method not allowed (read-only server)");
    }
    match resolve(out, req.url()) {
        Resolved::Asset(name) => match asset(name) {
            Some((_, bytes)) => reply(200, content_type(name), Box::new(bytes), bytes.len() as u64, vec![]),
            None => text(404, "not found"),
        },
        Resolved::Manifest => match serde_json::to_vec(&out.manifest()) {
            Ok(b) => {
                let n = b.len() as u64;
                reply(200, "application/json", Box::new(std::io::Cursor::new(b)), n, vec![])
            }
            Err(_) => text(500, "cannot list the output folder"),
        },
        Resolved::File(p) => {
            let range = req.headers().iter().find(|h| h.field.equiv("Range")).map(|h| h.value.as_str().to_string());
            serve_file(&p, range.as_deref())
        }
        Resolved::Refused(code, why) => text(code, why),
    }
}

/// The page's server for one output folder.
pub struct Server {
    http: Arc<tiny_http::Server>,
    out: OutDir,
    url: String,
    policy: HostPolicy,
}

impl Server {
    /// Check `out` and listen on 127.0.0.1:`port` (0: any free port).
    pub fn bind(out: OutDir, port: u16) -> Result<Self> {
        Self::bind_on(out, "127.0.0.1", port, Vec::new())
    }

    /// [`Server::bind`] on the address `host` (an IP), answering also to the `Host` names in `allow_hosts`.
    pub fn bind_on(out: OutDir, host: &str, port: u16, allow_hosts: Vec<String>) -> Result<Self> {
        let addr = if host.contains(':') { format!("[{host}]:{port}") } else { format!("{host}:{port}") };
        let http = tiny_http::Server::http(&addr).map_err(|e| ViewerError::Bind { addr: addr.clone(), msg: e.to_string() })?;
        let port = http.server_addr().to_ip().map(|a| a.port()).unwrap_or(port);
        let url = if host.contains(':') { format!("http://[{host}]:{port}/") } else { format!("http://{host}:{port}/") };
        Ok(Self { http: Arc::new(http), out, url, policy: HostPolicy { port, allowed: allow_hosts } })
    }

    /// The page's address.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Serve until the process ends, `threads` requests at a time (a large `gaussians.ply` download must not
    /// hold up the frames and the video).
    pub fn serve(self, threads: usize) {
        let workers: Vec<_> = (0..threads.max(1))
            .map(|_| {
                let (http, out, policy) = (self.http.clone(), self.out.clone(), self.policy.clone());
                std::thread::spawn(move || {
                    for req in http.incoming_requests() {
                        let resp = respond(&out, &policy, &req);
                        // A client that went away mid-response is not our error.
                        let _ = req.respond(resp);
                    }
                })
            })
            .collect();
        for w in workers {
            let _ = w.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_answered() {
        let p = HostPolicy { port: 8080, allowed: vec!["gpu-box.tail1234.ts.net".into()] };
        for ok in
            ["127.0.0.1:8080", "127.0.0.1", "localhost:8080", "LOCALHOST", "app.localhost:8080", "[::1]:8080", "10.1.2.3:8080", "gpu-box.tail1234.ts.net:8080"]
        {
            assert!(p.accepts(ok), "{ok}");
        }
        for bad in ["evil.example", "evil.example:8080", "127.0.0.1:9999", "localhost.evil.example:8080", "[::1", "[nothost]:8080", "", "127.0.0.1:80:80"] {
            assert!(!p.accepts(bad), "{bad}");
        }
    }

    #[test]
    fn ranges() {
        assert_eq!(parse_range("bytes=0-9", 100), Some((0, 9)));
        assert_eq!(parse_range("bytes=90-", 100), Some((90, 99)));
        assert_eq!(parse_range("bytes=-10", 100), Some((90, 99)));
        assert_eq!(parse_range("bytes=50-500", 100), Some((50, 99)));
        assert_eq!(parse_range("bytes=100-", 100), None);
        assert_eq!(parse_range("bytes=5-1", 100), None);
        assert_eq!(parse_range("bytes=0-1,3-4", 100), None);
        assert_eq!(parse_range("items=0-1", 100), None);
    }
}
