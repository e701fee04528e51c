//! sgm `Denoiser(VScalingWithEDMcNoise)`, `EDMDiscretization`, `EulerEDMSampler` (s_churn = 0) and
//! `LinearPredictionGuider`, as MVSplat360 configures them (`svd_wo_mb_fps`).

use candle_core::{Result, Tensor};

use crate::unet::util::{linspace_f32, timestep_embedding};
use crate::unet::{UNetInputs, VideoUNet};

/// Sampler settings; defaults = MVSplat360 (25 steps, σ_max 700, σ_min 0.002, ρ 7, guidance 1 → 2.5, cond_aug 0.02).
#[derive(Debug, Clone, PartialEq)]
pub struct SamplerConfig {
    pub num_steps: usize,
    pub sigma_min: f64,
    pub sigma_max: f64,
    pub rho: f64,
    pub min_scale: f32,
    pub max_scale: f32,
    pub cond_aug: f32,
    /// Local temporal attention windows (MVSplat360 `test_time_attn_num_splits`, 4 for 56-frame videos).
    pub num_splits: Option<usize>,
}

impl Default for SamplerConfig {
    fn default() -> Self {
        Self { num_steps: 25, sigma_min: 0.002, sigma_max: 700.0, rho: 7.0, min_scale: 1.0, max_scale: 2.5, cond_aug: 0.02, num_splits: None }
    }
}

/// EDM (Karras) sigmas, `steps` values from σ_max down to σ_min, then a final 0. Computed in f64 and
/// rounded to f32 (like diffusers' numpy path; sgm's float32 torch path differs by ≤ 1 ulp).
pub fn edm_sigmas(steps: usize, sigma_min: f64, sigma_max: f64, rho: f64) -> Vec<f32> {
    let (lo, hi) = (sigma_min.powf(1.0 / rho), sigma_max.powf(1.0 / rho));
    let mut s: Vec<f32> = (0..steps)
        .map(|i| {
            let r = if steps > 1 { i as f64 / (steps - 1) as f64 } else { 0.0 };
            (hi + r * (lo - hi)).powf(rho) as f32
        })
        .collect();
    s.push(0.0);
    s
}

/// `VScalingWithEDMcNoise`: (c_skip, c_out, c_in, c_noise) for one σ, in f32 like the torch code.
pub fn v_scaling_edm(sigma: f32) -> (f32, f32, f32, f32) {
    let s2 = sigma * sigma + 1.0;
    (1.0 / s2, -sigma / s2.sqrt(), 1.0 / s2.sqrt(), 0.25 * sigma.ln())
}

/// `LinearPredictionGuider` per-frame scales: `linspace(min, max, frames)` over the frames of one UNet call.
pub fn linear_guidance_scales(frames: usize, min_scale: f32, max_scale: f32) -> Vec<f32> {
    linspace_f32(min_scale, max_scale, frames)
}

/// Everything one sampling step produced (for parity tests and debugging).
#[derive(Debug, Clone)]
pub struct StepRecord {
    pub index: usize,
    pub sigma: f32,
    pub c_noise: f32,
    /// (2·B·F, C_in, h, w): [uncond; cond] UNet input.
    pub unet_input: Tensor,
    pub v_uncond: Tensor,
    pub v_cond: Tensor,
    pub v_guided: Tensor,
    pub denoised: Tensor,
    /// Latents after the Euler step.
    pub latents: Tensor,
}

/// Conditioning of one refinement run.
pub struct SampleInputs<'a> {
    /// (B·F, 4, h, w) standard-normal noise.
    pub noise: &'a Tensor,
    /// (B, Lc, D) cross-attention context (the averaged CLIP token), repeated per frame here.
    pub context: &'a Tensor,
    /// (B·F, Cc, h, w) concat condition (resized rendered features).
    pub concat: &'a Tensor,
    pub num_frames: usize,
}

/// Build the [uncond; cond] batch: noisy latent × c_in followed by the concat channels (zeros for uncond).
pub fn guided_unet_input(x: &Tensor, concat: &Tensor, c_in: f32) -> Result<Tensor> {
    let xs = (x * c_in as f64)?;
    let uc = Tensor::cat(&[&xs, &concat.zeros_like()?], 1)?;
    let c = Tensor::cat(&[&xs, concat], 1)?;
    Tensor::cat(&[&uc, &c], 0)
}

/// Per-frame guidance scales as a (B·F, 1, 1, 1) tensor.
fn scale_tensor(scales: &[f32], batch: usize, like: &Tensor) -> Result<Tensor> {
    let v: Vec<f32> = (0..batch).flat_map(|_| scales.iter().copied()).collect();
    Tensor::from_vec(v, (scales.len() * batch, 1, 1, 1), like.device())
}

/// Euler EDM sampling with linear-prediction guidance; returns the final latents (B·F, 4, h, w).
/// `on_step` sees every step's intermediates.
pub fn sample(unet: &VideoUNet, cfg: &SamplerConfig, inp: &SampleInputs, mut on_step: Option<&mut dyn FnMut(&StepRecord)>) -> Result<Tensor> {
    let f = inp.num_frames;
    let n = inp.noise.dim(0)?;
    if f == 0 || n % f != 0 {
        candle_core::bail!("sample: noise batch {n} is not a multiple of num_frames {f}");
    }
    let b = n / f;
    let (bc, lc, dc) = inp.context.dims3()?;
    if bc != b {
        candle_core::bail!("sample: context batch {bc} != videos {b}");
    }
    // Context per frame, [uncond (zeros); cond].
    let ctx = inp.context.unsqueeze(1)?.broadcast_as((b, f, lc, dc))?.reshape((n, lc, dc))?;
    let ctx2 = Tensor::cat(&[&ctx.zeros_like()?, &ctx], 0)?;
    // Vector condition: sinusoidal embedding of cond_aug, identical for both branches.
    let y = match unet.cfg.adm_in_channels {
        Some(adm) => Some(timestep_embedding(&vec![cfg.cond_aug; 2 * n], adm, 10000.0, inp.noise.device())?),
        None => None,
    };
    let sigmas = edm_sigmas(cfg.num_steps, cfg.sigma_min, cfg.sigma_max, cfg.rho);
    let scales = scale_tensor(&linear_guidance_scales(f, cfg.min_scale, cfg.max_scale), b, inp.noise)?;
    let mut x = (inp.noise * ((1.0 + sigmas[0] * sigmas[0]).sqrt()) as f64)?;
    for i in 0..cfg.num_steps {
        let sigma = sigmas[i];
        let (c_skip, c_out, c_in, c_noise) = v_scaling_edm(sigma);
        let unet_input = guided_unet_input(&x, inp.concat, c_in)?;
        let ts = vec![c_noise; 2 * n];
        let v = unet.forward(&UNetInputs { x: &unet_input, timesteps: &ts, context: &ctx2, y: y.as_ref(), num_video_frames: f, num_splits: cfg.num_splits })?;
        let v_u = v.narrow(0, 0, n)?;
        let v_c = v.narrow(0, n, n)?;
        // Guidance on v (diffusers order); sgm guides the denoised outputs — algebraically identical.
        let v_g = (&v_u + (&v_c - &v_u)?.broadcast_mul(&scales)?)?;
        let denoised = ((&v_g * c_out as f64)? + (&x * c_skip as f64)?)?;
        let d = ((&x - &denoised)? / sigma as f64)?;
        x = (&x + (d * (sigmas[i + 1] - sigma) as f64)?)?;
        if let Some(cb) = on_step.as_mut() {
            cb(&StepRecord { index: i, sigma, c_noise, unet_input, v_uncond: v_u, v_cond: v_c, v_guided: v_g, denoised, latents: x.clone() });
        }
    }
    Ok(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edm_sigmas_closed_form_endpoints() {
        let s = edm_sigmas(25, 0.002, 700.0, 7.0);
        assert_eq!(s.len(), 26);
        assert!((s[0] - 700.0).abs() < 1e-3);
        assert!((s[24] - 0.002).abs() < 1e-8);
        assert_eq!(s[25], 0.0);
        assert!(s.windows(2).all(|w| w[0] > w[1]));
    }

    #[test]
    fn v_scaling_reconstructs_v_prediction_identity() {
        // x = x0 + σε and the v-target (ε − σ·x0)/√(σ²+1): the denoiser must return x0 exactly.
        let (sigma, x0, eps) = (3.0f32, 0.7f32, -1.3f32);
        let x = x0 + sigma * eps;
        let v = (eps - sigma * x0) / (sigma * sigma + 1.0).sqrt();
        let (c_skip, c_out, c_in, c_noise) = v_scaling_edm(sigma);
        assert!((v * c_out + x * c_skip - x0).abs() < 1e-5);
        assert!((c_in - 1.0 / 10f32.sqrt()).abs() < 1e-7);
        assert!((c_noise - 0.25 * 3f32.ln()).abs() < 1e-7);
    }
}
