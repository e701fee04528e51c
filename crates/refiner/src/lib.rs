//! MVSplat360 refiner: Stable Video Diffusion img2vid (sgm layout) with 4 extra feature input channels,
//! temporal VAE, OpenCLIP ViT-H image embedder, EDM sampler with linear guidance, histogram matching.

pub mod bench;
pub mod clip;
pub mod histogram;
pub mod kernels;
pub mod keymap;
pub mod refiner;
pub mod sampling;
pub mod state_dict;
pub mod unet;
pub mod vae;
pub mod weights;

/// A diffusers component folder's weights (`unet/`, `vae/`): the full-precision file first, else the fp16 one.
pub const DIFFUSERS_WEIGHTS: [&str; 2] = ["diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.fp16.safetensors"];

/// The first of [`DIFFUSERS_WEIGHTS`] present in `dir`.
pub fn diffusers_weights_file(dir: &std::path::Path) -> Option<std::path::PathBuf> {
    DIFFUSERS_WEIGHTS.iter().map(|f| dir.join(f)).find(|p| p.is_file())
}
