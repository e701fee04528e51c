//! The weight-stationary bf16 gemm of the convolutions: A = the weights, rounded to bf16 and packed once
//! ([`Bf16Rows`]: [`MR`]-row micro-panels of K-pairs), B = the activations as rows of K-pair words
//! (`bf16(X[2p][j]) | bf16(X[2p+1][j]) << 16`) that start at arbitrary offsets of one buffer, so a conv tap's
//! shifted view or a clip's frames are just offsets. C (f32) = α·A·B, or C += α·A·B.
//!
//! Per task (a range of 32-column B panels × a range of A panels, chosen by `split`), per block of [`KCP`] pairs: the task's B
//! panels are copied into a contiguous block (the rows are strided and the shifts unaligned; a packed panel
//! of 32 KiB stays in L1 while the A panels of a [`MBP`]-panel block stream from L2), then the 12 × 32
//! register tile of the linear gemm (`vdpbf16ps`, A broadcast from memory) sweeps them.

use super::{f32_to_bf16, MR, NR};

/// K-pairs per block (a packed B panel 32 KiB, as in the linear gemm).
#[cfg(target_arch = "x86_64")]
const KCP: usize = 256;
/// A micro-panels per inner block (96 rows, 96 KiB of A per K-block in L2).
#[cfg(target_arch = "x86_64")]
const MBP: usize = 8;
/// Most B panels per task (256 columns, 256 KiB packed per K-block).
#[cfg(target_arch = "x86_64")]
const NCH: usize = 8;

/// A (M × K) in bf16 (round to nearest even at pack time): for each [`MR`]-row panel, for each K-pair p, the
/// MR words `A[r][2p] | A[r][2p+1] << 16` (zero past M).
pub(crate) struct Bf16Rows {
    m: usize,
    kp: usize,
    data: Vec<u32>,
}

impl Bf16Rows {
    /// Packs M rows of `kp` pairs; `at(r, p)` gives row r's two values of pair p (f32, rounded here).
    pub(crate) fn pack(m: usize, kp: usize, at: impl Fn(usize, usize) -> (f32, f32) + Sync) -> Self {
        use rayon::prelude::*;
        let mut data = vec![0u32; m.div_ceil(MR) * kp * MR];
        if kp > 0 {
            data.par_chunks_mut(kp * MR).enumerate().for_each(|(mp, panel)| {
                for r in 0..MR.min(m - mp * MR) {
                    for p in 0..kp {
                        let (lo, hi) = at(mp * MR + r, p);
                        panel[p * MR + r] = f32_to_bf16(lo) as u32 | (f32_to_bf16(hi) as u32) << 16;
                    }
                }
            });
        }
        Bf16Rows { m, kp, data }
    }

    /// The stored pair word of row r, pair p.
    pub(crate) fn word(&self, r: usize, p: usize) -> u32 {
        self.data[((r / MR) * self.kp + p) * MR + r % MR]
    }

    pub(crate) fn bytes(&self) -> usize {
        self.data.len() * 4
    }
}

/// One row of pair words from two f32 rows (`hi` None: zero high halves), round to nearest even as
/// `f32_to_bf16`. Vectorised with AVX512-BF16; the scalar conversion elsewhere (same bits).
pub(crate) fn pair_row(lo: &[f32], hi: Option<&[f32]>, out: &mut [u32]) {
    assert!(out.len() <= lo.len() && hi.is_none_or(|h| out.len() <= h.len()), "pair row: {} words from {} values", out.len(), lo.len());
    #[cfg(target_arch = "x86_64")]
    if super::hardware_dpbf16() {
        // SAFETY: the features were detected; the lengths were asserted above.
        unsafe { avx::pair_row(lo, hi, out) };
        return;
    }
    for (j, o) in out.iter_mut().enumerate() {
        *o = f32_to_bf16(lo[j]) as u32 | (hi.map_or(0, |h| f32_to_bf16(h[j])) as u32) << 16;
    }
}

/// C (m × n, row stride `ldc`) = α·A·B, or C += α·A·B when `accumulate`, where B's row q (A's pair `a0 + q`)
/// is the n words `b[rows[q]..rows[q] + n]`. Needs AVX512-BF16 (the callers check [`super::path`]).
#[allow(clippy::too_many_arguments)]
pub(crate) fn matmul_rows(a: &Bf16Rows, a0: usize, b: &[u32], rows: &[usize], n: usize, c: &mut [f32], ldc: usize, alpha: f32, accumulate: bool) {
    let m = a.m;
    assert!(a0 + rows.len() <= a.kp, "bf16 rows gemm: pairs {a0}..{} of {}", a0 + rows.len(), a.kp);
    assert!(rows.iter().all(|&r| r + n <= b.len()), "bf16 rows gemm: a B row runs past {} words", b.len());
    assert!(m == 0 || n == 0 || (ldc >= n && c.len() >= (m - 1) * ldc + n), "bf16 rows gemm: C shorter than {m}×{n} at stride {ldc}");
    if m == 0 || n == 0 {
        return;
    }
    if rows.is_empty() {
        if !accumulate {
            c.chunks_mut(ldc).take(m).for_each(|r| r[..n].fill(0.0));
        }
        return;
    }
    assert!(super::hardware_dpbf16(), "bf16 rows gemm: no AVX512-BF16 on this CPU");
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the features were detected; B rows, A's pair range and C's extent were asserted above.
    unsafe {
        avx::matmul_rows(a, a0, b, rows, n, c, ldc, alpha, accumulate)
    };
}

#[cfg(target_arch = "x86_64")]
mod avx {
    use std::arch::x86_64::*;

    use rayon::prelude::*;

    use super::{Bf16Rows, KCP, MBP, MR, NCH, NR};

    #[derive(Clone, Copy)]
    struct SendPtr(*mut f32);
    // SAFETY: tasks write disjoint tiles of C.
    unsafe impl Send for SendPtr {}
    unsafe impl Sync for SendPtr {}

    #[inline]
    fn mask(cols: usize) -> __mmask16 {
        if cols >= 16 {
            0xffff
        } else {
            ((1u32 << cols) - 1) as __mmask16
        }
    }

    /// 16 f32 → 16 bf16 (RNE) zero-extended to u32 lanes.
    #[inline]
    #[target_feature(enable = "avx512f,avx512bf16")]
    unsafe fn widen16(v: __m512) -> __m512i {
        _mm512_cvtepu16_epi32(std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(v)))
    }

    #[target_feature(enable = "avx512f,avx512bf16")]
    pub(super) unsafe fn pair_row(lo: &[f32], hi: Option<&[f32]>, out: &mut [u32]) {
        let n = out.len();
        let mut j = 0;
        while j < n {
            let k = mask(n - j);
            let l = widen16(_mm512_maskz_loadu_ps(k, lo.as_ptr().add(j)));
            let w = match hi {
                Some(h) => _mm512_or_si512(l, _mm512_slli_epi32::<16>(widen16(_mm512_maskz_loadu_ps(k, h.as_ptr().add(j))))),
                None => l,
            };
            _mm512_mask_storeu_epi32(out.as_mut_ptr().add(j) as *mut _, k, w);
            j += 16;
        }
    }

    /// See [`super::matmul_rows`]; the caller checked the features and the extents.
    #[target_feature(enable = "avx512f,avx512bf16")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn matmul_rows(a: &Bf16Rows, a0: usize, b: &[u32], rows: &[usize], n: usize, c: &mut [f32], ldc: usize, alpha: f32, accumulate: bool) {
        let (m, kp) = (a.m, rows.len());
        let (mpanels, npanels) = (m.div_ceil(MR), n.div_ceil(NR));
        let (chunk, mchunk) = split(mpanels, npanels, rayon::current_num_threads());
        let (nchunks, msplit) = (npanels.div_ceil(chunk), mpanels.div_ceil(mchunk));
        let cp = SendPtr(c.as_mut_ptr());
        (0..nchunks * msplit).into_par_iter().for_each(|t| {
            #[allow(clippy::redundant_locals)] // the whole Send wrapper, not its raw-pointer field (edition 2021 captures)
            let cp = cp;
            let (nc, mc) = (t / msplit, t % msplit);
            let (np0, np1) = (nc * chunk, ((nc + 1) * chunk).min(npanels));
            let (mp0, mp1) = (mc * mchunk, ((mc + 1) * mchunk).min(mpanels));
            let mut bpack = vec![0u32; (np1 - np0) * KCP * NR];
            let mut p0 = 0;
            while p0 < kp {
                let pl = KCP.min(kp - p0);
                for np in np0..np1 {
                    let (j0, cols) = (np * NR, (n - np * NR).min(NR));
                    let (k0, k1) = (mask(cols), mask(cols.saturating_sub(16)));
                    let dst = bpack.as_mut_ptr().add((np - np0) * KCP * NR);
                    for q in 0..pl {
                        // SAFETY: row + j0 + cols ≤ row + n ≤ b.len() (asserted by the caller).
                        let src = b.as_ptr().add(rows[p0 + q] + j0);
                        _mm512_storeu_si512(dst.add(q * NR) as *mut _, _mm512_maskz_loadu_epi32(k0, src as *const _));
                        _mm512_storeu_si512(dst.add(q * NR + 16) as *mut _, _mm512_maskz_loadu_epi32(k1, src.add(16) as *const _));
                    }
                }
                let mut mb = mp0;
                while mb < mp1 {
                    let me = (mb + MBP).min(mp1);
                    for np in np0..np1 {
                        let cols = (n - np * NR).min(NR);
                        let bpanel = bpack.as_ptr().add((np - np0) * KCP * NR);
                        for mp in mb..me {
                            let rows_here = (m - mp * MR).min(MR);
                            let apanel = a.data.as_ptr().add((mp * a.kp + a0 + p0) * MR);
                            // SAFETY: the tile (rows_here × cols at mp·MR, np·NR) lies inside C and belongs
                            // to this task only; A holds pl pairs from a0 + p0, the packed panel pl pairs.
                            tile(pl, apanel, bpanel, cp.0.add(mp * MR * ldc + np * NR), ldc, rows_here, cols, alpha, accumulate || p0 > 0);
                        }
                    }
                    mb = me;
                }
                p0 += pl;
            }
        });
    }

    /// (B panels, A panels) per task: at least 4 tasks a thread (an even share where there are few), and of
    /// those splits the least traffic: each column chunk streams its A range over all K, each A range packs
    /// its B columns — nchunks·M + msplit·N words per pair.
    fn split(mpanels: usize, npanels: usize, threads: usize) -> (usize, usize) {
        let want = 4 * threads;
        let mut best = (usize::MAX, 1, mpanels);
        for chunk in 1..=NCH.min(npanels) {
            let nchunks = npanels.div_ceil(chunk);
            let mut msplit = want.div_ceil(nchunks).clamp(1, mpanels);
            while nchunks * msplit < 2 * want && (nchunks * msplit) % threads != 0 && msplit < mpanels {
                msplit += 1;
            }
            let mchunk = mpanels.div_ceil(msplit);
            let cost = nchunks * mpanels * MR + mpanels.div_ceil(mchunk) * npanels * NR;
            if cost < best.0 || (cost == best.0 && chunk > best.1) {
                best = (cost, chunk, mchunk);
            }
        }
        (best.1, best.2)
    }

    /// One MR × NR tile over `pl` pairs (A: [pair][MR] words, B: [pair][NR] words): acc = Σ_p A[·][p] ⊙ B[p][·],
    /// then C = α·acc, or C += α·acc when `load`; stores rows × cols.
    #[target_feature(enable = "avx512f,avx512bf16")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn tile(pl: usize, a: *const u32, b: *const u32, c: *mut f32, ldc: usize, rows: usize, cols: usize, alpha: f32, load: bool) {
        let (m0, m1) = (mask(cols), mask(cols.saturating_sub(16)));
        let mut acc = [[_mm512_setzero_ps(); 2]; MR];
        for p in 0..pl {
            let b0: __m512bh = std::mem::transmute(_mm512_loadu_si512(b.add(p * NR) as *const _));
            let b1: __m512bh = std::mem::transmute(_mm512_loadu_si512(b.add(p * NR + 16) as *const _));
            let ar = a.add(p * MR);
            for (r, row) in acc.iter_mut().enumerate() {
                let av: __m512bh = std::mem::transmute(_mm512_set1_epi32(*ar.add(r) as i32));
                row[0] = _mm512_dpbf16_ps(row[0], av, b0);
                row[1] = _mm512_dpbf16_ps(row[1], av, b1);
            }
        }
        let al = _mm512_set1_ps(alpha);
        for (r, row) in acc.iter().enumerate().take(rows) {
            let cr = c.add(r * ldc);
            let (v0, v1) = if load {
                (_mm512_fmadd_ps(al, row[0], _mm512_maskz_loadu_ps(m0, cr)), _mm512_fmadd_ps(al, row[1], _mm512_maskz_loadu_ps(m1, cr.add(16))))
            } else {
                (_mm512_mul_ps(al, row[0]), _mm512_mul_ps(al, row[1]))
            };
            _mm512_mask_storeu_ps(cr, m0, v0);
            _mm512_mask_storeu_ps(cr.add(16), m1, v1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::bench::fill;
    use super::super::{bf16_to_f32_daz, error_bound, path, Bf16Path};
    use super::*;

    /// Rounded the way the kernel reads an operand.
    fn r(x: f32) -> f64 {
        bf16_to_f32_daz(f32_to_bf16(x)) as f64
    }

    #[test]
    fn pair_row_rounds_as_the_scalar_conversion() {
        let mut v = fill(77, 3);
        // Ties both ways, the largest finite value, a denormal, NaN.
        v[..6].copy_from_slice(&[1.0 + 2f32.powi(-8), 1.0 + 3.0 * 2f32.powi(-8), f32::MAX, 1e-40, f32::NAN, -0.0]);
        let hi = fill(77, 4);
        for len in [0, 1, 15, 16, 17, 38] {
            for h in [None, Some(&hi[..])] {
                let mut got = vec![7u32; len];
                pair_row(&v, h, &mut got);
                for j in 0..len {
                    let want = f32_to_bf16(v[j]) as u32 | (h.map_or(0, |h| f32_to_bf16(h[j])) as u32) << 16;
                    assert_eq!(got[j], want, "len {len} word {j}");
                }
            }
        }
    }

    /// Pairs of A from a0 against arbitrary row offsets of B, α ≠ 1, accumulate onto C: every output within
    /// the model of the unrounded operands (+ C's own store rounding per K-block, 2⁻²⁴·(|C₀| + |α|·Σ|ab|)).
    #[test]
    fn rows_gemm_holds_the_error_model_on_offsets_ranges_and_accumulate() {
        if path() != Bf16Path::Dpbf16 {
            eprintln!("no AVX512-BF16 on this CPU: the rows gemm is not exercised");
            return;
        }
        for (seed, (m, kp_all, a0, kp, n, ldc)) in
            [(1u64, (13, 9, 2, 5, 45, 50)), (2, (25, 600, 30, 521, 70, 70)), (3, (1, 1, 0, 1, 1, 1)), (4, (40, 300, 0, 300, 200, 203))].into_iter()
        {
            let av = fill(m * 2 * kp_all, seed);
            let a = Bf16Rows::pack(m, kp_all, |i, p| (av[i * 2 * kp_all + 2 * p], av[i * 2 * kp_all + 2 * p + 1]));
            // B rows scattered over a buffer: row q at a pseudo-random offset.
            let blen = kp * 3 + n + 64;
            let bv = fill(2 * blen, seed + 10);
            let mut b = vec![0u32; blen];
            pair_row(&bv[..blen], Some(&bv[blen..]), &mut b);
            let rows: Vec<usize> = (0..kp).map(|q| (q * 7 + seed as usize * 13) % (blen - n)).collect();
            let bval = |q: usize, j: usize, h: usize| if h == 0 { bv[rows[q] + j] } else { bv[blen + rows[q] + j] };
            for accumulate in [false, true] {
                let alpha = 0.75f32;
                let c0 = fill(m * ldc, seed + 20);
                let mut c = c0.clone();
                matmul_rows(&a, a0, &b, &rows, n, &mut c, ldc, alpha, accumulate);
                let blocks = kp.div_ceil(256) as f64;
                for i in 0..m {
                    for j in 0..n {
                        let (mut s, mut sa) = (0f64, 0f64);
                        for q in 0..kp {
                            for h in 0..2 {
                                let t = av[i * 2 * kp_all + 2 * (a0 + q) + h] as f64 * bval(q, j, h) as f64;
                                s += t;
                                sa += t.abs();
                            }
                        }
                        let base = if accumulate { c0[i * ldc + j] as f64 } else { 0.0 };
                        let want = base + alpha as f64 * s;
                        let tol = alpha as f64 * error_bound(2 * kp, sa) + blocks * 2f64.powi(-24) * (base.abs() + alpha as f64 * sa);
                        let got = c[i * ldc + j] as f64;
                        assert!((got - want).abs() <= tol, "seed {seed} acc {accumulate}: C[{i},{j}] {got} want {want} tol {tol}");
                        // The tight check: the rounded operands' sum, only f32 summation differs.
                        let terms = (0..kp).flat_map(|q| (0..2).map(move |h| (q, h)));
                        let (sr, sra) = terms.fold((0f64, 0f64), |(s, sa), (q, h)| {
                            let t = r(av[i * 2 * kp_all + 2 * (a0 + q) + h]) * r(bval(q, j, h));
                            (s + t, sa + t.abs())
                        });
                        let tight = alpha as f64 * (2 * kp) as f64 * 2f64.powi(-24) * sra + blocks * 2f64.powi(-24) * (base.abs() + alpha as f64 * sra);
                        assert!(
                            (got - base - alpha as f64 * sr).abs() <= tight,
                            "seed {seed}: C[{i},{j}] {got} off the rounded-operand sum {}",
                            base + alpha as f64 * sr
                        );
                    }
                    // Columns past n stay untouched.
                    for j in n..ldc {
                        assert_eq!(c[i * ldc + j].to_bits(), c0[i * ldc + j].to_bits(), "seed {seed}: C[{i},{j}] past n written");
                    }
                }
            }
        }
    }
}
