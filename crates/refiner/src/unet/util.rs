//! Numeric building blocks shared by the VideoUNet (sgm `diffusionmodules/util.py`, `attention.py`); the
//! kernels behind them are `mvsplat360_nn`'s (fast CPU paths, composed ops in differentiable mode).

use candle_core::{DType, Device, Result, Tensor, D};

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

/// Linear layer with torch weight layout (out, in).
#[derive(Debug, Clone)]
pub struct Linear {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
}

impl Linear {
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        mvsplat360_nn::linear::linear_fused(x, &self.weight, self.bias.as_ref(), 1.0, &[])
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
