//! Numeric building blocks shared by the VideoUNet (sgm `diffusionmodules/util.py`, `attention.py`); the
//! kernels behind them are `mvsplat360_nn`'s (fast CPU paths, composed ops in differentiable mode).

use std::sync::Arc;

use candle_core::{DType, Device, Result, Tensor, D};
use mvsplat360_nn::bf16::Bf16Weights;
use mvsplat360_nn::conv::bf16::{Bf16ConvWeights, Bf16TemporalWeights};
use mvsplat360_nn::conv::{self, Conv2dConfig, ConvEpilogue};
use mvsplat360_nn::linear;

/// Sinusoidal embedding `[cos(t·f_k), sin(t·f_k)]`, `f_k = exp(-ln(max_period)·k/half)`, computed in f32
/// like sgm `timestep_embedding` / diffusers `Timesteps(flip_sin_to_cos=True, downscale_freq_shift=0)`.
pub fn timestep_embedding(t: &[f32], dim: usize, max_period: f32, device: &Device) -> Result<Tensor> {
    let half = dim / 2;
    let freqs: Vec<f32> = (0..half).map(|k| ((-max_period.ln() * k as f32) / half as f32).exp()).collect();
    let mut out = vec![0f32; t.len() * dim];
    for (i, &ti) in t.iter().enumerate() {
        let row = &mut out[i * dim..(i + 1) * dim];
        for k in 0..half {
            let a = ti * freqs[k];
            row[k] = a.cos();
            row[half + k] = a.sin();
        }
        // odd dim: sgm pads one zero column
    }
    Tensor::from_vec(out, (t.len(), dim), device)
}

/// `torch.linspace(start, end, n)` in f32, with torch's symmetric evaluation (exact endpoints).
pub fn linspace_f32(start: f32, end: f32, n: usize) -> Vec<f32> {
    if n == 1 {
        return vec![start];
    }
    let step = (end - start) / (n - 1) as f32;
    let halfway = n / 2;
    (0..n).map(|i| if i < halfway { start + step * i as f32 } else { end - step * (n - i - 1) as f32 }).collect()
}

/// How a model keeps its products' weights on the CPU (`--dtype`): as loaded (f32, or a GPU's f16/bf16
/// tensors), packed once in bf16 for `vdpbf16ps` (bf16: f32 activations rounded while packed, f32 sums; storage
/// only without AVX512-BF16), or stored in f16 and widened per call for the f32 kernels (f16: half the
/// weights' memory, f32 arithmetic: the CPU has no f16 dot product). Inference only.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WeightStore {
    F32,
    Bf16,
    F16,
}

impl WeightStore {
    /// The store `--dtype` picks on `device` (F32 = the tensors as loaded, in `dtype`, on a GPU).
    pub fn for_dtype(dtype: DType, device: &Device) -> Self {
        match (dtype, device.is_cpu()) {
            (DType::BF16, true) => WeightStore::Bf16,
            (DType::F16, true) => WeightStore::F16,
            _ => WeightStore::F32,
        }
    }
}

/// Linear layer with torch weight layout (out, in), its weight kept as [`WeightStore`] says.
#[derive(Debug, Clone)]
pub struct Linear {
    weight: LinearWeight,
    pub bias: Option<Tensor>,
}

#[derive(Clone)]
enum LinearWeight {
    F32(Tensor),
    Bf16(Arc<Bf16Weights>),
    F16(Tensor),
}

impl std::fmt::Debug for LinearWeight {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LinearWeight::F32(t) => write!(f, "F32({:?})", t.dims()),
            LinearWeight::Bf16(w) => write!(f, "Bf16({}x{})", w.n(), w.k()),
            LinearWeight::F16(t) => write!(f, "F16({:?})", t.dims()),
        }
    }
}

impl LinearWeight {
    /// The weight as the f32 kernels read it (an f16 store widened for this call).
    fn dense(&self) -> Result<Tensor> {
        match self {
            LinearWeight::F32(w) => Ok(w.clone()),
            LinearWeight::F16(w) => w.to_dtype(DType::F32),
            LinearWeight::Bf16(_) => candle_core::bail!("linear: a bf16-packed weight has no dense form"),
        }
    }
}

impl Linear {
    pub fn new(weight: Tensor, bias: Option<Tensor>) -> Self {
        Self { weight: LinearWeight::F32(weight), bias }
    }

    /// `weight` (out, in) kept as `store` says.
    pub fn stored(weight: Tensor, bias: Option<Tensor>, store: WeightStore) -> Result<Self> {
        let weight = match store {
            WeightStore::F32 => LinearWeight::F32(weight),
            WeightStore::Bf16 => LinearWeight::Bf16(Arc::new(Bf16Weights::from_linear(&weight)?)),
            WeightStore::F16 => LinearWeight::F16(weight.to_dtype(DType::F16)?),
        };
        Ok(Self { weight, bias })
    }

    /// Output width.
    pub fn out_dim(&self) -> Result<usize> {
        match &self.weight {
            LinearWeight::F32(w) | LinearWeight::F16(w) => w.dim(0),
            LinearWeight::Bf16(w) => Ok(w.n()),
        }
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_fused(x, 1.0, &[])
    }

    /// `scale·(x @ wᵀ + bias) + Σ cᵢ·addᵢ`.
    pub fn forward_fused(&self, x: &Tensor, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
        match &self.weight {
            LinearWeight::Bf16(w) => linear::linear_fused_bf16(x, w, self.bias.as_ref(), scale, adds),
            dense => linear::linear_fused(x, &dense.dense()?, self.bias.as_ref(), scale, adds),
        }
    }

    /// Channels-first x (N, C, S) → tokens (N, S, O) (see `mvsplat360_nn::linear::linear_from_channels_first`).
    pub fn from_channels_first(&self, x: &Tensor) -> Result<Tensor> {
        let Some(b) = &self.bias else { candle_core::bail!("linear from channels-first without bias") };
        match &self.weight {
            LinearWeight::Bf16(w) => linear::linear_from_channels_first_bf16(x, w, b),
            dense => linear::linear_from_channels_first(x, &dense.dense()?, b),
        }
    }

    /// Tokens h (N, S, K) → channels-first (N, O, S) + residual (see `linear_to_channels_first`).
    pub fn to_channels_first(&self, h: &Tensor, residual: &Tensor) -> Result<Tensor> {
        let Some(b) = &self.bias else { candle_core::bail!("linear to channels-first without bias") };
        match &self.weight {
            LinearWeight::Bf16(w) => linear::linear_to_channels_first_bf16(h, w, b, residual),
            dense => linear::linear_to_channels_first(h, &dense.dense()?, b, residual),
        }
    }
}

/// GEGLU feed-forward `scale·(w2·geglu(w1·x + b1) + b2) + Σ cᵢ·addᵢ` of two [`Linear`]s, both f32 or both bf16.
pub fn geglu_ff(x: &Tensor, proj: &Linear, out: &Linear, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
    let (Some(b1), Some(b2)) = (&proj.bias, &out.bias) else { candle_core::bail!("feed-forward without bias") };
    match (&proj.weight, &out.weight) {
        (LinearWeight::Bf16(w1), LinearWeight::Bf16(w2)) => linear::geglu_ff_bf16(x, w1, b1, w2, b2, scale, adds),
        (LinearWeight::Bf16(_), _) | (_, LinearWeight::Bf16(_)) => candle_core::bail!("feed-forward: both projections must be packed in bf16 or neither"),
        (w1, w2) => linear::geglu_ff(x, &w1.dense()?, b1, &w2.dense()?, b2, scale, adds),
    }
}

/// A convolution weight (Co, C, kh, kw) kept as [`WeightStore`] says. Shared by the UNet's and the VAE's
/// convolutions.
pub enum ConvWeight {
    F32(Tensor),
    Bf16(Bf16ConvWeights),
    F16(Tensor),
}

impl std::fmt::Debug for ConvWeight {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ConvWeight::F32(t) => write!(f, "F32({:?})", t.dims()),
            ConvWeight::Bf16(w) => write!(f, "Bf16({:?})", w.dims()),
            ConvWeight::F16(t) => write!(f, "F16({:?})", t.dims()),
        }
    }
}

impl ConvWeight {
    pub fn new(w: Tensor, store: WeightStore) -> Result<Self> {
        Ok(match store {
            WeightStore::F32 => ConvWeight::F32(w),
            WeightStore::Bf16 => ConvWeight::Bf16(Bf16ConvWeights::from_conv(&w)?),
            WeightStore::F16 => ConvWeight::F16(w.to_dtype(DType::F16)?),
        })
    }

    /// `residual + scale·(conv(x) + bias + item_bias)` (see `mvsplat360_nn::conv::conv2d_epilogue`).
    pub fn conv(&self, x: &Tensor, bias: Option<&Tensor>, cfg: Conv2dConfig, epi: ConvEpilogue) -> Result<Tensor> {
        match self {
            ConvWeight::F32(w) => conv::conv2d_epilogue(x, w, bias, cfg, epi),
            ConvWeight::Bf16(w) => conv::bf16::conv2d_fused_bf16(x, w, bias, cfg, epi),
            ConvWeight::F16(w) => conv::conv2d_epilogue(x, &w.to_dtype(DType::F32)?, bias, cfg, epi),
        }
    }
}

/// The weight of a Conv3d with kernel (kt, 1, 1) on (B·T, C, H, W) frames, as `mvsplat360_nn::conv::temporal_conv`
/// reads it: (Co, kt·C) tap-major (in f16 for [`WeightStore::F16`], widened per call). A trainable weight stays
/// the stored (Co, C, kt, 1, 1) `Var` and is rearranged at every call, so that its updates are seen; CPU
/// `--dtype bf16` packs it once.
pub enum TemporalWeight {
    Var { w5: Tensor, cin: usize, cout: usize },
    TapMajor(Tensor),
    Bf16(Bf16TemporalWeights),
}

impl std::fmt::Debug for TemporalWeight {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TemporalWeight::Var { w5, .. } => write!(f, "Var({:?})", w5.dims()),
            TemporalWeight::TapMajor(t) => write!(f, "TapMajor({:?})", t.dims()),
            TemporalWeight::Bf16(w) => write!(f, "Bf16({:?})", w.dims()),
        }
    }
}

/// (Co, C, kt, 1, 1) → (Co, kt·C), tap-major columns.
fn tap_major(w5: &Tensor, o: usize, i: usize, kt: usize) -> Result<Tensor> {
    w5.reshape((o, i, kt))?.transpose(1, 2)?.contiguous()?.reshape((o, kt * i))
}

impl TemporalWeight {
    /// `w5` (Co, C, kt, 1, 1) as stored.
    pub fn new(w5: Tensor, cout: usize, cin: usize, kt: usize, trainable: bool, store: WeightStore) -> Result<Self> {
        if trainable {
            return Ok(TemporalWeight::Var { w5, cin, cout });
        }
        let wt = tap_major(&w5, cout, cin, kt)?;
        Ok(match store {
            WeightStore::F32 => TemporalWeight::TapMajor(wt),
            WeightStore::Bf16 => TemporalWeight::Bf16(Bf16TemporalWeights::from_temporal(&wt, kt)?),
            WeightStore::F16 => TemporalWeight::TapMajor(wt.to_dtype(DType::F16)?),
        })
    }

    /// `residual + scale·(conv(x) + bias + item_bias)` over clips of `frames` frames.
    #[allow(clippy::too_many_arguments)]
    pub fn conv(
        &self,
        x: &Tensor,
        bias: &Tensor,
        kt: usize,
        frames: usize,
        item_bias: Option<&Tensor>,
        residual: Option<&Tensor>,
        scale: f32,
    ) -> Result<Tensor> {
        match self {
            TemporalWeight::Var { w5, cin, cout } => conv::temporal_conv(x, &tap_major(w5, *cout, *cin, kt)?, bias, kt, frames, item_bias, residual, scale),
            TemporalWeight::TapMajor(w) if w.dtype() != x.dtype() => {
                conv::temporal_conv(x, &w.to_dtype(x.dtype())?, bias, kt, frames, item_bias, residual, scale)
            }
            TemporalWeight::TapMajor(w) => conv::temporal_conv(x, w, bias, kt, frames, item_bias, residual, scale),
            TemporalWeight::Bf16(w) => conv::bf16::temporal_conv_bf16(x, w, bias, kt, frames, item_bias, residual, scale),
        }
    }
}

/// Affine parameters of a GroupNorm / LayerNorm.
#[derive(Debug, Clone)]
pub struct Norm {
    pub weight: Tensor,
    pub bias: Tensor,
    pub eps: f64,
}

impl Norm {
    /// LayerNorm over the last dimension.
    pub fn layer_norm(&self, x: &Tensor) -> Result<Tensor> {
        layer_norm(x, &self.weight, &self.bias, self.eps)
    }

    /// GroupNorm(32) on (N, C, ...); statistics pooled over `frames` consecutive batch items
    /// (frames > 1 reproduces a GroupNorm on the (B, C, T, H, W) tensor of a temporal ResBlock).
    pub fn group_norm(&self, x: &Tensor, groups: usize, frames: usize, silu: bool) -> Result<Tensor> {
        group_norm(x, groups, frames, &self.weight, &self.bias, self.eps, silu)
    }
}

/// LayerNorm over the last dim (see `mvsplat360_nn::norm::layer_norm`).
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    let _p = mvsplat360_nn::prof::scope("layer_norm");
    mvsplat360_nn::norm::layer_norm(x, weight, bias, eps)
}

/// See [`Norm::group_norm`] and `mvsplat360_nn::norm::group_norm`.
pub fn group_norm(x: &Tensor, groups: usize, frames: usize, weight: &Tensor, bias: &Tensor, eps: f64, silu: bool) -> Result<Tensor> {
    let _p = mvsplat360_nn::prof::scope("group_norm");
    mvsplat360_nn::norm::group_norm(x, groups, frames, weight, bias, eps, silu)
}

/// Scaled dot-product attention, heads folded: q (N, Lq, H·d), k/v (N, Lk, H·d); off the fast path the
/// score buffer stays below `max_score_elems` floats (see `mvsplat360_nn::attention::multi_head_attention`).
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, max_score_elems: usize) -> Result<Tensor> {
    let _p = mvsplat360_nn::prof::scope("attention_core");
    mvsplat360_nn::attention::multi_head_attention(q, k, v, heads, max_score_elems)
}

/// Sigmoid of a 1-element mix factor as f64 (AlphaBlender `learned_with_images`, image_only_indicator = 0).
pub fn sigmoid_scalar(t: &Tensor) -> Result<f64> {
    let v = t.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?;
    let m = v.first().copied().unwrap_or(0.0);
    Ok(1.0 / (1.0 + (-m).exp()))
}

/// sgm `AlphaBlender` (`learned_with_images`, image_only_indicator = 0) from ops with a backward:
/// `alpha·a + (1 − alpha)·b`, alpha = sigmoid(mix) as a tensor (mix: 1 element), so `mix` gets a gradient.
pub fn blend_learned(a: &Tensor, b: &Tensor, mix: &Tensor) -> Result<Tensor> {
    let m = mix.flatten_all()?.to_dtype(a.dtype())?.reshape(())?;
    let alpha = (m.neg()?.exp()? + 1.0)?.recip()?;
    let one_minus = alpha.affine(-1.0, 1.0)?;
    a.broadcast_mul(&alpha)?.add(&b.broadcast_mul(&one_minus)?)
}

/// `alpha·a + (1−alpha)·b`.
pub fn blend(a: &Tensor, b: &Tensor, alpha: f64) -> Result<Tensor> {
    mvsplat360_nn::activation::axpby(a, alpha as f32, b, (1.0 - alpha) as f32)
}

/// GEGLU gate: first half times exact-GELU of the second half (sgm/diffusers `GEGLU`).
pub fn geglu(h: &Tensor) -> Result<Tensor> {
    let inner = h.dim(D::Minus1)? / 2;
    let a = h.narrow(D::Minus1, 0, inner)?;
    let g = h.narrow(D::Minus1, inner, inner)?;
    a * g.gelu_erf()?
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linspace_matches_torch_endpoints_and_steps() {
        let l = linspace_f32(1.0, 2.5, 6);
        assert_eq!(l[0], 1.0);
        assert_eq!(l[5], 2.5);
        assert!((l[2] - 1.6).abs() < 1e-6);
    }

    #[test]
    fn timestep_embedding_is_cos_then_sin() {
        let e = timestep_embedding(&[0.0, 2.0], 8, 10000.0, &Device::Cpu).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(&e[0][..4], &[1.0; 4]);
        assert_eq!(&e[0][4..], &[0.0; 4]);
        let f1 = (-(10000f64.ln()) / 4.0).exp();
        assert!((e[1][1] as f64 - (2.0 * f1).cos()).abs() < 1e-6);
        assert!((e[1][5] as f64 - (2.0 * f1).sin()).abs() < 1e-6);
    }
}
