//! Training errors: each names the file, field or step and what to do.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{path}: {msg}")]
    Config { path: PathBuf, msg: String },
    #[error("data: {0}")]
    Data(String),
    #[error("checkpoint: {0}")]
    Checkpoint(String),
    #[error("step {step}: the loss is not finite ({what}); lower `train.lr` or check the data")]
    NonFinite { step: u64, what: String },
    #[error("cannot write {path}: {msg}")]
    Write { path: PathBuf, msg: String },
    /// Data-parallel runs: the launcher, the hub or a rank's link.
    #[error("data parallel: {0}")]
    Dist(String),
    #[error("interrupted")]
    Interrupted,
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    #[error(transparent)]
    Pipeline(#[from] mvsplat360_pipeline::PipelineError),
    #[error(transparent)]
    Splat(#[from] mvsplat360_splat::SplatError),
}

pub type Result<T> = std::result::Result<T, TrainError>;
