//! Small building blocks shared by the backbone. Trainable inputs (tensors that track gradients) take composed
//! ops, because candle's fused layer_norm / softmax_last_dim record no backward; inference takes the fused ones.

use candle_core::{DType, Module, Result, Tensor, D};
use candle_nn::VarBuilder;

/// Softmax over the last dimension.
pub fn softmax_last(x: &Tensor) -> Result<Tensor> {
    if x.track_op() {
        let max = x.max_keepdim(D::Minus1)?;
        let e = x.broadcast_sub(&max)?.exp()?;
        e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
    } else {
        candle_nn::ops::softmax_last_dim(x)
    }
}

/// `nn.LayerNorm(d)` with affine parameters (eps 1e-5).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    pub fn new(vb: VarBuilder, d: usize) -> Result<Self> {
        Ok(Self { weight: vb.get(d, "weight")?, bias: vb.get(d, "bias")?, eps: 1e-5 })
    }
}

impl Module for LayerNorm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if x.track_op() || self.weight.track_op() {
            let mean = x.mean_keepdim(D::Minus1)?;
            let xc = x.broadcast_sub(&mean)?;
            let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
            xc.broadcast_div(&(var + self.eps)?.sqrt()?)?.broadcast_mul(&self.weight)?.broadcast_add(&self.bias)
        } else {
            candle_nn::ops::layer_norm(&x.contiguous()?, &self.weight, &self.bias, self.eps as f32)
        }
    }
}

/// `nn.InstanceNorm2d(c)` as used by the UniMatch CNN: no affine parameters, no running stats, eps 1e-5.
pub fn instance_norm(x: &Tensor) -> Result<Tensor> {
    let (n, c, h, w) = x.dims4()?;
    let xf = x.reshape((n, c, h * w))?;
    let mean = xf.mean_keepdim(D::Minus1)?;
    let xc = xf.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    xc.broadcast_div(&(var + 1e-5)?.sqrt()?)?.reshape((n, c, h, w))
}

/// 2-D convolution with PyTorch's weight layout `[out, in, kh, kw]` (square kernel, symmetric padding).
#[derive(Debug, Clone)]
pub struct Conv2d {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
    pub stride: usize,
    pub padding: usize,
}

impl Conv2d {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, k: usize, stride: usize, padding: usize, bias: bool) -> Result<Self> {
        let weight = vb.get((c_out, c_in, k, k), "weight")?;
        let bias = if bias { Some(vb.get(c_out, "bias")?) } else { None };
        Ok(Self { weight, bias, stride, padding })
    }
}

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = crate::backbone::conv::conv2d(x, &self.weight, self.stride, self.padding)?;
        match &self.bias {
            Some(b) => y.broadcast_add(&b.reshape((1, b.dim(0)?, 1, 1))?),
            None => Ok(y),
        }
    }
}

/// Bias-free linear layer, weight `[out, in]`, applied to the last dimension of any-rank input.
#[derive(Debug, Clone)]
pub struct LinearNoBias {
    pub weight: Tensor,
}

impl LinearNoBias {
    pub fn new(vb: VarBuilder, d_in: usize, d_out: usize) -> Result<Self> {
        Ok(Self { weight: vb.get((d_out, d_in), "weight")? })
    }
}

impl Module for LinearNoBias {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let d_in = dims[dims.len() - 1];
        let rows = x.elem_count() / d_in.max(1);
        let y = x.reshape((rows, d_in))?.matmul(&self.weight.t()?)?;
        let mut out = dims;
        let last = out.len() - 1;
        out[last] = self.weight.dim(0)?;
        y.reshape(out)
    }
}

pub fn ensure_f32(x: &Tensor, what: &str) -> Result<()> {
    if x.dtype() != DType::F32 {
        candle_core::bail!("{what}: expected f32, got {:?}", x.dtype())
    }
    Ok(())
}

/// erf in f32 (Abramowitz & Stegun 7.1.26, |error| ≤ 1.5e-7 plus f32 rounding), branch-free.
#[inline(always)]
fn erf_fast(x: f32) -> f32 {
    let a = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * a);
    let poly = ((((1.061_405_4 * t - 1.453_152_1) * t + 1.421_413_8) * t - 0.284_496_74) * t + 0.254_829_6) * t;
    let y = 1.0 - poly * exp_fast(-a * a);
    y.copysign(x)
}

/// Scalar exact-form GELU with the fast erf (as the [`gelu`] kernel).
#[inline(always)]
pub fn gelu_scalar(x: f32) -> f32 {
    0.5 * x * (1.0 + erf_fast(x * std::f32::consts::FRAC_1_SQRT_2))
}

/// Exact-form GELU `x·Φ(x)` (PyTorch `nn.GELU()`), multi-threaded, with backward.
struct GeluErf;
/// Its derivative `Φ(x) + x·φ(x)`.
struct GeluErfGrad;

#[inline(always)]
fn map_chunk_impl<F: Fn(f32) -> f32>(d: &mut [f32], s: &[f32], f: F) {
    for (o, &i) in d.iter_mut().zip(s) {
        *o = f(i);
    }
}

/// AVX2 build of the elementwise loop (the default target vectorises only 4 lanes); no FMA, so the results are
/// bit-identical to the portable path.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn map_chunk_avx2<F: Fn(f32) -> f32>(d: &mut [f32], s: &[f32], f: F) {
    map_chunk_impl(d, s, f)
}

fn map_chunk<F: Fn(f32) -> f32>(d: &mut [f32], s: &[f32], f: F) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is available on this CPU.
        return unsafe { map_chunk_avx2(d, s, f) };
    }
    map_chunk_impl(d, s, f)
}

fn map_par(storage: &candle_core::CpuStorage, layout: &candle_core::Layout, f: impl Fn(f32) -> f32 + Sync, name: &str) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
    use rayon::prelude::*;
    let src = match storage {
        candle_core::CpuStorage::F32(v) => v,
        _ => candle_core::bail!("{name}: only f32 is supported"),
    };
    let src = match layout.contiguous_offsets() {
        Some((a, b)) => &src[a..b],
        None => candle_core::bail!("{name}: input must be contiguous"),
    };
    let mut dst = vec![0f32; src.len()];
    dst.par_chunks_mut(1 << 14).zip(src.par_chunks(1 << 14)).for_each(|(d, s)| map_chunk(d, s, &f));
    Ok((candle_core::CpuStorage::F32(dst), layout.shape().clone()))
}

impl candle_core::CustomOp1 for GeluErf {
    fn name(&self) -> &'static str {
        "gelu-erf-par"
    }
    fn cpu_fwd(&self, s: &candle_core::CpuStorage, l: &candle_core::Layout) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        map_par(s, l, |x| 0.5 * x * (1.0 + erf_fast(x * std::f32::consts::FRAC_1_SQRT_2)), self.name())
    }
    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let d = arg.contiguous()?.apply_op1_no_bwd(&GeluErfGrad)?;
        Ok(Some(grad_res.mul(&d)?))
    }
}

impl candle_core::CustomOp1 for GeluErfGrad {
    fn name(&self) -> &'static str {
        "gelu-erf-grad"
    }
    fn cpu_fwd(&self, s: &candle_core::CpuStorage, l: &candle_core::Layout) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        map_par(
            s,
            l,
            |x| {
                let cdf = 0.5 * (1.0 + erf_fast(x * std::f32::consts::FRAC_1_SQRT_2));
                let pdf = exp_fast(-0.5 * x * x) * 0.398_942_3;
                cdf + x * pdf
            },
            self.name(),
        )
    }
}

/// GELU (erf form). Uses the multi-threaded CPU kernel on the CPU, candle's `gelu_erf` elsewhere.
pub fn gelu(x: &Tensor) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == DType::F32 {
        x.contiguous()?.apply_op1(GeluErf)
    } else {
        x.gelu_erf()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// exp_fast within 3e-7 relative of f64 exp over the softmax range; the fused (masked) softmax equals the
    /// composed definition to 1e-6.
    #[test]
    fn fused_softmax_matches_composed() -> Result<()> {
        assert_eq!(exp_fast(-86.5), 0.0);
        assert_eq!(exp_fast(f32::NEG_INFINITY), 0.0);
        for i in 0..=20000 {
            let x = -86.0 + i as f32 * 0.0043;
            let e = (x as f64).exp();
            let rel = ((exp_fast(x) as f64 - e) / e).abs();
            assert!(rel < 3e-7, "exp_fast({x}) rel err {rel}");
        }
        let dev = Device::Cpu;
        let scores = (Tensor::randn(0f32, 3.0, (6, 5, 37), &dev)?).contiguous()?;
        let mask = Tensor::randn(0f32, 1.0, (3, 5, 37), &dev)?.ge(0.5)?.to_dtype(DType::F32)?.affine(-100.0, 0.0)?;
        let got = masked_softmax(&scores, Some(&mask))?;
        let want = {
            let x = scores.reshape((2, 3, 5, 37))?.broadcast_add(&mask)?.reshape((6, 5, 37))?;
            let e = (x.broadcast_sub(&x.max_keepdim(2)?))?.exp()?;
            e.broadcast_div(&e.sum_keepdim(2)?)?
        };
        let d = (got - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert!(d < 1e-6, "masked softmax diff {d}");
        let got = masked_softmax(&scores, None)?;
        let want = candle_nn::ops::softmax_last_dim(&scores)?;
        let d = (got - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert!(d < 1e-6, "softmax diff {d}");
        Ok(())
    }

    /// Fast GELU against candle's reference `gelu_erf` (≤ 1e-6 abs) and its gradient against central differences.
    #[test]
    fn gelu_matches_reference_and_fd() -> Result<()> {
        let xs: Vec<f32> = (0..2001).map(|i| -10.0 + i as f32 * 0.01).collect();
        let x = Tensor::new(xs.as_slice(), &Device::Cpu)?;
        let a: Vec<f32> = gelu(&x)?.to_vec1()?;
        let b: Vec<f32> = x.gelu_erf()?.to_vec1()?;
        let err = a.iter().zip(&b).map(|(p, q)| (p - q).abs()).fold(0f32, f32::max);
        assert!(err <= 1e-6, "gelu err {err}");
        let v = candle_core::Var::from_tensor(&x.to_dtype(DType::F64)?.to_dtype(DType::F32)?)?;
        let g = gelu(v.as_tensor())?.sum_all()?.backward()?;
        let g: Vec<f32> = g.get(v.as_tensor()).expect("grad").to_vec1()?;
        for (i, &xi) in xs.iter().enumerate().step_by(37) {
            let h = 1e-3f64;
            let f = |t: f64| 0.5 * t * (1.0 + erf_fast((t / std::f64::consts::SQRT_2) as f32) as f64);
            let fd = (f(xi as f64 + h) - f(xi as f64 - h)) / (2.0 * h);
            assert!((fd - g[i] as f64).abs() < 2e-4, "x {xi}: fd {fd} vs {}", g[i]);
        }
        Ok(())
    }
}

/// `exp(x)` in f32 for the softmax kernel: range reduction to `r ∈ [−ln2/2, ln2/2]` and a degree-7 Taylor
/// polynomial (relative error ≤ 1e-8 before rounding), branch-free so the compiler vectorises it. Inputs below
/// −86 give exactly 0: their true value (< 5e-38) is irrelevant next to a softmax row maximum of 1, and
/// denormal outputs would make every later multiply (the attention·V gemm) many times slower.
#[inline(always)]
pub fn exp_fast(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    const ROUND: f32 = 12_582_912.0; // 1.5·2^23: adding and subtracting rounds to the nearest integer
    let tiny = x < -86.0;
    let x = x.clamp(-86.0, 88.0);
    let n = (x * LOG2E + ROUND) - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    let y = p * f32::from_bits(((n as i32 + 127) as u32) << 23);
    if tiny {
        0.0
    } else {
        y
    }
}

/// Inference kernel: softmax over the last dim of `scores [R, S]`, optionally after adding `mask [P, S]` to row
/// `r` as mask row `r mod P` — one multi-threaded pass instead of add + max + sub + exp + sum + div.
struct FusedSoftmax;

fn softmax_rows(x: &[f32], mask: Option<&[f32]>, s: usize) -> Vec<f32> {
    use rayon::prelude::*;
    let mut dst = vec![0f32; x.len()];
    let p = mask.map(|m| m.len() / s.max(1)).unwrap_or(1).max(1);
    dst.par_chunks_mut(s).zip(x.par_chunks(s)).enumerate().for_each(|(r, (d, xr))| {
        match mask {
            Some(m) => {
                let mr = &m[(r % p) * s..(r % p + 1) * s];
                d.iter_mut().zip(xr.iter().zip(mr)).for_each(|(o, (&a, &b))| *o = a + b);
            }
            None => d.copy_from_slice(xr),
        }
        let mx = d.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        d.iter_mut().for_each(|o| *o = exp_fast(*o - mx));
        // 8 partial sums: vectorisable and slightly more accurate than one running sum.
        let mut acc = [0f32; 8];
        let mut chunks = d.chunks_exact(8);
        for c in &mut chunks {
            for i in 0..8 {
                acc[i] += c[i];
            }
        }
        let sum: f32 = acc.iter().sum::<f32>() + chunks.remainder().iter().sum::<f32>();
        let inv = 1.0 / sum;
        d.iter_mut().for_each(|o| *o *= inv);
    });
    dst
}

fn f32_slice<'a>(s: &'a candle_core::CpuStorage, l: &candle_core::Layout, name: &str) -> Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (candle_core::CpuStorage::F32(v), Some((a, b))) => Ok(&v[a..b]),
        _ => candle_core::bail!("{name}: needs a contiguous f32 tensor"),
    }
}

impl candle_core::CustomOp1 for FusedSoftmax {
    fn name(&self) -> &'static str {
        "fused-softmax"
    }
    fn cpu_fwd(&self, s1: &candle_core::CpuStorage, l1: &candle_core::Layout) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = f32_slice(s1, l1, self.name())?;
        let s = *l1.dims().last().unwrap_or(&1);
        Ok((candle_core::CpuStorage::F32(softmax_rows(x, None, s)), l1.shape().clone()))
    }
}

impl candle_core::CustomOp2 for FusedSoftmax {
    fn name(&self) -> &'static str {
        "fused-masked-softmax"
    }
    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = f32_slice(s1, l1, "fused-masked-softmax")?;
        let m = f32_slice(s2, l2, "fused-masked-softmax")?;
        let s = *l1.dims().last().unwrap_or(&1);
        Ok((candle_core::CpuStorage::F32(softmax_rows(x, Some(m), s)), l1.shape().clone()))
    }
}

/// `softmax(scores + mask)` over the last dim; `scores [R, Lw, S]`, `mask [P, Lw, S]` with `R` a multiple of `P`
/// (mask tiled over the leading dim). Composed (differentiable) ops when gradients are tracked.
pub fn masked_softmax(scores: &Tensor, mask: Option<&Tensor>) -> Result<Tensor> {
    let fused = !scores.track_op() && scores.device().is_cpu() && scores.dtype() == DType::F32;
    let (r, lw, s) = scores.dims3()?;
    match mask {
        None if fused => scores.contiguous()?.apply_op1_no_bwd(&FusedSoftmax),
        None => softmax_last(scores),
        Some(mask) if fused => {
            let m = mask.contiguous()?;
            let p = m.elem_count() / s;
            scores.contiguous()?.reshape((r * lw, s))?.apply_op2_no_bwd(&m.reshape((p, s))?, &FusedSoftmax)?.reshape((r, lw, s))
        }
        Some(mask) => {
            let p = mask.dim(0)?;
            let x = scores.reshape((r / p, p, lw, s))?.broadcast_add(mask)?.reshape((r, lw, s))?;
            softmax_last(&x)
        }
    }
}
