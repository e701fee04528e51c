//! Numeric building blocks shared by the VideoUNet (sgm `diffusionmodules/util.py`, `attention.py`).
//! CPU f32 fast paths build their outputs directly (no autograd graph); in the kernels' differentiable
//! mode ([`crate::kernels::set_differentiable`]) every function here uses composed candle ops instead.

use candle_core::{DType, Device, Result, Tensor, D};
use rayon::prelude::*;

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
    (0..n)
        .map(|i| if i < halfway { start + step * i as f32 } else { end - step * (n - i - 1) as f32 })
        .collect()
}

/// Linear layer with torch weight layout (out, in).
#[derive(Debug, Clone)]
pub struct Linear {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
}

impl Linear {
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if crate::kernels::is_cpu_f32(x) {
            return crate::kernels::linear_fused(x, &self.weight, self.bias.as_ref(), 1.0, &[]);
        }
        let dims = x.dims().to_vec();
        let last = *dims.last().unwrap_or(&1);
        let out = self.weight.dim(0)?;
        let x2 = x.reshape(((), last))?;
        let mut y = x2.matmul(&self.weight.t()?)?;
        if let Some(b) = &self.bias {
            y = y.broadcast_add(b)?;
        }
        let mut od = dims;
        if let Some(l) = od.last_mut() {
            *l = out;
        }
        y.reshape(od)
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

/// LayerNorm over the last dim. CPU f32 path: per-row two-pass statistics in f64 (candle's fused op
/// uses E[x²]−E[x]² in f32, which loses ~1e-4 on rows with a large mean).
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    let _p = crate::prof::scope("layer_norm");
    let dims = x.dims().to_vec();
    let c = *dims.last().unwrap_or(&1);
    if crate::kernels::is_cpu_f32(x) {
        let w = weight.to_vec1::<f32>()?;
        let b = bias.to_vec1::<f32>()?;
        let mut out = vec![0f32; x.elem_count()];
        crate::kernels::with_f32(x, |data| {
            let rows = (1usize << 14) / c.max(1) + 1;
            out.par_chunks_mut(c * rows).zip(data.par_chunks(c * rows)).for_each(|(dst, src)| layer_norm_rows(src, dst, c, &w, &b, eps));
        })?;
        return Tensor::from_vec(out, dims, x.device());
    }
    let mean = x.mean_keepdim(D::Minus1)?;
    let xc = x.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    xc.broadcast_div(&(var + eps)?.sqrt()?)?.broadcast_mul(weight)?.broadcast_add(bias)
}

/// See [`Norm::group_norm`]. CPU f32 fast path (one stats pass, one write pass), composed ops elsewhere.
pub fn group_norm(
    x: &Tensor,
    groups: usize,
    frames: usize,
    weight: &Tensor,
    bias: &Tensor,
    eps: f64,
    silu: bool,
) -> Result<Tensor> {
    let _p = crate::prof::scope("group_norm");
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    let s: usize = dims[2..].iter().product();
    if c % groups != 0 || n % frames != 0 {
        candle_core::bail!("group_norm: {c} channels / {groups} groups or {n} items / {frames} frames not divisible");
    }
    let cg = c / groups;
    let bn = n / frames;
    if crate::kernels::is_cpu_f32(x) {
        let w = weight.to_vec1::<f32>()?;
        let b = bias.to_vec1::<f32>()?;
        let mut out = vec![0f32; x.elem_count()];
        crate::kernels::with_f32(x, |data| group_norm_cpu(data, &mut out, (bn, frames, groups, cg, c, s), &w, &b, eps, silu))?;
        return Tensor::from_vec(out, dims, x.device());
    }
    let xr = x.reshape((bn, frames, groups, cg * s))?;
    let mean = xr.mean_keepdim(3)?.mean_keepdim(1)?;
    let xc = xr.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(3)?.mean_keepdim(1)?;
    let xn = xc.broadcast_div(&(var + eps)?.sqrt()?)?.reshape((n, c, s))?;
    let y = xn.broadcast_mul(&weight.reshape((1, c, 1))?)?.broadcast_add(&bias.reshape((1, c, 1))?)?;
    let y = if silu { y.silu()? } else { y };
    y.reshape(dims)
}

/// CPU GroupNorm(+SiLU): statistics per (item, group, pooled over frames) in f64, then one fused
/// scale/shift(/SiLU) pass.
#[allow(clippy::too_many_arguments)]
fn group_norm_cpu(data: &[f32], out: &mut [f32], (bn, frames, groups, cg, c, s): (usize, usize, usize, usize, usize, usize), w: &[f32], b: &[f32], eps: f64, silu: bool) {
    let stats: Vec<(f32, f32)> = (0..bn * groups)
        .into_par_iter()
        .map(|idx| {
            let (bi, g) = (idx / groups, idx % groups);
            let mut sum = 0f64;
            let mut sq = 0f64;
            for t in 0..frames {
                let base = ((bi * frames + t) * c + g * cg) * s;
                let (s1, s2) = sum_sq(&data[base..base + cg * s]);
                sum += s1;
                sq += s2;
            }
            let cnt = (frames * cg * s) as f64;
            let mean = sum / cnt;
            let var = (sq / cnt - mean * mean).max(0.0);
            (mean as f32, (1.0 / (var + eps).sqrt()) as f32)
        })
        .collect();
    out.par_chunks_mut(s).enumerate().for_each(|(row, dst)| {
        let item = row / c;
        let ch = row % c;
        let bi = item / frames;
        let (mean, rstd) = stats[bi * groups + ch / cg];
        let a = rstd * w[ch];
        let o = b[ch] - mean * a;
        scale_shift_silu(&data[row * s..(row + 1) * s], dst, a, o, silu);
    });
}

crate::kernels::simd_dispatch! {
    /// (Σx, Σx²) in f64, accumulated per block of 64 values in f32 lanes.
    fn sum_sq(x: &[f32]) -> (f64, f64) {
        let (mut s1, mut s2) = (0f64, 0f64);
        for blk in x.chunks(64) {
            let mut a = [0f32; 16];
            let mut q = [0f32; 16];
            let mut it = blk.chunks_exact(16);
            for c in &mut it {
                for i in 0..16 {
                    a[i] += c[i];
                    q[i] = c[i].mul_add(c[i], q[i]);
                }
            }
            for &v in it.remainder() {
                a[0] += v;
                q[0] = v.mul_add(v, q[0]);
            }
            s1 += a.iter().map(|&v| v as f64).sum::<f64>();
            s2 += q.iter().map(|&v| v as f64).sum::<f64>();
        }
        (s1, s2)
    }
}

crate::kernels::simd_dispatch! {
    fn scale_shift_silu(src: &[f32], dst: &mut [f32], a: f32, o: f32, silu: bool) {
        if silu {
            for (d, &v) in dst.iter_mut().zip(src) {
                let y = v.mul_add(a, o);
                *d = y / (1.0 + crate::kernels::exp_f32(-y));
            }
        } else {
            for (d, &v) in dst.iter_mut().zip(src) {
                *d = v.mul_add(a, o);
            }
        }
    }
}

crate::kernels::simd_dispatch! {
    fn layer_norm_rows(src: &[f32], dst: &mut [f32], c: usize, w: &[f32], b: &[f32], eps: f64) {
        for (s, d) in src.chunks_exact(c).zip(dst.chunks_exact_mut(c)) {
            let mean = s.iter().map(|&v| v as f64).sum::<f64>() / c as f64;
            let var = s.iter().map(|&v| (v as f64 - mean) * (v as f64 - mean)).sum::<f64>() / c as f64;
            let rstd = (1.0 / (var + eps).sqrt()) as f32;
            let m = mean as f32;
            for i in 0..c {
                d[i] = ((s[i] - m) * rstd).mul_add(w[i], b[i]);
            }
        }
    }
}

/// Scaled dot-product attention, heads folded into the batch, computed in blocks of (batch·head, query)
/// so the score buffer stays below `max_score_elems` floats. q: (N, Lq, H·d), k/v: (N, Lk, H·d).
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, max_score_elems: usize) -> Result<Tensor> {
    let _p = crate::prof::scope("attention_core");
    if crate::kernels::is_cpu_f32(q) {
        return crate::kernels::attention_tensors(q, k, v, heads);
    }
    let (n, lq, inner) = q.dims3()?;
    let lk = k.dim(1)?;
    let d = inner / heads;
    let split = |t: &Tensor, l: usize| -> Result<Tensor> {
        t.reshape((n, l, heads, d))?.transpose(1, 2)?.reshape((n * heads, l, d))?.contiguous()
    };
    let scale = 1.0 / (d as f64).sqrt();
    let q = (split(q, lq)? * scale)?;
    let k = split(k, lk)?;
    let v = split(v, lk)?;
    let kt = k.transpose(1, 2)?;
    let nb = n * heads;
    let per_bh = lq * lk;
    let softmax = |s: &Tensor| -> Result<Tensor> {
        if crate::kernels::is_differentiable() {
            crate::kernels::softmax_last_dim_differentiable(s)
        } else {
            candle_nn::ops::softmax_last_dim(s)
        }
    };
    let out = if nb * per_bh <= max_score_elems {
        let s = softmax(&q.matmul(&kt)?)?;
        s.matmul(&v)?
    } else if per_bh <= max_score_elems {
        let bs = (max_score_elems / per_bh).max(1);
        let mut parts = Vec::new();
        let mut i = 0;
        while i < nb {
            let m = bs.min(nb - i);
            let s = softmax(&q.narrow(0, i, m)?.matmul(&kt.narrow(0, i, m)?)?)?;
            parts.push(s.matmul(&v.narrow(0, i, m)?)?);
            i += m;
        }
        Tensor::cat(&parts, 0)?
    } else {
        let qb = (max_score_elems / lk).max(1);
        let mut rows = Vec::with_capacity(nb);
        for bh in 0..nb {
            let (qh, kh, vh) = (q.narrow(0, bh, 1)?, kt.narrow(0, bh, 1)?, v.narrow(0, bh, 1)?);
            let mut parts = Vec::new();
            let mut j = 0;
            while j < lq {
                let m = qb.min(lq - j);
                let s = softmax(&qh.narrow(1, j, m)?.matmul(&kh)?)?;
                parts.push(s.matmul(&vh)?);
                j += m;
            }
            rows.push(Tensor::cat(&parts, 1)?);
        }
        Tensor::cat(&rows, 0)?
    };
    out.reshape((n, heads, lq, d))?.transpose(1, 2)?.reshape((n, lq, inner))
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
    crate::kernels::axpby(a, alpha as f32, b, (1.0 - alpha) as f32)
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
    fn group_norm_fast_path_matches_composed_ops() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (6, 64, 3, 5), &dev).unwrap();
        let w = Tensor::randn(1f32, 0.2, 64, &dev).unwrap();
        let b = Tensor::randn(0f32, 0.1, 64, &dev).unwrap();
        for frames in [1, 3] {
            let fast = group_norm(&x, 32, frames, &w, &b, 1e-5, true).unwrap();
            let slow = group_norm(&x.to_dtype(DType::F64).unwrap(), 32, frames, &w.to_dtype(DType::F64).unwrap(), &b.to_dtype(DType::F64).unwrap(), 1e-5, true)
                .unwrap()
                .to_dtype(DType::F32)
                .unwrap();
            let d = (fast - slow).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(d < 1e-5, "frames {frames}: {d}");
        }
    }

    #[test]
    fn chunked_attention_matches_single_block() {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (3, 17, 8), &dev).unwrap();
        let k = Tensor::randn(0f32, 1.0, (3, 11, 8), &dev).unwrap();
        let v = Tensor::randn(0f32, 1.0, (3, 11, 8), &dev).unwrap();
        let full = attention(&q, &k, &v, 2, usize::MAX).unwrap();
        for budget in [11 * 17 * 2, 11 * 5] {
            let c = attention(&q, &k, &v, 2, budget).unwrap();
            let d = (c - &full).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(d < 1e-6, "budget {budget}: {d}");
        }
        // Closed form on one head: a single key gives back its value.
        let one = attention(&q, &k.narrow(1, 0, 1).unwrap(), &v.narrow(1, 0, 1).unwrap(), 2, usize::MAX).unwrap();
        let d = (one - v.narrow(1, 0, 1).unwrap().broadcast_as((3, 17, 8)).unwrap()).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-6);
    }

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
