//! The server core that `view` and `app` share: std `TcpListener` + `httparse`, a thread per connection, each
//! held to [`Limits`]; the `Host`/`Origin`/`Sec-Fetch-Site` policy and the page's token checked before any route
//! sees a request; request bodies read only through [`Body`] (sized, rate-limited, fewer uploads at once than
//! connections, [`BodyLimits`]); answers with a `Content-Length`, or an event stream ([`EventSource`]).
//!
//! Routes are a [`Handler`]: a closure `Fn(&Request, &mut Body) -> Response`.
//!
//! ```no_run
//! use mvsplat360_viewer::http::{Body, EventSource, HttpServer, PageToken, Request, Response, APP_PORT};
//! let token = PageToken::random();
//! let events = EventSource::new(1000);
//! let server = HttpServer::bind("127.0.0.1", APP_PORT).unwrap().with_token(token.clone());
//! println!("{}", server.url());
//! server.serve(move |req: &Request, body: &mut Body<'_>| -> Response {
//!     let _ = (req, body, &events, &token);
//!     Response::text(404, "not found")
//! });
//! ```
//!
//! **Uploads** are one raw `PUT /…/NAME` per file, the body being the file's bytes (`fetch(url, {method: "PUT",
//! body: file, headers: {"X-Mvsplat360-Token": token}})`); the route streams it with [`Body::save_into`] into its
//! staging folder. Refused: a name that is not a plain file name (400), a declared length over the limit (413,
//! nothing written), a body slower than the minimum rate (408, the partial file removed), more uploads at once
//! than allowed (503, `Retry-After`).

mod body;
mod policy;
mod request;
mod response;
mod sse;

use std::io::{Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

pub use body::{safe_file_name, Body, BodyError, BodyLimits};
pub use policy::{HostPolicy, PageToken, TOKEN_HEADER};
pub use request::Request;
pub use response::{content_type, Payload, Response, StreamFn};
pub use sse::{Event, EventSource, Next, Subscription};

use crate::error::{Result, ViewerError};
use request::{read_head, Head};
use response::reason;

/// `mvsplat360 view`'s default port.
pub const VIEW_PORT: u16 = 8080;
/// `mvsplat360 app`'s default port: not `view`'s [`VIEW_PORT`], so both run at once.
pub const APP_PORT: u16 = 8090;

/// How long the server waits on a client before dropping it, and how many it holds at once.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// From a request's first byte to the end of its head (slow senders).
    pub head: Duration,
    /// Between requests on a kept-alive connection, and before a new connection's first byte (idle clients).
    pub idle: Duration,
    /// Without any byte of a response taken by the client (stalled downloads, vanished event-stream clients).
    pub write: Duration,
    /// Connections served at once (one thread each); more are answered 503 and closed.
    pub connections: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self { head: Duration::from_secs(10), idle: Duration::from_secs(15), write: Duration::from_secs(30), connections: 256 }
    }
}

/// The event streams' heartbeat interval unless configured ([`HttpServer::with_heartbeat`]): below the idle
/// limit, and a third of the write limit.
pub const HEARTBEAT: Duration = Duration::from_secs(10);

/// A body the server reads and drops to keep the connection when the route left it unread.
const MAX_DISCARD: u64 = 1 << 20;
/// Over-cap connections answered at once (each by a short-lived thread that reads the request head first);
/// beyond these a connection is closed without an answer.
const MAX_REFUSERS: usize = 16;

/// The routes: called once per request that passed the policy (and token) checks, on the connection's thread.
pub trait Handler: Send + Sync + 'static {
    fn handle(&self, req: &Request, body: &mut Body<'_>) -> Response;
}

impl<F> Handler for F
where
    F: Fn(&Request, &mut Body<'_>) -> Response + Send + Sync + 'static,
{
    fn handle(&self, req: &Request, body: &mut Body<'_>) -> Response {
        self(req, body)
    }
}

/// Live counts of a running server (for tests and a status line).
#[derive(Clone, Default)]
pub struct Stats {
    live: Arc<AtomicUsize>,
    uploads: Arc<AtomicUsize>,
}

impl Stats {
    /// Connections being served now (each holds a thread and a slot).
    pub fn connections(&self) -> usize {
        self.live.load(Ordering::Acquire)
    }

    /// Uploads under way now.
    pub fn uploads(&self) -> usize {
        self.uploads.load(Ordering::Acquire)
    }
}

/// Listen on `host`:`port` (an IP; `port` 0: any free port). A port in use is [`ViewerError::PortInUse`], whose
/// message is one line naming the port and `--port`.
pub fn bind_listener(host: &str, port: u16) -> Result<TcpListener> {
    let addr = if host.contains(':') { format!("[{host}]:{port}") } else { format!("{host}:{port}") };
    TcpListener::bind(&addr).map_err(|e| match e.kind() {
        std::io::ErrorKind::AddrInUse => ViewerError::PortInUse { host: host.to_string(), port },
        _ => ViewerError::Bind { addr: addr.clone(), msg: e.to_string() },
    })
}

/// The server core: a listener, its policy and limits; [`HttpServer::serve`] runs a [`Handler`] on it.
pub struct HttpServer {
    listener: TcpListener,
    url: String,
    policy: HostPolicy,
    token: Option<PageToken>,
    limits: Limits,
    body: BodyLimits,
    heartbeat: Duration,
    stats: Stats,
}

struct Shared<H> {
    handler: H,
    policy: HostPolicy,
    token: Option<PageToken>,
    limits: Limits,
    body: BodyLimits,
    heartbeat: Duration,
    uploads: Arc<AtomicUsize>,
}

impl HttpServer {
    /// Listen on `host`:`port` ([`bind_listener`]), answering `Host` names that are IP literals and localhost.
    pub fn bind(host: &str, port: u16) -> Result<Self> {
        let listener = bind_listener(host, port)?;
        let port = listener.local_addr().map(|a| a.port()).unwrap_or(port);
        let url = if host.contains(':') { format!("http://[{host}]:{port}/") } else { format!("http://{host}:{port}/") };
        Ok(Self {
            listener,
            url,
            policy: HostPolicy { port, allowed: Vec::new() },
            token: None,
            limits: Limits::default(),
            body: BodyLimits::default(),
            heartbeat: HEARTBEAT,
            stats: Stats::default(),
        })
    }

    /// Also answer these `Host` names (a tunnel's or proxy's, `--allow-host`).
    pub fn allow_hosts(mut self, names: Vec<String>) -> Self {
        self.policy.allowed = names;
        self
    }

    /// Require `token` in [`TOKEN_HEADER`] on every request but GET, HEAD and OPTIONS (403 before any route sees
    /// it). Without a token such requests reach the routes (which may answer 405).
    pub fn with_token(mut self, token: PageToken) -> Self {
        self.token = Some(token);
        self
    }

    /// Other timeouts and connection cap than [`Limits::default`].
    pub fn with_limits(mut self, limits: Limits) -> Self {
        self.limits = limits;
        self
    }

    /// Other body limits than [`BodyLimits::default`].
    pub fn with_body_limits(mut self, body: BodyLimits) -> Self {
        self.body = body;
        self
    }

    /// Another event-stream heartbeat interval than [`HEARTBEAT`].
    pub fn with_heartbeat(mut self, every: Duration) -> Self {
        self.heartbeat = every;
        self
    }

    /// The page's address (`http://HOST:PORT/`).
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The port listened on (the one chosen when 0 was asked).
    pub fn port(&self) -> u16 {
        self.policy.port
    }

    /// Live counts, valid while the server runs.
    pub fn stats(&self) -> Stats {
        self.stats.clone()
    }

    /// Serve until the process ends: a thread per connection, each dropped when its client is idle, slow or stops
    /// reading ([`Limits`]); over the cap a connection gets a whole 503 (its request head read first, then the
    /// write side shut and the rest drained briefly, so no reset destroys the answer).
    pub fn serve(self, handler: impl Handler) {
        let Self { listener, policy, token, limits, body, heartbeat, stats, .. } = self;
        // Uploads never take every connection: one is always left for the page and its event stream.
        let body = BodyLimits { uploads: body.uploads.min(limits.connections.saturating_sub(1)).max(1), ..body };
        let shared = Arc::new(Shared { handler, policy, token, limits, body, heartbeat, uploads: stats.uploads.clone() });
        let refusers = Arc::new(AtomicUsize::new(0));
        for conn in listener.incoming() {
            let s = match conn {
                Ok(s) => s,
                // Out of file descriptors, or a connection reset before it was taken: wait a little, go on.
                Err(_) => {
                    std::thread::sleep(Duration::from_millis(20));
                    continue;
                }
            };
            if stats.live.fetch_add(1, Ordering::AcqRel) >= limits.connections {
                stats.live.fetch_sub(1, Ordering::AcqRel);
                if refusers.fetch_add(1, Ordering::AcqRel) >= MAX_REFUSERS {
                    refusers.fetch_sub(1, Ordering::AcqRel);
                    continue;
                }
                let slot = Slot(refusers.clone());
                let head = limits.head.min(Duration::from_secs(1));
                let _ = std::thread::Builder::new().name("http-503".into()).spawn(move || {
                    let _slot = slot;
                    refuse_over_cap(s, head);
                });
                continue;
            }
            let slot = Slot(stats.live.clone());
            let shared = shared.clone();
            let spawned = std::thread::Builder::new().name("http-conn".into()).spawn(move || {
                let _slot = slot;
                connection(s, &shared);
            });
            // A thread that cannot start drops its connection (and its slot) with it.
            drop(spawned);
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

/// Over the cap: read the request head (at most `wait`, 16 KiB), answer 503, shut the write side and drain the
/// rest briefly.
fn refuse_over_cap(mut s: TcpStream, wait: Duration) {
    let deadline = Instant::now() + wait;
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    while buf.len() < request::MAX_HEAD && !buf.windows(4).any(|w| w == b"\r\n\r\n") {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() || s.set_read_timeout(Some(left)).is_err() {
            break;
        }
        match s.read(&mut chunk) {
            Ok(0) => break,
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted) => {}
            Err(_) => return,
        }
    }
    let _ = s.set_write_timeout(Some(Duration::from_secs(2)));
    let r = Response::text(503, "too many connections; retry in a moment").header("Retry-After", "1");
    if send(&mut s, r, false, false, HEARTBEAT) {
        linger_close(s);
    }
}

/// Send `r`; false when the connection is no longer usable. Bodies of unknown length (streams) are followed by
/// closing the connection.
fn send(s: &mut TcpStream, r: Response, head_only: bool, keep: bool, heartbeat: Duration) -> bool {
    let len = r.body.len();
    let keep = keep && len.is_some();
    let mut head = format!("HTTP/1.1 {} {}\r\n", r.status, reason(r.status));
    for (k, v) in &r.headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    // The length is known for all but streams, so the page can show how much of the Gaussians has arrived.
    if let Some(n) = len {
        head.push_str(&format!("Content-Length: {n}\r\n"));
    }
    head.push_str(if keep { "Connection: keep-alive\r\n\r\n" } else { "Connection: close\r\n\r\n" });
    if s.write_all(head.as_bytes()).is_err() {
        return false;
    }
    if head_only {
        return true;
    }
    // The write timeout bounds each write without progress, so a client that stops reading frees its thread.
    match r.body {
        Payload::Bytes(b) => s.write_all(&b).is_ok(),
        Payload::Reader { reader, len } => matches!(std::io::copy(&mut reader.take(len), s), Ok(n) if n == len),
        Payload::Events(sub) => {
            sse::pump(s, sub, heartbeat);
            false
        }
        Payload::Stream(f) => {
            let _ = f(s).and_then(|_| s.flush());
            true
        }
    }
}

/// Close after a refusal, letting the client read it: a close with unread input would reset the connection and
/// could destroy the answer before the client saw it. Drains at most 1 s and 4 MiB.
fn linger_close(mut s: TcpStream) {
    let _ = s.shutdown(Shutdown::Write);
    let _ = s.set_read_timeout(Some(Duration::from_millis(500)));
    let mut sink = [0u8; 16 << 10];
    let t0 = Instant::now();
    let mut drained = 0usize;
    while t0.elapsed() < Duration::from_secs(1) && drained < 4 << 20 {
        match s.read(&mut sink) {
            Ok(n) if n > 0 => drained += n,
            _ => break,
        }
    }
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

/// Bound how long sent data may stay unacknowledged before the kernel gives the connection up (Linux's
/// `TCP_USER_TIMEOUT`): a client whose machine vanished (no FIN, no reset: a closed laptop, a dropped network)
/// then fails the next write of an event stream's heartbeat within the write limit, although its socket buffer
/// never fills. Elsewhere such a client is noticed when the buffer fills or the system's retransmissions end.
fn bound_unacked(s: &TcpStream, limit: Duration) {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        let ms = limit.as_millis().clamp(1, u32::MAX as u128) as libc::c_uint;
        // SAFETY: a valid socket descriptor and a pointer to a c_uint of the size given.
        unsafe {
            libc::setsockopt(
                s.as_raw_fd(),
                libc::IPPROTO_TCP,
                libc::TCP_USER_TIMEOUT,
                (&ms as *const libc::c_uint).cast(),
                std::mem::size_of::<libc::c_uint>() as libc::socklen_t,
            );
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (s, limit);
}

fn connection<H: Handler>(mut s: TcpStream, sh: &Shared<H>) {
    let _ = s.set_nodelay(true);
    bound_unacked(&s, sh.limits.write);
    if s.set_write_timeout(Some(sh.limits.write)).is_err() {
        return;
    }
    let mut buf = Vec::new();
    loop {
        let (req, n) = match read_head(&mut s, &mut buf, &sh.limits) {
            Head::Request(r, n) => (r, n),
            Head::Gone => return,
            Head::Refuse(code, why) => {
                if send(&mut s, Response::text(code, why), false, false, sh.heartbeat) {
                    linger_close(s);
                }
                return;
            }
        };
        buf.drain(..n);
        // None: a length the server cannot frame (chunked, malformed): never read, the connection closed after.
        // Two lengths (or one with a length besides a transfer coding) could frame the body two ways: refused.
        let lengths: Vec<&str> = req.headers_named("Content-Length").collect();
        if lengths.len() > 1 || (lengths.len() == 1 && req.header("Transfer-Encoding").is_some()) {
            if send(&mut s, Response::text(400, "ambiguous body length"), false, false, sh.heartbeat) {
                linger_close(s);
            }
            return;
        }
        let len = match (lengths.first(), req.header("Transfer-Encoding")) {
            (_, Some(_)) => None,
            (Some(v), None) => Some(v.trim()).filter(|v| !v.is_empty() && v.bytes().all(|b| b.is_ascii_digit())).and_then(|v| v.parse::<u64>().ok()),
            (None, None) => Some(0),
        };
        let expect_continue = req.header("Expect").is_some_and(|v| v.trim().eq_ignore_ascii_case("100-continue"));
        let (r, remaining) = {
            let mut body = Body { stream: &mut s, buf: &mut buf, len, taken: 0, broken: false, expect_continue, limits: sh.body, uploads: sh.uploads.clone() };
            let checked = sh.policy.check(&req).and_then(|_| sh.token.as_ref().map_or(Ok(()), |t| t.check(&req)));
            let r = match checked {
                Err(refusal) => refusal.response(),
                Ok(()) => sh.handler.handle(&req, &mut body),
            };
            // A client that waits for `100 Continue` may never send a body the route left unread: close.
            let waiting = body.expect_continue && body.remaining() != Some(0);
            let remaining = if body.broken || waiting { None } else { body.remaining() };
            (r, remaining)
        };
        let drainable = remaining.filter(|&n| n <= MAX_DISCARD);
        let keep = req.keep_alive() && drainable.is_some() && !r.close && r.body.len().is_some();
        let streamed = r.body.len().is_none();
        if !send(&mut s, r, req.method == "HEAD", keep, sh.heartbeat) {
            return;
        }
        if !keep {
            if !streamed || remaining != Some(0) {
                linger_close(s);
            }
            return;
        }
        if !discard_body(&mut s, &mut buf, drainable.unwrap_or(0), &sh.limits) {
            return;
        }
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    #[test]
    fn unacknowledged_data_is_bounded_by_the_write_limit() {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let _c = TcpStream::connect(l.local_addr().unwrap()).unwrap();
        let (s, _) = l.accept().unwrap();
        bound_unacked(&s, Duration::from_millis(1500));
        let mut ms: libc::c_uint = 0;
        let mut n = std::mem::size_of::<libc::c_uint>() as libc::socklen_t;
        use std::os::fd::AsRawFd;
        // SAFETY: a valid socket and a buffer of the size given.
        let rc = unsafe { libc::getsockopt(s.as_raw_fd(), libc::IPPROTO_TCP, libc::TCP_USER_TIMEOUT, (&mut ms as *mut libc::c_uint).cast(), &mut n) };
        assert_eq!((rc, ms), (0, 1500));
    }
}
