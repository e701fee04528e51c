//! Errors: each says what went wrong and what to do about it.

use std::path::Path;

/// What can go wrong when a name is turned into a local file.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The text is neither an existing path nor a name this crate understands.
    #[error("{0}")]
    BadName(String),
    /// A gated repository: no token, a token without access, or an invalid token.
    #[error("{0}")]
    Gated(String),
    /// The Hub refused the token (401 "Invalid credentials").
    #[error("{0}")]
    BadToken(String),
    /// The repository, the revision or the file does not exist (or is private).
    #[error("{0}")]
    NotFound(String),
    /// `HF_HUB_OFFLINE` is set and the file is not in the cache.
    #[error("{0}")]
    Offline(String),
    /// The Hub could not be reached and the file is not in the cache.
    #[error("{0}")]
    Unreachable(String),
    /// The transfer stopped before the announced size; the partial file is kept for a resume.
    #[error("{0}")]
    Interrupted(String),
    /// The downloaded bytes do not match the Hub's checksum; the partial file was deleted.
    #[error("{0}")]
    Corrupt(String),
    /// Any other answer of the Hub.
    #[error("{0}")]
    Http(String),
    /// A zip that may not be unpacked (entries leaving the folder, links, too large).
    #[error("{0}")]
    Zip(String),
    /// A file-system error, with the path it concerns.
    #[error("{0}")]
    Io(String),
}

/// This crate's result.
pub type Result<T> = std::result::Result<T, Error>;

/// An I/O error about `path`, saying what was being done.
pub(crate) fn io(what: &str, path: &Path, e: std::io::Error) -> Error {
    Error::Io(format!("{what} {}: {e}", path.display()))
}
