//! Elementwise ops: exact-erf GELU and the fused blend `a·ca + b·cb`. Two GELU kernels keep their models'
//! numerics: [`gelu`] (encoder: a custom op with backward, no FMA) and [`gelu_inference`] (refiner: FMA,
//! vectorised to the machine's width, no backward outside differentiable mode). Other devices: candle's ops.

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use crate::math::{erf_fast, exp_fast, gelu_f32, gelu_scalar, simd_dispatch};
use crate::mode::{cpu_f32, is_cpu_f32, with_f32};

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

fn map_par(
    storage: &candle_core::CpuStorage,
    layout: &candle_core::Layout,
    f: impl Fn(f32) -> f32 + Sync,
    name: &str,
) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
    let src = crate::mode::f32_slice(storage, layout, name)?;
    let mut dst = vec![0f32; src.len()];
    dst.par_chunks_mut(1 << 14).zip(src.par_chunks(1 << 14)).for_each(|(d, s)| map_chunk(d, s, &f));
    Ok((candle_core::CpuStorage::F32(dst), layout.shape().clone()))
}

/// [`gelu`]'s values in place (the same expression and instruction choice: no FMA), for kernels that apply it
/// as an epilogue instead of writing an intermediate.
pub(crate) fn gelu_erf_in_place(d: &mut [f32]) {
    #[inline(always)]
    fn imp(d: &mut [f32]) {
        for v in d {
            *v = gelu_scalar(*v);
        }
    }
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        unsafe fn avx2(d: &mut [f32]) {
            imp(d)
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is available on this CPU.
            return unsafe { avx2(d) };
        }
    }
    imp(d)
}

impl candle_core::CustomOp1 for GeluErf {
    fn name(&self) -> &'static str {
        "gelu-erf-par"
    }
    fn cpu_fwd(&self, s: &candle_core::CpuStorage, l: &candle_core::Layout) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        map_par(s, l, gelu_scalar, self.name())
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

/// GELU (erf form), as `nn.GELU()`: the multi-threaded CPU kernel (≤ 1e-6 from candle's `gelu_erf`, with
/// backward) on CPU f32, candle's `gelu_erf` elsewhere.
pub fn gelu(x: &Tensor) -> Result<Tensor> {
    if cpu_f32(x) {
        x.contiguous()?.apply_op1(GeluErf)
    } else {
        x.gelu_erf()
    }
}

/// Exact-erf GELU, vectorised on CPU f32 outside differentiable mode (no backward there).
pub fn gelu_inference(x: &Tensor) -> Result<Tensor> {
    if !is_cpu_f32(x) {
        return x.gelu_erf();
    }
    let mut v = with_f32(x, |d| d.to_vec())?;
    v.par_chunks_mut(1 << 14).for_each(gelu_inplace);
    Tensor::from_vec(v, x.dims(), x.device())
}

/// `a·ca + b·cb` in one pass (same shapes).
pub fn axpby(a: &Tensor, ca: f32, b: &Tensor, cb: f32) -> Result<Tensor> {
    if !is_cpu_f32(a) || a.dims() != b.dims() {
        return (a * ca as f64)? + (b * cb as f64)?;
    }
    let mut out = vec![0f32; a.elem_count()];
    with_f32(a, |ad| {
        with_f32(b, |bd| {
            out.par_chunks_mut(1 << 14).zip(ad.par_chunks(1 << 14)).zip(bd.par_chunks(1 << 14)).for_each(|((o, x), y)| axpby_chunk(o, x, ca, y, cb))
        })
    })??;
    Tensor::from_vec(out, a.dims(), a.device())
}

simd_dispatch! {
    fn axpby_chunk(o: &mut [f32], x: &[f32], ca: f32, y: &[f32], cb: f32) {
        for ((o, &x), &y) in o.iter_mut().zip(x).zip(y) {
            *o = ca.mul_add(x, cb * y);
        }
    }
}

simd_dispatch! {
    pub(crate) fn gelu_inplace(x: &mut [f32]) {
        for v in x {
            *v = gelu_f32(*v);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

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

    #[test]
    fn gelu_inference_matches_candle() {
        let x = Tensor::arange(-600i64, 600, &Device::Cpu).unwrap().to_dtype(DType::F32).unwrap().affine(0.01, 0.0).unwrap();
        let d = (gelu_inference(&x).unwrap() - x.gelu_erf().unwrap()).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-6, "gelu vs candle gelu_erf: {d}");
    }
}
