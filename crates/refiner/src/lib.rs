//! MVSplat360 refiner: Stable Video Diffusion img2vid (sgm layout) with 4 extra feature input channels,
//! temporal VAE, OpenCLIP ViT-H image embedder, EDM sampler with linear guidance, histogram matching.

pub mod clip;
pub mod histogram;
pub mod kernels;
pub mod keymap;
pub mod prof;
pub mod refiner;
pub mod bench;
pub mod sampling;
pub mod state_dict;
pub mod unet;
pub mod vae;
