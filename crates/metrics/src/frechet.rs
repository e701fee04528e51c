//! Fréchet distance between the Gaussians fitted to two feature sets (FID when the features are InceptionV3
//! pool3 activations):
//!
//! `d² = ‖μ₁ − μ₂‖² + tr(Σ₁) + tr(Σ₂) − 2·tr(sqrtm(Σ₁Σ₂))`
//!
//! with `μ` the feature means and `Σ` the sample covariances (divisor N − 1, as `np.cov`), all in f64.
//!
//! ## The matrix square root
//! The references (pytorch-fid, fid-helper-pytorch) call `scipy.linalg.sqrtm(Σ₁Σ₂)` — a general (Schur)
//! square root of a non-symmetric product that can come out complex and is then cut to its real part. Only its
//! trace is needed, and `Σ₁Σ₂` is similar to the symmetric positive semi-definite `√Σ₁ Σ₂ √Σ₁`
//! (same eigenvalues λᵢ ≥ 0), so `tr(sqrtm(Σ₁Σ₂)) = Σᵢ √λᵢ` is computed from real symmetric
//! eigendecompositions only (nalgebra):
//!
//! 1. `√Σ₁ = V diag(√max(eᵢ, 0)) Vᵀ` from the eigendecomposition `Σ₁ = V diag(e) Vᵀ`;
//! 2. the eigenvalues λᵢ of `M = √Σ₁ Σ₂ √Σ₁` (symmetrised, `(M + Mᵀ)/2`, against rounding);
//! 3. `Σᵢ √max(λᵢ, 0)`.
//!
//! Clamping at 0: both matrices are PSD in exact arithmetic, but a covariance of N samples in D dimensions has
//! rank ≤ N − 1, so for N ≤ D (a few hundred images vs. 2048 features) most of its eigenvalues are exactly 0,
//! and rounding turns them into values of either sign around ±1e−16·‖Σ‖; their square roots would be NaN
//! (or, in scipy, tiny imaginary parts that `np.real` drops). Clamping maps them to the 0 they are.
//!
//! ## Faster equivalent forms (the result is the same quantity)
//! Eigendecompositions of a 2048×2048 matrix take seconds to tens of seconds in nalgebra, so two shortcuts
//! are taken when they apply (tests check them against the form above):
//! * **few samples** (`min(N₁, N₂) ≤ D`): with the centred data `X₁` (N₁×D), `X₂` (N₂×D),
//!   `Σ₁Σ₂ = X₁ᵀX₁X₂ᵀX₂/c` (c = (N₁−1)(N₂−1)) has the same non-zero eigenvalues as `K Kᵀ/c` with
//!   `K = X₁X₂ᵀ` (N₁×N₂), so the trace is `Σᵢ √λᵢ(KKᵀ or KᵀK) / √c` from an eigenvalue problem of size
//!   `min(N₁, N₂)` — the same symmetric-PSD form on a smaller matrix, with the same clamping;
//! * **many samples**: when `Σ₁` is positive definite, its Cholesky factor `L` (`Σ₁ = LLᵀ`) gives
//!   `Σ₁Σ₂ ~ LᵀΣ₂L` (symmetric PSD), so step 1's eigenvectors are not needed; when the factorisation fails
//!   (`Σ₁` singular) the eigendecomposition form above is used.

use candle_core::{DType, Tensor};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

/// Mean and sample covariance of a feature set.
#[derive(Debug, Clone)]
pub struct Gaussian {
    pub mean: DVector<f64>,
    /// D×D, divisor N − 1.
    pub cov: DMatrix<f64>,
}

/// Feature rows with their mean removed.
struct Centred {
    /// N×D.
    x: DMatrix<f64>,
    mean: DVector<f64>,
}

fn centre(rows: &[f64], n: usize, d: usize) -> Centred {
    assert_eq!(rows.len(), n * d, "frechet: {} values for {n}×{d} features", rows.len());
    // nalgebra is column-major: a row-major N×D buffer is the column-major D×N matrix.
    let xt = DMatrix::from_column_slice(d, n, rows);
    let mean = xt.column_mean();
    let mut x = xt.transpose();
    for mut row in x.row_iter_mut() {
        row -= mean.transpose();
    }
    Centred { x, mean }
}

/// `XᵀX/(N−1)`, parallel over row blocks.
fn covariance(c: &Centred) -> DMatrix<f64> {
    let (n, d) = c.x.shape();
    let blocks = rayon::current_num_threads().max(1).min(n.max(1));
    let step = n.div_ceil(blocks).max(1);
    let parts: Vec<DMatrix<f64>> = (0..n)
        .step_by(step)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|s| {
            let m = step.min(n - s);
            let xb = c.x.rows(s, m);
            xb.transpose() * xb
        })
        .collect();
    let mut cov = parts.into_iter().fold(DMatrix::zeros(d, d), |acc, p| acc + p);
    cov /= (n as f64 - 1.0).max(1.0);
    symmetrise(&mut cov);
    cov
}

fn symmetrise(m: &mut DMatrix<f64>) {
    let t = m.transpose();
    *m += t;
    *m *= 0.5;
}

impl Gaussian {
    /// Fit to `n` feature rows of dimension `d` (row-major `rows`). None for fewer than 2 rows. Panics when
    /// `rows.len() != n·d`.
    pub fn from_features(rows: &[f64], n: usize, d: usize) -> Option<Self> {
        if n < 2 {
            assert_eq!(rows.len(), n * d, "frechet: {} values for {n}×{d} features", rows.len());
            return None;
        }
        let c = centre(rows, n, d);
        let cov = covariance(&c);
        Some(Self { mean: c.mean, cov })
    }
}

/// Clamped `√λ` summed over the eigenvalues of a symmetric PSD matrix.
fn sum_sqrt_eigenvalues(m: DMatrix<f64>) -> f64 {
    m.symmetric_eigenvalues().iter().map(|&l| l.max(0.0).sqrt()).sum()
}

/// `tr(sqrtm(Σ₁Σ₂))` through `√Σ₁ Σ₂ √Σ₁` with symmetric eigendecompositions (the reference form; see the
/// module docs).
pub fn trace_sqrt_product_eigen(s1: &DMatrix<f64>, s2: &DMatrix<f64>) -> f64 {
    let e = s1.clone().symmetric_eigen();
    let v = &e.eigenvectors;
    let mut vs = v.clone();
    for (j, mut col) in vs.column_iter_mut().enumerate() {
        col *= e.eigenvalues[j].max(0.0).sqrt();
    }
    let root = &vs * v.transpose();
    let mut m = &root * s2 * &root;
    symmetrise(&mut m);
    sum_sqrt_eigenvalues(m)
}

/// Smallest accepted Cholesky pivot `L_jj²`, relative to the largest diagonal entry of `Σ₁`: below it `Σ₁` is
/// treated as singular (a pivot at rounding level would make the remaining columns of `L` noise).
const CHOLESKY_MIN_PIVOT: f64 = 1e-9;

/// `tr(sqrtm(Σ₁Σ₂))`: the Cholesky form when `Σ₁` is (numerically) positive definite, else
/// [`trace_sqrt_product_eigen`].
pub fn trace_sqrt_product(s1: &DMatrix<f64>, s2: &DMatrix<f64>) -> f64 {
    let max_diag = s1.diagonal().iter().fold(0.0f64, |m, &v| m.max(v));
    let chol = s1.clone().cholesky().filter(|ch| {
        let l = ch.l_dirty();
        (0..l.nrows()).all(|j| l[(j, j)] * l[(j, j)] > CHOLESKY_MIN_PIVOT * max_diag)
    });
    match chol {
        Some(ch) => {
            let l = ch.l();
            let mut m = l.transpose() * s2 * &l;
            symmetrise(&mut m);
            sum_sqrt_eigenvalues(m)
        }
        None => trace_sqrt_product_eigen(s1, s2),
    }
}

/// `tr(sqrtm(Σ₁Σ₂))` from centred data (N₁×D, N₂×D) through the N₁×N₂ cross-product (see the module docs).
fn trace_sqrt_product_gram(x1: &DMatrix<f64>, n1: usize, x2: &DMatrix<f64>, n2: usize) -> f64 {
    let k = x1 * x2.transpose();
    let mut g = if n1 <= n2 { &k * k.transpose() } else { k.transpose() * &k };
    symmetrise(&mut g);
    sum_sqrt_eigenvalues(g) / (((n1 - 1) * (n2 - 1)) as f64).sqrt()
}

/// Fréchet distance of two fitted Gaussians.
pub fn frechet_distance(g1: &Gaussian, g2: &Gaussian) -> f64 {
    let dm = (&g1.mean - &g2.mean).norm_squared();
    dm + g1.cov.trace() + g2.cov.trace() - 2.0 * trace_sqrt_product(&g1.cov, &g2.cov)
}

/// Fréchet distance between the feature sets `a` (`na`×`d`, row-major) and `b` (`nb`×`d`). None when either
/// set has fewer than 2 rows (no sample covariance). Panics when a buffer's length is not `n·d`.
pub fn frechet_from_features(a: &[f64], na: usize, b: &[f64], nb: usize, d: usize) -> Option<f64> {
    assert_eq!(a.len(), na * d, "frechet: {} values for {na}×{d} features", a.len());
    assert_eq!(b.len(), nb * d, "frechet: {} values for {nb}×{d} features", b.len());
    if na < 2 || nb < 2 {
        return None;
    }
    let (ca, cb) = rayon::join(|| centre(a, na, d), || centre(b, nb, d));
    let dm = (&ca.mean - &cb.mean).norm_squared();
    let trace = |c: &Centred, n: usize| c.x.iter().map(|v| v * v).sum::<f64>() / (n as f64 - 1.0);
    let (ta, tb) = (trace(&ca, na), trace(&cb, nb));
    let tr_sqrt = if na.min(nb) <= d {
        trace_sqrt_product_gram(&ca.x, na, &cb.x, nb)
    } else {
        let (sa, sb) = rayon::join(|| covariance(&ca), || covariance(&cb));
        trace_sqrt_product(&sa, &sb)
    };
    Some(dm + ta + tb - 2.0 * tr_sqrt)
}

/// [`frechet_from_features`] of two (N, D) tensors (any float dtype; computed in f64).
pub fn frechet_from_tensors(a: &Tensor, b: &Tensor) -> candle_core::Result<Option<f64>> {
    let (na, da) = a.dims2()?;
    let (nb, db) = b.dims2()?;
    if da != db {
        candle_core::bail!("frechet: feature dimensions {da} and {db} differ");
    }
    let va = a.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    let vb = b.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    Ok(frechet_from_features(&va, na, &vb, nb, da))
}
