//! Fused attention for heads of 64 on AVX-512 (VGGT's DINOv2, frame and global attention: 782 and 3910
//! tokens): per (sequence, head, block of query rows), keys in chunks with an online softmax, both products
//! in register tiles of 6 rows × 64 columns (24 zmm accumulators) written for these shapes, instead of two
//! `gemm` calls per chunk that each pack their operands (the score block twice).
//!
//! - Keys are transposed once per call into tiles `[tile][t][64 keys]` (16 KiB each, read contiguously by
//!   every row group), zero-padded past the sequence; scores of padded keys are computed and never read.
//! - Queries are broadcast from the `[q | k | v]` rows as they are; values are read in place (64 contiguous
//!   floats per key).
//! - The softmax (row max, exp, running sum, the rescale of the accumulated output when the max grows) runs
//!   on each chunk's score block between the two products; the rescale is applied when the output tile is
//!   loaded for the value product.
//!
//! f32 products and sums as the chunked path; the exp is this module's own (see `softmax_chunk`), its error
//! inside the per-key u of the same error model (the tests hold the chunked path's bound).

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

use rayon::prelude::*;

use crate::attention::{for_each_row_block, RowBlock};
use crate::math::exp_f32;

/// The head size this kernel is written for.
pub(crate) const D: usize = 64;
/// Keys per score tile: 4 zmm.
pub(crate) const KT: usize = 64;
/// Rows per register tile.
pub(crate) const MR: usize = 6;
/// Query rows per task and keys per chunk: the score block (rows × chunk) and the chunk's keys and values stay in
/// L2. On 2 Zen 4 cores, VGGT-1B's shapes: 48–192 rows and 128–512 keys all within 10 % of this choice.
pub(crate) const Q_BLOCK: usize = 96;
pub(crate) const K_CHUNK: usize = 256;

/// Whether the fused kernel runs on this CPU.
pub(crate) fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `buf`: rows of `[q | k | v]` (width 3c, heads of [`D`]), `n` sequences of `l` rows → `out` (n·l × c).
/// Returns false (nothing written) where the CPU lacks AVX-512; the caller then takes another path.
/// `q_block` rows per task, `k_chunk` keys per chunk (a positive multiple of 64).
pub(crate) fn attention_d64(buf: &[f32], n: usize, l: usize, c: usize, heads: usize, out: &mut [f32], q_block: usize, k_chunk: usize) -> bool {
    assert!(c == heads * D && buf.len() == n * l * 3 * c && out.len() == n * l * c, "attention_d64: shapes");
    assert!(k_chunk >= KT && k_chunk % KT == 0 && q_block > 0, "attention_d64: blocks {q_block}×{k_chunk}");
    if !available() {
        return false;
    }
    if l == 0 {
        return true;
    }
    #[cfg(target_arch = "x86_64")]
    {
        let tiles = l.div_ceil(KT);
        let per_head = tiles * D * KT;
        let kt = transpose_keys(buf, n, l, c, heads, tiles);
        let row = 3 * c;
        let qb = q_block.min(l);
        let scratch = || (vec![0f32; qb * k_chunk], vec![0f32; qb]);
        for_each_row_block(n, l, c, heads, D, q_block, out, scratch, |b, st, (s, corr)| {
            let RowBlock { g, h, q0, m } = b;
            let base = g * l;
            let kth = &kt[(g * heads + h) * per_head..(g * heads + h + 1) * per_head];
            for j0 in (0..l).step_by(k_chunk) {
                let kc = k_chunk.min(l - j0);
                // SAFETY: AVX-512F was detected; rows q0..q0+m and keys j0..j0+kc of sequence g lie in `buf`,
                // tiles j0/64.. of `kth` exist (zero-padded), `s` holds m × k_chunk, `acc` m × 64 floats.
                unsafe {
                    scores(&buf[(base + q0) * row + h * D..], row, m, &kth[(j0 / KT) * D * KT..], kc.div_ceil(KT), s, k_chunk);
                    softmax_chunk(&mut s[..m * k_chunk], k_chunk, kc, &mut st.mx[..m], &mut st.sum[..m], &mut corr[..m]);
                    values(s, k_chunk, m, kc, &buf[(base + j0) * row + 2 * c + h * D..], row, &mut st.acc, corr);
                }
            }
        });
    }
    true
}

/// Keys of every (sequence, head) as `[tile][t][64 keys]`, keys past `l` zero.
#[cfg(target_arch = "x86_64")]
fn transpose_keys(buf: &[f32], n: usize, l: usize, c: usize, heads: usize, tiles: usize) -> Vec<f32> {
    let per_head = tiles * D * KT;
    let mut kt = vec![0f32; n * heads * per_head];
    let row = 3 * c;
    kt.par_chunks_mut(D * KT).enumerate().for_each(|(i, tile)| {
        let (gh, ti) = (i / tiles, i % tiles);
        let (g, h) = (gh / heads, gh % heads);
        for j in 0..KT.min(l - ti * KT) {
            let src = &buf[(g * l + ti * KT + j) * row + c + h * D..][..D];
            for (t, v) in src.iter().enumerate() {
                tile[t * KT + j] = *v;
            }
        }
    });
    kt
}

/// Calls `$f::<R>` for `R = $r` (1..=6).
macro_rules! by_rows {
    ($r:expr, $f:ident($($a:expr),*)) => {
        match $r {
            6 => $f::<6>($($a),*),
            5 => $f::<5>($($a),*),
            4 => $f::<4>($($a),*),
            3 => $f::<3>($($a),*),
            2 => $f::<2>($($a),*),
            _ => $f::<1>($($a),*),
        }
    };
}
pub(crate) use by_rows;

/// Scores of `m` query rows (`q`, row stride `qs`) against `tiles` key tiles → `s` (row stride `ss`), scaled by
/// 1/8 (= 1/√64, exact). Tile-outer so one 16 KiB key tile serves every row group from L1.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn scores(q: &[f32], qs: usize, m: usize, kt: &[f32], tiles: usize, s: &mut [f32], ss: usize) {
    debug_assert!(kt.len() >= tiles * D * KT && s.len() >= (m - 1) * ss + tiles * KT && q.len() >= (m - 1) * qs + D);
    for ti in 0..tiles {
        let k = kt.as_ptr().add(ti * D * KT);
        let mut r0 = 0;
        while r0 < m {
            let r = MR.min(m - r0);
            by_rows!(r, score_tile(q.as_ptr().add(r0 * qs), qs, k, s.as_mut_ptr().add(r0 * ss + ti * KT), ss));
            r0 += r;
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn score_tile<const R: usize>(q: *const f32, qs: usize, k: *const f32, s: *mut f32, ss: usize) {
    let mut acc = [[_mm512_setzero_ps(); 4]; R];
    for t in 0..D {
        let kp = k.add(t * KT);
        let b = [_mm512_loadu_ps(kp), _mm512_loadu_ps(kp.add(16)), _mm512_loadu_ps(kp.add(32)), _mm512_loadu_ps(kp.add(48))];
        for (r, acc) in acc.iter_mut().enumerate() {
            let a = _mm512_set1_ps(*q.add(r * qs + t));
            for i in 0..4 {
                acc[i] = _mm512_fmadd_ps(a, b[i], acc[i]);
            }
        }
    }
    let scale = _mm512_set1_ps(1.0 / 8.0);
    for (r, acc) in acc.iter().enumerate() {
        for (i, a) in acc.iter().enumerate() {
            _mm512_storeu_ps(s.add(r * ss + i * 16), _mm512_mul_ps(*a, scale));
        }
    }
}

/// `o (m × 64) ← corr ⊙ o + p · v` over `kc` keys: `p` the chunk's exp-scores (row stride `ps`), `v` the
/// chunk's value rows (stride `vs`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
unsafe fn values(p: &[f32], ps: usize, m: usize, kc: usize, v: &[f32], vs: usize, o: &mut [f32], corr: &[f32]) {
    debug_assert!(p.len() >= (m - 1) * ps + kc && v.len() >= (kc - 1) * vs + D && o.len() >= m * D && corr.len() >= m);
    let mut r0 = 0;
    while r0 < m {
        let r = MR.min(m - r0);
        by_rows!(r, value_tile(p.as_ptr().add(r0 * ps), ps, kc, v.as_ptr(), vs, o.as_mut_ptr().add(r0 * D), corr.as_ptr().add(r0)));
        r0 += r;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn value_tile<const R: usize>(p: *const f32, ps: usize, kc: usize, v: *const f32, vs: usize, o: *mut f32, corr: *const f32) {
    let mut acc = [[_mm512_setzero_ps(); 4]; R];
    for (r, acc) in acc.iter_mut().enumerate() {
        let c = _mm512_set1_ps(*corr.add(r));
        for (i, a) in acc.iter_mut().enumerate() {
            *a = _mm512_mul_ps(_mm512_loadu_ps(o.add(r * D + i * 16)), c);
        }
    }
    for j in 0..kc {
        let vp = v.add(j * vs);
        let b = [_mm512_loadu_ps(vp), _mm512_loadu_ps(vp.add(16)), _mm512_loadu_ps(vp.add(32)), _mm512_loadu_ps(vp.add(48))];
        for (r, acc) in acc.iter_mut().enumerate() {
            let a = _mm512_set1_ps(*p.add(r * ps + j));
            for i in 0..4 {
                acc[i] = _mm512_fmadd_ps(a, b[i], acc[i]);
            }
        }
    }
    for (r, acc) in acc.iter().enumerate() {
        for (i, a) in acc.iter().enumerate() {
            _mm512_storeu_ps(o.add(r * D + i * 16), *a);
        }
    }
}

/// 2^f on [−½, ½]: degree-6 polynomial fitted for relative error (1.9e-9 in exact arithmetic; f32 Horner adds
/// about an ulp). The fit's linear coefficient rounds to ln 2 in f32 (same bits).
const EXP2_POLY: [f32; 7] = [1.0, std::f32::consts::LN_2, 0.240_226_46, 0.055_503_29, 0.009_618_52, 0.001_339_986, 0.000_153_375_78];

/// One chunk of the online softmax over the first `kc` scores of each row (stride `ss`): in place
/// exp(s − new row max), the running sum rescaled by `corr` = exp(old max − new max) (which the value product
/// applies to the accumulated output).
///
/// exp(x) for x = s − max ≤ 0 as 2^t, t = x·log₂e: n = round(t), 2^(t−n) by [`EXP2_POLY`], scaled by 2^n
/// (`vscalefps`); x < −86 gives exactly 0 (as `math::exp_fast`: no denormals into the value product). The
/// rounding of t (|t|·u) moves a weight e^x by at most |x|·e^x·u ≤ u/e absolutely, inside the error model's
/// per-key u.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
pub(crate) unsafe fn softmax_chunk(s: &mut [f32], ss: usize, kc: usize, mx: &mut [f32], sum: &mut [f32], corr: &mut [f32]) {
    let full = kc / 16;
    let tail: __mmask16 = ((1u32 << (kc % 16)) - 1) as __mmask16;
    let ninf = _mm512_set1_ps(f32::NEG_INFINITY);
    let log2e = _mm512_set1_ps(std::f32::consts::LOG2_E);
    let floor = _mm512_set1_ps(-86.0);
    let c: [__m512; 7] = EXP2_POLY.map(|v| _mm512_set1_ps(v));
    let exp = |x: __m512| -> __m512 {
        let t = _mm512_mul_ps(x, log2e);
        let n = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(t);
        let f = _mm512_sub_ps(t, n);
        let mut p = c[6];
        for k in (0..6).rev() {
            p = _mm512_fmadd_ps(p, f, c[k]);
        }
        _mm512_maskz_scalef_ps(_mm512_cmp_ps_mask::<_CMP_GE_OQ>(x, floor), p, n)
    };
    for (r, row) in s.chunks_exact_mut(ss).enumerate() {
        let p = row.as_mut_ptr();
        let mut vm = ninf;
        for i in 0..full {
            vm = _mm512_max_ps(vm, _mm512_loadu_ps(p.add(16 * i)));
        }
        if tail != 0 {
            vm = _mm512_max_ps(vm, _mm512_mask_loadu_ps(ninf, tail, p.add(16 * full)));
        }
        let m_new = _mm512_reduce_max_ps(vm).max(mx[r]);
        corr[r] = exp_f32(mx[r] - m_new);
        let m = _mm512_set1_ps(m_new);
        let mut vs = _mm512_setzero_ps();
        for i in 0..full {
            let e = exp(_mm512_sub_ps(_mm512_loadu_ps(p.add(16 * i)), m));
            _mm512_storeu_ps(p.add(16 * i), e);
            vs = _mm512_add_ps(vs, e);
        }
        if tail != 0 {
            let e = _mm512_maskz_mov_ps(tail, exp(_mm512_sub_ps(_mm512_mask_loadu_ps(m, tail, p.add(16 * full)), m)));
            _mm512_mask_storeu_ps(p.add(16 * full), tail, e);
            vs = _mm512_add_ps(vs, e);
        }
        sum[r] = sum[r] * corr[r] + _mm512_reduce_add_ps(vs);
        mx[r] = m_new;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rope::qkv_attention;
    use crate::rope::test_support::{assert_within_attention_bound, qkv_data};
    use candle_core::{Device, Tensor};

    /// The fused kernel against the composed ops (differentiable mode takes them), on several sizes: ragged
    /// row groups (not multiples of 6), ragged key tiles and chunks (not multiples of 64), one key, several
    /// sequences and heads, and through `qkv_attention` with QK-norm and RoPE at VGGT's frame length.
    #[test]
    fn fused_kernel_matches_composed_ops() {
        if !available() {
            eprintln!("fused_kernel_matches_composed_ops: this CPU has no AVX-512; the kernel cannot run here (qkv_attention takes the chunked path, tested in rope.rs)");
            return;
        }
        let dev = Device::Cpu;
        let check = |fast: &Tensor, slow: &Tensor, qkv: &Tensor, c: usize, l: usize, what: &str| assert_within_attention_bound(fast, slow, qkv, c, D, l, what);
        let composed = |qkv: &Tensor, heads: usize| {
            let _g = crate::mode::differentiable();
            qkv_attention(qkv, heads, None, None, None).unwrap()
        };
        for (i, (n, l, heads, qb, kc)) in
            [(1, 1, 1, 96, 64), (2, 65, 2, 7, 64), (1, 200, 1, 13, 128), (3, 131, 2, 96, 256), (1, 300, 1, 6, 64)].into_iter().enumerate()
        {
            let c = heads * D;
            let qkv = qkv_data(n, l, c, 2.5, 11 + i as u64);
            let buf = qkv.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let mut out = vec![f32::NAN; n * l * c];
            assert!(attention_d64(&buf, n, l, c, heads, &mut out, qb, kc));
            let fast = Tensor::from_vec(out, (n, l, c), &dev).unwrap();
            check(&fast, &composed(&qkv, heads), &qkv, c, l, &format!("n {n} l {l} heads {heads} blocks {qb}x{kc}"));
        }
        // The public path with QK-norm and RoPE, two seeds.
        for seed in [3u64, 4] {
            let (n, l, heads) = (1, 782, 2);
            let c = heads * D;
            let qkv = qkv_data(n, l, c, 1.5, seed);
            let w = (Tensor::randn(0f32, 0.3, D, &dev).unwrap() + 1.0).unwrap();
            let b = Tensor::randn(0f32, 0.1, D, &dev).unwrap();
            let pos: Vec<(u32, u32)> = (0..l as u32).map(|i| (i / 37, i % 37)).collect();
            let (cos, sin) = crate::rope::rope2d_tables(&pos, D, 100.0);
            let cos = Tensor::from_vec(cos, (l, D), &dev).unwrap();
            let sin = Tensor::from_vec(sin, (l, D), &dev).unwrap();
            let norm = Some(crate::rope::HeadNorm { weight: &w, bias: &b, eps: 1e-5 });
            let rope = Some(crate::rope::Rope2dTables { cos: &cos, sin: &sin });
            let fast = qkv_attention(&qkv, heads, norm, norm, rope).unwrap();
            let slow = {
                let _g = crate::mode::differentiable();
                qkv_attention(&qkv, heads, norm, norm, rope).unwrap()
            };
            // After QK-norm, |q|, |k| are bounded by the norm's output, not the inputs: bound from the normed values.
            let normed = {
                let _g = crate::mode::differentiable();
                let x = qkv.narrow(2, 0, 2 * c).unwrap().reshape((n, l, 2 * heads, D)).unwrap();
                let mean = x.mean_keepdim(3).unwrap();
                let xc = x.broadcast_sub(&mean).unwrap();
                let var = xc.sqr().unwrap().mean_keepdim(3).unwrap();
                let y = xc.broadcast_div(&(var + 1e-5).unwrap().sqrt().unwrap()).unwrap().broadcast_mul(&w).unwrap().broadcast_add(&b).unwrap();
                Tensor::cat(&[y.reshape((n, l, 2 * c)).unwrap(), qkv.narrow(2, 2 * c, c).unwrap()], 2).unwrap()
            };
            check(&fast, &slow, &normed, c, l, &format!("qkv_attention, QK-norm and RoPE, seed {seed}"));
        }
    }
}
