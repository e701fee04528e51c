//! The pipeline's errors: each names the flag, file or view involved and what to do.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// A command-line choice that cannot work with this scene (the flag is named).
    #[error("{flag}: {msg}")]
    Flag { flag: &'static str, msg: String },
    #[error(transparent)]
    Dataset(#[from] mvsplat360_dataset::DatasetError),
    #[error(transparent)]
    Camera(#[from] mvsplat360_camera::CameraError),
    /// Weights or a model folder that cannot be used.
    #[error("{path}: {msg}")]
    Model { path: PathBuf, msg: String },
    /// No model given and no default model present.
    #[error("{0}")]
    NoModel(String),
    #[error("{path}: cannot write: {msg}")]
    Write { path: PathBuf, msg: String },
    /// A stage failed while computing (a bug or an input the model cannot handle).
    #[error("{stage}: {msg}")]
    Compute { stage: &'static str, msg: String },
    /// A stage produced non-finite values: reported instead of writing NaN images.
    #[error("{stage} produced non-finite values ({count} of {total}); the weights or the cameras are likely wrong")]
    NonFinite { stage: &'static str, count: usize, total: usize },
}

pub type Result<T> = std::result::Result<T, PipelineError>;

pub(crate) fn flag(flag: &'static str, msg: impl Into<String>) -> PipelineError {
    PipelineError::Flag { flag, msg: msg.into() }
}

/// Wrap a lower-level error as a failure of `stage`.
pub(crate) fn compute<E: std::fmt::Display>(stage: &'static str) -> impl Fn(E) -> PipelineError {
    move |e| PipelineError::Compute { stage, msg: e.to_string() }
}

/// Fail instead of writing NaN/inf.
pub fn check_finite(stage: &'static str, t: &candle_core::Tensor) -> Result<()> {
    let v = t.to_dtype(candle_core::DType::F32).and_then(|t| t.flatten_all()).and_then(|t| t.to_vec1::<f32>()).map_err(compute(stage))?;
    let bad = v.iter().filter(|x| !x.is_finite()).count();
    if bad > 0 {
        return Err(PipelineError::NonFinite { stage, count: bad, total: v.len() });
    }
    Ok(())
}
