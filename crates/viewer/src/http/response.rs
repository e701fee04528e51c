//! What a route answers: a status, headers and a body of known length (bytes, a file or any reader), an event
//! stream, or a stream written by the route.

use std::borrow::Cow;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::Path;

use super::sse::Subscription;

/// A route's answer.
pub struct Response {
    pub status: u16,
    /// Sent in order; the server adds `Content-Length` (sized bodies) and `Connection`.
    pub headers: Vec<(String, String)>,
    pub body: Payload,
    /// Close the connection after this answer.
    pub close: bool,
}

/// A response's body.
pub enum Payload {
    /// Bytes in memory.
    Bytes(Cow<'static, [u8]>),
    /// `len` bytes from a reader (a file, or a part of one); fewer is a broken connection.
    Reader { reader: Box<dyn Read + Send>, len: u64 },
    /// A `text/event-stream` fed by an [`EventSource`](super::EventSource): written as events arrive, with a
    /// heartbeat comment whenever none came for the server's heartbeat interval, until the source closes or the
    /// client goes; then the connection is closed.
    Events(Subscription),
    /// Written by the closure as it goes (no `Content-Length`; the connection is closed after it). Each write is
    /// bounded by the server's write limit; an error ends the response.
    Stream(StreamFn),
}

/// A streamed body's writer.
pub type StreamFn = Box<dyn FnOnce(&mut dyn Write) -> std::io::Result<()> + Send>;

impl Payload {
    /// The body's length when it is known before it is sent.
    pub fn len(&self) -> Option<u64> {
        match self {
            Payload::Bytes(b) => Some(b.len() as u64),
            Payload::Reader { len, .. } => Some(*len),
            Payload::Events(_) | Payload::Stream(_) => None,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == Some(0)
    }
}

impl Response {
    /// `status` with `Content-Type: ctype`, the headers every answer carries (`Cache-Control: no-cache`,
    /// `X-Content-Type-Options: nosniff`, `Referrer-Policy: no-referrer`) and `body`.
    pub fn new(status: u16, ctype: &str, body: Payload) -> Self {
        let headers = vec![
            ("Content-Type".to_string(), ctype.to_string()),
            ("Cache-Control".into(), "no-cache".into()),
            ("X-Content-Type-Options".into(), "nosniff".into()),
            ("Referrer-Policy".into(), "no-referrer".into()),
        ];
        Self { status, headers, body, close: false }
    }

    /// Bytes (static or owned).
    pub fn bytes(status: u16, ctype: &str, body: impl Into<Cow<'static, [u8]>>) -> Self {
        Self::new(status, ctype, Payload::Bytes(body.into()))
    }

    /// `STATUS msg` as plain text (errors and refusals).
    pub fn text(status: u16, msg: &str) -> Self {
        Self::bytes(status, "text/plain; charset=utf-8", format!("{status} {msg}\n").into_bytes())
    }

    /// A value as JSON (500 when it cannot be serialised).
    pub fn json(status: u16, value: &impl serde::Serialize) -> Self {
        match serde_json::to_vec(value) {
            Ok(b) => Self::bytes(status, "application/json", b),
            Err(_) => Self::text(500, "cannot serialise the answer"),
        }
    }

    /// A file, whole or the one byte range asked for (`Range: bytes=…`, as a video seek asks); 404 when it cannot
    /// be opened. The path must already be checked by the route.
    pub fn file(path: &Path, range: Option<&str>) -> Self {
        let ctype = content_type(&path.to_string_lossy());
        let Ok(mut f) = std::fs::File::open(path) else { return Self::text(404, "not found") };
        let Ok(len) = f.metadata().map(|m| m.len()) else { return Self::text(500, "cannot read file") };
        if let Some(r) = range {
            let Some((s, e)) = parse_range(r, len) else {
                return Self::bytes(416, "text/plain", &b""[..]).header("Content-Range", format!("bytes */{len}"));
            };
            if f.seek(SeekFrom::Start(s)).is_err() {
                return Self::text(500, "cannot read file");
            }
            let n = e - s + 1;
            return Self::new(206, ctype, Payload::Reader { reader: Box::new(f.take(n)), len: n })
                .header("Accept-Ranges", "bytes")
                .header("Content-Range", format!("bytes {s}-{e}/{len}"));
        }
        Self::new(200, ctype, Payload::Reader { reader: Box::new(f), len }).header("Accept-Ranges", "bytes")
    }

    /// An event stream (`text/event-stream`) of `sub`'s events.
    pub fn events(sub: Subscription) -> Self {
        Self::new(200, "text/event-stream; charset=utf-8", Payload::Events(sub)).header("X-Accel-Buffering", "no")
    }

    /// A body written by `f` as it goes.
    pub fn stream(status: u16, ctype: &str, f: impl FnOnce(&mut dyn Write) -> std::io::Result<()> + Send + 'static) -> Self {
        Self::new(status, ctype, Payload::Stream(Box::new(f)))
    }

    /// One more header (replacing none).
    pub fn header(mut self, name: &str, value: impl Into<String>) -> Self {
        self.headers.push((name.to_string(), value.into()));
        self
    }

    /// Close the connection after this answer.
    pub fn closing(mut self) -> Self {
        self.close = true;
        self
    }
}

/// A content type by file extension (the page's and the render's files).
pub fn content_type(name: &str) -> &'static str {
    match name.rsplit('.').next().unwrap_or("") {
        "html" => "text/html; charset=utf-8",
        "js" => "text/javascript; charset=utf-8",
        "css" => "text/css; charset=utf-8",
        "json" => "application/json",
        "txt" => "text/plain; charset=utf-8",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        "mp4" => "video/mp4",
        _ => "application/octet-stream",
    }
}

pub(crate) fn reason(status: u16) -> &'static str {
    match status {
        100 => "Continue",
        200 => "OK",
        201 => "Created",
        202 => "Accepted",
        204 => "No Content",
        206 => "Partial Content",
        400 => "Bad Request",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        409 => "Conflict",
        411 => "Length Required",
        413 => "Content Too Large",
        416 => "Range Not Satisfiable",
        422 => "Unprocessable Content",
        429 => "Too Many Requests",
        431 => "Request Header Fields Too Large",
        501 => "Not Implemented",
        503 => "Service Unavailable",
        _ => "Internal Server Error",
    }
}

/// `bytes=a-b`, `bytes=a-`, `bytes=-n` (one range; browsers ask for one when seeking in a video).
pub(crate) fn parse_range(v: &str, len: u64) -> Option<(u64, u64)> {
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

#[cfg(test)]
mod tests {
    use super::*;

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
