//! DISTS (Ding et al. 2020): structure and texture similarity on VGG16 features with L2 pooling — the
//! `DISTS_pytorch` package's `DISTS()(x, y)` for inputs in [0, 1]. Weights: `vgg16.safetensors` (torchvision's
//! ImageNet VGG16, which DISTS uses) and `dists.safetensors` (its alpha / beta) of the weights folder.

use std::path::Path;

use candle_core::{DType, Device, Result, Tensor};

use crate::lpips::as_batch;
use crate::nets::{filter2d, spatial_mean, vgg::Vgg16};
use crate::weights::{self, files, MetricsWeightsError};

/// Channels of the six compared representations: the image itself, then relu1_2 … relu5_3.
const CHANNELS: [usize; 6] = [3, 64, 128, 256, 512, 512];
/// Pairs per network pass in [`Dists::distance`].
const CHUNK: usize = 4;
const C1: f64 = 1e-6;
const C2: f64 = 1e-6;
/// `np.hanning(5)[1:-1]` = [0.5, 1, 0.5], normalised so that its outer product sums to 1.
const L2POOL_TAPS: [f64; 3] = [0.25, 0.5, 0.25];

/// The DISTS metric with its pretrained weights.
#[derive(Debug, Clone)]
pub struct Dists {
    vgg: Vgg16,
    /// alpha / (Σalpha + Σbeta), beta / (Σalpha + Σbeta), split per representation: (1, C_k).
    alpha: Vec<Tensor>,
    beta: Vec<Tensor>,
    mean: Tensor,
    std: Tensor,
}

impl Dists {
    /// Loads the weights located through [`weights::locate`] (`weights_dir` = `--weights-dir`).
    pub fn load(weights_dir: Option<&Path>, device: &Device) -> std::result::Result<Self, MetricsWeightsError> {
        let vw = weights::load_file(weights_dir, files::VGG16, device)?;
        let dw = weights::load_file(weights_dir, files::DISTS, device)?;
        let vgg = Vgg16::load(&vw, device)?;
        let total: usize = CHANNELS.iter().sum();
        let alpha = dw.get("alpha", &[1, total, 1, 1])?.reshape((1, total))?;
        let beta = dw.get("beta", &[1, total, 1, 1])?.reshape((1, total))?;
        let w_sum = (alpha.sum_all()? + beta.sum_all()?)?;
        let (alpha, beta) = (alpha.broadcast_div(&w_sum)?, beta.broadcast_div(&w_sum)?);
        let mut a = Vec::new();
        let mut b = Vec::new();
        let mut off = 0;
        for &c in &CHANNELS {
            a.push(alpha.narrow(1, off, c)?);
            b.push(beta.narrow(1, off, c)?);
            off += c;
        }
        let mean = Tensor::from_slice(&[0.485f32, 0.456, 0.406], (1, 3, 1, 1), device)?;
        let std = Tensor::from_slice(&[0.229f32, 0.224, 0.225], (1, 3, 1, 1), device)?;
        Ok(Self { vgg, alpha: a, beta: b, mean, std })
    }

    /// The six representations of a batch in [0, 1].
    fn features(&self, x: &Tensor) -> Result<Vec<Tensor>> {
        let mut h = x.broadcast_sub(&self.mean)?.broadcast_div(&self.std)?;
        let mut out = vec![x.clone()];
        for s in 0..5 {
            if s > 0 {
                h = l2_pool(&h)?;
            }
            h = self.vgg.stage(s, &h)?;
            out.push(h.clone());
        }
        Ok(out)
    }

    /// Per-pair DISTS (N) of `a`, `b`: (N, 3, H, W) in [0, 1]. Built from differentiable ops.
    pub fn forward(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        let (a, b) = (as_batch(a)?, as_batch(b)?);
        if a.dims() != b.dims() || a.dim(1)? != 3 {
            candle_core::bail!("dists: inputs {:?} and {:?}, expected two (N, 3, H, W)", a.dims(), b.dims());
        }
        let n = a.dim(0)?;
        let x = Tensor::cat(&[&a, &b], 0)?.to_dtype(DType::F32)?;
        let feats = self.features(&x)?;
        let mut dist: Option<Tensor> = None;
        for (k, f) in feats.iter().enumerate() {
            let (fx, fy) = (f.narrow(0, 0, n)?, f.narrow(0, n, n)?);
            let (xm, ym) = (spatial_mean(&fx)?, spatial_mean(&fy)?); // (N, C)
            let s1 = ((((&xm * &ym)? * 2.0)? + C1)? / ((xm.sqr()? + ym.sqr()?)? + C1)?)?;
            let xm4 = xm.unsqueeze(2)?.unsqueeze(3)?;
            let ym4 = ym.unsqueeze(2)?.unsqueeze(3)?;
            let xv = spatial_mean(&fx.broadcast_sub(&xm4)?.sqr()?)?;
            let yv = spatial_mean(&fy.broadcast_sub(&ym4)?.sqr()?)?;
            let cov = (spatial_mean(&(&fx * &fy)?)? - (&xm * &ym)?)?;
            let s2 = (((cov * 2.0)? + C2)? / ((xv + yv)? + C2)?)?;
            let d = (s1.broadcast_mul(&self.alpha[k])?.sum(1)? + s2.broadcast_mul(&self.beta[k])?.sum(1)?)?;
            dist = Some(match dist {
                None => d,
                Some(t) => (t + d)?,
            });
        }
        dist.expect("six representations").affine(-1.0, 1.0)
    }

    /// Per-pair DISTS of `a`, `b` ((N, 3, H, W) or (3, H, W) in [0, 1]), `CHUNK` pairs at a time.
    pub fn distance(&self, a: &Tensor, b: &Tensor) -> Result<Vec<f32>> {
        let (a, b) = (as_batch(a)?, as_batch(b)?);
        let n = a.dim(0)?;
        let mut out = Vec::with_capacity(n);
        for s in (0..n).step_by(CHUNK) {
            let m = CHUNK.min(n - s);
            out.extend(self.forward(&a.narrow(0, s, m)?, &b.narrow(0, s, m)?)?.to_vec1::<f32>()?);
        }
        Ok(out)
    }
}

/// DISTS' L2pooling: sqrt(hanning-filter(x², stride 2, padding 1) + 1e-12), per channel.
fn l2_pool(x: &Tensor) -> Result<Tensor> {
    (filter2d(&x.sqr()?, &L2POOL_TAPS, 2, 1)? + 1e-12)?.sqrt()
}
