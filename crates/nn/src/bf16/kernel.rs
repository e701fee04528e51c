//! The AVX512-BF16 gemm: A packed in [`MR`]-row micro-panels, B in [`NR`]-column micro-panels (both as u32
//! K-pairs), a 12 × 32 register tile (24 zmm accumulators, `vdpbf16ps` with A broadcast from memory), K blocked
//! by [`KCP`] pairs so a B micro-panel stays in L1 while the A panels of one block stream from L2; rayon over
//! (row block, column block) tasks.

use std::arch::x86_64::*;

use rayon::prelude::*;

use super::{f32_to_bf16, Bf16Weights, MR, NR};

/// K-pairs per block: a B micro-panel is KCP·32·4 = 24 KiB, an A micro-panel KCP·12·4 = 9 KiB.
const KCP: usize = 192;
/// Micro-panels of A per task (96 rows).
const MBP: usize = 8;
/// Micro-panels of B per task (128 columns).
const NBP: usize = 4;

#[derive(Clone, Copy)]
struct SendPtr(*mut f32);
// SAFETY: tasks write disjoint tiles of C.
unsafe impl Send for SendPtr {}
unsafe impl Sync for SendPtr {}

/// Converts one row of A to bf16 words (pairs), round to nearest even, zero-padded to `words.len()` pairs.
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn row_to_pairs(row: &[f32], words: &mut [u32]) {
    let k = row.len();
    let mut i = 0;
    // 32 f32 → 32 bf16 = 16 words per step.
    while i + 32 <= k {
        let lo = _mm512_loadu_ps(row.as_ptr().add(i));
        let hi = _mm512_loadu_ps(row.as_ptr().add(i + 16));
        // cvtne2ps_pbh(a, b): b → the low 16 bf16, a → the high 16.
        let v: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(hi, lo));
        _mm512_storeu_si512(words.as_mut_ptr().add(i / 2) as *mut _, v);
        i += 32;
    }
    while i < k {
        let lo = f32_to_bf16(row[i]) as u32;
        let hi = if i + 1 < k { f32_to_bf16(row[i + 1]) as u32 } else { 0 };
        words[i / 2] = lo | (hi << 16);
        i += 2;
    }
    for w in &mut words[k.div_ceil(2)..] {
        *w = 0;
    }
}

/// A (m × k) → [panel][pair][MR] words; rows past m are zero.
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn pack_a(a: &[f32], m: usize, k: usize) -> Vec<u32> {
    let kp = k.div_ceil(2);
    let panels = m.div_ceil(MR);
    let mut out = vec![0u32; panels * kp * MR];
    out.par_chunks_mut(kp * MR).enumerate().for_each(|(mp, panel)| {
        let mut words = vec![0u32; kp];
        for r in 0..MR {
            let row = mp * MR + r;
            if row >= m {
                break;
            }
            // SAFETY: the caller's features; the row lies inside a.
            unsafe { row_to_pairs(&a[row * k..row * k + k], &mut words) };
            for (p, w) in words.iter().enumerate() {
                panel[p * MR + r] = *w;
            }
        }
    });
    out
}

/// Packed A of `matmul` for tests: the rounded words of row `r`, pair `p`.
#[cfg(test)]
pub(crate) fn packed_a_for_test(a: &[f32], m: usize, k: usize) -> Vec<u32> {
    // SAFETY: tests call this only where the feature was detected.
    unsafe { pack_a(a, m, k) }
}

/// C = A·B (or += when `accumulate`).
///
/// # Safety
/// avx512f and avx512bf16 must be available; a, b, c must hold m×k, k×n (packed), m×n values.
#[target_feature(enable = "avx512f,avx512bf16")]
pub(crate) unsafe fn matmul(a: &[f32], m: usize, k: usize, b: &Bf16Weights, c: &mut [f32], accumulate: bool) {
    let n = b.n;
    let kp = k.div_ceil(2);
    if kp == 0 {
        if !accumulate {
            c[..m * n].fill(0.0);
        }
        return;
    }
    let ap = pack_a(a, m, k);
    let (mpanels, npanels) = (m.div_ceil(MR), n.div_ceil(NR));
    let (mblocks, nblocks) = (mpanels.div_ceil(MBP), npanels.div_ceil(NBP));
    let cp = SendPtr(c.as_mut_ptr());
    let bp = &b.data;
    (0..mblocks * nblocks).into_par_iter().for_each(|t| {
        #[allow(clippy::redundant_locals)] // the whole Send wrapper, not its raw-pointer field (edition 2021 captures)
        let cp = cp;
        let (mb, nb) = (t / nblocks, t % nblocks);
        let mut p0 = 0;
        while p0 < kp {
            let pl = KCP.min(kp - p0);
            for np in nb * NBP..((nb + 1) * NBP).min(npanels) {
                let cols = (n - np * NR).min(NR);
                let bpanel = &bp[np * kp * NR + p0 * NR..];
                for mp in mb * MBP..((mb + 1) * MBP).min(mpanels) {
                    let rows = (m - mp * MR).min(MR);
                    let apanel = &ap[mp * kp * MR + p0 * MR..];
                    // SAFETY: the panels hold pl pairs from p0; the tile (rows × cols at mp·MR, np·NR) lies
                    // inside C and belongs to this task only.
                    unsafe {
                        tile(pl, apanel.as_ptr(), bpanel.as_ptr(), cp.0.add(mp * MR * n + np * NR), n, rows, cols, accumulate || p0 > 0);
                    }
                }
            }
            p0 += pl;
        }
    });
}

/// One MR × NR tile over `pl` K-pairs: acc = (load ? C : 0) + Σ_p A[·][p] ⊙ B[p][·]; stores rows × cols.
#[target_feature(enable = "avx512f,avx512bf16")]
#[allow(clippy::too_many_arguments)]
unsafe fn tile(pl: usize, a: *const u32, b: *const u32, c: *mut f32, ldc: usize, rows: usize, cols: usize, load: bool) {
    let m0: __mmask16 = if cols >= 16 { 0xffff } else { ((1u32 << cols) - 1) as __mmask16 };
    let m1: __mmask16 = if cols >= 32 {
        0xffff
    } else if cols > 16 {
        ((1u32 << (cols - 16)) - 1) as __mmask16
    } else {
        0
    };
    let mut acc = [[_mm512_setzero_ps(); 2]; MR];
    if load {
        for (r, row) in acc.iter_mut().enumerate() {
            if r < rows {
                let cr = c.add(r * ldc);
                row[0] = _mm512_maskz_loadu_ps(m0, cr);
                row[1] = _mm512_maskz_loadu_ps(m1, cr.add(16));
            }
        }
    }
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
    for (r, row) in acc.iter().enumerate() {
        if r < rows {
            let cr = c.add(r * ldc);
            _mm512_mask_storeu_ps(cr, m0, row[0]);
            _mm512_mask_storeu_ps(cr.add(16), m1, row[1]);
        }
    }
}
