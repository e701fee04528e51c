//! Refiner (Stable Video Diffusion) training losses of MVSplat360: the sgm `StandardDiffusionLoss` on the
//! target latents with the rendered features as concat condition, and the latent-alignment MSE between the
//! rendered features and the VAE encoding of the target views. Total refiner loss (weight 1, added to the
//! 3DGS losses, `model_wrapper.py` l.195): `diffusion_loss + latent_alignment_loss` (`svd_diffuser.py` l.117).
//!
//! References (mvsplat360 = donydchen/mvsplat360, sgm = Stability-AI/generative-models `sgm/`):
//! - σ sampling: `DiscreteSampling(num_idx=1000, LegacyDDPMDiscretization())` (`svd_wo_mb_fps.yaml` l.143–147,
//!   defaults linear_start 0.00085, linear_end 0.012; `sigma_sampling.py` l.16–31): one uniform index per
//!   sample of the batch, and the batch is (B·F) frames, so σ is drawn **per frame**.
//!   σ_i = √((1 − ᾱ_i)/ᾱ_i), ᾱ_i = Π_{j≤i}(1 − β_j), β_j = (√0.00085 + j/999·(√0.012 − √0.00085))²
//!   (`discretizer.py` l.42–69, `util.py` `make_beta_schedule`), ascending after DiscreteSampling's flip.
//! - Noising: x_σ = x + σ·n, n ~ N(0, I), no offset noise (`loss.py` l.72–84, offset_noise_level 0).
//! - Denoiser `VScalingWithEDMcNoise` (`denoiser_scaling.py` l.51–59, `denoiser.py` l.23–39):
//!   c_skip = 1/(σ²+1), c_out = −σ/√(σ²+1), c_in = 1/√(σ²+1), c_noise = ¼·ln σ;
//!   D = c_out·UNet([c_in·x_σ, F̂], c_noise, ctx, y) + c_skip·x_σ, concat after the latent (`wrappers.py` l.27).
//! - Weighting `EpsWeighting` w(σ) = σ⁻² (`loss_weighting.py` l.30–32, `svd_wo_mb_fps.yaml` l.141);
//!   L = mean_frames mean_elems w·(D − x)² (`loss.py` l.89–96 `get_loss` l2, then `.mean()`).
//! - x = 0.18215 · sample of the first-stage posterior of the targets, bilinear ×2 (align_corners) and
//!   mapped to [−1, 1] (`svd_diffuser.py` l.131–142, `diffusion.py` `encode_first_stage`,
//!   `DiagonalGaussianRegularizer(sample=True)`).
//! - Concat condition F̂ = interpolate(rendered features, ×0.25, bilinear, align_corners) (mvsplat360
//!   `svd_modules/loss.py` l.38–43, `dl3dv_mvsplat360.yaml` l.43 gs_feat_scale_factor 0.25); crossattn = the
//!   CLIP token averaged over context views repeated per frame; vector y = 256-d embedding of cond_aug 0.02.
//! - Latent alignment (`svd_modules/loss.py` l.33, l.48–49; `svd_diffuser.py` l.188–213 with
//!   train_gs_feat_enc_type `target_gt`, weight 0.01, `dl3dv_mvsplat360.yaml` l.45–46):
//!   E = mode of `AutoencoderKLModeOnly.encode(up2(targets)·2 − 1 + 0.02·n)`, no 0.18215 scaling
//!   (`VideoPredictionEmbedderWithEncoder` scale_factor 1), detached; L = 0.01·mean((F̂[:, :4] − E)²).

use candle_core::{Result, Tensor};
use mvsplat360_refiner::kernels;
use mvsplat360_refiner::sampling::v_scaling_edm;
use mvsplat360_refiner::unet::util::timestep_embedding;
use mvsplat360_refiner::unet::{UNetInputs, VideoUNet};
use mvsplat360_refiner::vae::{prepare_encoder_input, AutoencoderKL};
use rand::Rng;

/// `LegacyDDPMDiscretization` defaults (the official config sets none).
pub const LINEAR_START: f64 = 0.00085;
pub const LINEAR_END: f64 = 0.0120;
/// `DiscreteSampling.num_idx` = number of DDPM timesteps.
pub const NUM_TIMESTEPS: usize = 1000;
/// `cond_aug`: the vector condition's value and the noise level added to the encoder input of E.
pub const COND_AUG: f32 = 0.02;
/// First-stage latent scale (applies to the diffusion target x, not to E).
pub const LATENT_SCALE_FACTOR: f64 = 0.18215;
/// Targets are upsampled by `gs_feat_scale_factor·8` = 2 before the VAE encoder.
pub const TARGET_UPSAMPLE: usize = 2;
/// Rendered features are resized by `gs_feat_scale_factor` = 0.25 to the latent grid.
pub const FEATURE_SCALE: f64 = 0.25;
/// Weight of [`diffusion_loss`] in the total loss.
pub const DIFFUSION_LOSS_WEIGHT: f64 = 1.0;
/// `weight_train_gs_feat_via_enc`; [`latent_alignment_loss`] already includes it.
pub const LATENT_ALIGNMENT_WEIGHT: f64 = 0.01;

/// The discrete σ's of `LegacyDDPMDiscretization` as `DiscreteSampling` holds them (ascending, index 0 the
/// smallest), in f32 like the torch buffer.
#[derive(Debug, Clone, PartialEq)]
pub struct DdpmSigmas {
    sigmas: Vec<f32>,
}

impl Default for DdpmSigmas {
    fn default() -> Self {
        Self::official()
    }
}

impl DdpmSigmas {
    /// 1000 steps, linear β from 0.00085 to 0.012 (in √β).
    pub fn official() -> Self {
        Self::legacy_ddpm(LINEAR_START, LINEAR_END, NUM_TIMESTEPS)
    }

    /// β_j = linspace(√start, √end, n)_j² in f64 (torch's symmetric linspace), ᾱ = cumprod(1 − β) in f64,
    /// σ = sqrt(f32((1 − ᾱ)/ᾱ)) (cast to f32 before the square root, as `to_torch(...) ** 0.5`).
    pub fn legacy_ddpm(linear_start: f64, linear_end: f64, n: usize) -> Self {
        let (a, b) = (linear_start.sqrt(), linear_end.sqrt());
        let step = if n > 1 { (b - a) / (n - 1) as f64 } else { 0.0 };
        let half = n / 2;
        let mut prod = 1.0f64;
        let sigmas = (0..n)
            .map(|i| {
                let r = if i < half { a + step * i as f64 } else { b - step * (n - 1 - i) as f64 };
                prod *= 1.0 - r * r;
                (((1.0 - prod) / prod) as f32).sqrt()
            })
            .collect();
        Self { sigmas }
    }

    pub fn as_slice(&self) -> &[f32] {
        &self.sigmas
    }

    pub fn len(&self) -> usize {
        self.sigmas.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sigmas.is_empty()
    }

    /// `n` independent draws (one per frame of the batch): σ[idx], idx uniform in 0..len.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R, n: usize) -> Vec<f32> {
        (0..n).map(|_| self.sigmas[rng.gen_range(0..self.sigmas.len())]).collect()
    }
}

/// Denoiser scalings of `VScalingWithEDMcNoise` for one σ (f32, as the torch code).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scalings {
    pub c_skip: f32,
    pub c_out: f32,
    pub c_in: f32,
    pub c_noise: f32,
}

/// c_skip = 1/(σ²+1), c_out = −σ/√(σ²+1), c_in = 1/√(σ²+1), c_noise = ¼·ln σ.
pub fn scalings(sigma: f32) -> Scalings {
    let (c_skip, c_out, c_in, c_noise) = v_scaling_edm(sigma);
    Scalings { c_skip, c_out, c_in, c_noise }
}

/// `EpsWeighting`: w(σ) = σ⁻².
pub fn loss_weighting(sigma: f32) -> f32 {
    sigma.powi(-2)
}

/// (N, 1, 1, 1) column of per-frame values.
fn per_frame(v: Vec<f32>, like: &Tensor) -> Result<Tensor> {
    let n = v.len();
    Tensor::from_vec(v, (n, 1, 1, 1), like.device())
}

/// Cross-attention context per frame: (B, Lc, D) repeated F times (b-major), or already (B·F, Lc, D).
fn per_frame_context(ctx: &Tensor, n: usize, num_frames: usize) -> Result<Tensor> {
    let (b, lc, d) = ctx.dims3()?;
    if b == n {
        return Ok(ctx.clone());
    }
    if b * num_frames != n {
        candle_core::bail!("diffusion loss: context batch {b} is neither the {n} frames nor {n}/{num_frames} videos");
    }
    ctx.unsqueeze(1)?.broadcast_as((b, num_frames, lc, d))?.reshape((n, lc, d))
}

/// sgm `StandardDiffusionLoss` (l2, `EpsWeighting`, `VScalingWithEDMcNoise`) as MVSplat360 trains it.
///
/// - `latents`: (B·F, 4, h, w) clean targets x (already ×0.18215, see [`target_latents`]), constants;
/// - `features`: (B·F, Cc, h, w) concat condition F̂ (rendered features at latent size, see
///   [`features_to_latent`]); gradients flow to it (and to the UNet's `Var` weights, if any);
/// - `clip_embedding`: (B, Lc, D) averaged CLIP token of each video (or already per frame);
/// - `sigmas`: one σ per frame ([`DdpmSigmas::sample`]); `noise`: (B·F, 4, h, w) standard normal.
///
/// Returns the scalar mean of σ⁻²·(D − x)² (weight [`DIFFUSION_LOSS_WEIGHT`] = 1 not applied). The UNet
/// runs in the kernels' differentiable mode (composed candle ops, slower than inference).
pub fn diffusion_loss(
    unet: &VideoUNet,
    latents: &Tensor,
    features: &Tensor,
    clip_embedding: &Tensor,
    sigmas: &[f32],
    noise: &Tensor,
    num_frames: usize,
) -> Result<Tensor> {
    let (n, _, h, w) = latents.dims4()?;
    let (nf, _, hf, wf) = features.dims4()?;
    if sigmas.len() != n || noise.dims() != latents.dims() || (nf, hf, wf) != (n, h, w) || num_frames == 0 || n % num_frames != 0 {
        candle_core::bail!(
            "diffusion loss: latents {:?}, features {:?}, noise {:?}, {} sigmas, {num_frames} frames per video",
            latents.dims(),
            features.dims(),
            noise.dims(),
            sigmas.len()
        );
    }
    let sc: Vec<Scalings> = sigmas.iter().map(|&s| scalings(s)).collect();
    let col = |f: fn(&Scalings) -> f32| per_frame(sc.iter().map(f).collect(), latents);
    let sigma = per_frame(sigmas.to_vec(), latents)?;
    let weight = per_frame(sigmas.iter().map(|&s| loss_weighting(s)).collect(), latents)?;
    let noised = (latents + noise.broadcast_mul(&sigma)?)?;
    let x_in = Tensor::cat(&[&noised.broadcast_mul(&col(|s| s.c_in)?)?, features], 1)?;
    let ctx = per_frame_context(clip_embedding, n, num_frames)?;
    let y = match unet.cfg.adm_in_channels {
        Some(adm) => Some(timestep_embedding(&vec![COND_AUG; n], adm, 10000.0, latents.device())?),
        None => None,
    };
    let c_noise: Vec<f32> = sc.iter().map(|s| s.c_noise).collect();
    let v = {
        let _g = kernels::differentiable();
        unet.forward(&UNetInputs { x: &x_in, timesteps: &c_noise, context: &ctx, y: y.as_ref(), num_video_frames: num_frames, num_splits: None })?
    };
    let denoised = (v.broadcast_mul(&col(|s| s.c_out)?)? + noised.broadcast_mul(&col(|s| s.c_skip)?)?)?;
    // Per-frame means then the mean over frames = one mean (every frame has as many elements).
    (denoised - latents)?.sqr()?.broadcast_mul(&weight)?.mean_all()
}

/// Runs `f` with the fast (non-differentiable) kernels, restoring the caller's mode.
fn without_grad<T>(f: impl FnOnce() -> Result<T>) -> Result<T> {
    let prev = kernels::set_differentiable(false);
    let r = f();
    kernels::set_differentiable(prev);
    r
}

/// Diffusion target x: targets (N, 3, H, W) in [0, 1] → bilinear ×2 (align_corners) → ·2 − 1 → first-stage
/// posterior (mean, logvar) → mean + exp(½·logvar)·`eps` (`eps` None: the mode) → ×0.18215. Detached.
pub fn target_latents(vae: &AutoencoderKL, targets: &Tensor, eps: Option<&Tensor>) -> Result<Tensor> {
    without_grad(|| {
        let x = prepare_encoder_input(targets, TARGET_UPSAMPLE).map_err(candle_core::Error::wrap)?;
        let (mean, logvar) = vae.encode(&x).map_err(candle_core::Error::wrap)?;
        let z = match eps {
            Some(e) => (&mean + (logvar * 0.5)?.exp()?.mul(e)?)?,
            None => mean,
        };
        Ok((z * LATENT_SCALE_FACTOR)?.detach())
    })
}

/// Latent-alignment target E: targets (N, 3, H, W) in [0, 1] → bilinear ×2 (align_corners) → ·2 − 1
/// → + 0.02·`noise` ((N, 3, 2H, 2W) standard normal; official training always adds it, None skips it) →
/// posterior mode (mean), unscaled. Detached. Officially the encoder is the conditioner's
/// `AutoencoderKLModeOnly` (`conditioner.embedders.1.encoder`, with `quant_conv`), not the first stage.
pub fn alignment_target(encoder: &AutoencoderKL, targets: &Tensor, noise: Option<&Tensor>) -> Result<Tensor> {
    without_grad(|| {
        let mut x = prepare_encoder_input(targets, TARGET_UPSAMPLE).map_err(candle_core::Error::wrap)?;
        if let Some(n) = noise {
            x = (x + (n * COND_AUG as f64)?)?;
        }
        let (mean, _) = encoder.encode(&x).map_err(candle_core::Error::wrap)?;
        Ok(mean.detach())
    })
}

/// `0.01·mean((F̂[:, :C] − E)²)` with E (N, C, h, w) from [`alignment_target`], F̂ (N, ≥C, h, w).
pub fn latent_alignment_loss_to(features: &Tensor, target: &Tensor) -> Result<Tensor> {
    let c = target.dim(1)?;
    if features.rank() != 4 || features.dim(1)? < c || features.dims()[2..] != target.dims()[2..] || features.dim(0)? != target.dim(0)? {
        candle_core::bail!("latent alignment: features {:?}, target {:?}", features.dims(), target.dims());
    }
    (features.narrow(1, 0, c)? - target)?.sqr()?.mean_all()? * LATENT_ALIGNMENT_WEIGHT
}

/// Latent-alignment loss (weight [`LATENT_ALIGNMENT_WEIGHT`] included): features (N, 4, 2H/8, 2W/8) at
/// latent size, targets (N, 3, H, W) in [0, 1], `noise` as in [`alignment_target`].
pub fn latent_alignment_loss(encoder: &AutoencoderKL, features: &Tensor, targets: &Tensor, noise: Option<&Tensor>) -> Result<Tensor> {
    latent_alignment_loss_to(features, &alignment_target(encoder, targets, noise)?)
}

/// (out × in) matrix of 1-D linear interpolation with `align_corners=True` (source = o·(in−1)/(out−1)).
fn interp_matrix(out: usize, inp: usize, like: &Tensor) -> Result<Tensor> {
    let mut m = vec![0f32; out * inp];
    for o in 0..out {
        let s = if out > 1 && inp > 1 { o as f32 * ((inp - 1) as f32 / (out - 1) as f32) } else { 0.0 };
        let i0 = (s.floor() as usize).min(inp - 1);
        let i1 = (i0 + 1).min(inp - 1);
        let f = s - i0 as f32;
        m[o * inp + i0] += 1.0 - f;
        m[o * inp + i1] += f;
    }
    Tensor::from_vec(m, (out, inp), like.device())?.to_dtype(like.dtype())
}

/// Bilinear resize with `align_corners=True` (PyTorch `F.interpolate`) as two matrix products, so it has a
/// backward (candle 0.11.1's `upsample_bilinear2d` has none): (N, C, H, W) → (N, C, oh, ow).
pub fn resize_bilinear_align_corners(x: &Tensor, oh: usize, ow: usize) -> Result<Tensor> {
    let (n, c, h, w) = x.dims4()?;
    let aw = interp_matrix(ow, w, x)?;
    let ah = interp_matrix(oh, h, x)?;
    let t = x.reshape((n * c * h, w))?.matmul(&aw.t()?)?; // (N·C·H, ow)
    let t = t.reshape((n * c, h, ow))?.transpose(1, 2)?.contiguous()?.reshape((n * c * ow, h))?;
    let t = t.matmul(&ah.t()?)?; // (N·C·ow, oh)
    t.reshape((n * c, ow, oh))?.transpose(1, 2)?.reshape((n, c, oh, ow))
}

/// Rendered features (N, C, H, W) → concat condition at the latent grid: ×0.25 bilinear, align_corners,
/// output floor(H/4) × floor(W/4) (`F.interpolate(scale_factor=0.25)`). Differentiable.
pub fn features_to_latent(features: &Tensor) -> Result<Tensor> {
    let (_, _, h, w) = features.dims4()?;
    let s = |v: usize| ((v as f64) * FEATURE_SCALE).floor() as usize;
    resize_bilinear_align_corners(features, s(h), s(w))
}
