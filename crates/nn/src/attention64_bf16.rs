//! `attention64`'s fused kernel with both products in bf16 (issue 73): `vdpbf16ps` (`_mm512_dpbf16_ps`) does
//! twice the multiply-adds of an f32 FMA on Zen 4. Same blocking and online softmax as `attention64`; the
//! operands are rounded to bf16 (round to nearest even) as they are packed in K-pairs (u32 words `lo | hi << 16`,
//! the pairs `vdpbf16ps` multiplies into one f32 lane):
//!
//! - QKᵀ: the keys of each (sequence, head) once per call as tiles `[tile][t-pair][64 keys]` (8 KiB), each query
//!   row block once as `[row][t-pair]`; 6 × 64 score tiles over 32 pairs of the head dim.
//! - PV: the values once per call as `[key-pair][64 dims]`; the exponentials of each chunk (f32, from
//!   `attention64::softmax_chunk`) rounded into `[row][key-pair]` words after the softmax step.
//!
//! Softmax (max, exp, the row sums of the f32 exponentials, rescaling) and the accumulators stay f32. The scale
//! 1/8 multiplies the f32 scores after the product (a power of two: exact, so scaling q before rounding would
//! give the same bits; the score bound below is scaled by it).
//!
//! Error model (u = 2⁻⁸; per product `bf16::error_bound`). Row r, keys j, output column t, exact weights w_j:
//! - scores: |δs_j| ≤ Δ_r = max_j ⅛·error_bound(64, Σ_t|q_t k_jt|);
//! - weights: ŵ_j = w_j·e^{δs_j} / Σ_i w_i e^{δs_i}, so |ŵ_j − w_j| ≤ (e^{2Δ_r} − 1)·w_j;
//! - PV on the computed weights: ≤ error_bound(l, ·) of Σ_j ŵ_j|v_jt| ≤ e^{2Δ_r}·A_t, A_t = Σ_j w_j|v_jt|;
//! - f32 softmax: the exp (a few ulp), the row sum, the per-chunk rescales and the division, ≤ (l + 2·chunks + 8)
//!   ulp relative on A_t, and the exp's argument rounding ≤ 2⁻²⁴/e absolute per weight (≤ l·2⁻²⁴·max_j|v_jt|).
//!
//! |o_t − exact| ≤ (e^{2Δ} − 1)·A_t + e^{2Δ}·(2u + u² + (2l + 2·chunks + 8)·2⁻²⁴)·A_t + l·2⁻²⁴·max_j|v_jt| + 2l·2⁻¹²⁶.
//! The exponentials are ≥ e⁻⁸⁶ > 2⁻¹²⁶ or exactly 0, so no denormal p is flushed.

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

#[cfg(target_arch = "x86_64")]
use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
use crate::attention::{for_each_row_block, RowBlock};
use crate::attention64::D;
#[cfg(target_arch = "x86_64")]
use crate::attention64::{by_rows, softmax_chunk, KT, MR};
use crate::bf16::{path, Bf16Path};

/// K-pairs of the head dim.
#[cfg(target_arch = "x86_64")]
const PAIRS: usize = D / 2;

/// `attention64::attention_d64` with bf16 products. Returns false (nothing written) unless [`path`] answers
/// `Dpbf16` on the calling thread (AVX-512F and AVX512-BF16, not masked); the caller then takes the f32 kernels.
#[allow(clippy::too_many_arguments)]
pub(crate) fn attention_d64_bf16(buf: &[f32], n: usize, l: usize, c: usize, heads: usize, out: &mut [f32], q_block: usize, k_chunk: usize) -> bool {
    attention_rounded::<false>(buf, n, l, c, heads, out, q_block, k_chunk)
}

/// The kernel; `TRUNC` truncates the operands instead of rounding them to nearest even (the tests' mutation).
#[allow(clippy::too_many_arguments)]
fn attention_rounded<const TRUNC: bool>(buf: &[f32], n: usize, l: usize, c: usize, heads: usize, out: &mut [f32], q_block: usize, k_chunk: usize) -> bool {
    assert!(c == heads * D && buf.len() == n * l * 3 * c && out.len() == n * l * c, "attention_d64_bf16: shapes");
    assert!(k_chunk >= 64 && k_chunk.is_multiple_of(64) && q_block > 0, "attention_d64_bf16: blocks {q_block}×{k_chunk}");
    if path() != Bf16Path::Dpbf16 {
        return false;
    }
    if l == 0 {
        return true;
    }
    #[cfg(target_arch = "x86_64")]
    {
        let tiles = l.div_ceil(KT);
        let (k_head, v_head) = (tiles * PAIRS * KT, l.div_ceil(2) * D);
        let (kw, vw) = (pack_keys::<TRUNC>(buf, n, l, c, heads, tiles), pack_values::<TRUNC>(buf, n, l, c, heads));
        let row = 3 * c;
        let qb = q_block.min(l);
        let pws = k_chunk / 2;
        let scratch = || (vec![0f32; qb * k_chunk], vec![0u32; qb * PAIRS], vec![0u32; qb * pws], vec![0f32; qb]);
        for_each_row_block(n, l, c, heads, D, q_block, out, scratch, |b, st, (s, qw, pw, corr)| {
            let RowBlock { g, h, q0, m } = b;
            let gh = g * heads + h;
            // SAFETY (all calls below): `path` answered Dpbf16 (AVX-512F and AVX512-BF16); rows q0..q0+m of
            // sequence g lie in `buf`; key tiles j0/64.. and value pairs j0/2.. of head (g, h) exist (zero-padded);
            // `s` holds m × k_chunk floats, `qw` m × 32 and `pw` m × k_chunk/2 words, `acc` m × 64 floats.
            unsafe { to_pairs::<TRUNC>(&buf[(g * l + q0) * row + h * D..], row, m, D, qw, PAIRS) };
            for j0 in (0..l).step_by(k_chunk) {
                let kc = k_chunk.min(l - j0);
                unsafe {
                    scores(qw, m, &kw[gh * k_head + (j0 / KT) * PAIRS * KT..], kc.div_ceil(KT), s, k_chunk);
                    softmax_chunk(&mut s[..m * k_chunk], k_chunk, kc, &mut st.mx[..m], &mut st.sum[..m], &mut corr[..m]);
                    to_pairs::<TRUNC>(s, k_chunk, m, kc, pw, pws);
                    values(pw, pws, m, kc.div_ceil(2), &vw[gh * v_head + (j0 / 2) * D..], &mut st.acc, corr);
                }
            }
        });
    }
    true
}

/// A bf16 pair word of two f32 values, RNE or truncated (the scalar path of the packers: tails and the
/// tests' mutation).
#[cfg(target_arch = "x86_64")]
#[inline]
pub(crate) fn pair<const TRUNC: bool>(lo: f32, hi: f32) -> u32 {
    let h = |x: f32| if TRUNC { x.to_bits() >> 16 } else { crate::bf16::f32_to_bf16(x) as u32 };
    h(lo) | (h(hi) << 16)
}

/// `rows` rows of `src` (stride `ss`), their first `len` values → `len.div_ceil(2)` words per row of `dst`
/// (stride `ds`), consecutive values paired, an odd last value paired with 0.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
pub(crate) unsafe fn to_pairs<const TRUNC: bool>(src: &[f32], ss: usize, rows: usize, len: usize, dst: &mut [u32], ds: usize) {
    debug_assert!(src.len() >= (rows - 1) * ss + len && dst.len() >= (rows - 1) * ds + len.div_ceil(2));
    for r in 0..rows {
        let (s, d) = (src.as_ptr().add(r * ss), dst.as_mut_ptr().add(r * ds));
        if TRUNC {
            for i in 0..len.div_ceil(2) {
                *d.add(i) = pair::<TRUNC>(*s.add(2 * i), if 2 * i + 1 < len { *s.add(2 * i + 1) } else { 0.0 });
            }
            continue;
        }
        let mut i = 0;
        while i < len {
            let rem = len - i;
            let m0: __mmask16 = if rem >= 16 { 0xffff } else { ((1u32 << rem) - 1) as __mmask16 };
            let m1: __mmask16 = if rem >= 32 {
                0xffff
            } else if rem > 16 {
                ((1u32 << (rem - 16)) - 1) as __mmask16
            } else {
                0
            };
            let lo = _mm512_maskz_loadu_ps(m0, s.add(i));
            let hi = _mm512_maskz_loadu_ps(m1, s.add(i + 16));
            // cvtne2ps_pbh(a, b): b → the low 16 bf16, a → the high 16, so word w holds values 2w, 2w + 1.
            let w = std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(hi, lo));
            let words = rem.min(32).div_ceil(2);
            let mw: __mmask16 = if words >= 16 { 0xffff } else { ((1u32 << words) - 1) as __mmask16 };
            _mm512_mask_storeu_epi32(d.add(i / 2) as *mut _, mw, w);
            i += 32;
        }
    }
}

/// Keys of every (sequence, head) as `[tile][t-pair][64 keys]` words, keys past `l` zero.
#[cfg(target_arch = "x86_64")]
fn pack_keys<const TRUNC: bool>(buf: &[f32], n: usize, l: usize, c: usize, heads: usize, tiles: usize) -> Vec<u32> {
    let mut kw = vec![0u32; n * heads * tiles * PAIRS * KT];
    let row = 3 * c;
    kw.par_chunks_mut(PAIRS * KT).enumerate().for_each(|(i, tile)| {
        let (gh, ti) = (i / tiles, i % tiles);
        let (g, h) = (gh / heads, gh % heads);
        let mut w = [0u32; PAIRS];
        for j in 0..KT.min(l - ti * KT) {
            let src = &buf[(g * l + ti * KT + j) * row + c + h * D..][..D];
            // SAFETY: the caller checked AVX-512F and AVX512-BF16; one row of 64 values into 32 words.
            unsafe { to_pairs::<TRUNC>(src, D, 1, D, &mut w, PAIRS) };
            for (tp, v) in w.iter().enumerate() {
                tile[tp * KT + j] = *v;
            }
        }
    });
    kw
}

/// Values of every (sequence, head) as `[key-pair][64 dims]` words (`v[2p][t] | v[2p + 1][t] << 16`), an odd
/// last key paired with 0.
#[cfg(target_arch = "x86_64")]
fn pack_values<const TRUNC: bool>(buf: &[f32], n: usize, l: usize, c: usize, heads: usize) -> Vec<u32> {
    let lp = l.div_ceil(2);
    let mut vw = vec![0u32; n * heads * lp * D];
    let row = 3 * c;
    vw.par_chunks_mut(lp * D).enumerate().for_each(|(gh, head)| {
        let (g, h) = (gh / heads, gh % heads);
        let zero = [0f32; D];
        for p in 0..lp {
            let v = |j: usize| if j < l { &buf[(g * l + j) * row + 2 * c + h * D..][..D] } else { &zero[..] };
            let (v0, v1, dst) = (v(2 * p), v(2 * p + 1), &mut head[p * D..(p + 1) * D]);
            if TRUNC {
                for t in 0..D {
                    dst[t] = pair::<TRUNC>(v0[t], v1[t]);
                }
            } else {
                // SAFETY: the caller checked AVX-512F and AVX512-BF16; 64 values each.
                unsafe { interleave(v0, v1, dst) };
            }
        }
    });
    vw
}

/// `dst[t] = bf16(a[t]) | bf16(b[t]) << 16` for 64 values, round to nearest even.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn interleave(a: &[f32], b: &[f32], dst: &mut [u32]) {
    for i in 0..D / 16 {
        let lo = _mm512_cvtepu16_epi32(std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(_mm512_loadu_ps(a.as_ptr().add(16 * i)))));
        let hi = _mm512_cvtepu16_epi32(std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(_mm512_loadu_ps(b.as_ptr().add(16 * i)))));
        _mm512_storeu_si512(dst.as_mut_ptr().add(16 * i) as *mut _, _mm512_or_si512(lo, _mm512_slli_epi32::<16>(hi)));
    }
}

/// Scores of `m` packed query rows (`qw`, 32 words each) against `tiles` packed key tiles → `s` (row stride
/// `ss`), scaled by 1/8 in f32 (exact). Tile-outer so one 8 KiB key tile serves every row group from L1.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn scores(qw: &[u32], m: usize, kw: &[u32], tiles: usize, s: &mut [f32], ss: usize) {
    debug_assert!(kw.len() >= tiles * PAIRS * KT && s.len() >= (m - 1) * ss + tiles * KT && qw.len() >= m * PAIRS);
    for ti in 0..tiles {
        let k = kw.as_ptr().add(ti * PAIRS * KT);
        let mut r0 = 0;
        while r0 < m {
            let r = MR.min(m - r0);
            by_rows!(r, score_tile(qw.as_ptr().add(r0 * PAIRS), k, s.as_mut_ptr().add(r0 * ss + ti * KT), ss));
            r0 += r;
        }
    }
}

/// 16 pair words as `vdpbf16ps` reads them.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
unsafe fn words(p: *const __m512i) -> __m512bh {
    std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(p as *const _))
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
unsafe fn score_tile<const R: usize>(q: *const u32, k: *const u32, s: *mut f32, ss: usize) {
    let mut acc = [[_mm512_setzero_ps(); 4]; R];
    for tp in 0..PAIRS {
        let kp = k.add(tp * KT) as *const __m512i;
        let b = [words(kp), words(kp.add(1)), words(kp.add(2)), words(kp.add(3))];
        for (r, acc) in acc.iter_mut().enumerate() {
            let a = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(*q.add(r * PAIRS + tp) as i32));
            for i in 0..4 {
                acc[i] = _mm512_dpbf16_ps(acc[i], a, b[i]);
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

/// `o (m × 64) ← corr ⊙ o + p · v` over `pairs` key pairs: `pw` the chunk's rounded exponentials (row stride
/// `ps` words), `vw` the chunk's packed value pairs.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[allow(clippy::too_many_arguments)]
unsafe fn values(pw: &[u32], ps: usize, m: usize, pairs: usize, vw: &[u32], o: &mut [f32], corr: &[f32]) {
    debug_assert!(pw.len() >= (m - 1) * ps + pairs && vw.len() >= pairs * D && o.len() >= m * D && corr.len() >= m);
    let mut r0 = 0;
    while r0 < m {
        let r = MR.min(m - r0);
        by_rows!(r, value_tile(pw.as_ptr().add(r0 * ps), ps, pairs, vw.as_ptr(), o.as_mut_ptr().add(r0 * D), corr.as_ptr().add(r0)));
        r0 += r;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
unsafe fn value_tile<const R: usize>(p: *const u32, ps: usize, pairs: usize, v: *const u32, o: *mut f32, corr: *const f32) {
    let mut acc = [[_mm512_setzero_ps(); 4]; R];
    for (r, acc) in acc.iter_mut().enumerate() {
        let c = _mm512_set1_ps(*corr.add(r));
        for (i, a) in acc.iter_mut().enumerate() {
            *a = _mm512_mul_ps(_mm512_loadu_ps(o.add(r * D + i * 16)), c);
        }
    }
    for jp in 0..pairs {
        let vp = v.add(jp * D) as *const __m512i;
        let b = [words(vp), words(vp.add(1)), words(vp.add(2)), words(vp.add(3))];
        for (r, acc) in acc.iter_mut().enumerate() {
            let a = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(*p.add(r * ps + jp) as i32));
            for i in 0..4 {
                acc[i] = _mm512_dpbf16_ps(acc[i], a, b[i]);
            }
        }
    }
    for (r, acc) in acc.iter().enumerate() {
        for (i, a) in acc.iter().enumerate() {
            _mm512_storeu_ps(o.add(r * D + i * 16), *a);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bf16::{bf16_to_f32_daz, error_bound, f32_to_bf16, with_bf16_masked};
    use crate::rope::test_support::qkv_data;
    use crate::rope::{prepare, qkv_attention, qkv_attention_bf16, rope2d_tables, HeadNorm, Rope2dTables};
    use candle_core::{Device, Tensor};

    const U: f64 = 1.0 / 256.0;
    /// 2⁻²⁴, f32's unit roundoff.
    const ULP: f64 = 1.0 / 16_777_216.0;

    /// What the f64 reference multiplies: the f32 operands as given, or rounded to bf16 as the kernel rounds them.
    #[derive(Clone, Copy, PartialEq)]
    enum Against {
        Exact,
        Rounded,
    }

    /// The f64 attention of `[q | k | v]` rows, per output (row, column): o, A = Σ_j w_j|v_jt| and M = max_j|v_jt|;
    /// per (row, head): Δ, the bound on a score's error (the module's model for `Exact`; for `Rounded` only the
    /// f32 summation of exact bf16 products, 64·2⁻²⁴·Σ|q'k'|, and the flush term).
    struct Reference {
        o: Vec<f64>,
        a: Vec<f64>,
        m: Vec<f64>,
        delta: Vec<f64>,
    }

    /// One row's o, A, M (64 each) and Δ.
    type RowRef = (Vec<f64>, Vec<f64>, Vec<f64>, f64);

    fn reference(buf: &[f32], n: usize, l: usize, c: usize, heads: usize, against: Against) -> Reference {
        let x = |v: f32| if against == Against::Rounded { bf16_to_f32_daz(f32_to_bf16(v)) as f64 } else { v as f64 };
        let row = 3 * c;
        let mut r = Reference { o: vec![0.0; n * l * c], a: vec![0.0; n * l * c], m: vec![0.0; n * l * c], delta: vec![0.0; n * l * heads] };
        for g in 0..n {
            for h in 0..heads {
                // Head h of sequence g as l × 64 f64 (part 0: q, 1: k, 2: v).
                let part = |p: usize| -> Vec<f64> { (0..l).flat_map(|j| buf[(g * l + j) * row + p * c + h * D..][..D].iter().map(|v| x(*v))).collect() };
                let (q, k, v) = (part(0), part(1), part(2));
                let rows: Vec<RowRef> = (0..l)
                    .into_par_iter()
                    .map(|i| {
                        let qi = &q[i * D..(i + 1) * D];
                        let mut delta = 0f64;
                        let s: Vec<f64> = (0..l)
                            .map(|j| {
                                let (dot, abs) = qi.iter().zip(&k[j * D..(j + 1) * D]).fold((0f64, 0f64), |(d, b), (p, r)| (d + p * r, b + (p * r).abs()));
                                let e = match against {
                                    Against::Exact => error_bound(D, abs),
                                    Against::Rounded => D as f64 * ULP * abs + 2.0 * D as f64 * 2f64.powi(-126),
                                };
                                delta = delta.max(e / 8.0);
                                dot / 8.0
                            })
                            .collect();
                        let mx = s.iter().fold(f64::NEG_INFINITY, |p, v| p.max(*v));
                        let w: Vec<f64> = s.iter().map(|v| (v - mx).exp()).collect();
                        let z: f64 = w.iter().sum();
                        let (mut o, mut a, mut m) = (vec![0f64; D], vec![0f64; D], vec![0f64; D]);
                        for (j, wj) in w.iter().enumerate() {
                            for (t, vt) in v[j * D..(j + 1) * D].iter().enumerate() {
                                o[t] += wj / z * vt;
                                a[t] += wj / z * vt.abs();
                                m[t] = m[t].max(vt.abs());
                            }
                        }
                        (o, a, m, delta)
                    })
                    .collect();
                for (i, (o, a, m, delta)) in rows.into_iter().enumerate() {
                    let at = (g * l + i) * c + h * D;
                    r.o[at..at + D].copy_from_slice(&o);
                    r.a[at..at + D].copy_from_slice(&a);
                    r.m[at..at + D].copy_from_slice(&m);
                    r.delta[(g * l + i) * heads + h] = delta;
                }
            }
        }
        r
    }

    /// The module's bound for output `idx` (row-major n·l × c), keys in chunks of `k_chunk`. Against the rounded
    /// operands the product's own error is the rounding of the exponentials only: u instead of 2u + u².
    fn bound(r: &Reference, idx: usize, l: usize, c: usize, k_chunk: usize, against: Against) -> f64 {
        let (rowi, h) = (idx / c, (idx % c) / D);
        let e = (2.0 * r.delta[rowi * (c / D) + h]).exp();
        let lf = l as f64;
        let product = if against == Against::Exact { 2.0 * U + U * U } else { U };
        let f32s = (2.0 * lf + 2.0 * l.div_ceil(k_chunk) as f64 + 8.0) * ULP;
        (e - 1.0) * r.a[idx] + e * (product + f32s) * r.a[idx] + lf * ULP * r.m[idx] + 2.0 * lf * 2f64.powi(-126)
    }

    /// Ok: the largest |got − o| / bound; Err names the first output past its bound.
    fn check(got: &[f32], r: &Reference, l: usize, c: usize, k_chunk: usize, against: Against) -> Result<f64, String> {
        let mut worst = 0f64;
        for (idx, g) in got.iter().enumerate() {
            let b = bound(r, idx, l, c, k_chunk, against);
            let err = (*g as f64 - r.o[idx]).abs();
            if err.is_nan() || err > b {
                return Err(format!("output {idx} (row {}, column {}): {g} against {}, |err| {err:.3e} > {b:.3e}", idx / c, idx % c, r.o[idx]));
            }
            worst = worst.max(err / b);
        }
        Ok(worst)
    }

    fn run<const TRUNC: bool>(buf: &[f32], n: usize, l: usize, heads: usize, qb: usize, kc: usize) -> Vec<f32> {
        let mut out = vec![f32::NAN; n * l * heads * D];
        assert!(attention_rounded::<TRUNC>(buf, n, l, heads * D, heads, &mut out, qb, kc));
        out
    }

    /// Both checks (against the f64 attention of the f32 operands, and of the operands rounded to bf16) on ragged
    /// row groups (not multiples of 6), key tiles and chunks (not multiples of 64; odd l, so a key pair padded),
    /// one key, several sequences and heads, two seeds; then `qkv_attention_bf16` with QK-norm and RoPE at
    /// VGGT's frame length, checked on the exact q and k the kernel sees (`rope::prepare`).
    #[test]
    fn bf16_attention_holds_the_error_model() {
        if path() != Bf16Path::Dpbf16 {
            eprintln!("no AVX512-BF16 on this CPU: the bf16 attention kernel cannot run (qkv_attention_bf16 is qkv_attention there; see the masked test)");
            return;
        }
        let mut worst = [0f64; 2];
        let mut record = |got: &[f32], buf: &[f32], n: usize, l: usize, heads: usize, kc: usize, what: &str| {
            for (i, against) in [Against::Exact, Against::Rounded].into_iter().enumerate() {
                let r = reference(buf, n, l, heads * D, heads, against);
                let w = check(got, &r, l, heads * D, kc, against).unwrap_or_else(|e| panic!("{what}, {}: {e}", ["exact", "rounded"][i]));
                worst[i] = worst[i].max(w);
            }
        };
        for seed in [1u64, 2] {
            for (n, l, heads, qb, kc) in [(1, 1, 1, 96, 64), (2, 65, 2, 7, 64), (3, 131, 2, 96, 128), (1, 300, 3, 13, 256), (1, 300, 1, 6, 64)] {
                let buf = qkv_data(n, l, heads * D, 2.0, seed * 100 + l as u64).flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let got = run::<false>(&buf, n, l, heads, qb, kc);
                record(&got, &buf, n, l, heads, kc, &format!("seed {seed}: n {n} l {l} heads {heads} blocks {qb}x{kc}"));
            }
            let dev = Device::Cpu;
            let (l, heads) = (782, 2);
            let qkv = qkv_data(1, l, heads * D, 1.5, seed + 10);
            let w = (Tensor::randn(0f32, 0.3, D, &dev).unwrap() + 1.0).unwrap();
            let b = Tensor::randn(0f32, 0.1, D, &dev).unwrap();
            let pos: Vec<(u32, u32)> = (0..l as u32).map(|i| (i / 37, i % 37)).collect();
            let (cos, sin) = rope2d_tables(&pos, D, 100.0);
            let (cos, sin) = (Tensor::from_vec(cos, (l, D), &dev).unwrap(), Tensor::from_vec(sin, (l, D), &dev).unwrap());
            let norm = Some(HeadNorm { weight: &w, bias: &b, eps: 1e-5 });
            let rope = Some(Rope2dTables { cos: &cos, sin: &sin });
            let got = qkv_attention_bf16(&qkv, heads, norm, norm, rope).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let f32s = qkv_attention(&qkv, heads, norm, norm, rope).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert_ne!(got, f32s, "the bf16 products ran");
            let buf = prepare(&qkv, heads, norm, norm, rope).unwrap().unwrap();
            record(&got, &buf, 1, l, heads, crate::attention64::K_CHUNK, &format!("seed {seed}: qkv_attention_bf16, l {l}, QK-norm and RoPE"));
        }
        eprintln!("largest |err| / bound: against the f32 operands {:.3}, against the rounded operands {:.3}", worst[0], worst[1]);
        assert!(worst[0] > 0.0 && worst[1] > 0.0, "no rounding error at all is suspicious");
    }

    /// Truncation instead of round to nearest even fails both checks, and a result 1 % off fails the model, on
    /// values just below a bf16 tie's far side: v = (1 + 2⁻⁷ − 2⁻²³)·2^e, all positive, which RNE moves by 2⁻²³
    /// and truncation by ≈ 2u, with small q and k (Δ ≈ 0, so the bound is ≈ (2u + u²)·A = 2.0u·|o|). Also a
    /// result moved to 1.01 × its bound fails, at 0.99 × passes (the check reads each output's own bound).
    #[test]
    fn truncation_and_a_moved_result_are_caught() {
        if path() != Bf16Path::Dpbf16 {
            return;
        }
        let (n, l, heads, qb, kc) = (1, 131, 2, 13, 64);
        let c = heads * D;
        let mut buf = qkv_data(n, l, c, 0.05, 9).flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let near = 1.0 + 2f32.powi(-7) - 2f32.powi(-23);
        for (i, v) in buf.iter_mut().enumerate().filter(|(i, _)| i % (3 * c) >= 2 * c) {
            *v = near * [1.0, 2.0, 4.0][i % 3];
        }
        let exact = reference(&buf, n, l, c, heads, Against::Exact);
        let rounded = reference(&buf, n, l, c, heads, Against::Rounded);
        let rne = run::<false>(&buf, n, l, heads, qb, kc);
        check(&rne, &exact, l, c, kc, Against::Exact).expect("RNE holds the model");
        check(&rne, &rounded, l, c, kc, Against::Rounded).expect("RNE holds the tight check");
        let trunc = run::<true>(&buf, n, l, heads, qb, kc);
        let e = check(&trunc, &exact, l, c, kc, Against::Exact).expect_err("truncation must fail the model");
        eprintln!("truncated: {e}");
        check(&trunc, &rounded, l, c, kc, Against::Rounded).expect_err("truncation must fail the tight check");
        let scaled: Vec<f32> = rne.iter().map(|v| v * 1.01).collect();
        check(&scaled, &exact, l, c, kc, Against::Exact).expect_err("1 % off must fail");

        let (l, heads) = (300, 2);
        let c = heads * D;
        let buf = qkv_data(1, l, c, 2.0, 5).flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let r = reference(&buf, 1, l, c, heads, Against::Exact);
        let mut got = run::<false>(&buf, 1, l, heads, 96, 256);
        check(&got, &r, l, c, 256, Against::Exact).expect("holds");
        for idx in [0, 77 * c + 100, got.len() - 1] {
            let keep = got[idx];
            let b = bound(&r, idx, l, c, 256, Against::Exact);
            got[idx] = (r.o[idx] + 0.99 * b) as f32;
            check(&got, &r, l, c, 256, Against::Exact).expect("0.99 × the bound passes");
            got[idx] = (r.o[idx] - 1.01 * b) as f32;
            check(&got, &r, l, c, 256, Against::Exact).expect_err("1.01 × the bound fails");
            got[idx] = keep;
        }
    }

    /// Masked (`bf16::with_bf16_masked`) or with heads other than 64, `qkv_attention_bf16` is `qkv_attention`,
    /// bit for bit: with QK-norm and RoPE through the fused f32 kernel, and the chunked path (heads of 8).
    #[test]
    fn masked_or_other_heads_equal_qkv_attention() {
        let dev = Device::Cpu;
        for (l, heads, d, seed) in [(131usize, 2usize, D, 3u64), (300, 1, D, 4), (300, 2, 8, 5)] {
            let c = heads * d;
            let qkv = qkv_data(2, l, c, 2.0, seed);
            let w = (Tensor::randn(0f32, 0.3, d, &dev).unwrap() + 1.0).unwrap();
            let b = Tensor::randn(0f32, 0.1, d, &dev).unwrap();
            let pos: Vec<(u32, u32)> = (0..l as u32).map(|i| (i / 17, i % 17)).collect();
            let (cos, sin) = rope2d_tables(&pos, d, 100.0);
            let (cos, sin) = (Tensor::from_vec(cos, (l, d), &dev).unwrap(), Tensor::from_vec(sin, (l, d), &dev).unwrap());
            let norm = Some(HeadNorm { weight: &w, bias: &b, eps: 1e-5 });
            let rope = Some(Rope2dTables { cos: &cos, sin: &sin });
            let v = |t: Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let f32s = v(qkv_attention(&qkv, heads, norm, norm, rope).unwrap());
            let masked = with_bf16_masked(|| v(qkv_attention_bf16(&qkv, heads, norm, norm, rope).unwrap()));
            assert!(masked.iter().zip(&f32s).all(|(a, b)| a.to_bits() == b.to_bits()), "l {l} heads {heads}×{d}: masked");
            let plain = v(qkv_attention_bf16(&qkv, heads, None, None, None).unwrap());
            let plain32 = v(qkv_attention(&qkv, heads, None, None, None).unwrap());
            let same = plain.iter().zip(&plain32).all(|(a, b)| a.to_bits() == b.to_bits());
            assert_eq!(same, d != D || path() != Bf16Path::Dpbf16, "l {l} heads {heads}×{d}: bf16 exactly where the kernel applies");
        }
    }
}
