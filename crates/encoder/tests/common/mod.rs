//! The error model of the encoder's Gaussians against the official ones, shared by the adapter, depth-predictor
//! and end-to-end parity tests. Every bound is per entry and is built from the reference's own scale, so it holds
//! for any seed and image size (checked on fixtures of 3 seeds × 2 sizes made by scripts/fixtures/official_encoder.py;
//! scripts/fixtures/check-parity-seeds re-runs that check).
//!
//! Model. Two float32 implementations of the network round differently; upstream of the Gaussian adapter that
//! noise is an absolute error on the predicted **disparity**, at most τ × the largest disparity (1/near). Depth =
//! 1/disparity turns it into |Δd| ≤ τ·d²·max(1/d) (×1e4 at the far plane: why element-wise rtols on depths, means
//! or covariances fit one fixture and fail the next), and everything built from d inherits it:
//! - depths: τ·d²·D + ρ·d (D = max disparity; ρ: the reciprocal's own rounding);
//! - means (per Gaussian): τ·d²·D (unit ray direction) + ρ·(d + max|mean_g|) (origin + d·dir can cancel);
//! - scales ∝ d: (τ·d·D)·s + ρ·max|s_g|;
//! - covariances ∝ d² and rotated by the quaternion: (2τ·d·D + 2·q + ρ)·max|Σ_g|, relative to the **Gaussian's
//!   own** largest entry: off-diagonal entries cancel (a 0.6 % error on an entry 1e-4 of the Gaussian's largest is
//!   noise), and a per-tensor scale would let small Gaussians' errors go unseen;
//! - rotations (unit quaternions, xyzw): absolute q (normalising short raw quaternions amplifies the raw noise);
//! - opacities (sigmoid, in (0,1)): absolute o;
//! - SH, per degree l (values already × the degree's mask): σ × max|block| of that degree, because rotated
//!   coefficients are sums of products that cancel;
//! - disparity (1/depths): τ·D + ρ·(1/d).

use candle_core::Tensor;
use mvsplat360_encoder::EncoderGaussians;
use mvsplat360_testkit::{self as tk, Tol};

/// Factors of the model above (dimensionless).
#[derive(Debug, Clone, Copy)]
pub struct GaussianTol {
    /// τ: disparity error / max disparity.
    pub disparity: f64,
    /// ρ: float32 rounding of the final arithmetic, relative to the Gaussian's scale.
    pub rounding: f64,
    /// q: absolute error of a unit-quaternion component.
    pub rotation: f64,
    /// o: absolute error of an opacity.
    pub opacity: f64,
    /// σ: SH error relative to the degree block's largest coefficient.
    pub sh: f64,
}

/// Per-entry bounds of the depth-derived outputs. `d` = the official depth of each Gaussian (G entries).
fn depth_bounds(d: &[f64], reference: &[f64], per: usize, t: &GaussianTol, f: impl Fn(f64, f64) -> f64) -> Vec<f64> {
    assert_eq!(reference.len(), d.len() * per, "reference is not {per} values per Gaussian");
    let mut out = Vec::with_capacity(reference.len());
    for (g, chunk) in reference.chunks(per).enumerate() {
        let scale = chunk.iter().fold(0f64, |m, x| m.max(x.abs()));
        out.extend(chunk.iter().map(|&e| f(d[g], e) + t.rounding * scale));
    }
    out
}

/// Compare `ours` with the official Gaussians in `official` (keys of outputs.safetensors); failures are appended.
pub fn check_gaussians(prefix: &str, ours: &EncoderGaussians, official: &std::collections::HashMap<String, Tensor>, t: GaussianTol, fails: &mut Vec<String>) {
    let get = |k: &str| tk::to_f64(tk::get(official, k));
    let d = get("depths");
    let disp_max = d.iter().fold(0f64, |m, &x| m.max(1.0 / x));
    let td = t.disparity * disp_max; // absolute disparity error
    let mut run = |name: &str, a: &Tensor, e: &[f64], bounds: Vec<f64>| {
        fails.extend(tk::check_bounds(&format!("{prefix}{name}"), &tk::to_f64(a), e, &bounds));
    };
    let depths = get("depths");
    let b = depth_bounds(&d, &depths, 1, &t, |dg, _| td * dg * dg);
    run("depths", &ours.depths, &depths, b);
    let disp: Vec<f64> = d.iter().map(|x| 1.0 / x).collect();
    let b = disp.iter().map(|x| td + t.rounding * x).collect();
    run("disparity (1/depths)", &ours.depths.recip().unwrap(), &disp, b);
    let means = get("gaussians.means");
    // The rounding scale of a mean is the ray length d plus the mean's own size (origin + d·dir cancels).
    let b = depth_bounds(&d, &means, 3, &t, |dg, _| td * dg * dg + t.rounding * dg);
    run("gaussians.means", &ours.means, &means, b);
    let scales = get("gaussians.scales");
    let b = depth_bounds(&d, &scales, 3, &t, |dg, e| td * dg * e.abs());
    run("gaussians.scales", &ours.scales, &scales, b);
    let cov = get("gaussians.covariances");
    let b = {
        let mut out = Vec::with_capacity(cov.len());
        for (g, chunk) in cov.chunks(9).enumerate() {
            let scale = chunk.iter().fold(0f64, |m, x| m.max(x.abs()));
            out.extend(std::iter::repeat((2.0 * td * d[g] + 2.0 * t.rotation + t.rounding) * scale).take(9));
        }
        out
    };
    run("gaussians.covariances", &ours.covariances, &cov, b);
    let rot = get("gaussians.rotations");
    run("gaussians.rotations", &ours.rotations, &rot, Tol::abs(t.rotation).bounds(&rot));
    let op = get("gaussians.opacities");
    run("gaussians.opacities", &ours.opacities, &op, Tol::abs(t.opacity).bounds(&op));
    for (name, a, degrees) in [("gaussians.harmonics", &ours.harmonics, 4), ("gaussians.feature_harmonics", &ours.feature_harmonics, 2)] {
        for l in 0..=degrees {
            let e = tk::to_f64(&tk::sh_degree_block(tk::get(official, name), l));
            let b = Tol::of_max(t.sh).bounds(&e);
            run(&format!("{name} degree {l}"), &tk::sh_degree_block(a, l), &e, b);
        }
    }
}
