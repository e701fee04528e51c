//! The error model of the bf16 gemm (see the module doc), the rounding, the denormal flush and the fallback.

use super::bench::{f32_gemm, fill};
use super::*;

/// Row-major A (m × k) and B (k × n) of the sign of `fill` and magnitudes spread over 2^±`spread`.
fn operands(m: usize, k: usize, n: usize, seed: u64, spread: i32) -> (Vec<f32>, Vec<f32>) {
    let scale = |v: Vec<f32>, s: u64| {
        let e = fill(v.len(), s);
        v.into_iter().zip(e).map(|(x, e)| x * 2f32.powi((e * spread as f32).round() as i32)).collect::<Vec<_>>()
    };
    (scale(fill(m * k, seed), seed + 100), scale(fill(k * n, seed + 1), seed + 200))
}

/// Per output: |c − Σ a'b'| ≤ K·2⁻²⁴·Σ|a'b'| + 2K·2⁻¹²⁶ against the f64 sum of the rounded operands (a', b':
/// bf16, denormals as zero), and |c − Σ ab| ≤ [`error_bound`] against the unrounded ones. Err names the first
/// output past either bound.
fn check(a: &[f32], b: &[f32], c: &[f32], m: usize, k: usize, n: usize) -> std::result::Result<f64, String> {
    let r = |x: f32| bf16_to_f32_daz(f32_to_bf16(x)) as f64;
    let mut worst = 0f64;
    for i in 0..m {
        for j in 0..n {
            let (mut s, mut sa, mut sr, mut sra) = (0f64, 0f64, 0f64, 0f64);
            for p in 0..k {
                let (x, y) = (a[i * k + p] as f64, b[p * n + j] as f64);
                s += x * y;
                sa += (x * y).abs();
                let q = r(a[i * k + p]) * r(b[p * n + j]);
                sr += q;
                sra += q.abs();
            }
            let got = c[i * n + j] as f64;
            let tight = k as f64 * 2f64.powi(-24) * sra + 2.0 * k as f64 * 2f64.powi(-126);
            if (got - sr).abs() > tight {
                return Err(format!("C[{i},{j}] = {got}: rounded-operand sum {sr}, |diff| {} > {tight}", (got - sr).abs()));
            }
            let bound = error_bound(k, sa);
            if (got - s).abs() > bound {
                return Err(format!("C[{i},{j}] = {got}: exact {s}, |diff| {} > {bound}", (got - s).abs()));
            }
            worst = worst.max((got - s).abs() / bound);
        }
    }
    Ok(worst)
}

/// The shapes: K odd, K = 1, K at and across the K-block (256 pairs: K = 512 one block, 513 a block and one
/// pair, 1001 two), M and N off the 12 × 32 tile and off a task.
const SHAPES: [(usize, usize, usize); 8] = [(1, 1, 1), (13, 7, 33), (37, 129, 65), (12, 512, 32), (20, 513, 40), (50, 385, 70), (97, 1001, 129), (5, 2, 200)];

#[test]
fn gemm_holds_the_error_model_on_seeds_and_edges() {
    if path() != Bf16Path::Dpbf16 {
        eprintln!("no AVX512-BF16 on this CPU: the dpbf16 gemm is not exercised (the fallback test covers this path)");
        return;
    }
    for seed in [1u64, 7, 42] {
        for &(m, k, n) in &SHAPES {
            for spread in [0, 12] {
                let (a, b) = operands(m, k, n, seed, spread);
                let w = Bf16Weights::from_kn(&b, k, n);
                let mut c = vec![f32::NAN; m * n];
                assert_eq!(matmul_bf16(&a, m, k, &w, &mut c, false), Bf16Path::Dpbf16);
                let worst = check(&a, &b, &c, m, k, n).unwrap_or_else(|e| panic!("seed {seed} {m}×{k}×{n} spread {spread}: {e}"));
                assert!(worst > 0.0 || k == 1, "seed {seed} {m}×{k}×{n}: no rounding error at all is suspicious");
                // Against today's f32 gemm of the unrounded operands: the bound plus f32's own K·2⁻²⁴·Σ|ab|.
                let mut c32 = vec![0f32; m * n];
                f32_gemm(&a, &b, &mut c32, m, k, n, 1);
                for i in 0..m {
                    for j in 0..n {
                        let sa: f64 = (0..k).map(|p| (a[i * k + p] as f64 * b[p * n + j] as f64).abs()).sum();
                        let bound = error_bound(k, sa) + k as f64 * 2f64.powi(-24) * sa;
                        let d = (c[i * n + j] as f64 - c32[i * n + j] as f64).abs();
                        assert!(d <= bound, "seed {seed} {m}×{k}×{n}: C[{i},{j}] bf16 {} f32 {} |diff| {d} > {bound}", c[i * n + j], c32[i * n + j]);
                    }
                }
            }
        }
    }
}

#[test]
fn from_nk_packs_the_transpose_and_accumulate_adds() {
    if path() != Bf16Path::Dpbf16 {
        return;
    }
    let (m, k, n) = (19, 45, 37);
    let (a, b) = operands(m, k, n, 3, 0);
    let mut wt = vec![0f32; n * k];
    for p in 0..k {
        for j in 0..n {
            wt[j * k + p] = b[p * n + j];
        }
    }
    let (w1, w2) = (Bf16Weights::from_kn(&b, k, n), Bf16Weights::from_nk(&wt, n, k));
    let (mut c1, mut c2) = (vec![0f32; m * n], vec![0f32; m * n]);
    matmul_bf16(&a, m, k, &w1, &mut c1, false);
    matmul_bf16(&a, m, k, &w2, &mut c2, false);
    assert_eq!(c1, c2);
    let mut c3 = vec![1.5f32; m * n];
    matmul_bf16(&a, m, k, &w1, &mut c3, true);
    for (x, y) in c3.iter().zip(&c1) {
        assert!((x - 1.5 - y).abs() <= 1e-5 * (1.0 + y.abs()), "{x} vs 1.5 + {y}");
    }
}

/// The vector conversion of the packer (`vcvtne2ps2bf16`) and the scalar one agree bit for bit, ties to even
/// included, and both round to nearest even.
#[test]
fn packing_rounds_to_nearest_even_as_the_scalar_conversion() {
    if path() != Bf16Path::Dpbf16 {
        return;
    }
    let mut vals: Vec<f32> = vec![
        1.0 + 2f32.powi(-8),                  // tie, even below: → 1
        1.0 + 3.0 * 2f32.powi(-8),            // tie, odd below: → 1 + 2⁻⁶
        1.0 + 2f32.powi(-8) + 2f32.powi(-20), // above the tie: → 1 + 2⁻⁷
        -(1.0 + 2f32.powi(-8) + 2f32.powi(-20)),
        f32::MAX,
        f32::INFINITY,
        f32::NEG_INFINITY,
        1e-40,
        -1e-40,
        f32::MIN_POSITIVE,
        0.0,
        -0.0,
    ];
    vals.extend(fill(200, 9).iter().map(|x| x * 1e3));
    let k = vals.len(); // 212: 6 words of 32-wide vector conversion, the rest scalar
    assert_eq!(f32_to_bf16(vals[0]), 0x3f80);
    assert_eq!(f32_to_bf16(vals[1]), 0x3f82);
    assert_eq!(f32_to_bf16(vals[2]), 0x3f81);
    assert_eq!(f32_to_bf16(f32::MAX), 0x7f80, "RNE overflows f32::MAX to infinity");
    assert_eq!(f32_to_bf16(1e-40), 0, "denormal → +0");
    assert_eq!(f32_to_bf16(-1e-40), 0x8000, "denormal → −0");
    assert_eq!(f32_to_bf16(f32::NAN) & 0x7fc0, 0x7fc0);
    for shift in 0..2 {
        // Shifted by one so each value meets both the vector and the scalar converter.
        let row: Vec<f32> = vals.iter().cycle().skip(shift).take(k).copied().collect();
        let packed = kernel::packed_a_for_test(&row, 1, k);
        for (i, x) in row.iter().enumerate() {
            let w = packed[(i / 2) * MR];
            let h = if i % 2 == 0 { w as u16 } else { (w >> 16) as u16 };
            assert_eq!(h, f32_to_bf16(*x), "value {x:e} at {i}: packer {h:#06x}, scalar {:#06x}", f32_to_bf16(*x));
        }
    }
}

/// Truncation instead of round to nearest even moves results past the model: a "kernel" fed truncated
/// operands (what a truncating packer computes) fails `check`, the real one passes, on crafted values.
#[test]
fn truncation_is_caught_by_the_error_model() {
    if path() != Bf16Path::Dpbf16 {
        return;
    }
    let trunc = |x: f32| f32::from_bits(x.to_bits() & 0xffff_0000);
    // K = 1: a = b = 1 + 2⁻⁷ − 2⁻²³ — RNE gives 1 + 2⁻⁷ (error 2⁻²³), truncation 1 (error ≈ 2⁻⁷ = 2u each,
    // ≈ 4u on the product > 2u + u²).
    let x = 1.0 + 2f32.powi(-7) - 2f32.powi(-23);
    // K = 64: values just above a tie, where truncation drops ≈ u relative every term.
    let row: Vec<f32> = (0..64).map(|i| (1.0 + 2f32.powi(-8) + 2f32.powi(-18)) * if i % 3 == 0 { 1.5 } else { 1.0 }).collect();
    for (a, b, k) in [(vec![x], vec![x], 1usize), (row.clone(), vec![1.0; 64], 64)] {
        let w = Bf16Weights::from_kn(&b, k, 1);
        let mut c = vec![0f32; 1];
        matmul_bf16(&a, 1, k, &w, &mut c, false);
        check(&a, &b, &c, 1, k, 1).expect("round to nearest even holds the model");
        let at: Vec<f32> = a.iter().map(|v| trunc(*v)).collect();
        let bt: Vec<f32> = b.iter().map(|v| trunc(*v)).collect();
        let wt = Bf16Weights::from_kn(&bt, k, 1);
        let mut ct = vec![0f32; 1];
        matmul_bf16(&at, 1, k, &wt, &mut ct, false);
        let e = check(&a, &b, &ct, 1, k, 1).expect_err("truncation must fail the model");
        eprintln!("K = {k}, truncated: {e}");
        if k == 1 {
            // Past the bound against the unrounded operands too, not only the tight one.
            let exact = x as f64 * x as f64;
            assert!((ct[0] as f64 - exact).abs() > error_bound(1, exact));
            assert!((c[0] as f64 - exact).abs() <= error_bound(1, exact));
        }
    }
    // A result moved by a few f32 ulps past the f32 summation allowance also fails.
    let (m, k, n) = (8, 300, 8);
    let (a, b) = operands(m, k, n, 5, 0);
    let w = Bf16Weights::from_kn(&b, k, n);
    let mut c = vec![0f32; m * n];
    matmul_bf16(&a, m, k, &w, &mut c, false);
    check(&a, &b, &c, m, k, n).expect("holds");
    let sa: f64 = (0..k).map(|p| (a[p] as f64 * b[p * n] as f64).abs()).sum();
    c[0] += (error_bound(k, sa) * 1.01) as f32 * c[0].signum();
    assert!(check(&a, &b, &c, m, k, n).is_err());
}

/// `vdpbf16ps` on this CPU: denormal operands read as zero (DAZ), a product below 2⁻¹²⁶ flushed (FTZ), as the
/// Intel SDM specifies the instruction (MXCSR not consulted).
#[test]
fn denormals_are_flushed() {
    if path() != Bf16Path::Dpbf16 {
        return;
    }
    let run = |a: &[f32], b: &[f32]| {
        let k = a.len();
        let w = Bf16Weights::from_kn(b, k, 1);
        let mut c = vec![f32::NAN; 1];
        matmul_bf16(a, 1, k, &w, &mut c, false);
        c[0]
    };
    // A denormal activation times 2¹⁰⁰: f32 gives ≈ 1.3e-10, the bf16 path exactly 0.
    assert_eq!(run(&[1e-40, 0.0], &[2f32.powi(100), 0.0]), 0.0);
    // Two normal operands whose product (2⁻¹⁴⁰) is denormal: flushed to 0.
    assert_eq!(run(&[2f32.powi(-70)], &[2f32.powi(-70)]), 0.0);
    // Normal products are exact: 2⁻⁶³ · 2⁻⁶³ = 2⁻¹²⁶ survives.
    assert_eq!(run(&[2f32.powi(-63)], &[2f32.powi(-63)]), 2f32.powi(-126));
}

/// With detection masked, bf16 is storage only: the f32 gemm of the unrounded activations and the widened
/// bf16 weights, bit for bit, within the error model; the mask is per thread and undone after.
#[test]
fn masked_detection_falls_back_to_storage_only() {
    let hw = hardware_dpbf16();
    assert_eq!(path() == Bf16Path::Dpbf16, hw);
    for &(m, k, n) in &[(13usize, 7usize, 33usize), (50, 385, 70), (3, 0, 4)] {
        let (a, b) = operands(m, k, n, 11, 4);
        let w = Bf16Weights::from_kn(&b, k, n);
        let mut c = vec![f32::NAN; m * n];
        let p = with_bf16_masked(|| {
            assert_eq!(path(), Bf16Path::StorageOnly);
            matmul_bf16(&a, m, k, &w, &mut c, false)
        });
        assert_eq!(p, Bf16Path::StorageOnly);
        assert_eq!(path() == Bf16Path::Dpbf16, hw, "the mask is undone");
        let wf = w.to_f32_kn();
        let mut want = vec![0f32; m * n];
        if k > 0 {
            f32_gemm(&a, &wf, &mut want, m, k, n, 1);
        }
        assert_eq!(c, want, "{m}×{k}×{n}");
        let sums: Vec<f64> = (0..m * n).map(|ij| (0..k).map(|p| (a[(ij / n) * k + p] as f64 * b[p * n + ij % n] as f64).abs()).sum()).collect();
        for (ij, s) in sums.iter().enumerate() {
            let exact: f64 = (0..k).map(|p| a[(ij / n) * k + p] as f64 * b[p * n + ij % n] as f64).sum();
            assert!((c[ij] as f64 - exact).abs() <= error_bound(k, *s), "{m}×{k}×{n}: {ij}");
        }
    }
}
