//! MVSplat360 encoder (`EncoderCostVolume`): CNN + multi-view transformer backbone, local-group cost volume,
//! depth refinement and the Gaussian adapter. Module files mirror the official PyTorch module tree.

pub mod backbone;
pub mod bench;
pub mod bf16;
pub mod common;
pub mod config;
pub mod costvolume;
pub mod encoder_costvolume;
pub mod weights;

pub use common::gaussian_adapter::EncoderGaussians;
pub use config::EncoderCostVolumeCfg;
pub use encoder_costvolume::{to_splat_gaussians, EncoderCostVolume, ENCODER_PREFIX};
pub use weights::{load_strict, Checkpoint, StrictLoader, WeightsError};
