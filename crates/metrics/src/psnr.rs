//! PSNR as MVSplat's evaluation computes it (`compute_psnr`): both images clipped to [0, 1], then
//! `−10·log10(MSE)` with the MSE over every pixel and channel of one image (data range 1).
//!
//! Identical images give `+∞` (MSE 0), as the reference does; note that JSON has no infinity, so a
//! serialised `+∞` becomes `null`. Sums are accumulated in f64.

use candle_core::{DType, Result, Tensor};
use rayon::prelude::*;

/// Mean squared error of `a` and `b` after clipping both to [0, 1]. Panics when the lengths differ;
/// `NaN` for empty slices.
pub fn mse_clipped(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "psnr: images of {} and {} values", a.len(), b.len());
    let sum: f64 = a
        .par_chunks(1 << 16)
        .zip(b.par_chunks(1 << 16))
        .map(|(ca, cb)| {
            ca.iter()
                .zip(cb)
                .map(|(&x, &y)| {
                    let d = x.clamp(0.0, 1.0) as f64 - y.clamp(0.0, 1.0) as f64;
                    d * d
                })
                .sum::<f64>()
        })
        .sum();
    sum / a.len() as f64
}

/// PSNR (dB, data range 1) of one image pair given as equal-length slices (any layout: the MSE is over all
/// values). `+∞` for identical (after clipping) images. Panics when the lengths differ.
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    psnr_from_mse(mse_clipped(a, b))
}

/// `−10·log10(mse)`.
pub fn psnr_from_mse(mse: f64) -> f64 {
    -10.0 * mse.log10()
}

/// PSNR of one pair of (3, H, W) (or any equal-shape) tensors.
pub fn psnr_tensor(a: &Tensor, b: &Tensor) -> Result<f64> {
    if a.dims() != b.dims() {
        candle_core::bail!("psnr: shapes {:?} and {:?} differ", a.dims(), b.dims());
    }
    let a = a.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let b = b.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    Ok(psnr(&a, &b))
}

/// Per-image PSNR of two (N, C, H, W) batches.
pub fn psnr_batch(a: &Tensor, b: &Tensor) -> Result<Vec<f64>> {
    if a.dims() != b.dims() || a.rank() != 4 {
        candle_core::bail!("psnr_batch: expected two equal (N, C, H, W) shapes, got {:?} and {:?}", a.dims(), b.dims());
    }
    let n = a.dim(0)?;
    let a = a.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let b = b.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    if n == 0 {
        return Ok(Vec::new());
    }
    let per = a.len() / n;
    if per == 0 {
        candle_core::bail!("psnr_batch: empty images {:?}", a.len());
    }
    Ok(a.chunks(per).zip(b.chunks(per)).map(|(x, y)| psnr(x, y)).collect())
}
