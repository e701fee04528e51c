//! A request's head: reading it within the limits, and what a route asks of it.

use std::io::Read;
use std::net::TcpStream;
use std::time::Instant;

use super::Limits;

/// A request's head, as parsed. Its body, if any, is the [`Body`](super::Body) handed to the route beside it.
#[derive(Debug, Clone)]
pub struct Request {
    /// As sent (`GET`, `POST`, …; case-sensitive, as HTTP methods are).
    pub method: String,
    /// The request target as sent, still percent-encoded (`/path?query`).
    pub target: String,
    /// HTTP/1.x minor version.
    pub(crate) minor: u8,
    /// Name and value of every header, in order (a value that is not UTF-8 is read lossily).
    pub headers: Vec<(String, String)>,
}

impl Request {
    /// A request built by hand (for a route's unit tests).
    pub fn new(method: &str, target: &str, headers: &[(&str, &str)]) -> Self {
        Self { method: method.into(), target: target.into(), minor: 1, headers: headers.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect() }
    }

    /// The target's path, still percent-encoded (without `?query` and `#fragment`).
    pub fn path(&self) -> &str {
        self.target.split(['?', '#']).next().unwrap_or("")
    }

    /// The target's query (after `?`, before any `#`), still percent-encoded.
    pub fn query(&self) -> Option<&str> {
        let (_, q) = self.target.split_once('?')?;
        Some(q.split('#').next().unwrap_or(""))
    }

    /// The first query parameter `name`, percent-decoded (`+` read as a space); None when absent or not UTF-8.
    pub fn query_param(&self, name: &str) -> Option<String> {
        self.query()?.split('&').find_map(|kv| {
            let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
            let dec = |s: &str| percent_encoding::percent_decode_str(&s.replace('+', " ")).decode_utf8().ok().map(|c| c.into_owned());
            (dec(k)? == name).then(|| dec(v)).flatten()
        })
    }

    /// The first header `name` (case-insensitive).
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k.eq_ignore_ascii_case(name)).map(|(_, v)| v.as_str())
    }

    /// Every value of the header `name`, in order.
    pub fn headers_named<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a str> + 'a {
        self.headers.iter().filter(move |(k, _)| k.eq_ignore_ascii_case(name)).map(|(_, v)| v.as_str())
    }

    /// `Last-Event-ID` as a number (an event stream resumed by the browser after a reload or a dropped
    /// connection); also read from the query parameter `lastEventId`, for a page that reopens a stream itself.
    pub fn last_event_id(&self) -> Option<u64> {
        self.header("Last-Event-ID").and_then(|v| v.trim().parse().ok()).or_else(|| self.query_param("lastEventId")?.trim().parse().ok())
    }

    /// Whether the client keeps the connection for another request.
    pub(crate) fn keep_alive(&self) -> bool {
        let conn = self.header("Connection").map(|v| v.to_ascii_lowercase()).unwrap_or_default();
        if self.minor >= 1 {
            !conn.contains("close")
        } else {
            conn.contains("keep-alive")
        }
    }
}

pub(crate) const MAX_HEAD: usize = 16 << 10;

pub(crate) enum Head {
    Request(Request, usize),
    /// The client closed the connection or stayed silent: close without a word.
    Gone,
    /// Answer with this status, then close.
    Refuse(u16, &'static str),
}

/// Read one request head into `buf` (which may already hold pipelined bytes): waiting at most `idle` for its
/// first byte and `head` from there to its end.
pub(crate) fn read_head(s: &mut TcpStream, buf: &mut Vec<u8>, lim: &Limits) -> Head {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn path_and_query() {
        let r = Request::new("GET", "/jobs/3?x=a%20b&last+one=c+d&lastEventId=7#frag", &[("last-event-id", " 9 ")]);
        assert_eq!(r.path(), "/jobs/3");
        assert_eq!(r.query(), Some("x=a%20b&last+one=c+d&lastEventId=7"));
        assert_eq!(r.query_param("x").as_deref(), Some("a b"));
        assert_eq!(r.query_param("last one").as_deref(), Some("c d"));
        assert_eq!(r.query_param("y"), None);
        assert_eq!(r.last_event_id(), Some(9));
        assert_eq!(Request::new("GET", "/?lastEventId=7", &[]).last_event_id(), Some(7));
        assert_eq!(Request::new("GET", "/", &[]).query(), None);
    }
}
