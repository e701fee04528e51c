//! Seeded random refiner weights under the MVSplat360 checkpoint's key names, so a model folder made with
//! them loads through exactly the same code as real weights (tests, tiny demo models).

use candle_core::{Device, Tensor};

use crate::clip::ClipVisionConfig;
use crate::unet::{VideoUNet, VideoUNetConfig, Weights};
use crate::vae::AutoencoderConfig;
use crate::weights::StrictWeights;

/// Key prefixes of the refiner's parts in an official MVSplat360 checkpoint.
pub const UNET_PREFIX: &str = "refiner.model.diffusion_model.";
pub const VAE_PREFIX: &str = "refiner.first_stage_model.";
pub const CLIP_PREFIX: &str = "refiner.conditioner.embedders.0.open_clip.model.visual.";

/// Random UNet, VAE and CLIP vision tower with the given configs, as (official key, tensor) pairs.
pub fn random_refiner_state_dict(unet: &VideoUNetConfig, vae: &AutoencoderConfig, clip: &ClipVisionConfig, seed: u64) -> Result<Vec<(String, Tensor)>, String> {
    let dev = Device::Cpu;
    let mut out = Vec::new();
    let w = Weights::random(seed, &dev);
    VideoUNet::new(unet, &w).map_err(|e| format!("UNet config: {e}"))?;
    out.extend(w.take_recorded().into_iter().map(|(k, t)| (format!("{UNET_PREFIX}{k}"), t)));
    let w = StrictWeights::random(seed.wrapping_add(1), "VAE", &dev);
    crate::vae::AutoencoderKL::build_with(&w, vae).map_err(|e| format!("VAE config: {e}"))?;
    out.extend(w.take_recorded().into_iter().map(|(k, t)| (format!("{VAE_PREFIX}{k}"), t)));
    let w = StrictWeights::random(seed.wrapping_add(2), "CLIP vision", &dev);
    crate::clip::ClipImageEmbedder::build_with(&w, clip).map_err(|e| format!("CLIP config: {e}"))?;
    out.extend(w.take_recorded().into_iter().map(|(k, t)| (format!("{CLIP_PREFIX}{k}"), t)));
    Ok(out)
}
