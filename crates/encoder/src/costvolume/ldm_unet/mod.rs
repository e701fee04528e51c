//! The ldm-style UNet (`costvolume/ldm_unet/`) as configured by the depth predictor: post-norm ResBlocks,
//! legacy-QKV attention across all views' tokens, no timestep embedding.

pub mod unet;
pub mod util;

pub use unet::{AttentionBlock, ResBlock, UNetCfg, UNetModel};
pub use util::{Conv2d, GroupNorm};
