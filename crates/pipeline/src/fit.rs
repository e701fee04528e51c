//! Test-time fitting of the encoder's Gaussians to the context photos (not in the official pipeline; off for
//! official weights, on by default for models whose `config.json` asks for it — the shipped model, see its
//! MODEL.md for what it adds on held-out scenes).
//!
//! Each context view is rendered from the *other* views' Gaussians and compared with its photo, where that
//! render covers the pixel: a view's own Gaussians reproduce its photo whatever their depth, so only the
//! leave-one-out renders say whether the geometry agrees across views. Optimised, with Adam: each Gaussian's
//! distance along its pixel ray (a log scale; its covariance is scaled with it, so its footprint in its own
//! view is unchanged) and its opacity (a logit). Colours, shapes and features stay as the encoder made them.

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{AdamW, Optimizer, ParamsAdamW};
use mvsplat360_camera::Camera;
use mvsplat360_dataset::ImageF32;
use mvsplat360_splat::op::{render as rasterize, RenderOptions};
use mvsplat360_splat::Gaussians;
use serde::{Deserialize, Serialize};

use crate::error::{check_finite, compute, flag, PipelineError, Result};
use crate::progress::Progress;
use mvsplat360_splat::camera::RasterCamera;

/// How the Gaussians are fitted (a model folder's `config.json` key `fit`; `render --fit-steps` overrides the
/// step count).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitSettings {
    /// Adam steps (0 = off).
    pub steps: usize,
    /// Learning rate of the log distance scale; the opacity logits use `opacity_lr_scale` times it.
    pub lr: f64,
    pub opacity_lr_scale: f64,
    /// Pixels count where the leave-one-out render's accumulated opacity is at least this.
    pub min_alpha: f32,
    /// Weight of a second term: each context view rendered from all the Gaussians against its photo (keeps a
    /// view's own Gaussians from fading where the other views disagree with them).
    pub self_weight: f64,
    /// Cosine decay of the rates to 0 over the steps (false: constant). Absent from a file: false.
    #[serde(default)]
    pub cosine: bool,
}

/// Keys that `fit` once had, measured and not adopted; a model folder that still carries one gets an error
/// naming the study. (key, study in docs/research/)
pub const REMOVED_KEYS: &[(&str, &str)] = &[
    ("size_lr_scale", "fit-size-factor.md"),
    ("adam_eps", "fit-adam-eps.md"),
    ("copies", "fit-depth-copies.md"),
    ("copy_ratio", "fit-depth-copies.md"),
    ("copy_opacity", "fit-depth-copies.md"),
    ("sweep", "plane-sweep.md"),
];

/// Off, with the shipped model's validated recipe for `--fit-steps N` on a model folder without `fit`.
impl Default for FitSettings {
    fn default() -> Self {
        Self { steps: 0, lr: 0.03, opacity_lr_scale: 5.0, min_alpha: 0.5, self_weight: 1.0, cosine: true }
    }
}

impl FitSettings {
    pub fn validate(&self) -> Result<()> {
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(flag("fit.lr", format!("must be a positive number, got {}", self.lr)));
        }
        if !(self.opacity_lr_scale.is_finite() && self.opacity_lr_scale >= 0.0) {
            return Err(flag("fit.opacity_lr_scale", format!("must be ≥ 0, got {}", self.opacity_lr_scale)));
        }
        if !(self.self_weight.is_finite() && self.self_weight >= 0.0) {
            return Err(flag("fit.self_weight", format!("must be ≥ 0, got {}", self.self_weight)));
        }
        if !(0.0..1.0).contains(&self.min_alpha) {
            return Err(flag("fit.min_alpha", format!("must be in [0, 1), got {}", self.min_alpha)));
        }
        Ok(())
    }
}

/// A fixed subset of the encoder's Gaussians (all of them, or all but one view's), with what stays constant
/// during the fit gathered once: colours, ray origins, offsets from them, covariances. Latent features are left
/// out: the fit compares RGB only, so rendering them would only cost time.
struct Part {
    /// Indices into the full set (None = all, in order).
    idx: Option<Tensor>,
    origins: Tensor,
    offsets: Tensor,
    covariances: Tensor,
    harmonics: Tensor,
    /// Zero channels.
    features: Tensor,
}

impl Part {
    fn new(g: &Gaussians, origins: &Tensor, idx: Option<Tensor>) -> candle_core::Result<Self> {
        let take = |t: &Tensor| match &idx {
            Some(i) => t.index_select(i, 0),
            None => Ok(t.clone()),
        };
        let means = take(&g.means)?;
        let origins = take(origins)?;
        let offsets = means.sub(&origins)?;
        // Stored (N,K,3) and viewed as (N,3,K): the rasterizer's packing transposes to (N,K·3), then a free reshape.
        let harmonics = take(&g.harmonics)?.transpose(1, 2)?.contiguous()?.transpose(1, 2)?;
        // Zero channels: tested on the CPU kernels (crates/train/tests/fit.rs) and the CUDA ones (splat tests/gpu_op.rs).
        let features = Tensor::zeros((harmonics.dim(0)?, 0, 1), DType::F32, harmonics.device())?;
        Ok(Self { origins, offsets, covariances: take(&g.covariances)?, harmonics, features, idx })
    }
}

/// The per-Gaussian variables of a fit.
struct Vars {
    log_scale: Var,
    logit: Var,
}

impl Vars {
    /// The fitted Gaussians of `part` (its variables gathered by its indices); RGB only.
    fn gaussians(&self, part: &Part) -> candle_core::Result<Gaussians> {
        let take = |v: &Var| match &part.idx {
            Some(i) => v.as_tensor().index_select(i, 0),
            None => Ok(v.as_tensor().clone()),
        };
        let s = take(&self.log_scale)?.exp()?;
        let means = (&part.origins + part.offsets.broadcast_mul(&s)?)?;
        let covariances = part.covariances.broadcast_mul(&s.sqr()?.unsqueeze(2)?)?;
        let opacities = candle_nn::ops::sigmoid(&take(&self.logit)?)?;
        Ok(Gaussians { means, covariances, opacities, harmonics: part.harmonics.clone(), feature_harmonics: part.features.clone() })
    }

    /// The fitted Gaussians with the encoder's colours (contiguous, unlike `all`'s view) and latent features.
    fn result(&self, g: &Gaussians, all: &Part) -> candle_core::Result<Gaussians> {
        let out = self.gaussians(all)?;
        Ok(Gaussians { harmonics: g.harmonics.clone(), feature_harmonics: g.feature_harmonics.clone(), ..out })
    }
}

/// The fitting loss: mean over context views of the leave-one-out render's masked MSE, plus `self_weight` × the
/// MSE of the render from all Gaussians.
fn fit_loss(x: &Vars, all: &Part, others: &[Part], cams: &[Camera], photos: &[Tensor], near: f32, far: f32, s: &FitSettings) -> candle_core::Result<Tensor> {
    let render = |g: &Gaussians, c: &Camera| {
        rasterize(g, &RasterCamera::from_camera(c, near, far), &RenderOptions::default()).map_err(|e| candle_core::Error::Msg(e.to_string()))
    };
    let whole = if s.self_weight > 0.0 { Some(x.gaussians(all)?) } else { None };
    let mut total = Tensor::zeros((), DType::F32, all.origins.device())?;
    for ((part, c), photo) in others.iter().zip(cams).zip(photos) {
        let r = render(&x.gaussians(part)?, c)?;
        let mask = r.alpha.detach().ge(s.min_alpha)?.to_dtype(DType::F32)?;
        total = (total + (r.rgb - photo)?.broadcast_mul(&mask)?.sqr()?.mean_all()?)?;
        if let Some(g) = &whole {
            let r = render(g, c)?;
            total = (total + ((r.rgb - photo)?.sqr()?.mean_all()? * s.self_weight)?)?;
        }
    }
    total / cams.len() as f64
}

/// Fit `g` (the encoder's Gaussians of `cams.len()` views, view-major, the same number per view) to the
/// context photos; returns the fitted Gaussians and the loss before and after.
pub fn fit(
    g: &Gaussians,
    cams: &[Camera],
    photos: &[ImageF32],
    near: f32,
    far: f32,
    s: &FitSettings,
    progress: &dyn Progress,
) -> Result<(Gaussians, [f64; 2])> {
    s.validate()?;
    let stage = "fitting";
    let dev: Device = g.means.device().clone();
    let n = g.means.dim(0).map_err(compute(stage))?;
    let v = cams.len();
    if v < 2 || photos.len() != v || n == 0 || n % v != 0 {
        return Err(PipelineError::Compute {
            stage,
            msg: format!(
                "needs ≥ 2 context views with one photo each and the same number of Gaussians per view (views {v}, photos {}, Gaussians {n})",
                photos.len()
            ),
        });
    }
    let per = n / v;
    let mut origins = Vec::with_capacity(3 * n);
    for c in cams {
        let o = c.center();
        for _ in 0..per {
            origins.extend_from_slice(&[o.x as f32, o.y as f32, o.z as f32]);
        }
    }
    let run = || -> candle_core::Result<(Gaussians, [f64; 2])> {
        let origins = Tensor::from_vec(origins.clone(), (n, 3), &dev)?;
        let detached = g.detach();
        let all = Part::new(&detached, &origins, None)?;
        let others: Vec<Part> = (0..v)
            .map(|j| {
                let idx: Vec<u32> = (0..n as u32).filter(|&i| i as usize / per != j).collect();
                Part::new(&detached, &origins, Some(Tensor::from_vec(idx, n - per, &dev)?))
            })
            .collect::<candle_core::Result<_>>()?;
        let photos: Vec<Tensor> =
            photos.iter().map(|p| Tensor::from_slice(&p.data, (3, p.height as usize, p.width as usize), &dev)).collect::<candle_core::Result<_>>()?;
        let op = detached.opacities.clamp(1e-4f32, 1.0 - 1e-4)?;
        let logit = Var::from_tensor(&(op.log()? - (op.neg()? + 1.0)?.log()?)?)?;
        let log_scale = Var::zeros((n, 1), DType::F32, &dev)?;
        let params = |lr: f64| ParamsAdamW { lr, weight_decay: 0.0, ..ParamsAdamW::default() };
        let mut opt_s = AdamW::new(vec![log_scale.clone()], params(s.lr))?;
        let mut opt_o = AdamW::new(vec![logit.clone()], params(s.lr * s.opacity_lr_scale))?;
        let x = Vars { log_scale, logit };
        let mut first = f64::NAN;
        for step in 0..s.steps {
            if s.cosine {
                let f = 0.5 * (1.0 + (std::f64::consts::PI * step as f64 / s.steps as f64).cos());
                opt_s.set_learning_rate(s.lr * f);
                opt_o.set_learning_rate(s.lr * s.opacity_lr_scale * f);
            }
            let loss = fit_loss(&x, &all, &others, cams, &photos, near, far, s)?;
            let lv = loss.to_scalar::<f32>()? as f64;
            if !lv.is_finite() {
                candle_core::bail!("the fitting loss is {lv}");
            }
            if first.is_nan() {
                first = lv;
            }
            // Each optimiser updates only its own variable from the shared gradient store.
            let grads = loss.backward()?;
            opt_s.step(&grads)?;
            opt_o.step(&grads)?;
            progress.advance(1);
        }
        let last = fit_loss(&x, &all, &others, cams, &photos, near, far, s)?.to_scalar::<f32>()? as f64;
        let out = x.result(&detached, &all)?.detach();
        Ok((out, [if first.is_nan() { last } else { first }, last]))
    };
    progress.begin(stage, s.steps as u64);
    let r = run().map_err(compute(stage));
    progress.end();
    let (out, losses) = r?;
    check_finite("fitting (Gaussian means)", &out.means)?;
    Ok((out, losses))
}
