//! Where the converted metric weights live and how a missing file is reported.
//!
//! INTERFACE (agreed between the metrics modules; the bodies are to be written):
//! - `pub const ENV_VAR: &str = "MVSPLAT360_METRIC_WEIGHTS";`
//! - `pub fn default_dir() -> PathBuf` (a per-user cache folder).
//! - `pub fn locate(explicit: Option<&Path>, file: &str) -> Result<PathBuf, MetricsWeightsError>`: the file in
//!   `--weights-dir`, else `$MVSPLAT360_METRIC_WEIGHTS`, else `default_dir()`; the error names the file, every
//!   place looked and the command that fetches it.
