//! [`fused_attention`](crate::attention::fused_attention) with both products in bf16 (issue 73): the encoder's
//! single-head attention — the multi-view transformer's shifted windows (heads of 128, the Swin region mask),
//! the depth UNets' heads of 32 — on `vdpbf16ps` (`_mm512_dpbf16_ps`), which does twice the multiply-adds of an
//! f32 FMA on Zen 4. Same semantics as `fused_attention`: `softmax(q·kᵀ (+ region mask))·v`, q carrying any
//! scale; heads of 32, 64 or 128 (`v` as wide as `q`).
//!
//! Layout as `attention64_bf16` (the operands rounded to bf16, round to nearest even, as they are packed in
//! pairs — u32 words `lo | hi << 16` that `vdpbf16ps` multiplies into one f32 lane):
//! - QKᵀ: the keys of each item once per call as tiles `[tile][d-pair][64 keys]` (d/2 · 256 bytes), each query
//!   row block as `[row][d-pair]`; register tiles of 6 rows × 64 keys. The region mask adds −100 in f32 to a
//!   tile's scores as they are stored (the labels compared 16 keys at a time), as the f32 kernel adds it.
//! - PV: the values once per call as `[key-pair][d]`; each chunk's f32 exponentials rounded to `[row][key-pair]`
//!   after the online-softmax step (`attention64::softmax_chunk`); output columns in blocks of 64.
//!
//! Softmax (max, exp, row sums of the f32 exponentials, rescales), the mask's addition and the accumulators
//! stay f32. Without AVX512-BF16 (or masked by `bf16::with_bf16_masked`, or off the CPU, or with gradients, or
//! other head sizes) [`fused_attention_bf16`] is `fused_attention`, bit for bit.
//!
//! Error model (u = 2⁻⁸; `bf16::error_bound`). Row r, keys j, output column t, exact weights w_j:
//! - scores: |δs_j| ≤ Δ_r = max_j error_bound(d, Σ_t|q_t k_jt|) (+ 2⁻²⁴·(|s_j| + 100) where the mask adds);
//! - weights: ŵ_j = w_j·e^{δs_j} / Σ_i w_i e^{δs_i}, so |ŵ_j − w_j| ≤ (e^{2Δ_r} − 1)·w_j;
//! - PV on the computed weights: ≤ error_bound(S, ·) of Σ_j ŵ_j|v_jt| ≤ e^{2Δ_r}·A_t, A_t = Σ_j w_j|v_jt|;
//! - f32 softmax: ≤ (S + 2·chunks + 8) ulp relative on A_t, and the exp's argument rounding ≤ 2⁻²⁴/e absolute
//!   per weight (≤ S·2⁻²⁴·max_j|v_jt|).
//!
//! |o_t − exact| ≤ (e^{2Δ} − 1)·A_t + e^{2Δ}·(2u + u² + (2S + 2·chunks + 8)·2⁻²⁴)·A_t + S·2⁻²⁴·max_j|v_jt| + 2S·2⁻¹²⁶.

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor};
#[cfg(target_arch = "x86_64")]
use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
use crate::attention::{for_each_row_block, RowBlock};
use crate::attention::{fused_attention, RegionMask};
#[cfg(target_arch = "x86_64")]
use crate::attention64::{softmax_chunk, KT, MR};
#[cfg(target_arch = "x86_64")]
use crate::attention64_bf16::{pair, to_pairs};
use crate::bf16::{path, Bf16Path};
use crate::mode::{cpu_f32, f32_slice};

/// Calls `$f::<R, G..>` for `R = $r` (1..=6): `attention64::by_rows` with the head's const parameters.
#[cfg(target_arch = "x86_64")]
macro_rules! by_rows {
    ($r:expr, $f:ident::<$($g:tt),*>($($a:expr),*)) => {
        match $r {
            6 => $f::<6, $($g),*>($($a),*),
            5 => $f::<5, $($g),*>($($a),*),
            4 => $f::<4, $($g),*>($($a),*),
            3 => $f::<3, $($g),*>($($a),*),
            2 => $f::<2, $($g),*>($($a),*),
            _ => $f::<1, $($g),*>($($a),*),
        }
    };
}

/// Query rows per task and keys per chunk (`attention64`'s choice; the score block and the chunk's packed keys
/// and values stay in L2).
const Q_BLOCK: usize = 96;
const K_CHUNK: usize = 256;

/// Whether the bf16 kernel takes heads of `d` (q, k and v all `d` wide).
pub fn supports_head(d: usize) -> bool {
    matches!(d, 32 | 64 | 128)
}

/// `q [B, Lq, d]`, `k [B, S, d]`, `v [B, S, d]` → `softmax(q·kᵀ (+ region mask))·v` `[B, Lq, d]` with the
/// products in bf16 where this thread's [`path`] is `Dpbf16` (see the module doc); otherwise, and for heads
/// other than 32/64/128, off the CPU or with gradients, [`fused_attention`] itself.
pub fn fused_attention_bf16(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&RegionMask>) -> Result<Tensor> {
    let (b, lq, d) = q.dims3()?;
    let (bk, s, dk) = k.dims3()?;
    let (bv, sv, dv) = v.dims3()?;
    let bf16 = bk == b
        && bv == b
        && dk == d
        && sv == s
        && dv == d
        && supports_head(d)
        && lq > 0
        && s > 0
        && [q, k, v].iter().all(|t| cpu_f32(t) && !t.track_op())
        && path() == Bf16Path::Dpbf16;
    if !bf16 {
        return fused_attention(q, k, v, mask);
    }
    if let Some(m) = mask {
        if m.p == 0 || b % m.p != 0 || m.q_labels.len() != m.p * lq || m.k_labels.len() != m.p * s {
            candle_core::bail!("bf16 attention: region mask does not fit the scores");
        }
    }
    q.contiguous()?.apply_op3_no_bwd(&k.contiguous()?, &v.contiguous()?, &Bf16Attention { mask })
}

struct Bf16Attention<'a> {
    mask: Option<&'a RegionMask>,
}

impl CustomOp3 for Bf16Attention<'_> {
    fn name(&self) -> &'static str {
        "fused-attention-bf16"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout, s3: &CpuStorage, l3: &Layout) -> Result<(CpuStorage, Shape)> {
        let (q, k, v) = (f32_slice(s1, l1, "bf16 attention")?, f32_slice(s2, l2, "bf16 attention")?, f32_slice(s3, l3, "bf16 attention")?);
        let (b, lq, d) = l1.shape().dims3()?;
        let s = l2.shape().dims3()?.1;
        let mut out = vec![0f32; b * lq * d];
        if !attention_rounded::<false>(q, k, v, b, lq, s, d, self.mask, &mut out, Q_BLOCK, K_CHUNK) {
            // The caller checked the path on this thread; a refusal here is a bug, not a fallback.
            candle_core::bail!("bf16 attention: the kernel refused heads of {d} on this thread");
        }
        Ok((CpuStorage::F32(out), Shape::from((b, lq, d))))
    }
}

/// The kernel on slices; `TRUNC` truncates the operands instead of rounding them (the tests' mutation).
/// Returns false (nothing written) unless [`path`] answers `Dpbf16` and the head size is supported.
#[allow(clippy::too_many_arguments)]
fn attention_rounded<const TRUNC: bool>(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    b: usize,
    lq: usize,
    s: usize,
    d: usize,
    mask: Option<&RegionMask>,
    out: &mut [f32],
    q_block: usize,
    k_chunk: usize,
) -> bool {
    assert!(q.len() == b * lq * d && k.len() == b * s * d && v.len() == b * s * d && out.len() == b * lq * d, "bf16 attention: shapes");
    assert!(k_chunk >= 64 && k_chunk.is_multiple_of(64) && q_block > 0, "bf16 attention: blocks {q_block}×{k_chunk}");
    if path() != Bf16Path::Dpbf16 || !supports_head(d) {
        return false;
    }
    if b * lq == 0 || s == 0 {
        return true;
    }
    #[cfg(target_arch = "x86_64")]
    match d {
        32 => run::<32, TRUNC>(q, k, v, b, lq, s, mask, out, q_block, k_chunk),
        64 => run::<64, TRUNC>(q, k, v, b, lq, s, mask, out, q_block, k_chunk),
        _ => run::<128, TRUNC>(q, k, v, b, lq, s, mask, out, q_block, k_chunk),
    }
    true
}

#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
fn run<const D: usize, const TRUNC: bool>(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    b: usize,
    lq: usize,
    s: usize,
    mask: Option<&RegionMask>,
    out: &mut [f32],
    q_block: usize,
    k_chunk: usize,
) {
    let pairs = D / 2;
    let tiles = s.div_ceil(KT);
    let (k_item, v_item) = (tiles * pairs * KT, s.div_ceil(2) * D);
    let (kw, vw) = (pack_keys::<D, TRUNC>(k, b, s, tiles), pack_values::<D, TRUNC>(v, b, s));
    // Key labels padded to whole tiles (the padded keys' scores are never read).
    let labels: Option<Vec<u8>> = mask.map(|m| {
        let mut l = vec![0u8; m.p * tiles * KT];
        for pi in 0..m.p {
            l[pi * tiles * KT..][..s].copy_from_slice(&m.k_labels[pi * s..][..s]);
        }
        l
    });
    let qb = q_block.min(lq);
    let pws = k_chunk / 2;
    let scratch = || (vec![0f32; qb * k_chunk], vec![0u32; qb * pairs], vec![0u32; qb * pws], vec![0f32; qb]);
    for_each_row_block(b, lq, D, 1, D, q_block, out, scratch, |blk, st, (sc, qw, pw, corr)| {
        let RowBlock { g, q0, m, .. } = blk;
        let lab = mask.zip(labels.as_deref()).map(|(mk, kl)| {
            let pi = g % mk.p;
            (&mk.q_labels[pi * lq + q0..][..m], &kl[pi * tiles * KT..][..tiles * KT])
        });
        // SAFETY (all calls below): `path` answered Dpbf16 (AVX-512F and AVX512-BF16); rows q0..q0+m of item g
        // lie in `q`; key tiles j0/64.. and value pairs j0/2.. of item g exist (zero-padded); `sc` holds
        // m × k_chunk floats, `qw` m × D/2 and `pw` m × k_chunk/2 words, `acc` m × D floats; the labels cover
        // the rows and every padded key.
        unsafe { to_pairs::<TRUNC>(&q[(g * lq + q0) * D..], D, m, D, qw, pairs) };
        for j0 in (0..s).step_by(k_chunk) {
            let kc = k_chunk.min(s - j0);
            let lab = lab.map(|(ql, kl)| (ql, &kl[j0..]));
            unsafe {
                scores::<D>(qw, m, &kw[g * k_item + (j0 / KT) * pairs * KT..], kc.div_ceil(KT), sc, k_chunk, lab);
                softmax_chunk(&mut sc[..m * k_chunk], k_chunk, kc, &mut st.mx[..m], &mut st.sum[..m], &mut corr[..m]);
                to_pairs::<TRUNC>(sc, k_chunk, m, kc, pw, pws);
                values::<D>(pw, pws, m, kc.div_ceil(2), &vw[g * v_item + (j0 / 2) * D..], &mut st.acc, corr);
            }
        }
    });
}

/// Keys of every item as `[tile][d-pair][64 keys]` words, keys past `s` zero.
#[cfg(target_arch = "x86_64")]
fn pack_keys<const D: usize, const TRUNC: bool>(k: &[f32], b: usize, s: usize, tiles: usize) -> Vec<u32> {
    let pairs = D / 2;
    let mut kw = vec![0u32; b * tiles * pairs * KT];
    kw.par_chunks_mut(pairs * KT).enumerate().for_each(|(i, tile)| {
        let (g, ti) = (i / tiles, i % tiles);
        let mut w = [0u32; 64];
        for j in 0..KT.min(s - ti * KT) {
            // SAFETY: the caller checked AVX-512F and AVX512-BF16; one key row of D values into D/2 words.
            unsafe { to_pairs::<TRUNC>(&k[(g * s + ti * KT + j) * D..][..D], D, 1, D, &mut w, pairs) };
            for (tp, v) in w[..pairs].iter().enumerate() {
                tile[tp * KT + j] = *v;
            }
        }
    });
    kw
}

/// Values of every item as `[key-pair][D]` words (`v[2p][t] | v[2p + 1][t] << 16`), an odd last key paired
/// with 0.
#[cfg(target_arch = "x86_64")]
fn pack_values<const D: usize, const TRUNC: bool>(v: &[f32], b: usize, s: usize) -> Vec<u32> {
    let sp = s.div_ceil(2);
    let mut vw = vec![0u32; b * sp * D];
    vw.par_chunks_mut(sp * D).enumerate().for_each(|(g, item)| {
        let zero = [0f32; D];
        for (p, dst) in item.chunks_exact_mut(D).enumerate() {
            let row = |j: usize| (j < s).then(|| &v[(g * s + j) * D..][..D]);
            let (v0, v1) = (row(2 * p).unwrap_or(&zero), row(2 * p + 1));
            if TRUNC {
                for t in 0..D {
                    dst[t] = pair::<TRUNC>(v0[t], v1.map_or(0.0, |h| h[t]));
                }
            } else {
                crate::bf16::conv_kernel::pair_row(v0, v1, dst);
            }
        }
    });
    vw
}

/// 16 pair words as `vdpbf16ps` reads them.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
unsafe fn words(p: *const u32) -> __m512bh {
    std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(p as *const _))
}

/// Scores of `m` packed query rows (`qw`, D/2 words each) against `tiles` packed key tiles → `s` (row stride
/// `ss`), −100 added where a row's label differs from a key's (`lab`: the rows' labels, the keys' from this
/// chunk's first). Tile-outer so one key tile serves every row group from L1.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn scores<const D: usize>(qw: &[u32], m: usize, kw: &[u32], tiles: usize, s: &mut [f32], ss: usize, lab: Option<(&[u8], &[u8])>) {
    let pairs = D / 2;
    debug_assert!(kw.len() >= tiles * pairs * KT && s.len() >= (m - 1) * ss + tiles * KT && qw.len() >= m * pairs);
    debug_assert!(lab.is_none_or(|(ql, kl)| ql.len() >= m && kl.len() >= tiles * KT));
    for ti in 0..tiles {
        let k = kw.as_ptr().add(ti * pairs * KT);
        let kl = lab.map(|(_, kl)| kl.as_ptr().add(ti * KT));
        let mut r0 = 0;
        while r0 < m {
            let r = MR.min(m - r0);
            let ql = lab.map(|(ql, _)| ql.as_ptr().add(r0));
            by_rows!(r, score_tile::<D>(qw.as_ptr().add(r0 * pairs), k, s.as_mut_ptr().add(r0 * ss + ti * KT), ss, ql, kl));
            r0 += r;
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
unsafe fn score_tile<const R: usize, const D: usize>(q: *const u32, k: *const u32, s: *mut f32, ss: usize, ql: Option<*const u8>, kl: Option<*const u8>) {
    let pairs = D / 2;
    let mut acc = [[_mm512_setzero_ps(); 4]; R];
    for tp in 0..pairs {
        let kp = k.add(tp * KT);
        let b = [words(kp), words(kp.add(16)), words(kp.add(32)), words(kp.add(48))];
        for (r, acc) in acc.iter_mut().enumerate() {
            let a = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(*q.add(r * pairs + tp) as i32));
            for i in 0..4 {
                acc[i] = _mm512_dpbf16_ps(acc[i], a, b[i]);
            }
        }
    }
    match ql.zip(kl) {
        Some((ql, kl)) => {
            let kls = [0, 1, 2, 3].map(|i| _mm512_cvtepu8_epi32(_mm_loadu_si128(kl.add(16 * i) as *const _)));
            let off = _mm512_set1_ps(-100.0);
            for (r, acc) in acc.iter().enumerate() {
                let rl = _mm512_set1_epi32(*ql.add(r) as i32);
                for (i, a) in acc.iter().enumerate() {
                    let differ = _mm512_cmpneq_epi32_mask(kls[i], rl);
                    _mm512_storeu_ps(s.add(r * ss + i * 16), _mm512_mask_add_ps(*a, differ, *a, off));
                }
            }
        }
        None => {
            for (r, acc) in acc.iter().enumerate() {
                for (i, a) in acc.iter().enumerate() {
                    _mm512_storeu_ps(s.add(r * ss + i * 16), *a);
                }
            }
        }
    }
}

/// `o (m × D) ← corr ⊙ o + p · v` over `pairs` key pairs: `pw` the chunk's rounded exponentials (row stride
/// `ps` words), `vw` the chunk's packed value pairs; columns in blocks of 64 (32 for D = 32).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn values<const D: usize>(pw: &[u32], ps: usize, m: usize, pairs: usize, vw: &[u32], o: &mut [f32], corr: &[f32]) {
    debug_assert!(pw.len() >= (m - 1) * ps + pairs && vw.len() >= pairs * D && o.len() >= m * D && corr.len() >= m);
    for c0 in (0..D).step_by(64) {
        let mut r0 = 0;
        while r0 < m {
            let r = MR.min(m - r0);
            let (p, v, o, c) = (pw.as_ptr().add(r0 * ps), vw.as_ptr().add(c0), o.as_mut_ptr().add(r0 * D + c0), corr.as_ptr().add(r0));
            if D == 32 {
                by_rows!(r, value_tile::<D, 2>(p, ps, pairs, v, o, c));
            } else {
                by_rows!(r, value_tile::<D, 4>(p, ps, pairs, v, o, c));
            }
            r0 += r;
        }
    }
}

/// `R` rows × `Z` zmm of output columns (the block at `o`, row stride D; `v` at the block's first column).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
unsafe fn value_tile<const R: usize, const D: usize, const Z: usize>(p: *const u32, ps: usize, pairs: usize, v: *const u32, o: *mut f32, corr: *const f32) {
    let mut acc = [[_mm512_setzero_ps(); Z]; R];
    for (r, acc) in acc.iter_mut().enumerate() {
        let c = _mm512_set1_ps(*corr.add(r));
        for (i, a) in acc.iter_mut().enumerate() {
            *a = _mm512_mul_ps(_mm512_loadu_ps(o.add(r * D + i * 16)), c);
        }
    }
    for jp in 0..pairs {
        let vp = v.add(jp * D);
        let mut b = [std::mem::transmute::<__m512i, __m512bh>(_mm512_setzero_si512()); Z];
        for (i, b) in b.iter_mut().enumerate() {
            *b = words(vp.add(16 * i));
        }
        for (r, acc) in acc.iter_mut().enumerate() {
            let a = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(*p.add(r * ps + jp) as i32));
            for i in 0..Z {
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
    use candle_core::Device;

    const U: f64 = 1.0 / 256.0;
    /// 2⁻²⁴, f32's unit roundoff.
    const ULP: f64 = 1.0 / 16_777_216.0;

    /// What the f64 reference multiplies: the f32 operands as given, or rounded to bf16 as the kernel rounds them.
    #[derive(Clone, Copy, PartialEq)]
    enum Against {
        Exact,
        Rounded,
    }

    fn data(len: usize, amp: f32, seed: u64) -> Vec<f32> {
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..len)
            .map(|_| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((x >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * amp
            })
            .collect()
    }

    struct Case {
        q: Vec<f32>,
        k: Vec<f32>,
        v: Vec<f32>,
        b: usize,
        lq: usize,
        s: usize,
        d: usize,
        mask: Option<RegionMask>,
    }

    fn case(b: usize, lq: usize, s: usize, d: usize, p: Option<usize>, seed: u64) -> Case {
        let mask = p.map(|p| {
            let lab = |n: usize, sd: u64| data(n, 1.0, sd).iter().map(|x| ((x + 1.0) * 1.5) as u8).collect::<Vec<u8>>();
            RegionMask { q_labels: lab(p * lq, seed + 7), k_labels: lab(p * s, seed + 8), p }
        });
        // q as the encoder scales it (1/√d folded in), k and v of order one.
        Case { q: data(b * lq * d, 2.5 / (d as f32).sqrt(), seed), k: data(b * s * d, 1.5, seed + 1), v: data(b * s * d, 2.0, seed + 2), b, lq, s, d, mask }
    }

    /// Per output: the f64 attention o, A = Σ_j w_j|v_jt|, M = max_j|v_jt|; per row: Δ, the bound on a score's
    /// error (the module's model for `Exact`; for `Rounded` only the f32 summation of exact bf16 products and
    /// the flush term), each plus the f32 rounding of the mask's addition where it adds.
    struct Reference {
        o: Vec<f64>,
        a: Vec<f64>,
        m: Vec<f64>,
        delta: Vec<f64>,
    }

    fn reference(c: &Case, against: Against) -> Reference {
        let x = |v: f32| if against == Against::Rounded { bf16_to_f32_daz(f32_to_bf16(v)) as f64 } else { v as f64 };
        let (b, lq, s, d) = (c.b, c.lq, c.s, c.d);
        let mut r = Reference { o: vec![0.0; b * lq * d], a: vec![0.0; b * lq * d], m: vec![0.0; b * lq * d], delta: vec![0.0; b * lq] };
        for g in 0..b {
            for i in 0..lq {
                let qi: Vec<f64> = c.q[(g * lq + i) * d..][..d].iter().map(|v| x(*v)).collect();
                let mut delta = 0f64;
                let sc: Vec<f64> = (0..s)
                    .map(|j| {
                        let kj = &c.k[(g * s + j) * d..][..d];
                        let (dot, abs) = qi.iter().zip(kj).fold((0f64, 0f64), |(dd, bb), (p, r)| (dd + p * x(*r), bb + (p * x(*r)).abs()));
                        let mut e = match against {
                            Against::Exact => error_bound(d, abs),
                            Against::Rounded => d as f64 * ULP * abs + 2.0 * d as f64 * 2f64.powi(-126),
                        };
                        let masked = c.mask.as_ref().is_some_and(|m| m.q_labels[(g % m.p) * lq + i] != m.k_labels[(g % m.p) * s + j]);
                        let sj = if masked { dot - 100.0 } else { dot };
                        if masked {
                            e += ULP * (dot.abs() + e + 100.0);
                        }
                        delta = delta.max(e);
                        sj
                    })
                    .collect();
                let mx = sc.iter().fold(f64::NEG_INFINITY, |p, v| p.max(*v));
                let w: Vec<f64> = sc.iter().map(|v| (v - mx).exp()).collect();
                let z: f64 = w.iter().sum();
                let at = (g * lq + i) * d;
                for (j, wj) in w.iter().enumerate() {
                    for (t, vt) in c.v[(g * s + j) * d..][..d].iter().enumerate() {
                        let vt = x(*vt);
                        r.o[at + t] += wj / z * vt;
                        r.a[at + t] += wj / z * vt.abs();
                        r.m[at + t] = r.m[at + t].max(vt.abs());
                    }
                }
                r.delta[g * lq + i] = delta;
            }
        }
        r
    }

    /// The module's bound for output `idx`. Against the rounded operands the product's own error is the
    /// rounding of the exponentials only: u instead of 2u + u².
    fn bound(r: &Reference, idx: usize, s: usize, d: usize, k_chunk: usize, against: Against) -> f64 {
        let e = (2.0 * r.delta[idx / d]).exp();
        let sf = s as f64;
        let product = if against == Against::Exact { 2.0 * U + U * U } else { U };
        let f32s = (2.0 * sf + 2.0 * s.div_ceil(k_chunk) as f64 + 8.0) * ULP;
        (e - 1.0) * r.a[idx] + e * (product + f32s) * r.a[idx] + sf * ULP * r.m[idx] + 2.0 * sf * 2f64.powi(-126)
    }

    /// Ok: the largest |got − o| / bound; Err names the first output past its bound.
    fn check(got: &[f32], r: &Reference, s: usize, d: usize, k_chunk: usize, against: Against) -> std::result::Result<f64, String> {
        let mut worst = 0f64;
        for (idx, g) in got.iter().enumerate() {
            let b = bound(r, idx, s, d, k_chunk, against);
            let err = (*g as f64 - r.o[idx]).abs();
            if err.is_nan() || err > b {
                return Err(format!("output {idx} (row {}, column {}): {g} against {}, |err| {err:.3e} > {b:.3e}", idx / d, idx % d, r.o[idx]));
            }
            worst = worst.max(err / b);
        }
        Ok(worst)
    }

    fn run_case<const TRUNC: bool>(c: &Case, qb: usize, kc: usize) -> Vec<f32> {
        let mut out = vec![f32::NAN; c.b * c.lq * c.d];
        assert!(attention_rounded::<TRUNC>(&c.q, &c.k, &c.v, c.b, c.lq, c.s, c.d, c.mask.as_ref(), &mut out, qb, kc));
        out
    }

    fn tensors(c: &Case) -> (Tensor, Tensor, Tensor) {
        let t = |x: &[f32], l: usize| Tensor::from_slice(x, (c.b, l, c.d), &Device::Cpu).unwrap();
        (t(&c.q, c.lq), t(&c.k, c.s), t(&c.v, c.s))
    }

    /// Heads of 32, 64 and 128 against the f64 attention of the f32 operands (the module's model) and of the
    /// operands rounded to bf16 (only the exponentials' rounding and f32 sums), with and without a region mask
    /// (2 and 1 label sets, three regions), on ragged sizes: rows not multiples of 6 or of the row block, keys
    /// not multiples of 64 or of the chunk, odd key counts (a value pair padded), one key, cross-attention
    /// shapes (more keys than queries); two seeds; then through `fused_attention_bf16` at the encoder's blocks.
    #[test]
    fn bf16_attention_holds_the_error_model() {
        if path() != Bf16Path::Dpbf16 {
            eprintln!("no AVX512-BF16 on this CPU: the bf16 attention kernel cannot run (fused_attention_bf16 is fused_attention there; see the masked test)");
            return;
        }
        let mut worst = [0f64; 2];
        for seed in [1u64, 2] {
            let cases = [
                (2, 131, 131, 128, Some(2), 96, 64),
                (1, 37, 262, 128, Some(1), 13, 256),
                (1, 70, 65, 128, None, 6, 64),
                (3, 1, 1, 64, None, 96, 64),
                (2, 65, 300, 64, Some(2), 7, 128),
                (2, 65, 300, 32, None, 7, 128),
                (1, 200, 199, 32, Some(1), 96, 256),
            ];
            for (b, lq, s, d, p, qb, kc) in cases {
                let c = case(b, lq, s, d, p, seed * 100 + (lq * s) as u64);
                let got = run_case::<false>(&c, qb, kc);
                let what = format!("seed {seed}: b {b} lq {lq} s {s} d {d} mask {p:?} blocks {qb}x{kc}");
                for (i, against) in [Against::Exact, Against::Rounded].into_iter().enumerate() {
                    let w = check(&got, &reference(&c, against), s, d, kc, against).unwrap_or_else(|e| panic!("{what}, {}: {e}", ["exact", "rounded"][i]));
                    worst[i] = worst[i].max(w);
                }
            }
            let c = case(2, 300, 600, 128, Some(2), seed + 50);
            let (q, k, v) = tensors(&c);
            let got = fused_attention_bf16(&q, &k, &v, c.mask.as_ref()).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            for against in [Against::Exact, Against::Rounded] {
                check(&got, &reference(&c, against), c.s, c.d, K_CHUNK, against).unwrap_or_else(|e| panic!("seed {seed}: fused_attention_bf16: {e}"));
            }
        }
        eprintln!("largest |err| / bound: against the f32 operands {:.3}, against the rounded operands {:.3}", worst[0], worst[1]);
        assert!(worst[0] > 0.0 && worst[1] > 0.0, "no rounding error at all is suspicious");
    }

    /// Truncation instead of round to nearest even fails both checks, and a result 1 % off fails the model, on
    /// values just below a bf16 tie's far side: v = (1 + 2⁻⁷ − 2⁻²³)·2^e, all positive, which RNE moves by 2⁻²³
    /// and truncation by ≈ 2u, with small q and k (Δ ≈ 0, so the bound is ≈ (2u + u²)·A). The mask matters:
    /// the same result checked against the unmasked reference fails. A result at 1.01 × its bound fails, at
    /// 0.99 × passes.
    #[test]
    fn truncation_a_lost_mask_and_a_moved_result_are_caught() {
        if path() != Bf16Path::Dpbf16 {
            return;
        }
        let (qb, kc) = (13, 64);
        let mut c = case(2, 131, 131, 128, Some(2), 9);
        c.q.iter_mut().chain(c.k.iter_mut()).for_each(|x| *x *= 0.02);
        let near = 1.0 + 2f32.powi(-7) - 2f32.powi(-23);
        for (i, v) in c.v.iter_mut().enumerate() {
            *v = near * [1.0, 2.0, 4.0][i % 3];
        }
        let (s, d) = (c.s, c.d);
        let exact = reference(&c, Against::Exact);
        let rounded = reference(&c, Against::Rounded);
        let rne = run_case::<false>(&c, qb, kc);
        check(&rne, &exact, s, d, kc, Against::Exact).expect("RNE holds the model");
        check(&rne, &rounded, s, d, kc, Against::Rounded).expect("RNE holds the tight check");
        let trunc = run_case::<true>(&c, qb, kc);
        let e = check(&trunc, &exact, s, d, kc, Against::Exact).expect_err("truncation must fail the model");
        eprintln!("truncated: {e}");
        check(&trunc, &rounded, s, d, kc, Against::Rounded).expect_err("truncation must fail the tight check");
        let scaled: Vec<f32> = rne.iter().map(|v| v * 1.01).collect();
        check(&scaled, &exact, s, d, kc, Against::Exact).expect_err("1 % off must fail");

        let mut c = case(2, 131, 262, 128, Some(2), 5);
        let r = reference(&c, Against::Exact);
        let mut got = run_case::<false>(&c, 96, 256);
        check(&got, &r, c.s, c.d, 256, Against::Exact).expect("holds");
        c.mask = None;
        check(&got, &reference(&c, Against::Exact), c.s, c.d, 256, Against::Exact).expect_err("the mask changes the result");
        for idx in [0, 77 * c.d + 100, got.len() - 1] {
            let keep = got[idx];
            let b = bound(&r, idx, c.s, c.d, 256, Against::Exact);
            got[idx] = (r.o[idx] + 0.99 * b) as f32;
            check(&got, &r, c.s, c.d, 256, Against::Exact).expect("0.99 × the bound passes");
            got[idx] = (r.o[idx] - 1.01 * b) as f32;
            check(&got, &r, c.s, c.d, 256, Against::Exact).expect_err("1.01 × the bound fails");
            got[idx] = keep;
        }
    }

    /// Masked (`bf16::with_bf16_masked`), or with heads other than 32/64/128, `fused_attention_bf16` is
    /// `fused_attention` bit for bit (with and without a region mask); unmasked on a heads-of-128 call it is not.
    #[test]
    fn masked_or_other_heads_equal_fused_attention() {
        let v = |t: Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let bits = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
        for (b, lq, s, d, p) in [(2, 131, 262, 128, Some(2)), (2, 65, 65, 32, None), (1, 40, 80, 48, Some(1))] {
            let c = case(b, lq, s, d, p, 3);
            let (q, k, vv) = tensors(&c);
            let f32s = v(fused_attention(&q, &k, &vv, c.mask.as_ref()).unwrap());
            let masked = with_bf16_masked(|| v(fused_attention_bf16(&q, &k, &vv, c.mask.as_ref()).unwrap()));
            assert!(bits(&masked, &f32s), "b {b} lq {lq} s {s} d {d}: masked");
            let plain = v(fused_attention_bf16(&q, &k, &vv, c.mask.as_ref()).unwrap());
            assert_eq!(bits(&plain, &f32s), !supports_head(d) || path() != Bf16Path::Dpbf16, "d {d}: bf16 exactly where the kernel applies");
        }
    }
}
