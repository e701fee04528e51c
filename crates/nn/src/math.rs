//! Scalar approximations the CPU kernels share, and the runtime SIMD dispatch. Two exp/erf families exist on
//! purpose: the encoder's (no FMA, so its AVX2 and portable builds agree bit for bit) and the refiner's (FMA,
//! vectorised to the machine's width); each keeps the numerics its parity tests were measured with.

/// `fn name(args) body` compiled three times (AVX-512, AVX2+FMA, baseline) with a runtime choice, so the
/// plain loops inside auto-vectorise to the machine's width without `-C target-cpu`.
macro_rules! simd_dispatch_impl {
    ($(#[$m:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$m])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            #[allow(clippy::too_many_arguments)]
            fn imp($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512bw,avx512dq,avx512vl,avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn v4($($arg: $ty),*) $(-> $ret)? { imp($($arg),*) }
                #[target_feature(enable = "avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn v3($($arg: $ty),*) $(-> $ret)? { imp($($arg),*) }
                if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bw")
                    && std::is_x86_feature_detected!("avx512dq") && std::is_x86_feature_detected!("avx512vl") {
                    // SAFETY: the features were detected at run time.
                    return unsafe { v4($($arg),*) };
                }
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    // SAFETY: as above.
                    return unsafe { v3($($arg),*) };
                }
            }
            imp($($arg),*)
        }
    };
}

pub(crate) use simd_dispatch_impl as simd_dispatch;

pub(crate) const LANES: usize = 16;

/// e^x for x ≤ 88 in f32 (Cephes `expf` polynomial, ≈1 ulp); inputs below −87 give ≈1e-38 instead of 0.
#[inline(always)]
pub(crate) fn exp_f32(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const MAGIC: f32 = 12_582_912.0; // 1.5·2²³: adding it rounds to the nearest integer
    let x = x.clamp(-87.0, 88.0);
    let k = (x * LOG2E + MAGIC) - MAGIC;
    let r = k.mul_add(-0.693_359_4, x);
    let r = k.mul_add(2.121_944_4e-4, r);
    let mut p = 1.987_569_1e-4f32;
    p = p.mul_add(r, 1.398_199_9e-3);
    p = p.mul_add(r, 8.333_452e-3);
    p = p.mul_add(r, 4.166_579_6e-2);
    p = p.mul_add(r, 1.666_666_5e-1);
    p = p.mul_add(r, 5.000_000_1e-1);
    let e = (p * r).mul_add(r, r) + 1.0;
    e * f32::from_bits(((k as i32 + 127) as u32) << 23)
}

/// erf(x), Abramowitz–Stegun 7.1.26 (|error| ≤ 1.5e-7).
#[inline(always)]
pub(crate) fn erf_f32(x: f32) -> f32 {
    let a = x.abs();
    let t = 1.0 / 0.327_591_1f32.mul_add(a, 1.0);
    let mut p = 1.061_405_4f32;
    p = p.mul_add(t, -1.453_152_1);
    p = p.mul_add(t, 1.421_413_8);
    p = p.mul_add(t, -0.284_496_74);
    p = p.mul_add(t, 0.254_829_6);
    let y = 1.0 - p * t * exp_f32(-a * a);
    y.copysign(x)
}

/// Exact-erf GELU.
#[inline(always)]
pub(crate) fn gelu_f32(x: f32) -> f32 {
    0.5 * x * (1.0 + erf_f32(x * std::f32::consts::FRAC_1_SQRT_2))
}

/// `exp(x)` in f32 for the softmax kernel: range reduction to `r ∈ [−ln2/2, ln2/2]` and a degree-7 Taylor
/// polynomial (relative error ≤ 1e-8 before rounding), branch-free so the compiler vectorises it. Inputs below
/// −86 give exactly 0: their true value (< 5e-38) is irrelevant next to a softmax row maximum of 1, and
/// denormal outputs would make every later multiply (the attention·V gemm) many times slower.
#[inline(always)]
pub(crate) fn exp_fast(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    const ROUND: f32 = 12_582_912.0; // 1.5·2^23: adding and subtracting rounds to the nearest integer
    let tiny = x < -86.0;
    let x = x.clamp(-86.0, 88.0);
    let n = (x * LOG2E + ROUND) - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    let y = p * f32::from_bits(((n as i32 + 127) as u32) << 23);
    if tiny {
        0.0
    } else {
        y
    }
}

/// erf in f32 (Abramowitz & Stegun 7.1.26, |error| ≤ 1.5e-7 plus f32 rounding), branch-free.
#[inline(always)]
pub(crate) fn erf_fast(x: f32) -> f32 {
    let a = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * a);
    let poly = ((((1.061_405_4 * t - 1.453_152_1) * t + 1.421_413_8) * t - 0.284_496_74) * t + 0.254_829_6) * t;
    let y = 1.0 - poly * exp_fast(-a * a);
    y.copysign(x)
}

/// Scalar exact-form GELU with the fast erf (as the [`gelu`] kernel).
#[inline(always)]
pub(crate) fn gelu_scalar(x: f32) -> f32 {
    0.5 * x * (1.0 + erf_fast(x * std::f32::consts::FRAC_1_SQRT_2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_and_erf_match_std_to_float_precision() {
        for i in -2000..=880 {
            let x = i as f32 * 0.1;
            let (a, e) = (exp_f32(x), (x as f64).exp());
            if x > -87.0 {
                assert!(((a as f64 - e) / e).abs() < 3e-7, "exp({x}) = {a}, want {e}");
            } else {
                assert!(a < 2e-38, "exp({x}) = {a}");
            }
        }
        assert!((erf_f32(0.5) - 0.520_499_9).abs() < 2e-7);
        assert!((erf_f32(-1.0) + 0.842_700_8).abs() < 2e-7);
        assert!((erf_f32(2.0) - 0.995_322_3).abs() < 2e-7);
        assert!(erf_f32(0.0).abs() < 2e-7);
    }

    /// exp_fast within 3e-7 relative of f64 exp over the softmax range, exactly 0 below it.
    #[test]
    fn exp_fast_matches_std() {
        assert_eq!(exp_fast(-86.5), 0.0);
        assert_eq!(exp_fast(f32::NEG_INFINITY), 0.0);
        for i in 0..=20000 {
            let x = -86.0 + i as f32 * 0.0043;
            let e = (x as f64).exp();
            let rel = ((exp_fast(x) as f64 - e) / e).abs();
            assert!(rel < 3e-7, "exp_fast({x}) rel err {rel}");
        }
    }
}
