//! Layers shared by the UNet and the depth predictor (`ldm_unet/util.py`). GroupNorm is composed from
//! differentiable ops (candle's fused norms record no backward); statistics are taken in f32 as the official
//! `GroupNorm8`/`GroupNorm4` do.

use candle_core::{DType, Module, Result, Tensor, D};
use candle_nn::VarBuilder;

/// `nn.Conv2d(c_in, c_out, k, stride, padding)` with bias, PyTorch weight layout `[out, in, k, k]`.
#[derive(Debug, Clone)]
pub struct Conv2d {
    pub weight: Tensor,
    pub bias: Tensor,
    pub stride: usize,
    pub padding: usize,
}

impl Conv2d {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, k: usize, stride: usize, padding: usize) -> Result<Self> {
        Ok(Self { weight: vb.get((c_out, c_in, k, k), "weight")?, bias: vb.get(c_out, "bias")?, stride, padding })
    }

    /// "Same" 3×3 convolution (stride 1, padding 1).
    pub fn same3(vb: VarBuilder, c_in: usize, c_out: usize) -> Result<Self> {
        Self::new(vb, c_in, c_out, 3, 1, 1)
    }
}

/// Largest im2col buffer (values) one convolution call may need; bigger ones run per image, then per band of
/// output rows. At DL3DV size the full-resolution Gaussian head would otherwise allocate ~5 GB at once.
const IM2COL_BUDGET: usize = 48 << 20;

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_budget(x, IM2COL_BUDGET)
    }
}

impl Conv2d {
    fn forward_budget(&self, x: &Tensor, budget: usize) -> Result<Tensor> {
        let (n, cin, h, w) = x.dims4()?;
        let (_, _, k, _) = self.weight.dims4()?;
        let (s, pd) = (self.stride, self.padding);
        if h + 2 * pd < k || w + 2 * pd < k {
            candle_core::bail!("conv2d: kernel {k} larger than padded input {h}x{w}");
        }
        let ho = (h + 2 * pd - k) / s + 1;
        let wo = (w + 2 * pd - k) / s + 1;
        if s == 1 && x.device().is_cpu() && x.dtype() == DType::F32 {
            // The shifted-gemm kernel bands large inputs itself (no im2col buffer): no splitting here, and
            // for inference the bias is fused into its output copy.
            let cfg = mvsplat360_nn::Conv2dConfig { padding: pd, stride: 1, dilation: 1 };
            return if x.track_op() || self.weight.track_op() || self.bias.track_op() {
                mvsplat360_nn::conv2d(x, &self.weight, Some(&self.bias), cfg)
            } else {
                mvsplat360_nn::conv2d_fused(x, &self.weight, Some(&self.bias), cfg, Default::default())
            };
        }
        let per_row = wo * cin * k * k;
        let y = if n * ho * per_row <= budget || k == 1 {
            crate::backbone::conv::conv2d(x, &self.weight, s, pd)?
        } else if ho * per_row <= budget {
            let per = (budget / (ho * per_row)).max(1);
            let parts = (0..n).step_by(per).map(|i| crate::backbone::conv::conv2d(&x.narrow(0, i, per.min(n - i))?, &self.weight, s, pd)).collect::<Result<Vec<_>>>()?;
            Tensor::cat(&parts, 0)?
        } else {
            // Bands of output rows over the zero-padded input (differentiable: pad/narrow/cat).
            let xp = x.pad_with_zeros(2, pd, pd)?.pad_with_zeros(3, pd, pd)?;
            let rows = (budget / per_row).max(1);
            let mut per_image = Vec::with_capacity(n);
            for i in 0..n {
                let xi = xp.narrow(0, i, 1)?;
                let mut bands = Vec::new();
                let mut r0 = 0;
                while r0 < ho {
                    let r1 = (r0 + rows).min(ho);
                    let band = xi.narrow(2, r0 * s, (r1 - 1) * s + k - r0 * s)?;
                    bands.push(crate::backbone::conv::conv2d(&band, &self.weight, s, 0)?);
                    r0 = r1;
                }
                per_image.push(Tensor::cat(&bands, 2)?);
            }
            Tensor::cat(&per_image, 0)?
        };
        y.broadcast_add(&self.bias.reshape((1, (), 1, 1))?)
    }
}

/// `nn.Conv1d(c_in, c_out, 1)` on `[N, C, T]` (weight `[out, in, 1]`), as one matrix product.
#[derive(Debug, Clone)]
pub struct Conv1x1 {
    pub weight: Tensor,
    pub bias: Tensor,
}

impl Conv1x1 {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize) -> Result<Self> {
        Ok(Self { weight: vb.get((c_out, c_in, 1), "weight")?, bias: vb.get(c_out, "bias")? })
    }
}

impl Module for Conv1x1 {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (n, _, _) = x.dims3()?;
        let w = self.weight.squeeze(2)?;
        w.broadcast_left(n)?.matmul(&x.contiguous()?)?.broadcast_add(&self.bias.reshape((1, (), 1))?)
    }
}

/// `nn.GroupNorm(groups, channels)` (eps 1e-5) on `[N, C, ...]`.
#[derive(Debug, Clone)]
pub struct GroupNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    groups: usize,
    eps: f64,
}

impl GroupNorm {
    pub fn new(vb: VarBuilder, groups: usize, channels: usize) -> Result<Self> {
        if groups == 0 || channels % groups != 0 {
            candle_core::bail!("GroupNorm at `{}`: {channels} channels not divisible into {groups} groups", vb.prefix());
        }
        Ok(Self { weight: vb.get(channels, "weight")?, bias: vb.get(channels, "bias")?, groups, eps: 1e-5 })
    }

    /// The UNet's `normalization(channels)`: 8 groups when divisible, else 4.
    pub fn unet(vb: VarBuilder, channels: usize) -> Result<Self> {
        Self::new(vb, if channels % 8 == 0 { 8 } else { 4 }, channels)
    }
}

/// Activation fused after a [`GroupNorm`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Act {
    None,
    Silu,
    Gelu,
}

/// `d = act(a·s + b)`.
#[inline(always)]
fn affine_act_impl(d: &mut [f32], s: &[f32], a: f32, b: f32, act: Act) {
    match act {
        Act::None => d.iter_mut().zip(s).for_each(|(o, &v)| *o = a * v + b),
        Act::Silu => d.iter_mut().zip(s).for_each(|(o, &v)| {
            let y = a * v + b;
            *o = y / (1.0 + crate::backbone::nn::exp_fast(-y));
        }),
        Act::Gelu => d.iter_mut().zip(s).for_each(|(o, &v)| *o = crate::backbone::nn::gelu_scalar(a * v + b)),
    }
}

/// AVX2 build of [`affine_act_impl`] (no FMA: bit-identical to the portable path).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn affine_act_avx2(d: &mut [f32], s: &[f32], a: f32, b: f32, act: Act) {
    affine_act_impl(d, s, a, b, act)
}

fn affine_act(d: &mut [f32], s: &[f32], a: f32, b: f32, act: Act) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is available on this CPU.
        return unsafe { affine_act_avx2(d, s, a, b, act) };
    }
    affine_act_impl(d, s, a, b, act)
}

impl GroupNorm {
    /// `act(GN(x))`. Inference (CPU f32, nothing tracks gradients) runs one fused multi-threaded pass per
    /// (image, group); otherwise the composed, differentiable ops.
    pub fn forward_act(&self, x: &Tensor, act: Act) -> Result<Tensor> {
        let fused = x.device().is_cpu()
            && x.dtype() == DType::F32
            && self.weight.dtype() == DType::F32
            && !(x.track_op() || self.weight.track_op() || self.bias.track_op());
        if !fused {
            let y = self.forward(x)?;
            return match act {
                Act::None => Ok(y),
                Act::Silu => y.silu(),
                Act::Gelu => gelu(&y),
            };
        }
        let dims = x.dims().to_vec();
        let (n, c) = (dims[0], dims[1]);
        let g = self.groups;
        let x = x.contiguous()?;
        let hw = x.elem_count() / (n * c).max(1);
        let (wv, bv) = (self.weight.to_vec1::<f32>()?, self.bias.to_vec1::<f32>()?);
        let xs = x.flatten_all()?;
        let (st, l) = xs.storage_and_layout();
        let src = match (&*st, l.contiguous_offsets()) {
            (candle_core::Storage::Cpu(candle_core::CpuStorage::F32(v)), Some((a, b))) => &v[a..b],
            _ => candle_core::bail!("group norm: expected a contiguous CPU f32 tensor"),
        };
        let cg = c / g;
        let len = cg * hw;
        let mut out = vec![0f32; src.len()];
        use rayon::prelude::*;
        out.par_chunks_mut(len).zip(src.par_chunks(len)).enumerate().for_each(|(task, (dst, xs))| {
            let gi = task % g;
            // Two-pass statistics with f64 partial sums (the official code takes them in f32).
            let sum: f64 = xs.chunks(4096).map(|ch| ch.iter().map(|&v| v as f64).sum::<f64>()).sum();
            let mean = sum / len as f64;
            let var: f64 = xs.chunks(4096).map(|ch| ch.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>()).sum::<f64>() / len as f64;
            let rstd = 1.0 / (var + self.eps).sqrt();
            for ci in 0..cg {
                let ch = gi * cg + ci;
                let a = (wv[ch] as f64 * rstd) as f32;
                let b = (bv[ch] as f64 - mean * wv[ch] as f64 * rstd) as f32;
                affine_act(&mut dst[ci * hw..(ci + 1) * hw], &xs[ci * hw..(ci + 1) * hw], a, b, act);
            }
        });
        drop(st);
        Tensor::from_vec(out, dims, x.device())
    }
}

impl Module for GroupNorm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let (n, c) = (dims[0], dims[1]);
        let in_dtype = x.dtype();
        let xg = x.to_dtype(DType::F32)?.reshape((n, self.groups, ()))?;
        let mean = xg.mean_keepdim(D::Minus1)?;
        let xc = xg.broadcast_sub(&mean)?;
        let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
        let xn = xc.broadcast_div(&(var + self.eps)?.sqrt()?)?.reshape(dims.as_slice())?;
        let mut pshape = vec![1usize; dims.len()];
        pshape[1] = c;
        let w = self.weight.to_dtype(DType::F32)?.reshape(pshape.as_slice())?;
        let b = self.bias.to_dtype(DType::F32)?.reshape(pshape.as_slice())?;
        xn.broadcast_mul(&w)?.broadcast_add(&b)?.to_dtype(in_dtype)
    }
}

/// Exact (erf) GELU, as `nn.GELU()` (the backbone's multi-threaded kernel, with backward, ≤ 1e-6 from
/// candle's `gelu_erf`).
pub fn gelu(x: &Tensor) -> Result<Tensor> {
    crate::backbone::nn::gelu(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// The fused inference GroupNorm(+SiLU/GELU) equals the composed ops (≤ 2e-5).
    #[test]
    fn fused_group_norm_matches_composed() {
        let dev = Device::Cpu;
        let gn = GroupNorm {
            weight: Tensor::randn(1f32, 0.3, 8, &dev).unwrap(),
            bias: Tensor::randn(0f32, 0.3, 8, &dev).unwrap(),
            groups: 4,
            eps: 1e-5,
        };
        let x = (Tensor::randn(0f32, 2.0, (3, 8, 5, 7), &dev).unwrap() + 0.7).unwrap();
        let base = gn.forward(&x).unwrap();
        for (act, want) in [(Act::None, base.clone()), (Act::Silu, base.silu().unwrap()), (Act::Gelu, base.gelu_erf().unwrap())] {
            let got = gn.forward_act(&x, act).unwrap();
            let e = (&got - &want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(e < 2e-5, "{act:?}: max diff {e}");
        }
    }

    #[test]
    fn banded_convolution_equals_direct() {
        let dev = Device::Cpu;
        for &(stride, padding) in &[(1usize, 1usize), (2, 1)] {
            let conv = Conv2d {
                weight: Tensor::randn(0f32, 0.3, (5, 3, 3, 3), &dev).unwrap(),
                bias: Tensor::randn(0f32, 0.3, 5, &dev).unwrap(),
                stride,
                padding,
            };
            let x = Tensor::randn(0f32, 1.0, (2, 3, 11, 9), &dev).unwrap();
            // Independent reference: candle's own convolution plus bias (stride 1 takes the shifted-gemm path,
            // stride 2 the banded im2col path).
            let direct = x
                .conv2d(&conv.weight, padding, stride, 1, 1)
                .unwrap()
                .broadcast_add(&conv.bias.reshape((1, (), 1, 1)).unwrap())
                .unwrap();
            for budget in [1usize, 100, 400] {
                let banded = conv.forward_budget(&x, budget).unwrap();
                let e = (&banded - &direct).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
                assert!(e < 1e-5, "stride {stride} budget {budget}: max diff {e}");
            }
        }
    }
}
