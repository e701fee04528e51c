//! PSNR, SSIM and the Fréchet distance against closed forms, against independent straightforward f64
//! implementations written here (direct loops, no shared code with the crate), and SSIM against values
//! computed once by scikit-image (`tests/fixtures/ssim_skimage.json`, written by
//! `scripts/fixtures/ssim_skimage.py`).
//!
//! Tolerances (absolute unless said otherwise):
//! * PSNR closed forms: 1e-9 dB; against the naive loop: 1e-9 dB.
//! * SSIM closed forms: 1e-9; against the naive 2D-window implementation: 1e-10; against skimage: 1e-12 for
//!   skimage in float64 (same arithmetic up to summation order), 1e-6 for skimage in float32 (MVSplat's
//!   call; skimage then filters and subtracts in f32; observed ≤ 1.3e-7).
//! * Fréchet: relative 1e-7 of the covariance trace for the closed forms and the cross-checks of the three
//!   trace-of-sqrtm routes; 1e-6 relative against a Denman–Beavers square root of the non-symmetric product.

use mvsplat360_metrics::frechet::{self, Gaussian};
use mvsplat360_metrics::psnr::{psnr, psnr_batch, psnr_tensor};
use mvsplat360_metrics::ssim::{self, ssim, ssim_batch, ssim_gray, ssim_tensor, SsimError};
use nalgebra::{DMatrix, DVector};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

fn random_image(rng: &mut StdRng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.gen::<f32>()).collect()
}

/// A prediction-like image: `a` blurred a little plus noise (realistic SSIM in (0, 1)).
fn degrade(rng: &mut StdRng, a: &[f32], amount: f32) -> Vec<f32> {
    a.iter().map(|&v| (v + amount * (rng.gen::<f32>() - 0.5)).clamp(0.0, 1.0)).collect()
}

// ---------------------------------------------------------------------------------------------------- PSNR

/// Independent PSNR: clip, mean of squared differences in f64, −10·log10.
fn naive_psnr(a: &[f32], b: &[f32]) -> f64 {
    let mut s = 0.0f64;
    for i in 0..a.len() {
        let x = (a[i] as f64).clamp(0.0, 1.0);
        let y = (b[i] as f64).clamp(0.0, 1.0);
        s += (x - y) * (x - y);
    }
    -10.0 * (s / a.len() as f64).log10()
}

#[test]
fn psnr_identical_is_infinite() {
    let mut rng = StdRng::seed_from_u64(1);
    let a = random_image(&mut rng, 3 * 8 * 9);
    let p = psnr(&a, &a);
    assert!(p.is_infinite() && p > 0.0, "{p}");
    // Equal after clipping counts as identical too.
    let over: Vec<f32> = a.iter().map(|_| 1.7).collect();
    let one: Vec<f32> = a.iter().map(|_| 1.0).collect();
    assert!(psnr(&over, &one).is_infinite());
}

#[test]
fn psnr_constant_offset_closed_form() {
    // |a − b| = δ everywhere: MSE = δ², PSNR = −20·log10(δ).
    for (va, vb) in [(0.25f32, 0.375f32), (0.5, 0.4), (0.0, 1.0), (0.9, 0.899)] {
        let a = vec![va; 3 * 5 * 7];
        let b = vec![vb; 3 * 5 * 7];
        let delta = (va as f64 - vb as f64).abs();
        let want = -20.0 * delta.log10();
        let got = psnr(&a, &b);
        assert!((got - want).abs() < 1e-9, "{va} vs {vb}: {got} != {want}");
    }
    // 0.25 vs 0.375: δ = 1/8 exactly, PSNR = 20·log10(8).
    assert!((psnr(&[0.25; 12], &[0.375; 12]) - 20.0 * 8f64.log10()).abs() < 1e-12);
    // Clipping to [0, 1] first: 1.5 → 1 and −1 → 0, so δ = 0.5 → 20·log10(2).
    let got = psnr(&[1.5; 6], &[0.5; 6]);
    assert!((got - 20.0 * 2f64.log10()).abs() < 1e-12, "{got}");
    assert!(psnr(&[-1.0; 6], &[0.0; 6]).is_infinite());
}

#[test]
fn psnr_matches_naive_on_random_images() {
    let mut rng = StdRng::seed_from_u64(2);
    for &(h, w) in &[(11, 13), (64, 40), (256, 448)] {
        let a: Vec<f32> = (0..3 * h * w).map(|_| rng.gen_range(-0.1f32..1.1)).collect();
        let b = degrade(&mut rng, &a, 0.3);
        let (got, want) = (psnr(&a, &b), naive_psnr(&a, &b));
        assert!((got - want).abs() < 1e-9, "{h}x{w}: {got} != {want}");
    }
}

#[test]
fn psnr_tensor_and_batch_agree_with_slices() {
    let mut rng = StdRng::seed_from_u64(3);
    let dev = candle_core::Device::Cpu;
    let (n, h, w) = (3, 12, 15);
    let a = random_image(&mut rng, n * 3 * h * w);
    let b = degrade(&mut rng, &a, 0.2);
    let ta = candle_core::Tensor::from_vec(a.clone(), (n, 3, h, w), &dev).unwrap();
    let tb = candle_core::Tensor::from_vec(b.clone(), (n, 3, h, w), &dev).unwrap();
    let batch = psnr_batch(&ta, &tb).unwrap();
    assert_eq!(batch.len(), n);
    let per = 3 * h * w;
    for i in 0..n {
        let want = naive_psnr(&a[i * per..(i + 1) * per], &b[i * per..(i + 1) * per]);
        assert!((batch[i] - want).abs() < 1e-9);
        let one = psnr_tensor(&ta.get(i).unwrap(), &tb.get(i).unwrap()).unwrap();
        assert!((one - want).abs() < 1e-9);
    }
    assert!(psnr_batch(&ta, &tb.narrow(0, 0, 2).unwrap()).is_err());
}

// ---------------------------------------------------------------------------------------------------- SSIM

/// scipy.ndimage `mode='reflect'` index: (d c b a | a b c d | d c b a).
fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    let mut i = i;
    loop {
        if i < 0 {
            i = -i - 1;
        } else if i >= n {
            i = 2 * n - i - 1;
        } else {
            return i as usize;
        }
    }
}

/// Independent skimage SSIM of one channel: the full 2D Gaussian window (outer product of
/// exp(−x²/(2·1.5²)), x = −5..=5, normalised), reflect padding, the whole map, then the mean over the map
/// cropped by 5 on every side.
fn naive_ssim_channel(a: &[f64], b: &[f64], h: usize, w: usize) -> f64 {
    let r = 5isize;
    let mut win = vec![vec![0.0f64; 11]; 11];
    let mut total = 0.0;
    for (i, row) in win.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            let (y, x) = (i as f64 - 5.0, j as f64 - 5.0);
            *v = (-(y * y + x * x) / (2.0 * 1.5 * 1.5)).exp();
            total += *v;
        }
    }
    let np = 121.0f64;
    let cov_norm = np / (np - 1.0);
    let (c1, c2) = (0.01f64 * 0.01, 0.03f64 * 0.03);
    let mut map = vec![0.0f64; h * w];
    for y in 0..h {
        for x in 0..w {
            let (mut mx, mut my, mut mxx, mut myy, mut mxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for dy in -r..=r {
                for dx in -r..=r {
                    let yy = reflect(y as isize + dy, h);
                    let xx = reflect(x as isize + dx, w);
                    let g = win[(dy + r) as usize][(dx + r) as usize] / total;
                    let (p, q) = (a[yy * w + xx], b[yy * w + xx]);
                    mx += g * p;
                    my += g * q;
                    mxx += g * p * p;
                    myy += g * q * q;
                    mxy += g * p * q;
                }
            }
            let vx = cov_norm * (mxx - mx * mx);
            let vy = cov_norm * (myy - my * my);
            let vxy = cov_norm * (mxy - mx * my);
            map[y * w + x] = ((2.0 * mx * my + c1) * (2.0 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2));
        }
    }
    let mut s = 0.0;
    let mut n = 0usize;
    for y in 5..h - 5 {
        for x in 5..w - 5 {
            s += map[y * w + x];
            n += 1;
        }
    }
    s / n as f64
}

fn naive_ssim(a: &[f32], b: &[f32], c: usize, h: usize, w: usize) -> f64 {
    let plane = h * w;
    let mut s = 0.0;
    for ch in 0..c {
        let pa: Vec<f64> = a[ch * plane..(ch + 1) * plane].iter().map(|&v| v as f64).collect();
        let pb: Vec<f64> = b[ch * plane..(ch + 1) * plane].iter().map(|&v| v as f64).collect();
        s += naive_ssim_channel(&pa, &pb, h, w);
    }
    s / c as f64
}

#[test]
fn ssim_constants_of_the_skimage_call() {
    assert_eq!(ssim::RADIUS, (ssim::TRUNCATE * ssim::SIGMA + 0.5) as usize);
    assert_eq!(ssim::WIN_SIZE, 11);
    assert!((ssim::COV_NORM - 121.0 / 120.0).abs() < 1e-15);
    assert!((ssim::C1 - 1e-4).abs() < 1e-18 && (ssim::C2 - 9e-4).abs() < 1e-18);
    let k = ssim::gaussian_kernel();
    assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-15);
    // scipy's _gaussian_kernel1d(1.5, 0, 5) (printed by scipy 1.17): centre and edge taps.
    assert!((k[5] - 0.26601172486179436).abs() < 1e-15, "{}", k[5]);
    assert!((k[0] - 0.00102838008447911).abs() < 1e-15 && k[0] == k[10], "{}", k[0]);
}

#[test]
fn ssim_identical_is_one() {
    let mut rng = StdRng::seed_from_u64(4);
    for &(h, w) in &[(11, 11), (20, 33), (64, 48)] {
        let a = random_image(&mut rng, 3 * h * w);
        let s = ssim(&a, &a, 3, h, w).unwrap();
        assert!((s - 1.0).abs() < 1e-12, "{h}x{w}: {s}");
    }
}

#[test]
fn ssim_constant_images_luminance_term() {
    // Constant images: every variance and covariance is 0, so the contrast-structure factor is C2/C2 = 1 and
    // SSIM = (2·μa·μb + C1) / (μa² + μb² + C1).
    let (h, w) = (16, 21);
    for (ma, mb) in [(0.5f32, 0.25f32), (0.1, 0.9), (0.0, 0.02), (1.0, 0.75)] {
        let a = vec![ma; 3 * h * w];
        let b = vec![mb; 3 * h * w];
        let (x, y) = (ma as f64, mb as f64);
        let want = (2.0 * x * y + 1e-4) / (x * x + y * y + 1e-4);
        let got = ssim(&a, &b, 3, h, w).unwrap();
        assert!((got - want).abs() < 1e-9, "{ma} vs {mb}: {got} != {want}");
    }
    // Per-channel constants: the mean of the three luminance terms.
    let (ma, mb) = ([0.2f32, 0.5, 0.8], [0.3f32, 0.5, 0.4]);
    let mut a = Vec::new();
    let mut b = Vec::new();
    let mut want = 0.0;
    for c in 0..3 {
        a.extend(std::iter::repeat_n(ma[c], h * w));
        b.extend(std::iter::repeat_n(mb[c], h * w));
        let (x, y) = (ma[c] as f64, mb[c] as f64);
        want += (2.0 * x * y + 1e-4) / (x * x + y * y + 1e-4) / 3.0;
    }
    let got = ssim(&a, &b, 3, h, w).unwrap();
    assert!((got - want).abs() < 1e-9, "{got} != {want}");
}

#[test]
fn ssim_matches_naive_2d_window_on_random_images() {
    let mut rng = StdRng::seed_from_u64(5);
    for &(c, h, w, amount) in &[(3, 11, 11, 0.5f32), (3, 17, 23, 0.3), (1, 30, 12, 0.1), (3, 40, 37, 0.05), (2, 13, 50, 1.0)] {
        let a = random_image(&mut rng, c * h * w);
        let b = degrade(&mut rng, &a, amount);
        let got = ssim(&a, &b, c, h, w).unwrap();
        let want = naive_ssim(&a, &b, c, h, w);
        assert!((got - want).abs() < 1e-10, "{c}x{h}x{w}: {got} != {want}");
        // Symmetric in its arguments.
        assert!((ssim(&b, &a, c, h, w).unwrap() - got).abs() < 1e-12);
    }
    // A smooth image (large local variances matter differently than white noise).
    let (h, w) = (32, 45);
    let a: Vec<f32> = (0..3 * h * w)
        .map(|i| {
            let (c, y, x) = (i / (h * w), (i / w) % h, i % w);
            0.5 + 0.4 * ((x as f32 / 5.0 + c as f32).sin() * (y as f32 / 7.0).cos())
        })
        .collect();
    let b = degrade(&mut rng, &a, 0.1);
    let (got, want) = (ssim(&a, &b, 3, h, w).unwrap(), naive_ssim(&a, &b, 3, h, w));
    assert!((got - want).abs() < 1e-10, "{got} != {want}");
    assert!(got > 0.5 && got < 0.999, "{got}");
}

#[test]
fn ssim_matches_skimage_fixture() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/ssim_skimage.json");
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let cases = v["cases"].as_array().unwrap();
    assert!(cases.len() >= 5);
    for case in cases {
        let name = case["name"].as_str().unwrap();
        let dim = |k: &str| case[k].as_u64().unwrap() as usize;
        let (c, h, w) = (dim("c"), dim("h"), dim("w"));
        let offset = case["offset"].as_i64().unwrap();
        let scale = case["scale"].as_f64().unwrap() as f32;
        // float32(q − offset) / float32(scale): one IEEE division, as numpy did.
        let decode = |k: &str| -> Vec<f32> { case[k].as_array().unwrap().iter().map(|q| (q.as_i64().unwrap() - offset) as f32 / scale).collect() };
        let (a, b) = (decode("a"), decode("b"));
        assert_eq!(a.len(), c * h * w);
        let got = ssim(&a, &b, c, h, w).unwrap();
        let want64 = case["ssim_f64"].as_f64().unwrap();
        let want32 = case["ssim_f32"].as_f64().unwrap();
        assert!((got - want64).abs() < 1e-12, "{name}: {got} != skimage f64 {want64}");
        assert!((got - want32).abs() < 1e-6, "{name}: {got} != skimage f32 {want32}");
    }
}

#[test]
fn ssim_shape_errors() {
    assert_eq!(ssim_gray(&[0.5; 100], &[0.5; 100], 10, 10), Err(SsimError::TooSmall { h: 10, w: 10 }));
    assert_eq!(ssim(&[0.5; 3 * 11 * 30], &[0.5; 3 * 11 * 30], 3, 11, 30).map(|s| (s - 1.0).abs() < 1e-12), Ok(true));
    assert!(matches!(ssim(&[0.5; 3 * 121], &[0.5; 3 * 120], 3, 11, 11), Err(SsimError::Length { .. })));
    assert!(matches!(ssim(&[0.5; 363], &[0.5; 363], 3, 11, 12), Err(SsimError::Length { .. })));
}

#[test]
fn ssim_tensor_and_batch_agree_with_slices() {
    let mut rng = StdRng::seed_from_u64(6);
    let dev = candle_core::Device::Cpu;
    let (n, h, w) = (3, 14, 19);
    let a = random_image(&mut rng, n * 3 * h * w);
    let b = degrade(&mut rng, &a, 0.3);
    let ta = candle_core::Tensor::from_vec(a.clone(), (n, 3, h, w), &dev).unwrap();
    let tb = candle_core::Tensor::from_vec(b.clone(), (n, 3, h, w), &dev).unwrap();
    let batch = ssim_batch(&ta, &tb).unwrap();
    let per = 3 * h * w;
    for i in 0..n {
        let want = naive_ssim(&a[i * per..(i + 1) * per], &b[i * per..(i + 1) * per], 3, h, w);
        assert!((batch[i] - want).abs() < 1e-10);
        let one = ssim_tensor(&ta.get(i).unwrap(), &tb.get(i).unwrap()).unwrap();
        assert!((one - want).abs() < 1e-10);
    }
    let small = candle_core::Tensor::zeros((1, 3, 8, 40), candle_core::DType::F32, &dev).unwrap();
    assert!(ssim_batch(&small, &small).is_err());
}

// ---------------------------------------------------------------------------------------------- Fréchet

fn rel_close(got: f64, want: f64, scale: f64, tol: f64) -> bool {
    (got - want).abs() <= tol * scale.max(1e-300)
}

/// Random features with correlated dimensions: z·A + μ, z ~ U(−1, 1).
fn features(rng: &mut StdRng, n: usize, d: usize, mix: &DMatrix<f64>, shift: f64) -> Vec<f64> {
    let z = DMatrix::from_fn(n, d, |_, _| rng.gen_range(-1.0..1.0));
    let x = z * mix;
    let mut out = Vec::with_capacity(n * d);
    for i in 0..n {
        for j in 0..d {
            out.push(x[(i, j)] + shift * (j as f64 + 1.0) / d as f64);
        }
    }
    out
}

fn random_mix(rng: &mut StdRng, d: usize) -> DMatrix<f64> {
    DMatrix::from_fn(d, d, |i, j| if i == j { 1.0 } else { 0.3 * rng.gen_range(-1.0..1.0) })
}

#[test]
fn frechet_needs_two_samples() {
    assert_eq!(frechet::frechet_from_features(&[1.0, 2.0], 1, &[1.0, 2.0, 3.0, 4.0], 2, 2), None);
    assert_eq!(frechet::frechet_from_features(&[1.0, 2.0, 3.0, 4.0], 2, &[], 0, 2), None);
    assert!(Gaussian::from_features(&[1.0, 2.0], 1, 2).is_none());
    assert!(frechet::frechet_from_features(&[1.0, 2.0, 3.0, 4.0], 2, &[1.0, 2.0, 3.0, 5.0], 2, 2).is_some());
}

#[test]
fn frechet_identical_sets_are_zero() {
    let mut rng = StdRng::seed_from_u64(7);
    // N ≤ D (the cross-product route) and N > D (covariance route).
    for &(n, d) in &[(20usize, 50usize), (3, 8), (200, 16)] {
        let mix = random_mix(&mut rng, d);
        let x = features(&mut rng, n, d, &mix, 1.0);
        let g = Gaussian::from_features(&x, n, d).unwrap();
        let tr = g.cov.trace();
        let f = frechet::frechet_from_features(&x, n, &x, n, d).unwrap();
        assert!(rel_close(f, 0.0, tr, 1e-7), "{n}x{d}: {f} (trace {tr})");
        let f2 = frechet::frechet_distance(&g, &g);
        assert!(rel_close(f2, 0.0, tr, 1e-7), "{n}x{d}: {f2} (trace {tr})");
    }
}

#[test]
fn frechet_shifted_sets_give_squared_mean_difference() {
    let mut rng = StdRng::seed_from_u64(8);
    for &(n, d) in &[(30usize, 64usize), (150, 12)] {
        let mix = random_mix(&mut rng, d);
        let x = features(&mut rng, n, d, &mix, 0.0);
        let delta: Vec<f64> = (0..d).map(|_| rng.gen_range(-2.0..2.0)).collect();
        let y: Vec<f64> = x.iter().enumerate().map(|(i, v)| v + delta[i % d]).collect();
        let want: f64 = delta.iter().map(|v| v * v).sum();
        let tr = Gaussian::from_features(&x, n, d).unwrap().cov.trace();
        let got = frechet::frechet_from_features(&x, n, &y, n, d).unwrap();
        assert!(rel_close(got, want, tr + want, 1e-7), "{n}x{d}: {got} != {want}");
    }
}

#[test]
fn frechet_diagonal_covariances_closed_form() {
    // Gaussians given directly: ‖Δμ‖² + Σₖ(√aₖ − √bₖ)², also after a common rotation (commuting covariances).
    let mut rng = StdRng::seed_from_u64(9);
    let d = 9;
    let a: Vec<f64> = (0..d).map(|_| rng.gen_range(0.0..4.0)).collect();
    let b: Vec<f64> = (0..d).map(|k| if k == 3 { 0.0 } else { rng.gen_range(0.1..4.0) }).collect();
    let m1 = DVector::from_fn(d, |_, _| rng.gen_range(-1.0..1.0));
    let m2 = DVector::from_fn(d, |_, _| rng.gen_range(-1.0..1.0));
    let want = (&m1 - &m2).norm_squared() + a.iter().zip(&b).map(|(x, y)| (x.sqrt() - y.sqrt()).powi(2)).sum::<f64>();
    let diag = |v: &[f64]| DMatrix::from_diagonal(&DVector::from_column_slice(v));
    let q = DMatrix::from_fn(d, d, |_, _| rng.gen_range(-1.0..1.0)).qr().q();
    for rot in [DMatrix::identity(d, d), q] {
        let g1 = Gaussian { mean: m1.clone(), cov: &rot * diag(&a) * rot.transpose() };
        let g2 = Gaussian { mean: m2.clone(), cov: &rot * diag(&b) * rot.transpose() };
        let got = frechet::frechet_distance(&g1, &g2);
        assert!(rel_close(got, want, want, 1e-7), "{got} != {want}");
        // Both trace-of-sqrtm routes (Σ₂ is singular: b₃ = 0; the Cholesky one factors Σ₁ when it is PD).
        let t = frechet::trace_sqrt_product_eigen(&g1.cov, &g2.cov);
        let want_t: f64 = a.iter().zip(&b).map(|(x, y)| (x * y).sqrt()).sum();
        assert!(rel_close(t, want_t, want_t, 1e-9), "{t} != {want_t}");
        let t2 = frechet::trace_sqrt_product(&g2.cov, &g1.cov);
        assert!(rel_close(t2, want_t, want_t, 1e-9), "{t2} != {want_t}");
    }
}

#[test]
fn frechet_sample_sets_with_diagonal_covariance() {
    // Each sample deviates from μ along one axis only (μ ± sₖeₖ), so the sample covariance is exactly
    // diagonal: var_k = 2·sₖ²/(N − 1). N = 2·(active dims).
    fn set(mu: &[f64], s: &[f64], d: usize) -> (Vec<f64>, usize, Vec<f64>) {
        let active = s.len();
        let n = 2 * active;
        let mut rows = Vec::with_capacity(n * d);
        for (k, &sk) in s.iter().enumerate() {
            for sign in [1.0, -1.0] {
                rows.extend(mu.iter().enumerate().map(|(j, &m)| m + if j == k { sign * sk } else { 0.0 }));
            }
        }
        let var = (0..d).map(|j| if j < active { 2.0 * s[j] * s[j] / (n as f64 - 1.0) } else { 0.0 }).collect();
        (rows, n, var)
    }
    let mut rng = StdRng::seed_from_u64(10);
    // d = 6 with all dims active (N = 12 > D: covariance route); d = 20 with 6 active (N = 12 ≤ D: the
    // cross-product route, singular covariances).
    for &d in &[6usize, 20] {
        let mu1: Vec<f64> = (0..d).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let mu2: Vec<f64> = (0..d).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let s1: Vec<f64> = (0..6).map(|_| rng.gen_range(0.2..2.0)).collect();
        let s2: Vec<f64> = (0..6).map(|_| rng.gen_range(0.2..2.0)).collect();
        let (x, nx, va) = set(&mu1, &s1, d);
        let (y, ny, vb) = set(&mu2, &s2, d);
        let dm: f64 = mu1.iter().zip(&mu2).map(|(p, q)| (p - q) * (p - q)).sum();
        let want = dm + va.iter().zip(&vb).map(|(p, q)| (p.sqrt() - q.sqrt()).powi(2)).sum::<f64>();
        let got = frechet::frechet_from_features(&x, nx, &y, ny, d).unwrap();
        assert!(rel_close(got, want, want, 1e-7), "d={d}: {got} != {want}");
        let g = frechet::frechet_distance(&Gaussian::from_features(&x, nx, d).unwrap(), &Gaussian::from_features(&y, ny, d).unwrap());
        assert!(rel_close(g, want, want, 1e-7), "d={d}: {g} != {want}");
    }
}

/// Independent: sqrtm of the non-symmetric product by the Denman–Beavers iteration (what scipy's sqrtm
/// returns for a product with positive eigenvalues), then its trace.
fn denman_beavers_trace_sqrt(a: &DMatrix<f64>) -> f64 {
    let n = a.nrows();
    let mut y = a.clone();
    let mut z = DMatrix::<f64>::identity(n, n);
    for _ in 0..100 {
        let yi = y.clone().try_inverse().unwrap();
        let zi = z.clone().try_inverse().unwrap();
        let ny = (&y + zi) * 0.5;
        let nz = (&z + yi) * 0.5;
        let done = (&ny - &y).norm() < 1e-14 * ny.norm();
        y = ny;
        z = nz;
        if done {
            break;
        }
    }
    y.trace()
}

#[test]
fn frechet_routes_agree_and_match_denman_beavers() {
    let mut rng = StdRng::seed_from_u64(11);
    // N > D: all covariances PD, the non-symmetric product has a proper square root.
    let (n, d) = (120, 10);
    let mix1 = random_mix(&mut rng, d);
    let mix2 = random_mix(&mut rng, d);
    let x = features(&mut rng, n, d, &mix1, 0.5);
    let y = features(&mut rng, n + 17, d, &mix2, -0.3);
    let g1 = Gaussian::from_features(&x, n, d).unwrap();
    let g2 = Gaussian::from_features(&y, n + 17, d).unwrap();
    let tr = g1.cov.trace() + g2.cov.trace();
    let want_t = denman_beavers_trace_sqrt(&(&g1.cov * &g2.cov));
    for t in [frechet::trace_sqrt_product(&g1.cov, &g2.cov), frechet::trace_sqrt_product(&g2.cov, &g1.cov), frechet::trace_sqrt_product_eigen(&g1.cov, &g2.cov)]
    {
        assert!(rel_close(t, want_t, tr, 1e-6), "{t} != {want_t}");
    }
    let want = (&g1.mean - &g2.mean).norm_squared() + tr - 2.0 * want_t;
    let got = frechet::frechet_from_features(&x, n, &y, n + 17, d).unwrap();
    assert!(rel_close(got, want, tr, 1e-6), "{got} != {want}");

    // N ≤ D: the cross-product route against the eigen form on the full D×D covariances.
    let (n1, n2, d) = (15, 22, 40);
    let mix = random_mix(&mut rng, d);
    let x = features(&mut rng, n1, d, &mix, 0.0);
    let y = features(&mut rng, n2, d, &mix, 1.0);
    let g1 = Gaussian::from_features(&x, n1, d).unwrap();
    let g2 = Gaussian::from_features(&y, n2, d).unwrap();
    let tr = g1.cov.trace() + g2.cov.trace();
    let want = (&g1.mean - &g2.mean).norm_squared() + tr - 2.0 * frechet::trace_sqrt_product_eigen(&g1.cov, &g2.cov);
    let got = frechet::frechet_from_features(&x, n1, &y, n2, d).unwrap();
    assert!(rel_close(got, want, tr, 1e-7), "{got} != {want}");
    assert!(got > 0.0);
    let sym = frechet::frechet_from_features(&y, n2, &x, n1, d).unwrap();
    assert!(rel_close(sym, got, tr, 1e-7), "{sym} != {got}");
}

#[test]
fn frechet_2048_dims_few_samples_is_fast() {
    // The usual FID shape with a few hundred images: must take well under a few seconds.
    let mut rng = StdRng::seed_from_u64(12);
    let (n, d) = (300, 2048);
    let x: Vec<f64> = (0..n * d).map(|_| rng.gen::<f64>()).collect();
    let y: Vec<f64> = (0..n * d).map(|_| rng.gen::<f64>() * 1.1).collect();
    let t = std::time::Instant::now();
    let f = frechet::frechet_from_features(&x, n, &y, n, d).unwrap();
    let secs = t.elapsed().as_secs_f64();
    assert!(f.is_finite() && f > 0.0, "{f}");
    assert!(secs < 20.0, "{secs} s");
}
