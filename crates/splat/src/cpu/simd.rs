//! 8-lane f32 vectors for the tile kernels: an AVX2 implementation (selected at run time) and a portable
//! array implementation with bit-identical results (no FMA contraction anywhere, same operation order).
//! Masks are vectors whose lanes are all-ones or all-zeros bits.

/// Lanes per vector.
pub(crate) const LANES: usize = 8;

pub(crate) trait F8: Copy {
    /// # Safety
    /// `p` must be valid for reading 8 f32.
    unsafe fn load(p: *const f32) -> Self;
    /// # Safety
    /// `p` must be valid for writing 8 f32.
    unsafe fn store(self, p: *mut f32);
    fn splat(v: f32) -> Self;
    /// (0, 1, …, 7)
    fn iota() -> Self;
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    fn div(self, o: Self) -> Self;
    /// Correctly rounded square root (IEEE, as `f32::sqrt`).
    fn sqrt(self) -> Self;
    /// Round towards +infinity (as `f32::ceil`).
    fn ceil(self) -> Self;
    /// Like `f32::min`: the non-NaN operand `o` wins when `self` is NaN.
    fn min(self, o: Self) -> Self;
    fn max(self, o: Self) -> Self;
    fn and(self, m: Self) -> Self;
    /// `self & !m`
    fn and_not(self, m: Self) -> Self;
    fn xor(self, m: Self) -> Self;
    /// `m ? a : b` per lane.
    fn select(m: Self, a: Self, b: Self) -> Self;
    fn gt(self, o: Self) -> Self;
    fn lt(self, o: Self) -> Self;
    fn le(self, o: Self) -> Self;
    fn ge(self, o: Self) -> Self;
    /// Signed 32-bit comparison of the raw bits.
    fn gt_i32(self, o: Self) -> Self;
    /// One bit per lane (lane k → bit k).
    fn bits(self) -> u32;
    /// ((raw bits + 127) << 23) reinterpreted as f32 (integer arithmetic on the bits).
    fn pow2_bits(self) -> Self;
    /// Horizontal sum in a fixed order: ((l0+l4)+(l2+l6)) + ((l1+l5)+(l3+l7)).
    fn hsum(self) -> f32;
}

const MAGIC: f32 = 12_582_912.0; // 1.5 · 2^23: adding it rounds to an integer held in the low mantissa bits

/// exp(x) (Cephes expf polynomial, ~1 ulp on the rasterizer's range; x clamped to [-87, 88]).
#[inline(always)]
pub(crate) fn exp8<V: F8>(x: V) -> V {
    let x = x.max(V::splat(-87.0)).min(V::splat(88.0));
    let v = x.mul(V::splat(std::f32::consts::LOG2_E)).add(V::splat(MAGIC));
    let n = v.sub(V::splat(MAGIC));
    let r = x.sub(n.mul(V::splat(0.693_359_4))).add(n.mul(V::splat(2.121_944_4e-4)));
    let z = r.mul(r);
    let mut p = V::splat(1.987_569_1e-4).mul(r).add(V::splat(1.398_199_9e-3));
    p = p.mul(r).add(V::splat(8.333_452e-3));
    p = p.mul(r).add(V::splat(4.166_579_6e-2));
    p = p.mul(r).add(V::splat(1.666_666_5e-1));
    p = p.mul(r).add(V::splat(5.000_000_1e-1));
    let y = p.mul(z).add(r).add(V::splat(1.0));
    y.mul(v.pow2_bits())
}

/// Scalar exp with exactly the operations of [`exp8`].
#[cfg(test)]
#[inline(always)]
pub(crate) fn exp1(x: f32) -> f32 {
    let x = x.max(-87.0).min(88.0);
    let v = x * std::f32::consts::LOG2_E + MAGIC;
    let n = v - MAGIC;
    let r = x - n * 0.693_359_4 + n * 2.121_944_4e-4;
    let z = r * r;
    let mut p = 1.987_569_1e-4 * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 5.000_000_1e-1;
    let y = p * z + r + 1.0;
    y * f32::from_bits(v.to_bits().wrapping_add(127) << 23)
}

/// Portable fallback: plain arrays (LLVM vectorises what it can).
#[derive(Clone, Copy)]
pub(crate) struct Arr(pub [f32; LANES]);

impl Arr {
    #[inline(always)]
    fn map(self, f: impl Fn(f32) -> f32) -> Self {
        Arr(self.0.map(f))
    }
    #[inline(always)]
    fn zip(self, o: Self, f: impl Fn(f32, f32) -> f32) -> Self {
        let mut r = [0f32; LANES];
        for k in 0..LANES {
            r[k] = f(self.0[k], o.0[k]);
        }
        Arr(r)
    }
    #[inline(always)]
    fn zipb(self, o: Self, f: impl Fn(u32, u32) -> u32) -> Self {
        self.zip(o, |a, b| f32::from_bits(f(a.to_bits(), b.to_bits())))
    }
    #[inline(always)]
    fn cmp(self, o: Self, f: impl Fn(f32, f32) -> bool) -> Self {
        self.zip(o, |a, b| f32::from_bits(if f(a, b) { !0 } else { 0 }))
    }
}

impl F8 for Arr {
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        Arr(std::ptr::read_unaligned(p as *const [f32; LANES]))
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        std::ptr::write_unaligned(p as *mut [f32; LANES], self.0)
    }
    #[inline(always)]
    fn splat(v: f32) -> Self {
        Arr([v; LANES])
    }
    #[inline(always)]
    fn iota() -> Self {
        Arr([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0])
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.zip(o, |a, b| a + b)
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self.zip(o, |a, b| a - b)
    }
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        self.zip(o, |a, b| a * b)
    }
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        self.zip(o, |a, b| a / b)
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        self.map(f32::sqrt)
    }
    #[inline(always)]
    fn ceil(self) -> Self {
        self.map(f32::ceil)
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        // minps semantics: the second operand when either is NaN or they compare equal.
        self.zip(o, |a, b| if a < b { a } else { b })
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        self.zip(o, |a, b| if a > b { a } else { b })
    }
    #[inline(always)]
    fn and(self, m: Self) -> Self {
        self.zipb(m, |a, b| a & b)
    }
    #[inline(always)]
    fn and_not(self, m: Self) -> Self {
        self.zipb(m, |a, b| a & !b)
    }
    #[inline(always)]
    fn xor(self, m: Self) -> Self {
        self.zipb(m, |a, b| a ^ b)
    }
    #[inline(always)]
    fn select(m: Self, a: Self, b: Self) -> Self {
        let mut r = [0f32; LANES];
        for k in 0..LANES {
            r[k] = if m.0[k].to_bits() >> 31 != 0 { a.0[k] } else { b.0[k] };
        }
        Arr(r)
    }
    #[inline(always)]
    fn gt(self, o: Self) -> Self {
        self.cmp(o, |a, b| a > b)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> Self {
        self.cmp(o, |a, b| a < b)
    }
    #[inline(always)]
    fn le(self, o: Self) -> Self {
        self.cmp(o, |a, b| a <= b)
    }
    #[inline(always)]
    fn ge(self, o: Self) -> Self {
        self.cmp(o, |a, b| a >= b)
    }
    #[inline(always)]
    fn gt_i32(self, o: Self) -> Self {
        self.zipb(o, |a, b| if (a as i32) > (b as i32) { !0 } else { 0 })
    }
    #[inline(always)]
    fn bits(self) -> u32 {
        let mut m = 0u32;
        for k in 0..LANES {
            m |= (self.0[k].to_bits() >> 31) << k;
        }
        m
    }
    #[inline(always)]
    fn pow2_bits(self) -> Self {
        self.map(|a| f32::from_bits(a.to_bits().wrapping_add(127) << 23))
    }
    #[inline(always)]
    fn hsum(self) -> f32 {
        let l = self.0;
        ((l[0] + l[4]) + (l[2] + l[6])) + ((l[1] + l[5]) + (l[3] + l[7]))
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) use avx::Avx;

#[cfg(target_arch = "x86_64")]
mod avx {
    use super::{F8, LANES};
    use std::arch::x86_64::*;

    /// AVX2 vector; only constructed inside `#[target_feature(enable = "avx2")]` functions.
    #[derive(Clone, Copy)]
    pub(crate) struct Avx(__m256);

    // SAFETY (all methods): these are only inlined into functions compiled with AVX2 enabled, which are only
    // called after `is_x86_feature_detected!("avx2")`.
    impl F8 for Avx {
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            Avx(_mm256_loadu_ps(p))
        }
        #[inline(always)]
        unsafe fn store(self, p: *mut f32) {
            _mm256_storeu_ps(p, self.0)
        }
        #[inline(always)]
        fn splat(v: f32) -> Self {
            unsafe { Avx(_mm256_set1_ps(v)) }
        }
        #[inline(always)]
        fn iota() -> Self {
            unsafe { Avx(_mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0)) }
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            unsafe { Avx(_mm256_add_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            unsafe { Avx(_mm256_sub_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            unsafe { Avx(_mm256_mul_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            unsafe { Avx(_mm256_div_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            unsafe { Avx(_mm256_sqrt_ps(self.0)) }
        }
        #[inline(always)]
        fn ceil(self) -> Self {
            unsafe { Avx(_mm256_round_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(self.0)) }
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            unsafe { Avx(_mm256_min_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            unsafe { Avx(_mm256_max_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn and(self, m: Self) -> Self {
            unsafe { Avx(_mm256_and_ps(self.0, m.0)) }
        }
        #[inline(always)]
        fn and_not(self, m: Self) -> Self {
            unsafe { Avx(_mm256_andnot_ps(m.0, self.0)) }
        }
        #[inline(always)]
        fn xor(self, m: Self) -> Self {
            unsafe { Avx(_mm256_xor_ps(self.0, m.0)) }
        }
        #[inline(always)]
        fn select(m: Self, a: Self, b: Self) -> Self {
            unsafe { Avx(_mm256_blendv_ps(b.0, a.0, m.0)) }
        }
        #[inline(always)]
        fn gt(self, o: Self) -> Self {
            unsafe { Avx(_mm256_cmp_ps::<_CMP_GT_OQ>(self.0, o.0)) }
        }
        #[inline(always)]
        fn lt(self, o: Self) -> Self {
            unsafe { Avx(_mm256_cmp_ps::<_CMP_LT_OQ>(self.0, o.0)) }
        }
        #[inline(always)]
        fn le(self, o: Self) -> Self {
            unsafe { Avx(_mm256_cmp_ps::<_CMP_LE_OQ>(self.0, o.0)) }
        }
        #[inline(always)]
        fn ge(self, o: Self) -> Self {
            unsafe { Avx(_mm256_cmp_ps::<_CMP_GE_OQ>(self.0, o.0)) }
        }
        #[inline(always)]
        fn gt_i32(self, o: Self) -> Self {
            unsafe { Avx(_mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_castps_si256(self.0), _mm256_castps_si256(o.0)))) }
        }
        #[inline(always)]
        fn bits(self) -> u32 {
            unsafe { _mm256_movemask_ps(self.0) as u32 }
        }
        #[inline(always)]
        fn pow2_bits(self) -> Self {
            unsafe {
                let i = _mm256_add_epi32(_mm256_castps_si256(self.0), _mm256_set1_epi32(127));
                Avx(_mm256_castsi256_ps(_mm256_slli_epi32::<23>(i)))
            }
        }
        #[inline(always)]
        fn hsum(self) -> f32 {
            unsafe {
                let lo = _mm256_castps256_ps128(self.0);
                let hi = _mm256_extractf128_ps::<1>(self.0);
                let s = _mm_add_ps(lo, hi); // (l0+l4, l1+l5, l2+l6, l3+l7)
                let t = _mm_add_ps(s, _mm_movehl_ps(s, s)); // (s0+s2, s1+s3, ..)
                let u = _mm_add_ss(t, _mm_shuffle_ps::<0b01>(t, t)); // t0 + t1
                _mm_cvtss_f32(u)
            }
        }
    }

    const _: () = assert!(LANES == 8);
}

/// Instruction sets the kernels are compiled for. `Avx512` runs the same 8-lane AVX2 code with AVX-512VL
/// enabled: 32 vector registers keep the kernels' constants out of memory (same operations, same results).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum Isa {
    Portable = 0,
    Avx2 = 1,
    Avx512 = 2,
}

/// Test hook: the highest instruction set the dispatchers may pick.
static MAX_ISA: std::sync::atomic::AtomicU8 = std::sync::atomic::AtomicU8::new(Isa::Avx512 as u8);

/// Serialises the tests that switch instruction sets (the hook is global).
#[cfg(test)]
pub(crate) static ISA_TEST_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

#[cfg(test)]
pub(crate) fn set_max_isa(isa: Isa) {
    MAX_ISA.store(isa as u8, std::sync::atomic::Ordering::SeqCst);
}

/// The best instruction set available here (and allowed by the test hook).
#[inline]
pub(crate) fn isa() -> Isa {
    let max = MAX_ISA.load(std::sync::atomic::Ordering::Relaxed);
    #[cfg(target_arch = "x86_64")]
    {
        let avx2 = std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma");
        let avx512 = avx2 && std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512vl");
        if avx512 && max >= Isa::Avx512 as u8 {
            return Isa::Avx512;
        }
        if avx2 && max >= Isa::Avx2 as u8 {
            return Isa::Avx2;
        }
    }
    let _ = max;
    Isa::Portable
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_lanes_match_scalar_and_std() {
        let xs: Vec<f32> = (0..4096).map(|i| -40.0 + i as f32 * 0.0123).collect();
        let mut worst = 0f64;
        for c in xs.chunks_exact(LANES) {
            let v = unsafe { Arr::load(c.as_ptr()) };
            let e = exp8(v).0;
            for k in 0..LANES {
                assert_eq!(e[k].to_bits(), exp1(c[k]).to_bits());
                let want = (c[k] as f64).exp();
                worst = worst.max(((e[k] as f64) - want).abs() / want);
            }
        }
        assert!(worst < 3e-7, "relative error {worst:.3e}");
    }

    #[test]
    fn portable_mask_ops() {
        let a = Arr([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        let m = a.gt(Arr::splat(2.5));
        assert_eq!(m.bits(), 0b1111_1000);
        assert_eq!(a.hsum(), 28.0);
        let s = Arr::select(m, Arr::splat(1.0), Arr::splat(-1.0));
        assert_eq!(s.0, [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0, 1.0]);
    }
}
