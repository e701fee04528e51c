//! Stage `vae` (`train.stage = "vae"`): the refiner's first-stage autoencoder trained alone on the training
//! views, from seeded random weights. MVSplat360 takes this autoencoder from SVD frozen; where SVD's weights are
//! not at hand, a small one trained here gives the refiner a latent space that means something (a random
//! autoencoder's latents carry no image prior). Loss as Stable Diffusion's autoencoders without the
//! discriminator: mean |x̂ − x| + `lpips_weight`·LPIPS + `kl_weight`·KL, on the views as the refiner sees them
//! (bilinear ×2, align_corners, in [−1, 1]); decoded one frame per call, as MVSplat360 decodes.

use std::path::Path;

use candle_core::{Device, Tensor, Var};
use mvsplat360_refiner::kernels;
use mvsplat360_refiner::state_dict::VAE_PREFIX;
use mvsplat360_refiner::vae::{prepare_encoder_input, AutoencoderConfig, AutoencoderKL, VaeLayout};
use rand::Rng;
use rand_distr::StandardNormal;

use crate::error::{Result, TrainError};
use crate::loss::diffusion::TARGET_UPSAMPLE;

/// The autoencoder being trained, its weights as `Var`s under the official keys (`refiner.first_stage_model.*`).
pub struct TrainVae {
    pub model: AutoencoderKL,
    pub vars: Vec<(String, Var)>,
}

/// One batch's terms (scalars with gradients) and the reconstruction at the views' size.
pub struct VaeLosses {
    /// mean |x̂ − x| in [−1, 1] units at the autoencoder's resolution.
    pub l1: Tensor,
    /// KL(q(z|x) ‖ N(0, I)) summed over latent elements, divided by the image elements (as `l1` is a mean).
    pub kl: Tensor,
    /// (N, 3, H, W) in about [0, 1] (not clamped, so LPIPS and MSE keep their gradients).
    pub recon: Tensor,
}

impl TrainVae {
    /// From `init` (`train.refiner_init`: a model folder, e.g. an earlier `vae` run's, a safetensors file with the
    /// VAE's keys, or a diffusers SVD folder's `vae/`), else seeded random weights.
    pub fn new(cfg: &AutoencoderConfig, init: Option<&Path>, seed: u64, dev: &Device) -> Result<Self> {
        let (model, vars) = match init {
            None => AutoencoderKL::random_trainable(cfg, seed, dev).map_err(|e| TrainError::Config { path: "model.refiner.vae".into(), msg: e.to_string() })?,
            Some(p) => {
                let (file, layout) = if p.join("vae").is_dir() {
                    let d = p.join("vae");
                    (
                        mvsplat360_refiner::diffusers_weights_file(&d).unwrap_or_else(|| d.join(mvsplat360_refiner::DIFFUSERS_WEIGHTS[0])),
                        Some(VaeLayout::Diffusers),
                    )
                } else if p.is_dir() {
                    (p.join(mvsplat360_pipeline::model::MODEL_WEIGHTS), None)
                } else {
                    (p.to_path_buf(), None)
                };
                let bad = |msg: String| TrainError::Config { path: file.clone(), msg: format!("train.refiner_init (stage vae): {msg}") };
                if !file.is_file() {
                    return Err(bad("no such file (a model folder, a safetensors file with the VAE's keys or a diffusers SVD folder)".into()));
                }
                AutoencoderKL::load_trainable(&file, layout, cfg, dev).map_err(|e| bad(e.to_string()))?
            }
        };
        Ok(Self { model, vars: vars.into_iter().map(|(k, v)| (format!("{VAE_PREFIX}{k}"), v)).collect() })
    }

    /// `views`: (N, 3, H, W) in [0, 1]; the posterior sample's noise comes from `rng` (drawn on the host).
    pub fn losses(&self, views: &Tensor, rng: &mut impl Rng) -> Result<VaeLosses> {
        let (_, _, h, w) = views.dims4()?;
        let x = prepare_encoder_input(views, TARGET_UPSAMPLE).map_err(vae_err)?;
        let _g = kernels::differentiable();
        let (mean, logvar) = self.model.encode(&x).map_err(vae_err)?;
        let n = mean.elem_count();
        let eps: Vec<f32> = (0..n).map(|_| rng.sample(StandardNormal)).collect();
        let eps = Tensor::from_vec(eps, mean.shape(), views.device())?;
        let z = (&mean + (&logvar * 0.5)?.exp()?.mul(&eps)?)?;
        let xr = self.model.decode(&z, 1).map_err(vae_err)?;
        let l1 = (&xr - &x)?.abs()?.mean_all()?;
        let kl = (((mean.sqr()? + logvar.exp()?)? - 1.0)? - &logvar)?.sum_all()?.affine(0.5 / x.elem_count() as f64, 0.0)?;
        // MVSplat360's way back to the render size (bilinear, align_corners), with a backward.
        let recon = crate::loss::diffusion::resize_bilinear_align_corners(&((xr + 1.0)? * 0.5)?, h, w)?;
        Ok(VaeLosses { l1, kl, recon })
    }
}

fn vae_err(e: impl std::fmt::Display) -> TrainError {
    TrainError::Data(format!("VAE: {e}"))
}
