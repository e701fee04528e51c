//! Request bodies: read only when a route asks, streamed to the route's sink (an upload: a new file) within a size
//! limit, a minimum rate and a cap on uploads at once.
//!
//! A body needs a `Content-Length` (browsers send one for a `fetch` or an `XMLHttpRequest` of a `File`); one
//! declared over the route's limit is refused before a byte is read. A body the route leaves unread is read and
//! dropped after the answer when it is small (≤ 1 MiB), else the connection is closed after the answer.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::response::Response;

/// How request bodies are read.
#[derive(Debug, Clone, Copy)]
pub struct BodyLimits {
    /// The slowest a body may arrive, in bytes per second averaged over each `window`: a body that brings less
    /// than `min_rate × window` bytes in a window (from its start) is cut off with 408, its file removed.
    pub min_rate: u64,
    pub window: Duration,
    /// Uploads ([`Body::save_to`], [`Body::save_file`], [`Body::save_into`]) at once, below the connection
    /// cap so that uploads never take every connection; more are answered 503.
    pub uploads: usize,
}

impl Default for BodyLimits {
    fn default() -> Self {
        Self { min_rate: 16 << 10, window: Duration::from_secs(10), uploads: 4 }
    }
}

/// Why a body was not taken. [`BodyError::response`] is the answer to give.
#[derive(Debug)]
pub enum BodyError {
    /// 413: the declared length is over the limit (nothing was read or written).
    TooLarge { len: u64, max: u64 },
    /// 408: fewer bytes than the minimum rate asks for arrived in a window.
    TooSlow,
    /// 503: as many uploads as allowed are under way.
    Busy,
    /// 411: no `Content-Length` (a chunked body).
    LengthRequired,
    /// 400: a file name that is not a plain one (see [`safe_file_name`]).
    BadName,
    /// The client closed the connection or it failed before the body's end.
    Closed,
    /// 500: the sink failed (disk full, file exists, …).
    Sink(std::io::Error),
}

impl std::fmt::Display for BodyError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BodyError::TooLarge { len, max } => write!(f, "the body is {len} bytes, over the limit of {max} bytes"),
            BodyError::TooSlow => write!(f, "the body arrived too slowly"),
            BodyError::Busy => write!(f, "too many uploads at once; retry when one has finished"),
            BodyError::LengthRequired => write!(f, "a body needs a Content-Length"),
            BodyError::BadName => write!(f, "not a plain file name (no folders, no leading dot, no control characters)"),
            BodyError::Closed => write!(f, "the connection closed before the body's end"),
            BodyError::Sink(e) => write!(f, "cannot store the body: {e}"),
        }
    }
}

impl std::error::Error for BodyError {}

impl BodyError {
    pub fn status(&self) -> u16 {
        match self {
            BodyError::TooLarge { .. } => 413,
            BodyError::TooSlow => 408,
            BodyError::Busy => 503,
            BodyError::LengthRequired => 411,
            BodyError::BadName => 400,
            BodyError::Closed => 400,
            BodyError::Sink(_) => 500,
        }
    }

    /// The answer (the connection is closed after it unless the body was left whole and small).
    pub fn response(&self) -> Response {
        let r = Response::text(self.status(), &self.to_string());
        match self {
            BodyError::Busy => r.header("Retry-After", "2"),
            _ => r,
        }
    }
}

/// Counts uploads under way; a permit is held while one runs.
pub(crate) struct Permit(Arc<AtomicUsize>);

impl Drop for Permit {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// The body of the request a route is answering: read (or not) through these methods only.
pub struct Body<'a> {
    pub(crate) stream: &'a mut TcpStream,
    /// Bytes read past the head (the body's start, or a pipelined request).
    pub(crate) buf: &'a mut Vec<u8>,
    /// `Content-Length`; None for a chunked body (not read).
    pub(crate) len: Option<u64>,
    pub(crate) taken: u64,
    /// A read failed or was cut off: the connection's state is unknown.
    pub(crate) broken: bool,
    pub(crate) expect_continue: bool,
    pub(crate) limits: BodyLimits,
    pub(crate) uploads: Arc<AtomicUsize>,
}

impl Body<'_> {
    /// The declared length (`Content-Length`); None when it is not given as one (a chunked body).
    pub fn len(&self) -> Option<u64> {
        self.len
    }

    /// Whether the request has no body.
    pub fn is_empty(&self) -> bool {
        self.len == Some(0)
    }

    /// Bytes not read yet.
    pub(crate) fn remaining(&self) -> Option<u64> {
        self.len.map(|n| n - self.taken)
    }

    fn permit(&self) -> Result<Permit, BodyError> {
        if self.uploads.fetch_add(1, Ordering::AcqRel) >= self.limits.uploads {
            self.uploads.fetch_sub(1, Ordering::AcqRel);
            return Err(BodyError::Busy);
        }
        Ok(Permit(self.uploads.clone()))
    }

    /// A small body (a form, a JSON request) into memory: at most `max` bytes, within the minimum rate. Counts as
    /// no upload.
    pub fn read_to_vec(&mut self, max: u64) -> Result<Vec<u8>, BodyError> {
        let mut v = Vec::new();
        self.pump(&mut v, max)?;
        Ok(v)
    }

    /// Stream the body into `sink`, at most `max` bytes, as one of the uploads at once; the bytes written. On an
    /// error the sink may hold part of the body (never more than `max` bytes): the caller removes it.
    pub fn save_to(&mut self, sink: &mut dyn Write, max: u64) -> Result<u64, BodyError> {
        let _permit = self.permit()?;
        self.pump(sink, max)
    }

    /// Stream the body into a new file at `path` (which must not exist), at most `max` bytes, as one of the
    /// uploads at once; the bytes written. On any error the file is removed.
    pub fn save_file(&mut self, path: &Path, max: u64) -> Result<u64, BodyError> {
        let _permit = self.permit()?;
        self.check_len(max)?;
        let f = std::fs::OpenOptions::new().write(true).create_new(true).open(path).map_err(BodyError::Sink)?;
        let mut w = std::io::BufWriter::with_capacity(256 << 10, f);
        let r = self.pump(&mut w, max).and_then(|n| {
            let f = w.into_inner().map_err(|e| BodyError::Sink(e.into_error()))?;
            f.sync_all().map_err(BodyError::Sink)?;
            Ok(n)
        });
        if r.is_err() {
            let _ = std::fs::remove_file(path);
        }
        r
    }

    /// [`Body::save_file`] into the folder `dir` under the name `raw_name` as the client sent it (percent-encoded,
    /// e.g. a `PUT /upload/NAME`'s last segment), refused unless it decodes to a plain file name
    /// ([`safe_file_name`]); the file's path.
    pub fn save_into(&mut self, dir: &Path, raw_name: &str, max: u64) -> Result<PathBuf, BodyError> {
        let name = safe_file_name(raw_name).ok_or(BodyError::BadName)?;
        let path = dir.join(name);
        self.save_file(&path, max)?;
        Ok(path)
    }

    fn check_len(&self, max: u64) -> Result<u64, BodyError> {
        let len = self.remaining().ok_or(BodyError::LengthRequired)?;
        if len > max {
            return Err(BodyError::TooLarge { len, max });
        }
        Ok(len)
    }

    /// Copy what is left of the body to `sink`, checking the rate once per window.
    fn pump(&mut self, sink: &mut dyn Write, max: u64) -> Result<u64, BodyError> {
        let len = self.check_len(max)?;
        if self.expect_continue && len > 0 {
            self.expect_continue = false;
            if self.stream.write_all(b"HTTP/1.1 100 Continue\r\n\r\n").is_err() {
                self.broken = true;
                return Err(BodyError::Closed);
            }
        }
        let mut done = 0u64;
        // The bytes already read with the head.
        let have = (self.buf.len() as u64).min(len) as usize;
        if have > 0 {
            sink.write_all(&self.buf[..have]).map_err(|e| self.fail(BodyError::Sink(e)))?;
            self.buf.drain(..have);
            self.taken += have as u64;
            done += have as u64;
        }
        let need = (self.limits.min_rate as f64 * self.limits.window.as_secs_f64()).ceil() as u64;
        let mut window_end = Instant::now() + self.limits.window;
        let mut in_window = have as u64;
        let mut chunk = vec![0u8; 64 << 10];
        while done < len {
            let now = Instant::now();
            if now >= window_end {
                if in_window < need {
                    return Err(self.fail(BodyError::TooSlow));
                }
                window_end = now + self.limits.window;
                in_window = 0;
                continue;
            }
            if self.stream.set_read_timeout(Some(window_end - now)).is_err() {
                return Err(self.fail(BodyError::Closed));
            }
            let want = (len - done).min(chunk.len() as u64) as usize;
            match self.stream.read(&mut chunk[..want]) {
                Ok(0) => return Err(self.fail(BodyError::Closed)),
                Ok(n) => {
                    self.taken += n as u64;
                    done += n as u64;
                    in_window += n as u64;
                    sink.write_all(&chunk[..n]).map_err(|e| self.fail(BodyError::Sink(e)))?;
                }
                Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted) => {}
                Err(_) => return Err(self.fail(BodyError::Closed)),
            }
        }
        Ok(done)
    }

    fn fail(&mut self, e: BodyError) -> BodyError {
        self.broken = true;
        e
    }
}

/// A client-given file name (percent-encoded, as in a request path), decoded, when it is a plain name: not
/// empty, at most 255 bytes, no `/`, `\`, `:`, NUL or other control characters, not starting with a dot (no
/// `.`, `..` nor hidden files) nor with `~` or `-`, not ending with a space or dot. None otherwise: refuse it.
pub fn safe_file_name(raw: &str) -> Option<String> {
    let name = percent_encoding::percent_decode_str(raw).decode_utf8().ok()?;
    let bad = name.is_empty()
        || name.len() > 255
        || name.starts_with(['.', '~', '-'])
        || name.ends_with([' ', '.'])
        || name.chars().any(|c| c.is_control() || matches!(c, '/' | '\\' | ':' | '\0'));
    (!bad).then(|| name.into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names() {
        for ok in ["a.jpg", "IMG_0001.JPG", "photo%20one.png", "v%C3%A9lo.mp4", "transforms.json"] {
            assert!(safe_file_name(ok).is_some(), "{ok}");
        }
        assert_eq!(safe_file_name("photo%20one.png").as_deref(), Some("photo one.png"));
        for bad in [
            "",
            ".",
            "..",
            "%2e%2e",
            "..%2fx",
            "%2e%2e%2fx",
            "a/b",
            "a%2fb",
            "a%5cb",
            "a\\b",
            "C:x",
            "x%00.png",
            ".hidden",
            "~x",
            "-rf",
            "a.",
            "a ",
            "%ff",
            "a%0ab",
        ] {
            assert!(safe_file_name(bad).is_none(), "{bad}");
        }
        assert!(safe_file_name(&"a".repeat(256)).is_none());
    }
}
