//! SSIM exactly as MVSplat's evaluation computes it (`compute_ssim`):
//! `skimage.metrics.structural_similarity(gt, pred, win_size=11, gaussian_weights=True, channel_axis=0,
//! data_range=1.0)` on (3, H, W) images, i.e. with skimage's defaults `sigma=1.5`, `use_sample_covariance=True`,
//! `K1=0.01`, `K2=0.03`. What that does (skimage 0.26 `metrics/_structural_similarity.py`):
//!
//! * each channel separately, then the mean over channels;
//! * local statistics with `scipy.ndimage.gaussian_filter(sigma=1.5, truncate=3.5, mode='reflect')`: radius
//!   `int(3.5·1.5 + 0.5) = 5`, an 11-tap kernel `exp(−x²/(2σ²))` normalised to sum 1, applied along each axis;
//! * `ux = G∗x`, `uy = G∗y`, `vx = f·(G∗x² − ux²)`, `vy = f·(G∗y² − uy²)`, `vxy = f·(G∗xy − ux·uy)` with the
//!   sample-covariance factor `f = NP/(NP−1)`, `NP = 11² = 121`;
//! * `S = (2·ux·uy + C1)(2·vxy + C2) / ((ux² + uy² + C1)(vx + vy + C2))`, `C1 = (0.01·1)²`, `C2 = (0.03·1)²`;
//! * the mean of `S` after cropping `(11 − 1)/2 = 5` pixels from every border.
//!
//! Because the crop equals the filter radius, every window that contributes to the mean lies entirely inside
//! the image: the `reflect` boundary handling never reaches the averaged region, so this implementation filters
//! only the "valid" region (no padding) and is exact, not an approximation of it. The filter is separable
//! (horizontal pass, then vertical), computed in f64 (skimage computes in the input's float type: f32 for
//! MVSplat's tensors, which differs from f64 by ~1e-6), parallel over channels and rows.
//!
//! Images smaller than 11×11 are an error, as in skimage. SSIM is not clipped to [0, 1] inputs (the
//! reference does not clip either).

use candle_core::{DType, Result, Tensor};
use rayon::prelude::*;

/// Gaussian standard deviation (pixels).
pub const SIGMA: f64 = 1.5;
/// `truncate` skimage passes to the Gaussian filter with `gaussian_weights=True`.
pub const TRUNCATE: f64 = 3.5;
/// Filter radius: `int(TRUNCATE·SIGMA + 0.5)`.
pub const RADIUS: usize = 5;
/// Window side `2·RADIUS + 1` (also the crop: `(WIN_SIZE − 1)/2` = `RADIUS`).
pub const WIN_SIZE: usize = 2 * RADIUS + 1;
pub const K1: f64 = 0.01;
pub const K2: f64 = 0.03;
/// Data range of the images.
pub const DATA_RANGE: f64 = 1.0;
pub const C1: f64 = (K1 * DATA_RANGE) * (K1 * DATA_RANGE);
pub const C2: f64 = (K2 * DATA_RANGE) * (K2 * DATA_RANGE);
/// Sample-covariance factor `NP/(NP−1)` with `NP = WIN_SIZE²` (`use_sample_covariance=True`).
pub const COV_NORM: f64 = (WIN_SIZE * WIN_SIZE) as f64 / (WIN_SIZE * WIN_SIZE - 1) as f64;

/// Shapes SSIM cannot be computed for.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SsimError {
    #[error("ssim: the images hold {a} and {b} values, expected {expected} ({c}×{h}×{w}) each")]
    Length { a: usize, b: usize, expected: usize, c: usize, h: usize, w: usize },
    #[error("ssim: a {h}×{w} image is smaller than the {WIN_SIZE}×{WIN_SIZE} window")]
    TooSmall { h: usize, w: usize },
}

/// scipy's `_gaussian_kernel1d(SIGMA, 0, RADIUS)`: `exp(−0.5/σ²·x²)` for x in −5..=5, normalised to sum 1.
pub fn gaussian_kernel() -> [f64; WIN_SIZE] {
    let mut k = [0.0; WIN_SIZE];
    for (i, v) in k.iter_mut().enumerate() {
        let x = i as f64 - RADIUS as f64;
        *v = (-0.5 / (SIGMA * SIGMA) * x * x).exp();
    }
    let s: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k
}

/// Mean SSIM of one single-channel (H, W) pair (row-major).
pub fn ssim_gray(a: &[f32], b: &[f32], h: usize, w: usize) -> std::result::Result<f64, SsimError> {
    ssim(a, b, 1, h, w)
}

/// Mean SSIM of one (C, H, W) pair (channel-first, row-major): the per-channel SSIMs averaged.
pub fn ssim(a: &[f32], b: &[f32], c: usize, h: usize, w: usize) -> std::result::Result<f64, SsimError> {
    let expected = c * h * w;
    if a.len() != expected || b.len() != expected {
        return Err(SsimError::Length { a: a.len(), b: b.len(), expected, c, h, w });
    }
    if h < WIN_SIZE || w < WIN_SIZE {
        return Err(SsimError::TooSmall { h, w });
    }
    if c == 0 {
        return Ok(f64::NAN);
    }
    let plane = h * w;
    let g = gaussian_kernel();
    let sum: f64 = (0..c).into_par_iter().map(|ch| ssim_plane(&a[ch * plane..(ch + 1) * plane], &b[ch * plane..(ch + 1) * plane], h, w, &g)).sum();
    Ok(sum / c as f64)
}

/// The five filtered statistics, in this order, for one row of products.
const MAPS: usize = 5;

/// Mean of the cropped SSIM map of one channel.
fn ssim_plane(a: &[f32], b: &[f32], h: usize, w: usize, g: &[f64; WIN_SIZE]) -> f64 {
    let (hv, wv) = (h - 2 * RADIUS, w - 2 * RADIUS);
    // Horizontal pass over every row: row y holds MAPS segments of wv values (x, y, x², y², xy filtered along
    // the row, output column j = input column j + RADIUS).
    let mut horiz = vec![0.0f64; h * MAPS * wv];
    horiz.par_chunks_mut(MAPS * wv).enumerate().for_each(|(y, out)| {
        let ra = &a[y * w..(y + 1) * w];
        let rb = &b[y * w..(y + 1) * w];
        let mut prod = vec![0.0f64; MAPS * w];
        for x in 0..w {
            let (p, q) = (ra[x] as f64, rb[x] as f64);
            prod[x] = p;
            prod[w + x] = q;
            prod[2 * w + x] = p * p;
            prod[3 * w + x] = q * q;
            prod[4 * w + x] = p * q;
        }
        for m in 0..MAPS {
            let src = &prod[m * w..(m + 1) * w];
            let dst = &mut out[m * wv..(m + 1) * wv];
            // Tap by tap over the whole row (vectorises across columns).
            dst.fill(0.0);
            for (k, &gk) in g.iter().enumerate() {
                for (d, &v) in dst.iter_mut().zip(&src[k..k + wv]) {
                    *d += gk * v;
                }
            }
        }
    });
    // Vertical pass for the cropped rows only, then the SSIM map and its row sums.
    let total: f64 = (0..hv)
        .into_par_iter()
        .map(|r| {
            let mut acc = vec![0.0f64; MAPS * wv];
            for (k, &gk) in g.iter().enumerate() {
                let src = &horiz[(r + k) * MAPS * wv..(r + k + 1) * MAPS * wv];
                for (d, &s) in acc.iter_mut().zip(src) {
                    *d += gk * s;
                }
            }
            let (ux, rest) = acc.split_at(wv);
            let (uy, rest) = rest.split_at(wv);
            let (uxx, rest) = rest.split_at(wv);
            let (uyy, uxy) = rest.split_at(wv);
            let mut row = 0.0f64;
            for j in 0..wv {
                let (mx, my) = (ux[j], uy[j]);
                let vx = COV_NORM * (uxx[j] - mx * mx);
                let vy = COV_NORM * (uyy[j] - my * my);
                let vxy = COV_NORM * (uxy[j] - mx * my);
                let a1 = 2.0 * mx * my + C1;
                let a2 = 2.0 * vxy + C2;
                let b1 = mx * mx + my * my + C1;
                let b2 = vx + vy + C2;
                row += (a1 * a2) / (b1 * b2);
            }
            row
        })
        .sum();
    total / (hv * wv) as f64
}

/// SSIM of one pair of (C, H, W) tensors (MVSplat passes (3, H, W)).
pub fn ssim_tensor(a: &Tensor, b: &Tensor) -> Result<f64> {
    if a.dims() != b.dims() || a.rank() != 3 {
        candle_core::bail!("ssim: expected two equal (C, H, W) shapes, got {:?} and {:?}", a.dims(), b.dims());
    }
    let (c, h, w) = a.dims3()?;
    let va = a.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let vb = b.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    ssim(&va, &vb, c, h, w).map_err(candle_core::Error::wrap)
}

/// Per-image SSIM of two (N, C, H, W) batches.
pub fn ssim_batch(a: &Tensor, b: &Tensor) -> Result<Vec<f64>> {
    if a.dims() != b.dims() || a.rank() != 4 {
        candle_core::bail!("ssim_batch: expected two equal (N, C, H, W) shapes, got {:?} and {:?}", a.dims(), b.dims());
    }
    let (n, c, h, w) = a.dims4()?;
    let va = a.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let vb = b.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let per = c * h * w;
    (0..n)
        .into_par_iter()
        .map(|i| ssim(&va[i * per..(i + 1) * per], &vb[i * per..(i + 1) * per], c, h, w))
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(candle_core::Error::wrap)
}
