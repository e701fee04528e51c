//! The local server: GET/HEAD only, on 127.0.0.1 unless told otherwise, the page's assets from the binary and the
//! render's files from an allow-list (the manifest) — a request can reach nothing else, whatever its encoding. A
//! thread per connection, each with timeouts, so that no client can hold the others up.

use std::io::{Read, Seek, SeekFrom, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

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

/// A response: status, extra headers, and a body of known length.
struct Reply {
    status: u16,
    headers: Vec<(&'static str, String)>,
    body: Box<dyn Read + Send>,
    len: u64,
}

fn reply(status: u16, ctype: &str, body: Box<dyn Read + Send>, len: u64, mut extra: Vec<(&'static str, String)>) -> Reply {
    let mut headers = vec![
        ("Content-Type", ctype.to_string()),
        ("Cache-Control", "no-cache".into()),
        ("X-Content-Type-Options", "nosniff".into()),
        ("Referrer-Policy", "no-referrer".into()),
    ];
    headers.append(&mut extra);
    Reply { status, headers, body, len }
}

fn text(status: u16, msg: &str) -> Reply {
    let b = format!("{status} {msg}\n").into_bytes();
    let n = b.len() as u64;
    reply(status, "text/plain; charset=utf-8", Box::new(std::io::Cursor::new(b)), n, vec![])
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        206 => "Partial Content",
        400 => "Bad Request",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        413 => "Content Too Large",
        416 => "Range Not Satisfiable",
        431 => "Request Header Fields Too Large",
        503 => "Service Unavailable",
        _ => "Internal Server Error",
    }
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
    let accept = ("Accept-Ranges", "bytes".to_string());
    if let Some(r) = range {
        let Some((s, e)) = parse_range(r, len) else {
            return reply(416, "text/plain", Box::new(std::io::empty()), 0, vec![("Content-Range", format!("bytes */{len}"))]);
        };
        if f.seek(SeekFrom::Start(s)).is_err() {
            return text(500, "cannot read file");
        }
        let n = e - s + 1;
        return reply(206, ctype, Box::new(f.take(n)), n, vec![accept, ("Content-Range", format!("bytes {s}-{e}/{len}"))]);
    }
    reply(200, ctype, Box::new(f), len, vec![accept])
}

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
enum Refusal {
    /// 400: no `Host`, several, or one that is not exactly an authority.
    BadHost,
    /// 403: a well-formed `Host` this server does not answer to.
    ForeignHost,
    /// 403: `Sec-Fetch-Site: cross-site`.
    CrossSite,
    /// 403: an `Origin` other than the accepted `Host`'s.
    ForeignOrigin,
}

impl Refusal {
    fn reply(self) -> Reply {
        match self {
            Refusal::BadHost => text(400, "missing, repeated or malformed Host header"),
            Refusal::ForeignHost => text(403, "this Host is not served (start `mvsplat360 view` with --allow-host NAME for a tunnel or proxy name)"),
            Refusal::CrossSite => text(403, "cross-site request refused"),
            Refusal::ForeignOrigin => text(403, "cross-origin request refused"),
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
    fn check(&self, req: &Request) -> std::result::Result<(), Refusal> {
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

/// A request's head, as parsed.
struct Request {
    method: String,
    target: String,
    /// HTTP/1.x minor version.
    minor: u8,
    headers: Vec<(String, String)>,
}

impl Request {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k.eq_ignore_ascii_case(name)).map(|(_, v)| v.as_str())
    }

    /// Every value of the header `name`, in order.
    fn headers_named<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a str> + 'a {
        self.headers.iter().filter(move |(k, _)| k.eq_ignore_ascii_case(name)).map(|(_, v)| v.as_str())
    }

    /// Whether the client keeps the connection for another request.
    fn keep_alive(&self) -> bool {
        let conn = self.header("Connection").map(|v| v.to_ascii_lowercase()).unwrap_or_default();
        if self.minor >= 1 {
            !conn.contains("close")
        } else {
            conn.contains("keep-alive")
        }
    }
}

fn respond(out: &OutDir, policy: &HostPolicy, req: &Request) -> Reply {
    if let Err(refusal) = policy.check(req) {
        return refusal.reply();
    }
    if req.method != "GET" && req.method != "HEAD" {
        return text(405, "method not allowed (read-only server)");
    }
    match resolve(out, &req.target) {
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
        Resolved::File(p) => serve_file(&p, req.header("Range")),
        Resolved::Refused(code, why) => text(code, why),
    }
}

/// How long the server waits on a client before dropping it, and how many it holds at once.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// From a request's first byte to the end of its head (slow senders).
    pub head: Duration,
    /// Between requests on a kept-alive connection, and before a new connection's first byte (idle clients).
    pub idle: Duration,
    /// Without any byte of a response taken by the client (stalled downloads).
    pub write: Duration,
    /// Connections served at once (one thread each); more are answered 503 and closed.
    pub connections: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self { head: Duration::from_secs(10), idle: Duration::from_secs(15), write: Duration::from_secs(30), connections: 256 }
    }
}

const MAX_HEAD: usize = 16 << 10;
/// A request body the server reads and drops to keep the connection (it answers no request with a body).
const MAX_DISCARD: u64 = 1 << 20;

enum Head {
    Request(Request, usize),
    /// The client closed the connection or stayed silent: close without a word.
    Gone,
    /// Answer with this status, then close.
    Refuse(u16, &'static str),
}

/// Read one request head into `buf` (which may already hold pipelined bytes): waiting at most `idle` for its
/// first byte and `head` from there to its end.
fn read_head(s: &mut TcpStream, buf: &mut Vec<u8>, lim: &Limits) -> Head {
    let mut deadline = Instant::now() + if buf.is_empty() { lim.idle } else { lim.head };
    let mut started = !buf.is_empty();
    let mut chunk = [0u8; 4096];
    loop {
        if !buf.is_empty() {
            let mut hs = [httparse::EMPTY_HEADER; 64];
            let mut r = httparse::Request::new(&mut hs);
            match r.parse(buf) {
                Ok(httparse::Status::Complete(n)) => {
                    let req = Request {
                        method: r.method.unwrap_or("").to_string(),
                        target: r.path.unwrap_or("").to_string(),
                        minor: r.version.unwrap_or(1),
                        headers: r.headers.iter().map(|h| (h.name.to_string(), String::from_utf8_lossy(h.value).into_owned())).collect(),
                    };
                    return Head::Request(req, n);
                }
                Ok(httparse::Status::Partial) if buf.len() < MAX_HEAD => {}
                Ok(httparse::Status::Partial) | Err(httparse::Error::TooManyHeaders) => return Head::Refuse(431, "request head too large"),
                Err(_) => return Head::Refuse(400, "malformed request"),
            }
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return if started { Head::Refuse(408, "request head not received in time") } else { Head::Gone };
        }
        if s.set_read_timeout(Some(left)).is_err() {
            return Head::Gone;
        }
        match s.read(&mut chunk) {
            Ok(0) => return Head::Gone,
            Ok(n) => {
                if !started {
                    started = true;
                    deadline = Instant::now() + lim.head;
                }
                buf.extend_from_slice(&chunk[..n]);
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(_) => return Head::Gone,
        }
    }
}

/// Send `r`; false when the connection is no longer usable.
fn send(s: &mut TcpStream, mut r: Reply, head_only: bool, keep: bool) -> bool {
    let mut head = format!("HTTP/1.1 {} {}\r\n", r.status, reason(r.status));
    for (k, v) in &r.headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    // The length is always known, so the page can show how much of the Gaussians has arrived.
    head.push_str(&format!("Content-Length: {}\r\n", r.len));
    head.push_str(if keep { "Connection: keep-alive\r\n\r\n" } else { "Connection: close\r\n\r\n" });
    if s.write_all(head.as_bytes()).is_err() {
        return false;
    }
    if head_only {
        return true;
    }
    // The write timeout bounds each write without progress, so a client that stops reading frees its thread.
    let mut body = (&mut r.body).take(r.len);
    matches!(std::io::copy(&mut body, s), Ok(n) if n == r.len)
}

/// Close after a refusal, letting the client read it: a close with unread input would reset the connection and
/// could destroy the answer before the client saw it.
fn linger_close(mut s: TcpStream) {
    let _ = s.shutdown(Shutdown::Write);
    let _ = s.set_read_timeout(Some(Duration::from_millis(500)));
    let mut sink = [0u8; 4096];
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(1) && matches!(s.read(&mut sink), Ok(n) if n > 0) {}
}

/// Drop a request body of `n` bytes (some of them already in `buf`); false when it cannot be done in time.
fn discard_body(s: &mut TcpStream, buf: &mut Vec<u8>, n: u64, lim: &Limits) -> bool {
    let have = (buf.len() as u64).min(n);
    buf.drain(..have as usize);
    let mut left = n - have;
    let deadline = Instant::now() + lim.head;
    let mut sink = [0u8; 4096];
    while left > 0 {
        let t = deadline.saturating_duration_since(Instant::now());
        if t.is_zero() || s.set_read_timeout(Some(t)).is_err() {
            return false;
        }
        match s.read(&mut sink[..left.min(4096) as usize]) {
            Ok(0) | Err(_) => return false,
            Ok(k) => left -= k as u64,
        }
    }
    true
}

fn connection(mut s: TcpStream, out: &OutDir, policy: &HostPolicy, lim: &Limits) {
    let _ = s.set_nodelay(true);
    if s.set_write_timeout(Some(lim.write)).is_err() {
        return;
    }
    let mut buf = Vec::new();
    loop {
        let (req, n) = match read_head(&mut s, &mut buf, lim) {
            Head::Request(r, n) => (r, n),
            Head::Gone => return,
            Head::Refuse(code, why) => {
                if send(&mut s, text(code, why), false, false) {
                    linger_close(s);
                }
                return;
            }
        };
        buf.drain(..n);
        let body = match (req.header("Content-Length"), req.header("Transfer-Encoding")) {
            (_, Some(_)) => None,
            (Some(v), None) => v.trim().parse::<u64>().ok().filter(|&n| n <= MAX_DISCARD),
            (None, None) => Some(0),
        };
        let keep = req.keep_alive() && body.is_some();
        let r = respond(out, policy, &req);
        if !send(&mut s, r, req.method == "HEAD", keep) {
            return;
        }
        if !keep {
            linger_close(s);
            return;
        }
        if !discard_body(&mut s, &mut buf, body.unwrap_or(0), lim) {
            return;
        }
    }
}

/// Counts a connection while its thread runs.
struct Slot(Arc<AtomicUsize>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// The page's server for one output folder.
pub struct Server {
    listener: TcpListener,
    out: OutDir,
    url: String,
    policy: HostPolicy,
    limits: Limits,
}

impl Server {
    /// Check `out` and listen on 127.0.0.1:`port` (0: any free port).
    pub fn bind(out: OutDir, port: u16) -> Result<Self> {
        Self::bind_on(out, "127.0.0.1", port, Vec::new())
    }

    /// [`Server::bind`] on the address `host` (an IP), answering also to the `Host` names in `allow_hosts`.
    pub fn bind_on(out: OutDir, host: &str, port: u16, allow_hosts: Vec<String>) -> Result<Self> {
        let addr = if host.contains(':') { format!("[{host}]:{port}") } else { format!("{host}:{port}") };
        let listener = TcpListener::bind(&addr).map_err(|e| ViewerError::Bind { addr: addr.clone(), msg: e.to_string() })?;
        let port = listener.local_addr().map(|a| a.port()).unwrap_or(port);
        let url = if host.contains(':') { format!("http://[{host}]:{port}/") } else { format!("http://{host}:{port}/") };
        Ok(Self { listener, out, url, policy: HostPolicy { port, allowed: allow_hosts }, limits: Limits::default() })
    }

    /// Other timeouts and connection limit than [`Limits::default`].
    pub fn with_limits(mut self, limits: Limits) -> Self {
        self.limits = limits;
        self
    }

    /// The page's address.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Serve until the process ends: a thread per connection (a large `gaussians.ply` download must not hold up
    /// the frames and the video), each dropped when its client is idle, slow or stops reading ([`Limits`]).
    pub fn serve(self) {
        let active = Arc::new(AtomicUsize::new(0));
        let shared = Arc::new((self.out, self.policy, self.limits));
        for conn in self.listener.incoming() {
            let mut s = match conn {
                Ok(s) => s,
                // Out of file descriptors, or a connection reset before it was taken: wait a little, go on.
                Err(_) => {
                    std::thread::sleep(Duration::from_millis(20));
                    continue;
                }
            };
            if active.fetch_add(1, Ordering::AcqRel) >= shared.2.connections {
                active.fetch_sub(1, Ordering::AcqRel);
                let _ = s.set_write_timeout(Some(Duration::from_millis(200)));
                let _ = send(&mut s, text(503, "too many connections"), false, false);
                continue;
            }
            let slot = Slot(active.clone());
            let shared = shared.clone();
            let spawned = std::thread::Builder::new().name("view-conn".into()).spawn(move || {
                let _slot = slot;
                let (out, policy, limits) = &*shared;
                connection(s, out, policy, limits);
            });
            // A thread that cannot start drops its connection (and its slot) with it.
            drop(spawned);
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
