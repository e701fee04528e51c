use std::path::{Path, PathBuf};

/// Every error says what happened, to which file, and what to do.
#[derive(Debug, thiserror::Error)]
pub enum PoseError {
    #[error("{program} not found (looked in {looked}); install it: {install}")]
    MissingProgram { program: String, looked: String, install: String },
    #[error("{program}: {msg}")]
    Engine { program: String, msg: String },
    #[error("{path}: {msg}")]
    Input { path: PathBuf, msg: String },
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{0}")]
    Dataset(#[from] mvsplat360_dataset::DatasetError),
    /// COLMAP ran but the scene could not be posed; the message says what it found and what to do.
    #[error("{0}")]
    NotPosed(String),
    /// The VGGT model: its weights (missing: where to get them; of another shape: the keys named), or a
    /// prediction that cannot be used.
    #[error("{0}")]
    Vggt(String),
    /// The output folder's lock was not taken: another run holds it (the message names the lock file and the
    /// process), or the file system refused it.
    #[error("{0}")]
    Busy(String),
    #[error("{stage} was stopped (Ctrl-C); the finished stages are kept in {work} and a rerun continues from them")]
    Interrupted { stage: String, work: PathBuf },
}

impl PoseError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        PoseError::Io { path: path.to_path_buf(), source }
    }

    pub(crate) fn input(path: &Path, msg: impl Into<String>) -> Self {
        PoseError::Input { path: path.to_path_buf(), msg: msg.into() }
    }
}
