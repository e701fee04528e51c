use std::path::PathBuf;

use mvsplat360_camera::CameraError;

/// Every error names the file (and view/field) involved and, where it helps, what to do.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: no such file or folder")]
    NotFound { path: PathBuf },
    #[error("{path}: not a recognised scene (expected transforms.json, a COLMAP folder with sparse/0/{{cameras,images}}.{{bin,txt}}, or a .torch chunk)")]
    UnknownFormat { path: PathBuf },
    #[error("{path}: cannot read: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: invalid JSON: {source}")]
    Json { path: PathBuf, source: serde_json::Error },
    #[error("{path}: {field}: {msg}")]
    Field { path: PathBuf, field: String, msg: String },
    #[error("{path}: malformed COLMAP file: {msg}")]
    Colmap { path: PathBuf, msg: String },
    #[error("{path}: malformed .torch chunk: {msg}")]
    Chunk { path: PathBuf, msg: String },
    #[error("image {what}: cannot decode: {msg}")]
    Image { what: String, msg: String },
    #[error("view {view}: image is {}x{} but its camera says {}x{}", found.0, found.1, expected.0, expected.1)]
    ImageSize { view: String, expected: (u32, u32), found: (u32, u32) },
    /// A lens this program cannot turn into a pinhole camera; never read as if it were one.
    #[error("{path}: {what} uses the {model} camera model, {why}; re-run `mvsplat360 pose` on the original photos, or undistort them to PINHOLE with `colmap image_undistorter` and read the folder it writes")]
    UnsupportedLens { path: PathBuf, what: String, model: String, why: String },
    #[error("scene {scene} has no views")]
    EmptyScene { scene: String },
    #[error(transparent)]
    Camera(#[from] CameraError),
}

pub(crate) fn field(path: &std::path::Path, field: impl Into<String>, msg: impl Into<String>) -> DatasetError {
    DatasetError::Field { path: path.to_path_buf(), field: field.into(), msg: msg.into() }
}

pub(crate) fn io(path: &std::path::Path, source: std::io::Error) -> DatasetError {
    DatasetError::Io { path: path.to_path_buf(), source }
}
