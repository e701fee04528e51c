//! MVSplat360 encoder (`EncoderCostVolume`): CNN + multi-view transformer backbone, local-group cost volume,
//! depth refinement and the Gaussian adapter. Module files mirror the official PyTorch module tree.

pub mod backbone;
pub mod bench;
pub mod common;
pub mod config;
pub mod costvolume;
pub mod encoder_costvolume;
pub mod weights;

pub use common::gaussian_adapter::EncoderGaussians;
pub use config::EncoderCostVolumeCfg;
pub use encoder_costvolume::{to_splat_gaussians, EncoderCostVolume, ENCODER_PREFIX};
pub use weights::{load_strict, Checkpoint, StrictLoader, WeightsError};

/// Stage timer for profiling: with `MVSPLAT360_PROFILE` set, prints the time since `t` under `label` to stderr.
pub(crate) fn prof(label: &str, t: &mut std::time::Instant) {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    if *ON.get_or_init(|| std::env::var_os("MVSPLAT360_PROFILE").is_some()) {
        eprintln!("[prof] {label}: {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    }
    *t = std::time::Instant::now();
}
