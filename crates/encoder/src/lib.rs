//! MVSplat360 encoder (`EncoderCostVolume`): CNN + multi-view transformer backbone, local-group cost volume,
//! depth refinement and the Gaussian adapter. Module files mirror the official PyTorch module tree.

pub mod backbone;
pub mod common;
pub mod config;
pub mod costvolume;
pub mod ops;

pub use config::EncoderCostVolumeCfg;
