//! The AVX512-BF16 gemm: A packed in [`MR`]-row micro-panels (rows of [`KCP`] words), B in [`NR`]-column
//! micro-panels (both as u32 K-pairs), a 12 × 32 register tile (24 zmm accumulators, `vdpbf16ps` with A broadcast from memory), K blocked
//! by [`KCP`] pairs so a B micro-panel stays in L1 while the task's A block (packed per K-block) stays in L2;
//! rayon over row blocks (and column ranges when the rows are too few to keep every thread busy).

use std::arch::x86_64::*;

use rayon::prelude::*;

use super::{f32_to_bf16, Bf16Weights, MR, NR};

/// K-pairs per block: a B micro-panel is KCP·32·4 = 32 KiB, an A micro-panel KCP·12·4 = 12 KiB (192 and 128 pairs
/// measured 0–10 % slower on the bench shapes).
const KCP: usize = 256;
/// Micro-panels of A per task (96 rows).
const MBP: usize = 8;

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

/// Rows `row0..row0 + MR·panels` of A (m × k), pairs `p0..p0 + pl`, → `out` as [panel][row][KCP] words (a
/// fixed row stride, so the kernel's broadcasts have constant offsets); rows past m are zero.
#[target_feature(enable = "avx512f,avx512bf16")]
#[allow(clippy::too_many_arguments)]
unsafe fn pack_a_block(a: &[f32], m: usize, k: usize, row0: usize, panels: usize, p0: usize, pl: usize, out: &mut [u32]) {
    let (k0, k1) = (2 * p0, (2 * (p0 + pl)).min(k));
    for lp in 0..panels {
        for r in 0..MR {
            let row = row0 + lp * MR + r;
            let dst = &mut out[(lp * MR + r) * KCP..(lp * MR + r) * KCP + pl];
            if row >= m {
                dst.fill(0);
            } else {
                row_to_pairs(&a[row * k + k0..row * k + k1], dst);
            }
        }
    }
}

/// A packed as `matmul` packs it, gathered over all of K, for tests: [panel][pair][MR] words.
#[cfg(test)]
pub(crate) fn packed_a_for_test(a: &[f32], m: usize, k: usize) -> Vec<u32> {
    let (kp, panels) = (k.div_ceil(2), m.div_ceil(MR));
    let mut out = vec![0u32; panels * kp * MR];
    let mut block = vec![0u32; panels * MR * KCP];
    let mut p0 = 0;
    while p0 < kp {
        let pl = KCP.min(kp - p0);
        // SAFETY: tests call this only where the feature was detected.
        unsafe { pack_a_block(a, m, k, 0, panels, p0, pl, &mut block) };
        for lp in 0..panels {
            for p in 0..pl {
                for r in 0..MR {
                    out[lp * kp * MR + (p0 + p) * MR + r] = block[(lp * MR + r) * KCP + p];
                }
            }
        }
        p0 += pl;
    }
    out
}

/// C = A·B (or += when `accumulate`). A task owns a block of [`MBP`] A micro-panels and a range of B
/// micro-panels (all of N unless there are too few row blocks to keep every thread busy); per K-block it
/// packs its A block once (round to nearest even) and sweeps its B panels over it.
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
    let (mpanels, npanels) = (m.div_ceil(MR), n.div_ceil(NR));
    let mblocks = mpanels.div_ceil(MBP);
    let want = 4 * rayon::current_num_threads();
    let nchunks = if mblocks >= want { 1 } else { want.div_ceil(mblocks).min(npanels) };
    let chunk = npanels.div_ceil(nchunks);
    let nchunks = npanels.div_ceil(chunk);
    let cp = SendPtr(c.as_mut_ptr());
    let bp = &b.data;
    (0..mblocks * nchunks).into_par_iter().for_each(|t| {
        #[allow(clippy::redundant_locals)] // the whole Send wrapper, not its raw-pointer field (edition 2021 captures)
        let cp = cp;
        let (mb, nc) = (t / nchunks, t % nchunks);
        let mp0 = mb * MBP;
        let panels = MBP.min(mpanels - mp0);
        let mut ablock = vec![0u32; panels * MR * KCP];
        let mut p0 = 0;
        while p0 < kp {
            let pl = KCP.min(kp - p0);
            // SAFETY: the caller's features; the block lies inside A (rows past m are padded).
            unsafe { pack_a_block(a, m, k, mp0 * MR, panels, p0, pl, &mut ablock) };
            for np in nc * chunk..((nc + 1) * chunk).min(npanels) {
                let cols = (n - np * NR).min(NR);
                let bpanel = &bp[np * kp * NR + p0 * NR..];
                for lp in 0..panels {
                    let mp = mp0 + lp;
                    let rows = (m - mp * MR).min(MR);
                    // SAFETY: the panels hold pl pairs; the tile (rows × cols at mp·MR, np·NR) lies inside C
                    // and belongs to this task only.
                    unsafe {
                        tile(pl, ablock[lp * MR * KCP..].as_ptr(), bpanel.as_ptr(), cp.0.add(mp * MR * n + np * NR), n, rows, cols, accumulate || p0 > 0);
                    }
                }
            }
            p0 += pl;
        }
    });
}

/// One MR × NR tile over `pl` K-pairs (A: MR rows of stride [`KCP`] words): acc = (load ? C : 0) + Σ_p A[·][p] ⊙ B[p][·]; stores rows × cols.
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
        let ar = a.add(p);
        for (r, row) in acc.iter_mut().enumerate() {
            let av: __m512bh = std::mem::transmute(_mm512_set1_epi32(*ar.add(r * KCP) as i32));
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
