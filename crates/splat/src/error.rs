//! Errors of the splat crate.

/// Everything the rasterizer and the Gaussian I/O can fail with.
#[derive(Debug, thiserror::Error)]
pub enum SplatError {
    /// A rasterizer input has the wrong size or an invalid value.
    #[error("rasterizer input `{name}`: {msg}")]
    Input { name: &'static str, msg: String },
    /// A tensor operation failed.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// A Gaussian file is malformed.
    #[error("{path}: {msg}")]
    Format { path: String, msg: String },
    /// Reading or writing a file failed.
    #[error("cannot access {path}: {source}")]
    File {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

pub type Result<T> = std::result::Result<T, SplatError>;

pub(crate) fn input_err(name: &'static str, msg: impl Into<String>) -> SplatError {
    SplatError::Input { name, msg: msg.into() }
}
