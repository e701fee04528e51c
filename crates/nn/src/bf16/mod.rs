//! bf16 products on the CPU (issue 73): weights converted once to bf16 and packed in K-pairs, activations
//! rounded to bf16 (round to nearest even) while packed, `vdpbf16ps` (`_mm512_dpbf16_ps`) accumulating in f32.
//!
//! Chosen at run time: with AVX512-BF16 ([`path`] = [`Bf16Path::Dpbf16`]) the products run in bf16; without it
//! bf16 is storage only ([`Bf16Path::StorageOnly`]): the bf16 weights are widened to f32 and multiplied by the
//! unrounded f32 activations in the f32 gemm — never an emulated bf16 dot product.
//!
//! Error model (u = 2⁻⁸, bf16's 8 significant bits): each output of a reduction of length K satisfies
//! |bf16 − exact| ≤ (2u + u² + K·2⁻²⁴)·Σ|aᵢbᵢ| — operands rounded once (|δ| ≤ u each, so a product is off by at
//! most 2u + u² relative), the product of two bf16 values exact in f32 (8 × 8 bits), the f32 sums off by at most
//! K·2⁻²⁴ (first order). `vdpbf16ps` treats denormal inputs as zero and flushes denormal results (DAZ/FTZ,
//! independent of MXCSR, Intel SDM), and the conversion `vcvtne2ps2bf16` maps denormal f32 to a signed zero:
//! a term with an operand below 2⁻¹²⁶ in magnitude is dropped whole, and a product or partial sum below 2⁻¹²⁶
//! is lost — an absolute error of at most 2⁻¹²⁶ per term and per addition, added to the bound
//! ([`error_bound`]); invisible at the magnitudes of weights and activations. See docs/research/cpu-bf16.md.

pub mod bench;
pub(crate) mod conv_kernel;
#[cfg(target_arch = "x86_64")]
mod kernel;
#[cfg(test)]
mod tests;

use std::cell::Cell;

/// How a bf16 product runs on this CPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bf16Path {
    /// AVX512-BF16 `vdpbf16ps`: bf16 operands, f32 accumulation.
    Dpbf16,
    /// No bf16 dot product on this CPU: bf16 weights widened to f32, f32 arithmetic (storage only).
    StorageOnly,
}

impl Bf16Path {
    /// The name recorded in bench JSON and run records.
    pub fn name(self) -> &'static str {
        match self {
            Bf16Path::Dpbf16 => "avx512bf16",
            Bf16Path::StorageOnly => "storage-only (no bf16 dot product on this CPU)",
        }
    }
}

thread_local! {
    static MASKED: Cell<bool> = const { Cell::new(false) };
}

/// Runs `f` with AVX512-BF16 detection masked on this thread: every bf16 product called from `f` (on this
/// thread) takes the storage-only path, as on a CPU without the feature. For tests of the fallback.
pub fn with_bf16_masked<R>(f: impl FnOnce() -> R) -> R {
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            MASKED.with(|m| m.set(self.0));
        }
    }
    let _restore = Restore(MASKED.with(|m| m.replace(true)));
    f()
}

/// Whether this CPU multiplies bf16 (`is_x86_feature_detected!("avx512bf16")` and AVX-512F), unless masked on
/// this thread by [`with_bf16_masked`].
pub fn path() -> Bf16Path {
    if MASKED.with(|m| m.get()) {
        return Bf16Path::StorageOnly;
    }
    if hardware_dpbf16() {
        Bf16Path::Dpbf16
    } else {
        Bf16Path::StorageOnly
    }
}

/// The CPU's own answer, ignoring the test mask.
pub fn hardware_dpbf16() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// f32 → bf16 bits, round to nearest even, as `vcvtne2ps2bf16`: zero and denormal → signed zero, infinities
/// kept, NaN → quiet NaN (truncated payload, quiet bit set).
#[inline]
pub fn f32_to_bf16(x: f32) -> u16 {
    let b = x.to_bits();
    let exp = b & 0x7f80_0000;
    if exp == 0 {
        return ((b >> 16) & 0x8000) as u16;
    }
    if exp == 0x7f80_0000 {
        if b & 0x007f_ffff != 0 {
            return ((b >> 16) | 0x0040) as u16;
        }
        return (b >> 16) as u16;
    }
    let lsb = (b >> 16) & 1;
    (b.wrapping_add(0x7fff + lsb) >> 16) as u16
}

/// bf16 bits → f32 (exact).
#[inline]
pub fn bf16_to_f32(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}

/// bf16 bits → f32 as `vdpbf16ps` reads an operand: denormals become a signed zero.
#[inline]
pub fn bf16_to_f32_daz(h: u16) -> f32 {
    if h & 0x7f80 == 0 {
        f32::from_bits(((h & 0x8000) as u32) << 16)
    } else {
        bf16_to_f32(h)
    }
}

/// Rows of A in one packed micro-panel (the register tile's height).
pub(crate) const MR: usize = 12;
/// Columns of B in one packed micro-panel (two zmm of 16 f32 lanes).
pub(crate) const NR: usize = 32;

/// B (K × N) in bf16, packed for `vdpbf16ps`: panels of 32 columns; in a panel, for each K-pair p, the 32
/// u32 words (`B[2p][n] | B[2p+1][n] << 16`) of its columns (zero past N and past an odd K).
pub struct Bf16Weights {
    k: usize,
    n: usize,
    data: Vec<u32>,
}

impl Bf16Weights {
    /// Packs B given row-major K × N.
    pub fn from_kn(b: &[f32], k: usize, n: usize) -> Self {
        assert!(b.len() >= k * n, "bf16 weights: {} values for {k}×{n}", b.len());
        Self::pack(k, n, |kk, nn| b[kk * n + nn])
    }

    /// Packs B = Wᵀ given W row-major N × K (a linear layer's `[out, in]` weight).
    pub fn from_nk(w: &[f32], n: usize, k: usize) -> Self {
        assert!(w.len() >= k * n, "bf16 weights: {} values for {n}×{k}", w.len());
        Self::pack(k, n, |kk, nn| w[nn * k + kk])
    }

    fn pack(k: usize, n: usize, at: impl Fn(usize, usize) -> f32 + Sync) -> Self {
        use rayon::prelude::*;
        let kp = k.div_ceil(2);
        let panels = n.div_ceil(NR);
        let mut data = vec![0u32; panels * kp * NR];
        if kp > 0 {
            data.par_chunks_mut(kp * NR).enumerate().for_each(|(np, panel)| {
                for p in 0..kp {
                    for j in 0..NR {
                        let col = np * NR + j;
                        if col >= n {
                            break;
                        }
                        let lo = f32_to_bf16(at(2 * p, col)) as u32;
                        let hi = if 2 * p + 1 < k { f32_to_bf16(at(2 * p + 1, col)) as u32 } else { 0 };
                        panel[p * NR + j] = lo | (hi << 16);
                    }
                }
            });
        }
        Bf16Weights { k, n, data }
    }

    /// Packs a linear layer's `[out, in]` weight (any dtype or device; read once as f32 on the CPU).
    pub fn from_linear(w: &candle_core::Tensor) -> candle_core::Result<Self> {
        let (n, k) = w.dims2()?;
        let v = w.to_dtype(candle_core::DType::F32)?.to_device(&candle_core::Device::Cpu)?.flatten_all()?.to_vec1::<f32>()?;
        Ok(Self::from_nk(&v, n, k))
    }

    /// Reduction length K.
    pub fn k(&self) -> usize {
        self.k
    }

    /// Output width N.
    pub fn n(&self) -> usize {
        self.n
    }

    /// Bytes held (half of the f32 weights, plus panel padding).
    pub fn bytes(&self) -> usize {
        self.data.len() * 4
    }

    /// `B[kk][nn]` as stored (the bf16 value widened exactly).
    pub fn get(&self, kk: usize, nn: usize) -> f32 {
        let kp = self.k.div_ceil(2);
        let w = self.data[(nn / NR) * kp * NR + (kk / 2) * NR + nn % NR];
        bf16_to_f32(if kk & 1 == 0 { w as u16 } else { (w >> 16) as u16 })
    }

    /// The stored weights widened to f32, row-major K × N (the storage-only path's operand).
    pub fn to_f32_kn(&self) -> Vec<f32> {
        use rayon::prelude::*;
        let (k, n) = (self.k, self.n);
        let mut out = vec![0f32; k * n];
        if n > 0 {
            out.par_chunks_mut(n).enumerate().for_each(|(kk, row)| {
                for (nn, v) in row.iter_mut().enumerate() {
                    *v = self.get(kk, nn);
                }
            });
        }
        out
    }
}

/// C (M × N, row-major, f32) = A (M × K, row-major, f32) · B, or C += A · B when `accumulate`. With AVX512-BF16,
/// A is rounded to bf16 (nearest even) while packed and the products accumulate in f32 in `vdpbf16ps`; otherwise
/// (storage only) B is widened to f32 and multiplied by the unrounded A in the f32 gemm. Returns the path taken.
pub fn matmul_bf16(a: &[f32], m: usize, k: usize, b: &Bf16Weights, c: &mut [f32], accumulate: bool) -> Bf16Path {
    assert_eq!(k, b.k, "bf16 matmul: A has K = {k}, B has K = {}", b.k);
    let n = b.n;
    assert!(a.len() >= m * k && c.len() >= m * n, "bf16 matmul: buffers shorter than {m}×{k} and {m}×{n}");
    let path = path();
    if m == 0 || n == 0 {
        return path;
    }
    match path {
        #[cfg(target_arch = "x86_64")]
        Bf16Path::Dpbf16 => {
            // SAFETY: `path` answered Dpbf16 only where avx512f and avx512bf16 were detected; the lengths
            // were asserted above.
            unsafe { kernel::matmul(a, m, k, b, c, accumulate) };
        }
        _ => {
            let bf = b.to_f32_kn();
            let threads = rayon::current_num_threads();
            let par = if threads > 1 && m * n * k > 1 << 16 { gemm::Parallelism::Rayon(threads) } else { gemm::Parallelism::None };
            if k == 0 {
                if !accumulate {
                    c[..m * n].fill(0.0);
                }
                return Bf16Path::StorageOnly;
            }
            // SAFETY: lengths asserted above; B is k × n row-major.
            unsafe {
                gemm::gemm(
                    m,
                    n,
                    k,
                    c.as_mut_ptr(),
                    1,
                    n as isize,
                    accumulate,
                    a.as_ptr(),
                    1,
                    k as isize,
                    bf.as_ptr(),
                    1,
                    n as isize,
                    1.0,
                    1.0,
                    false,
                    false,
                    false,
                    par,
                );
            }
            return Bf16Path::StorageOnly;
        }
    }
    path
}

/// The error model's bound for one output: (2u + u² + K·2⁻²⁴)·Σ|aᵢbᵢ| + 2K·2⁻¹²⁶ (the last term: the
/// denormal flush of operands, products and partial sums), with `abs_sum` = Σ|aᵢbᵢ| of the unrounded operands.
pub fn error_bound(k: usize, abs_sum: f64) -> f64 {
    let u = 2f64.powi(-8);
    (2.0 * u + u * u + k as f64 * 2f64.powi(-24)) * abs_sum + 2.0 * k as f64 * 2f64.powi(-126)
}
