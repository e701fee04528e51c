//! Softmax over the last dimension. candle's `softmax_last_dim` records no backward, so tracked inputs take
//! the composed ops; the encoder's masked softmax has a fused CPU kernel for inference.

use candle_core::{Result, Tensor, D};

use crate::math::exp_fast;
use crate::mode::f32_slice;

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
    let fused = !scores.track_op() && crate::mode::cpu_f32(scores);
    let (r, lw, s) = scores.dims3()?;
    match mask {
        None if fused => scores.contiguous()?.apply_op1_no_bwd(&FusedSoftmax),
        Some(mask) if fused => {
            let m = mask.contiguous()?;
            let p = m.elem_count() / s;
            scores.contiguous()?.reshape((r * lw, s))?.apply_op2_no_bwd(&m.reshape((p, s))?, &FusedSoftmax)?.reshape((r, lw, s))
        }
        _ => masked_softmax_composed(scores, mask),
    }
}

/// [`masked_softmax`] from tensor ops (differentiable, any device).
pub(crate) fn masked_softmax_composed(scores: &Tensor, mask: Option<&Tensor>) -> Result<Tensor> {
    match mask {
        None => softmax_last(scores),
        Some(mask) => {
            let (r, lw, s) = scores.dims3()?;
            let p = mask.dim(0)?;
            let x = scores.reshape((r / p, p, lw, s))?.broadcast_add(mask)?.reshape((r, lw, s))?;
            softmax_last(&x)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    /// The fused (masked) softmax equals the composed definition to 1e-6.
    #[test]
    fn fused_softmax_matches_composed() -> Result<()> {
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
}
