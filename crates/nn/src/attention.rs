//! Softmax attention. Two CPU kernels, each keeping the numerics its model's parity was measured with:
//! [`fused_attention`] (encoder: single head, q pre-scaled, optional Swin region mask, vectorised exp without
//! FMA) and [`multi_head_attention`] (refiner: heads folded in the rows, flash-style query blocks, FMA exp).
//! Both compute scores in small per-task blocks, never the whole `[B, Lq, S]` matrix, and record no backward;
//! with gradients (or on other devices) they run as matmul + softmax + matmul.

use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor, D};
use rayon::prelude::*;

use crate::math::{exp_f32, exp_fast, simd_dispatch, LANES};
use crate::mode::{cpu_f32, f32_slice, is_cpu_f32, is_differentiable, with_f32};

/// Swin region labels: score `(b, i, j)` gets −100 added where `q_labels[b mod P][i] != k_labels[b mod P][j]`
/// (equal to adding the dense shifted-window mask, without materialising it).
#[derive(Debug, Clone)]
pub struct RegionMask {
    /// `[P, Lq]`
    pub q_labels: Vec<u8>,
    /// `[P, S]`
    pub k_labels: Vec<u8>,
    pub p: usize,
}

struct FusedAttention<'a> {
    mask: Option<&'a RegionMask>,
}

/// Score-buffer budget per task (floats). Each block re-packs k and v inside gemm, so blocks need ≳ 100 query
/// rows to amortise that (measured on the DL3DV bench: 27-row blocks 6.4 s of transformer, 146-row blocks 5.4 s).
const BLOCK_FLOATS: usize = 512 * 1024;

fn slice<'a>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [f32]> {
    f32_slice(s, l, "fused attention")
}

#[derive(Clone, Copy)]
struct SendPtr(*mut f32);
// SAFETY: every task writes a disjoint set of output elements.
unsafe impl Send for SendPtr {}
unsafe impl Sync for SendPtr {}

/// One block of query rows of a blocked attention: sequence `g`, head `h`, rows `q0..q0 + m`.
#[derive(Clone, Copy)]
pub(crate) struct RowBlock {
    pub g: usize,
    pub h: usize,
    pub q0: usize,
    pub m: usize,
}

/// Online-softmax state of a [`RowBlock`]: the accumulated output (rows × d), each row's running max and sum.
pub(crate) struct OnlineRows {
    pub acc: Vec<f32>,
    pub mx: Vec<f32>,
    pub sum: Vec<f32>,
}

/// The frame of the blocked attentions (`rope`'s chunked path, `attention64`'s fused kernel): every
/// (sequence, head, block of `q_block` query rows) runs `f` in parallel from a reset state (acc 0, max −∞, sum 0)
/// with a per-thread `scratch`; its rows acc / sum are then written to head h's `d` columns of `out` (n·l × c).
#[allow(clippy::too_many_arguments)]
pub(crate) fn for_each_row_block<S: Send>(
    n: usize,
    l: usize,
    c: usize,
    heads: usize,
    d: usize,
    q_block: usize,
    out: &mut [f32],
    scratch: impl Fn() -> S + Sync + Send,
    f: impl Fn(RowBlock, &mut OnlineRows, &mut S) + Sync + Send,
) {
    assert!(out.len() >= n * l * c && heads * d <= c, "attention: output of {} for {n}×{l}×{c}", out.len());
    let qb = q_block.min(l).max(1);
    let qblocks = l.div_ceil(qb);
    let optr = SendPtr(out.as_mut_ptr());
    let init = || (OnlineRows { acc: vec![0f32; qb * d], mx: vec![0f32; qb], sum: vec![0f32; qb] }, scratch());
    (0..n * heads * qblocks).into_par_iter().for_each_init(init, |(st, sc), task| {
        let optr = optr;
        let q0 = (task % qblocks) * qb;
        let b = RowBlock { g: task / (heads * qblocks), h: (task / qblocks) % heads, q0, m: qb.min(l - q0) };
        st.acc[..b.m * d].fill(0.0);
        st.mx[..b.m].fill(f32::NEG_INFINITY);
        st.sum[..b.m].fill(0.0);
        f(b, st, sc);
        for r in 0..b.m {
            let inv = 1.0 / st.sum[r];
            // SAFETY: row q0 + r of sequence g, head h's d columns: this task's alone, inside `out` (asserted).
            let o = unsafe { std::slice::from_raw_parts_mut(optr.0.add((b.g * l + q0 + r) * c + b.h * d), d) };
            for (o, a) in o.iter_mut().zip(&st.acc[r * d..(r + 1) * d]) {
                *o = a * inv;
            }
        }
    });
}

impl CustomOp3 for FusedAttention<'_> {
    fn name(&self) -> &'static str {
        "fused-attention"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout, s3: &CpuStorage, l3: &Layout) -> Result<(CpuStorage, Shape)> {
        let (q, k, v) = (slice(s1, l1)?, slice(s2, l2)?, slice(s3, l3)?);
        let (b, lq, c) = l1.shape().dims3()?;
        let (_, s, _) = l2.shape().dims3()?;
        let cv = l3.shape().dims3()?.2;
        if let Some(m) = self.mask {
            if m.p == 0 || b % m.p != 0 || m.q_labels.len() != m.p * lq || m.k_labels.len() != m.p * s {
                candle_core::bail!("fused attention: region mask does not fit the scores");
            }
        }
        let rows = (BLOCK_FLOATS / s.max(1)).clamp(8, 256).min(lq.max(1));
        let blocks = lq.div_ceil(rows);
        let mut out = vec![0f32; b * lq * cv];
        let optr = SendPtr(out.as_mut_ptr());
        (0..b * blocks).into_par_iter().for_each_init(
            || vec![0f32; rows * s],
            |buf, task| {
                let optr = optr;
                let (bi, blk) = (task / blocks, task % blocks);
                let r0 = blk * rows;
                let nr = rows.min(lq - r0);
                let qb = &q[(bi * lq + r0) * c..];
                let kb = &k[bi * s * c..];
                let vb = &v[bi * s * cv..];
                // SAFETY: buf is nr × s (row stride s); q rows r0.. of item bi (nr × c); kᵀ read as c × s with
                // column stride c; v is s × cv; the output rows (bi, r0..r0+nr) belong to this task only.
                unsafe {
                    gemm::gemm(
                        nr,
                        s,
                        c,
                        buf.as_mut_ptr(),
                        1,
                        s as isize,
                        false,
                        qb.as_ptr(),
                        1,
                        c as isize,
                        kb.as_ptr(),
                        c as isize,
                        1,
                        0.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    );
                }
                let labels = self.mask.map(|m| {
                    let pi = bi % m.p;
                    (&m.q_labels[pi * lq + r0..][..nr], &m.k_labels[pi * s..][..s])
                });
                masked_softmax_rows(&mut buf[..nr * s], s, labels);
                unsafe {
                    gemm::gemm(
                        nr,
                        cv,
                        s,
                        optr.0.add((bi * lq + r0) * cv),
                        1,
                        cv as isize,
                        false,
                        buf.as_ptr(),
                        1,
                        s as isize,
                        vb.as_ptr(),
                        1,
                        cv as isize,
                        0.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    );
                }
            },
        );
        Ok((CpuStorage::F32(out), Shape::from((b, lq, cv))))
    }
}

/// Masked softmax of each row (length `s`) of `buf` in place.
#[inline(always)]
fn masked_softmax_rows_impl(buf: &mut [f32], s: usize, labels: Option<(&[u8], &[u8])>) {
    for (r, row) in buf.chunks_exact_mut(s).enumerate() {
        if let Some((ql, kl)) = labels {
            let lab = ql[r];
            row.iter_mut().zip(kl).for_each(|(x, &l)| *x += if l != lab { -100.0 } else { 0.0 });
        }
        let mx = row.iter().fold(f32::NEG_INFINITY, |a, &x| a.max(x));
        let mut acc = [0f32; 8];
        let mut chunks = row.chunks_exact_mut(8);
        for ch in &mut chunks {
            for i in 0..8 {
                ch[i] = exp_fast(ch[i] - mx);
                acc[i] += ch[i];
            }
        }
        let mut sum: f32 = acc.iter().sum();
        for x in chunks.into_remainder() {
            *x = exp_fast(*x - mx);
            sum += *x;
        }
        let inv = 1.0 / sum;
        row.iter_mut().for_each(|x| *x *= inv);
    }
}

/// The same code compiled for AVX2 (the default x86-64 target only vectorises 4 lanes); no FMA, so the results
/// are bit-identical to the portable path.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn masked_softmax_rows_avx2(buf: &mut [f32], s: usize, labels: Option<(&[u8], &[u8])>) {
    masked_softmax_rows_impl(buf, s, labels)
}

fn masked_softmax_rows(buf: &mut [f32], s: usize, labels: Option<(&[u8], &[u8])>) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is available on this CPU.
        return unsafe { masked_softmax_rows_avx2(buf, s, labels) };
    }
    masked_softmax_rows_impl(buf, s, labels)
}

impl RegionMask {
    /// The dense additive mask `[P, Lq, S]` (0 or −100) of these labels.
    fn dense(&self, lq: usize, s: usize) -> Vec<f32> {
        let mut dense = vec![0f32; self.p * lq * s];
        for pi in 0..self.p {
            for i in 0..lq {
                for j in 0..s {
                    if self.q_labels[pi * lq + i] != self.k_labels[pi * s + j] {
                        dense[(pi * lq + i) * s + j] = -100.0;
                    }
                }
            }
        }
        dense
    }
}

/// `q [B, Lq, C]`, `k [B, S, C]`, `v [B, S, Cv]` → `softmax(q·kᵀ (+ region mask))·v`, `[B, Lq, Cv]`
/// (q carries any scale). The CPU kernel runs when nothing tracks gradients; otherwise the composed ops.
pub fn fused_attention(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&RegionMask>) -> Result<Tensor> {
    let (b, _, c) = q.dims3()?;
    let (bk, s, ck) = k.dims3()?;
    let (bv, sv, _) = v.dims3()?;
    if bk != b || bv != b || ck != c || sv != s {
        candle_core::bail!("fused attention: shapes q {:?}, k {:?}, v {:?} do not match", q.dims(), k.dims(), v.dims());
    }
    let kernel = [q, k, v].iter().all(|t| cpu_f32(t) && !t.track_op());
    if !kernel {
        return fused_attention_composed(q, k, v, mask);
    }
    q.contiguous()?.apply_op3_no_bwd(&k.contiguous()?, &v.contiguous()?, &FusedAttention { mask })
}

/// Scores one composed [`fused_attention`] call may hold (floats); larger batches run in slices, and a single
/// sequence longer than that in slices of query rows (softmax runs along the keys, so slicing rows is exact).
/// Off the CPU this bounds the memory of the encoder UNets' cross-view attention, whose token count grows with
/// the image (a 256×448 input: 5·7168 tokens, a 5 GB score matrix per head unsliced).
const COMPOSED_SCORES: usize = 1 << 26;

/// [`fused_attention`] as matmul + softmax + matmul (differentiable, any device), in slices of at most
/// [`COMPOSED_SCORES`] scores.
pub(crate) fn fused_attention_composed(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&RegionMask>) -> Result<Tensor> {
    fused_attention_composed_capped(q, k, v, mask, COMPOSED_SCORES)
}

/// [`fused_attention_composed`] with a chosen score budget (tests use small ones to exercise the slicing).
pub(crate) fn fused_attention_composed_capped(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&RegionMask>, cap: usize) -> Result<Tensor> {
    let (b, lq, _) = q.dims3()?;
    let s = k.dim(1)?;
    let dense = match mask {
        Some(m) => {
            if m.p == 0 || b % m.p != 0 || m.q_labels.len() != m.p * lq || m.k_labels.len() != m.p * s {
                candle_core::bail!("fused attention: region mask does not fit the scores");
            }
            Some(Tensor::from_vec(m.dense(lq, s), (1, m.p, lq, s), q.device())?.to_dtype(q.dtype())?)
        }
        None => None,
    };
    let p = mask.map_or(1, |m| m.p);
    // (query rows r0.., batch slice) → attention of those rows; the mask's rows are sliced with the queries.
    let run = |q: &Tensor, k: &Tensor, v: &Tensor, r0: usize| -> Result<Tensor> {
        let (nb, rows, _) = q.dims3()?;
        let mut sc = q.contiguous()?.matmul(&k.contiguous()?.t()?)?;
        if let Some(d) = &dense {
            let d = d.narrow(2, r0, rows)?;
            sc = sc.reshape((nb / p, p, rows, s))?.broadcast_add(&d)?.reshape((nb, rows, s))?;
        }
        let e = sc.broadcast_sub(&sc.max_keepdim(D::Minus1)?)?.exp()?;
        e.broadcast_div(&e.sum_keepdim(D::Minus1)?)?.matmul(&v.contiguous()?)
    };
    // Slices start at multiples of p, so mask row `b mod p` stays aligned.
    let per = (cap / (lq * s).max(1) / p).max(1) * p;
    let rows = (cap / (p * s).max(1)).clamp(1, lq.max(1));
    let slice = |i: usize, m: usize| -> Result<Tensor> {
        let (q, k, v) = (q.narrow(0, i, m)?, k.narrow(0, i, m)?, v.narrow(0, i, m)?);
        if rows >= lq {
            return run(&q, &k, &v, 0);
        }
        let parts = (0..lq).step_by(rows).map(|r| run(&q.narrow(1, r, rows.min(lq - r))?, &k, &v, r));
        Tensor::cat(&parts.collect::<Result<Vec<_>>>()?, 1)
    };
    if b <= per {
        return slice(0, b);
    }
    let parts = (0..b).step_by(per).map(|i| slice(i, per.min(b - i)));
    Tensor::cat(&parts.collect::<Result<Vec<_>>>()?, 0)
}

#[inline(always)]
pub(crate) fn row_max(row: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; LANES];
    let mut it = row.chunks_exact(LANES);
    for c in &mut it {
        for i in 0..LANES {
            acc[i] = acc[i].max(c[i]);
        }
    }
    let mut m = it.remainder().iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
    for a in acc {
        m = m.max(a);
    }
    m
}

/// In place: row ← exp(row − max(row)); returns the sum (normalisation is left to the caller).
#[inline(always)]
fn exp_shift_sum(row: &mut [f32]) -> f32 {
    exp_sub_sum(row, row_max(row))
}

/// In place: row ← exp(row − m); returns the sum.
#[inline(always)]
pub(crate) fn exp_sub_sum(row: &mut [f32], m: f32) -> f32 {
    let mut acc = [0f32; LANES];
    let mut it = row.chunks_exact_mut(LANES);
    for c in &mut it {
        for i in 0..LANES {
            c[i] = exp_f32(c[i] - m);
            acc[i] += c[i];
        }
    }
    let mut s = 0f32;
    for v in it.into_remainder() {
        *v = exp_f32(*v - m);
        s += *v;
    }
    s + acc.iter().sum::<f32>()
}

simd_dispatch! {
    fn softmax_rows_unnormalised(s: &mut [f32], cols: usize, sums: &mut [f32]) {
        for (row, sum) in s.chunks_exact_mut(cols).zip(sums.iter_mut()) {
            *sum = exp_shift_sum(row);
        }
    }
}

simd_dispatch! {
    fn scale_rows(out: *mut f32, rows: usize, d: usize, stride: usize, sums: &[f32]) {
        for r in 0..rows {
            let inv = 1.0 / sums[r];
            // SAFETY: the caller owns rows × d elements at this stride.
            let o = unsafe { std::slice::from_raw_parts_mut(out.add(r * stride), d) };
            for v in o {
                *v *= inv;
            }
        }
    }
}

/// Where the sequences of an attention live inside a row-major (rows, row_len) matrix: sequence
/// g = (g / inner_count, g % inner_count) starts at row `(g / inner_count)·outer + (g % inner_count)·inner`
/// and its positions are `pos` rows apart. Lets spatial (tokens of a frame), temporal (one pixel over the
/// frames, in the frame-major layout) and windowed attention read q/k/v where they are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SeqLayout {
    pub count: usize,
    pub len: usize,
    pub inner_count: usize,
    pub outer: usize,
    pub inner: usize,
    pub pos: usize,
}

impl SeqLayout {
    /// `count` contiguous sequences of `len` rows.
    pub fn contiguous(count: usize, len: usize) -> Self {
        Self { count, len, inner_count: 1, outer: len, inner: 0, pos: 1 }
    }

    #[inline]
    fn row(&self, g: usize, p: usize) -> usize {
        (g / self.inner_count) * self.outer + (g % self.inner_count) * self.inner + p * self.pos
    }
}

/// One attention operand: data, row length (elements), sequence layout.
#[derive(Clone, Copy)]
pub(crate) struct AttnOperand<'a> {
    pub(crate) data: &'a [f32],
    pub(crate) row_len: usize,
    pub(crate) col_offset: usize,
}

simd_dispatch! {
    /// Small sequences: scores by dot products, softmax, weighted sum of values, all in registers/L1.
    fn attend_small(
        q: &[f32], qo: usize, qrow: usize, qpos: usize, lq: usize,
        k: &[f32], ko: usize, krow: usize, kpos: usize, lk: usize,
        v: &[f32], vo: usize, vrow: usize, vpos: usize,
        out: SendPtr, oo: usize, orow: usize, opos: usize, d: usize, scale: f32, s: &mut [f32]
    ) {
        let _ = (qrow, krow, vrow, orow);
        for i in 0..lq {
            let qi = &q[qo + i * qpos..][..d];
            for j in 0..lk {
                let kj = &k[ko + j * kpos..][..d];
                let mut acc = [0f32; LANES];
                let mut a = qi.chunks_exact(LANES);
                let mut b = kj.chunks_exact(LANES);
                for (x, y) in (&mut a).zip(&mut b) {
                    for l in 0..LANES {
                        acc[l] = x[l].mul_add(y[l], acc[l]);
                    }
                }
                let mut t: f32 = a.remainder().iter().zip(b.remainder()).map(|(x, y)| x * y).sum();
                t += acc.iter().sum::<f32>();
                s[j] = t * scale;
            }
            let sum = exp_shift_sum(&mut s[..lk]);
            let inv = 1.0 / sum;
            // SAFETY: row i of this sequence/head belongs to this task only.
            let o = unsafe { std::slice::from_raw_parts_mut(out.0.add(oo + i * opos), d) };
            o.fill(0.0);
            for j in 0..lk {
                let p = s[j] * inv;
                let vj = &v[vo + j * vpos..][..d];
                for (x, y) in o.iter_mut().zip(vj) {
                    *x = p.mul_add(*y, *x);
                }
            }
        }
    }
}

/// Softmax attention over `heads` heads of width `d` (head h = columns h·d.. of each row).
/// q/out share `ql`, k/v share `kl` (same sequence count). `out` has the row length of `out_row_len`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn attention_raw(
    q: AttnOperand,
    ql: SeqLayout,
    k: AttnOperand,
    v: AttnOperand,
    kl: SeqLayout,
    out: &mut [f32],
    out_row_len: usize,
    heads: usize,
    d: usize,
    scale: f32,
) {
    let (lq, lk) = (ql.len, kl.len);
    let small = lk <= 64 && lq <= 64;
    // Query block: ≈ 1 MiB of scores per task for long sequences.
    let qb = if small { lq } else { ((1usize << 18) / lk.max(1)).clamp(16, 256).min(lq) };
    let qblocks = lq.div_ceil(qb.max(1));
    let pairs = ql.count * heads;
    // Small problems: group (sequence, head) pairs so a task holds ≈ 1 MFLOP.
    let group = if small { ((1usize << 20) / (lq * lk * d * 4).max(1)).max(1) } else { 1 };
    let tasks = if small { pairs.div_ceil(group) } else { pairs * qblocks };
    let optr = SendPtr(out.as_mut_ptr());
    (0..tasks).into_par_iter().for_each_init(Vec::<f32>::new, |s, task| {
        let optr = optr;
        if small {
            s.resize(lk.max(1), 0.0);
            for pair in task * group..((task + 1) * group).min(pairs) {
                let (g, h) = (pair / heads, pair % heads);
                attend_small(
                    q.data,
                    ql.row(g, 0) * q.row_len + q.col_offset + h * d,
                    q.row_len,
                    ql.pos * q.row_len,
                    lq,
                    k.data,
                    kl.row(g, 0) * k.row_len + k.col_offset + h * d,
                    k.row_len,
                    kl.pos * k.row_len,
                    lk,
                    v.data,
                    kl.row(g, 0) * v.row_len + v.col_offset + h * d,
                    v.row_len,
                    kl.pos * v.row_len,
                    optr,
                    ql.row(g, 0) * out_row_len + h * d,
                    out_row_len,
                    ql.pos * out_row_len,
                    d,
                    scale,
                    s,
                );
            }
            return;
        }
        let pair = task / qblocks;
        let (g, h) = (pair / heads, pair % heads);
        let q0 = (task % qblocks) * qb;
        let m = qb.min(lq - q0);
        s.resize(m * lk + m, 0.0);
        let (scores, sums) = s.split_at_mut(m * lk);
        let qoff = ql.row(g, q0) * q.row_len + q.col_offset + h * d;
        let koff = kl.row(g, 0) * k.row_len + k.col_offset + h * d;
        let voff = kl.row(g, 0) * v.row_len + v.col_offset + h * d;
        let ooff = ql.row(g, q0) * out_row_len + h * d;
        // SAFETY: all reads stay inside q/k/v (rows of valid sequences, columns of head h); the output
        // block (rows q0..q0+m of sequence g, head h's columns) is written by this task only.
        unsafe {
            gemm::gemm(
                m,
                lk,
                d,
                scores.as_mut_ptr(),
                1,
                lk as isize,
                false,
                q.data.as_ptr().add(qoff),
                1,
                (ql.pos * q.row_len) as isize,
                k.data.as_ptr().add(koff),
                (kl.pos * k.row_len) as isize,
                1,
                0.0,
                scale,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        softmax_rows_unnormalised(scores, lk, sums);
        unsafe {
            gemm::gemm(
                m,
                d,
                lk,
                optr.0.add(ooff),
                1,
                (ql.pos * out_row_len) as isize,
                false,
                scores.as_ptr(),
                1,
                lk as isize,
                v.data.as_ptr().add(voff),
                1,
                (kl.pos * v.row_len) as isize,
                0.0,
                1.0,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        scale_rows(unsafe { optr.0.add(ooff) }, m, d, ql.pos * out_row_len, sums);
    });
}

/// Scaled dot-product attention on (N, L, H·d) tensors, heads folded, output (N, Lq, H·d).
fn attention_tensors(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize) -> Result<Tensor> {
    let (n, lq, inner) = q.dims3()?;
    let (nk, lk, _) = k.dims3()?;
    if nk != n || inner % heads != 0 {
        candle_core::bail!("attention: q {:?} k {:?} with {heads} heads", q.dims(), k.dims());
    }
    let d = inner / heads;
    let mut out = vec![0f32; n * lq * inner];
    with_f32(q, |qd| {
        with_f32(k, |kd| {
            with_f32(v, |vd| {
                attention_raw(
                    AttnOperand { data: qd, row_len: inner, col_offset: 0 },
                    SeqLayout::contiguous(n, lq),
                    AttnOperand { data: kd, row_len: inner, col_offset: 0 },
                    AttnOperand { data: vd, row_len: inner, col_offset: 0 },
                    SeqLayout::contiguous(n, lk),
                    &mut out,
                    inner,
                    heads,
                    d,
                    1.0 / (d as f32).sqrt(),
                )
            })
        })
    })???;
    Tensor::from_vec(out, (n, lq, inner), q.device())
}

/// Softmax over the last dim from ops that all record a backward (`candle_nn::ops::softmax_last_dim`
/// records none in candle 0.11.1); the row max is subtracted as a constant.
fn softmax_last_dim_differentiable(x: &Tensor) -> Result<Tensor> {
    let m = x.max_keepdim(candle_core::D::Minus1)?.detach();
    let e = x.broadcast_sub(&m)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(candle_core::D::Minus1)?)
}

/// Scaled dot-product attention, heads folded: q (N, Lq, H·d), k/v (N, Lk, H·d) → (N, Lq, H·d). The CPU
/// kernel outside differentiable mode; otherwise composed ops whose score blocks stay below
/// `max_score_elems` floats.
pub fn multi_head_attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, max_score_elems: usize) -> Result<Tensor> {
    if is_cpu_f32(q) {
        return attention_tensors(q, k, v, heads);
    }
    #[cfg(feature = "flash-attn")]
    if crate::flash_attn::applies(q, k, v) {
        match flash_multi_head_attention(q, k, v, heads) {
            Ok(Some(o)) => return Ok(o),
            Ok(None) => {}
            Err(e) => crate::flash_attn::note_fallback(&e),
        }
    }
    multi_head_attention_composed(q, k, v, heads, max_score_elems)
}

/// [`multi_head_attention`] on FlashAttention-2 ([`crate::flash_attn`]; CUDA f16/bf16, head dim 64), whatever
/// `MVSPLAT360_GPU_OPS` selects: the `(N, L, H·64)` operands are `(N, L, H, 64)` as they lie (a reshape, no copy
/// when contiguous). `Ok(None)` where the shapes do not fit that form; an error where the kernel cannot take the
/// operands (no CUDA, another dtype, past its limits). Records no backward.
#[cfg(feature = "flash-attn")]
pub fn flash_multi_head_attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize) -> Result<Option<Tensor>> {
    use crate::flash_attn::{flash_attention, HEAD_DIM};
    let (n, lq, inner) = q.dims3()?;
    let (nk, lk, ik) = k.dims3()?;
    if heads == 0 || inner != heads * HEAD_DIM || (nk, ik) != (n, inner) || v.dims3()? != (n, lk, inner) {
        return Ok(None);
    }
    let split = |t: &Tensor, l: usize| t.reshape((n, l, heads, HEAD_DIM));
    let o = flash_attention(&split(q, lq)?, &split(k, lk)?, &split(v, lk)?, 1.0 / (HEAD_DIM as f32).sqrt())?;
    Ok(Some(o.reshape((n, lq, inner))?))
}

/// [`multi_head_attention`] from matmul + softmax in score blocks of at most `max_score_elems`.
pub(crate) fn multi_head_attention_composed(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, max_score_elems: usize) -> Result<Tensor> {
    let (n, lq, inner) = q.dims3()?;
    let lk = k.dim(1)?;
    let d = inner / heads;
    let split = |t: &Tensor, l: usize| -> Result<Tensor> { t.reshape((n, l, heads, d))?.transpose(1, 2)?.reshape((n * heads, l, d))?.contiguous() };
    let scale = 1.0 / (d as f64).sqrt();
    let q = (split(q, lq)? * scale)?;
    let k = split(k, lk)?;
    let v = split(v, lk)?;
    let kt = k.transpose(1, 2)?;
    let nb = n * heads;
    let per_bh = lq * lk;
    let softmax = |s: &Tensor| -> Result<Tensor> {
        if is_differentiable() {
            softmax_last_dim_differentiable(s)
        } else {
            candle_nn::ops::softmax_last_dim(s)
        }
    };
    let out = if nb * per_bh <= max_score_elems {
        let s = softmax(&q.matmul(&kt)?)?;
        s.matmul(&v)?
    } else if per_bh <= max_score_elems {
        let bs = (max_score_elems / per_bh).max(1);
        let mut parts = Vec::new();
        let mut i = 0;
        while i < nb {
            let m = bs.min(nb - i);
            let s = softmax(&q.narrow(0, i, m)?.matmul(&kt.narrow(0, i, m)?)?)?;
            parts.push(s.matmul(&v.narrow(0, i, m)?)?);
            i += m;
        }
        Tensor::cat(&parts, 0)?
    } else {
        let qb = (max_score_elems / lk).max(1);
        let mut rows = Vec::with_capacity(nb);
        for bh in 0..nb {
            let (qh, kh, vh) = (q.narrow(0, bh, 1)?, kt.narrow(0, bh, 1)?, v.narrow(0, bh, 1)?);
            let mut parts = Vec::new();
            let mut j = 0;
            while j < lq {
                let m = qb.min(lq - j);
                let s = softmax(&qh.narrow(1, j, m)?.matmul(&kh)?)?;
                parts.push(s.matmul(&vh)?);
                j += m;
            }
            rows.push(Tensor::cat(&parts, 1)?);
        }
        Tensor::cat(&rows, 0)?
    };
    out.reshape((n, heads, lq, d))?.transpose(1, 2)?.reshape((n, lq, inner))
}

/// Self-attention over the sequences `layout` picks from the rows of q/k/v (each (rows, H·d), any leading
/// shape): spatial, temporal (frame-major) or windowed attention without transposes on the CPU. Output
/// (rows, H·d), rows not in any sequence are zero.
pub fn multi_head_attention_seqs(q: &Tensor, k: &Tensor, v: &Tensor, layout: SeqLayout, heads: usize, max_score_elems: usize) -> Result<Tensor> {
    if !is_cpu_f32(q) {
        #[cfg(feature = "flash-attn")]
        if crate::flash_attn::applies(q, k, v) {
            match flash_multi_head_attention_seqs(q, k, v, layout, heads) {
                Ok(Some(o)) => return Ok(o),
                Ok(None) => {}
                Err(e) => crate::flash_attn::note_fallback(&e),
            }
        }
        return multi_head_attention_seqs_composed(q, k, v, layout, heads, max_score_elems);
    }
    let inner = *q.dims().last().unwrap_or(&1);
    let rows = q.elem_count() / inner.max(1);
    let d = inner / heads;
    let mut out = vec![0f32; rows * inner];
    with_f32(q, |qd| {
        with_f32(k, |kd| {
            with_f32(v, |vd| {
                let op = |data| AttnOperand { data, row_len: inner, col_offset: 0 };
                attention_raw(op(qd), layout, op(kd), op(vd), layout, &mut out, inner, heads, d, 1.0 / (d as f32).sqrt())
            })
        })
    })???;
    Tensor::from_vec(out, (rows, inner), q.device())
}

/// [`multi_head_attention_seqs`] on FlashAttention-2 ([`crate::flash_attn`]; CUDA f16/bf16, head dim 64), whatever
/// `MVSPLAT360_GPU_OPS` selects, for the layouts that are a `(batch, seq, heads, 64)` view of the (rows, H·64)
/// operands (a reshape, no copy when contiguous), covering every row:
/// - contiguous sequences (spatial attention, windows of a frame's tokens): `(count, len, H, 64)`;
/// - temporal, frame-major (`inner == 1`, `pos == inner_count`, `outer == len·inner_count`: row
///   `(w·len + t)·s + p` for window w, frame t, pixel p, s = inner_count): `(count / s, len, s·H, 64)`, the
///   pixels folded into the heads (head stride 64 throughout).
///
/// `Ok(None)` for other layouts (the composed path gathers them); an error where the kernel cannot take the
/// operands. Output `(rows, H·64)` as [`multi_head_attention_seqs`]. Records no backward.
#[cfg(feature = "flash-attn")]
pub fn flash_multi_head_attention_seqs(q: &Tensor, k: &Tensor, v: &Tensor, layout: SeqLayout, heads: usize) -> Result<Option<Tensor>> {
    use crate::flash_attn::{flash_attention, HEAD_DIM};
    let inner = *q.dims().last().unwrap_or(&0);
    if heads == 0 || inner != heads * HEAD_DIM || k.dims() != q.dims() || v.dims() != q.dims() {
        return Ok(None);
    }
    let rows = q.elem_count() / inner;
    let SeqLayout { count, len, inner_count: ic, outer, inner: step, pos } = layout;
    if count * len != rows || rows == 0 {
        return Ok(None);
    }
    let (b, h) = if ic == 1 && outer == len && pos == 1 {
        (count, heads)
    } else if ic > 0 && count % ic == 0 && step == 1 && pos == ic && outer == len * ic {
        (count / ic, ic * heads)
    } else {
        return Ok(None);
    };
    let four = |t: &Tensor| t.reshape((b, len, h, HEAD_DIM));
    let o = flash_attention(&four(q)?, &four(k)?, &four(v)?, 1.0 / (HEAD_DIM as f32).sqrt())?;
    Ok(Some(o.reshape((rows, inner))?))
}

/// [`multi_head_attention_seqs`] for other devices: gather the sequences, attend, gather back. The way back is a
/// gather by the inverse row map (a zero row for rows in no sequence), not `index_add`: candle's CUDA
/// `index_add` walks all rows serially in one thread per column (≈ 200k steps per call for a 14-frame SVD UNet).
pub(crate) fn multi_head_attention_seqs_composed(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    layout: SeqLayout,
    heads: usize,
    max_score_elems: usize,
) -> Result<Tensor> {
    let inner = *q.dims().last().unwrap_or(&1);
    let rows = q.elem_count() / inner.max(1);
    let taken = layout.count * layout.len;
    let order: Vec<usize> = (0..layout.count).flat_map(|g| (0..layout.len).map(move |p| layout.row(g, p))).collect();
    if order.iter().any(|&r| r >= rows) {
        candle_core::bail!("attention: sequence layout {layout:?} reaches past the {rows} rows");
    }
    let attend = |q: &Tensor, k: &Tensor, v: &Tensor| -> Result<Tensor> {
        let seqs = |t: &Tensor| t.reshape((layout.count, layout.len, inner));
        multi_head_attention_composed(&seqs(q)?, &seqs(k)?, &seqs(v)?, heads, max_score_elems)?.reshape((taken, inner))
    };
    if taken == rows && order.iter().enumerate().all(|(j, &r)| j == r) {
        return attend(q, k, v);
    }
    // Sequences strided through blocks (temporal attention over frame-major rows): a transpose each way, whose
    // backward needs no scatter either.
    let ic = layout.inner_count;
    if taken == rows && layout.count % ic == 0 && layout.inner == 1 && layout.pos == ic && layout.outer == layout.len * ic {
        let blocks = layout.count / ic;
        let swap = |t: &Tensor, a: usize, b: usize| t.reshape((blocks, a, b, inner))?.transpose(1, 2)?.contiguous()?.reshape((rows, inner));
        let a = attend(&swap(q, layout.len, ic)?, &swap(k, layout.len, ic)?, &swap(v, layout.len, ic)?)?;
        return swap(&a, ic, layout.len);
    }
    let mut back = vec![u32::MAX; rows];
    for (j, &r) in order.iter().enumerate() {
        if back[r] != u32::MAX {
            candle_core::bail!("attention: sequence layout {layout:?} uses row {r} twice");
        }
        back[r] = j as u32;
    }
    let zero_row = taken as u32;
    let back: Vec<u32> = back.into_iter().map(|j| if j == u32::MAX { zero_row } else { j }).collect();
    let order: Vec<u32> = order.into_iter().map(|r| r as u32).collect();
    let (order, back) = (Tensor::from_vec(order, taken, q.device())?, Tensor::from_vec(back, rows, q.device())?);
    let gather = |t: &Tensor| t.reshape((rows, inner))?.index_select(&order, 0);
    let a = attend(&gather(q)?, &gather(k)?, &gather(v)?)?;
    Tensor::cat(&[&a, &Tensor::zeros((1, inner), a.dtype(), a.device())?], 0)?.index_select(&back, 0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Fused attention (with and without region mask) equals the composed definition to 1e-5.
    #[test]
    fn fused_attention_matches_composed() -> Result<()> {
        let dev = Device::Cpu;
        let (b, lq, s, c, cv, p) = (4, 37, 53, 16, 12, 2);
        let q = Tensor::randn(0f32, 1.0, (b, lq, c), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (b, s, c), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (b, s, cv), &dev)?;
        let q_labels: Vec<u8> = (0..p * lq).map(|i| ((i * 7) % 3) as u8).collect();
        let k_labels: Vec<u8> = (0..p * s).map(|i| ((i * 5) % 3) as u8).collect();
        let mut dense = vec![0f32; p * lq * s];
        for pi in 0..p {
            for i in 0..lq {
                for j in 0..s {
                    if q_labels[pi * lq + i] != k_labels[pi * s + j] {
                        dense[(pi * lq + i) * s + j] = -100.0;
                    }
                }
            }
        }
        let dense = Tensor::from_vec(dense, (1, p, lq, s), &dev)?;
        let mask = RegionMask { q_labels, k_labels, p };
        for m in [None, Some(&mask)] {
            let got = fused_attention(&q, &k, &v, m)?;
            let mut sc = q.matmul(&k.t()?)?;
            if m.is_some() {
                sc = sc.reshape((b / p, p, lq, s))?.broadcast_add(&dense)?.reshape((b, lq, s))?;
            }
            let e = sc.broadcast_sub(&sc.max_keepdim(D::Minus1)?)?.exp()?;
            let want = e.broadcast_div(&e.sum_keepdim(D::Minus1)?)?.matmul(&v)?;
            let d = (got - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "fused attention diff {d}");
        }
        Ok(())
    }

    fn naive_attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize) -> Tensor {
        let (n, lq, inner) = q.dims3().unwrap();
        let lk = k.dim(1).unwrap();
        let d = inner / heads;
        let sp = |t: &Tensor, l| t.reshape((n, l, heads, d)).unwrap().transpose(1, 2).unwrap().contiguous().unwrap();
        let s = (sp(q, lq).matmul(&sp(k, lk).t().unwrap()).unwrap() / (d as f64).sqrt()).unwrap();
        let p = candle_nn::ops::softmax_last_dim(&s).unwrap();
        p.matmul(&sp(v, lk)).unwrap().transpose(1, 2).unwrap().reshape((n, lq, inner)).unwrap()
    }

    #[test]
    fn attention_matches_naive_small_and_blocked() {
        let dev = Device::Cpu;
        // small path (≤ 64) and the gemm path with several query blocks (lk = 3000 → blocks of 87 rows)
        for (n, lq, lk, heads, d) in [(3, 14, 14, 2, 16), (2, 70, 3000, 2, 8), (1, 5, 1, 3, 4)] {
            let q = Tensor::randn(0f32, 1.0, (n, lq, heads * d), &dev).unwrap();
            let k = Tensor::randn(0f32, 1.0, (n, lk, heads * d), &dev).unwrap();
            let v = Tensor::randn(0f32, 1.0, (n, lk, heads * d), &dev).unwrap();
            let a = attention_tensors(&q, &k, &v, heads).unwrap();
            let e = naive_attention(&q, &k, &v, heads);
            let diff = (a - e).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(diff < 2e-5, "({n},{lq},{lk},{heads},{d}): {diff}");
        }
    }

    #[test]
    fn strided_layout_equals_transposed_attention() {
        // (b·t, s, c) frame-major tokens; temporal attention per (b, s) over t, in 2 windows.
        let dev = Device::Cpu;
        let (b, t, s, heads, d) = (2, 6, 5, 2, 8);
        let c = heads * d;
        let x = Tensor::randn(0f32, 1.0, (b * t, s, c), &dev).unwrap();
        let splits = 2;
        let tw = t / splits;
        let layout = SeqLayout { count: b * splits * s, len: tw, inner_count: s, outer: tw * s, inner: 1, pos: s };
        let mut out = vec![0f32; x.elem_count()];
        with_f32(&x, |xd| {
            let op = AttnOperand { data: xd, row_len: c, col_offset: 0 };
            attention_raw(op, layout, op, op, layout, &mut out, c, heads, d, 1.0 / (d as f32).sqrt());
        })
        .unwrap();
        let got = Tensor::from_vec(out, (b * t, s, c), &dev).unwrap();
        let seq = x.reshape((b, t, s, c)).unwrap().transpose(1, 2).unwrap().contiguous().unwrap().reshape((b * s * splits, tw, c)).unwrap();
        let want = naive_attention(&seq, &seq, &seq, heads).reshape((b, s, t, c)).unwrap().transpose(1, 2).unwrap().reshape((b * t, s, c)).unwrap();
        let diff = (got - want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(diff < 2e-5, "{diff}");
    }

    #[test]
    fn chunked_attention_matches_single_block() {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (3, 17, 8), &dev).unwrap();
        let k = Tensor::randn(0f32, 1.0, (3, 11, 8), &dev).unwrap();
        let v = Tensor::randn(0f32, 1.0, (3, 11, 8), &dev).unwrap();
        let full = multi_head_attention_composed(&q, &k, &v, 2, usize::MAX).unwrap();
        for budget in [11 * 17 * 2, 11 * 5] {
            let c = multi_head_attention_composed(&q, &k, &v, 2, budget).unwrap();
            let d = (c - &full).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(d < 1e-6, "budget {budget}: {d}");
        }
        // Closed form on one head: a single key gives back its value.
        let one = multi_head_attention_composed(&q, &k.narrow(1, 0, 1).unwrap(), &v.narrow(1, 0, 1).unwrap(), 2, usize::MAX).unwrap();
        let d = (one - v.narrow(1, 0, 1).unwrap().broadcast_as((3, 17, 8)).unwrap()).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-6);
    }

    /// The composed path (reshape, transpose or gather) against the CPU kernel, which reads the layout in place:
    /// contiguous, temporal windows (frame-major), and layouts leaving rows out or skipping rows (zeros there).
    #[test]
    fn composed_sequence_layouts_match_the_kernel() {
        let dev = Device::Cpu;
        let (heads, d) = (2, 4);
        let (b, t, s) = (2, 6, 5);
        let rows = b * t * s;
        let x = Tensor::randn(0f32, 1.0, (rows, heads * d), &dev).unwrap();
        let y = Tensor::randn(0f32, 1.0, (rows, heads * d), &dev).unwrap();
        let z = Tensor::randn(0f32, 1.0, (rows, heads * d), &dev).unwrap();
        let layouts = [
            ("contiguous", SeqLayout::contiguous(b * t, s)),
            ("temporal, 2 windows", SeqLayout { count: b * 2 * s, len: t / 2, inner_count: s, outer: t / 2 * s, inner: 1, pos: s }),
            ("rows left out", SeqLayout::contiguous(b * t - 3, s)),
            ("every other row", SeqLayout { count: 3, len: 10, inner_count: 1, outer: 20, inner: 0, pos: 2 }),
            ("windows inside frames", SeqLayout { count: 8, len: 3, inner_count: 2, outer: 15, inner: 1, pos: 5 }),
        ];
        for (what, layout) in layouts {
            let want = multi_head_attention_seqs(&x, &y, &z, layout, heads, usize::MAX).unwrap();
            let got = multi_head_attention_seqs_composed(&x, &y, &z, layout, heads, 7 * 11).unwrap();
            let diff = (got - &want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(diff < 1e-5, "{what}: {diff}");
            let zero_rows = want.abs().unwrap().sum(1).unwrap().to_vec1::<f32>().unwrap().iter().filter(|v| **v == 0.0).count();
            let covered = layout.count * layout.len;
            assert_eq!(zero_rows, rows - covered, "{what}: rows in no sequence are zero");
        }
        let twice = SeqLayout { count: 2, len: 3, inner_count: 1, outer: 1, inner: 0, pos: 1 };
        assert!(multi_head_attention_seqs_composed(&x, &y, &z, twice, heads, usize::MAX).is_err());
        let past = SeqLayout::contiguous(b * t + 1, s);
        assert!(multi_head_attention_seqs_composed(&x, &y, &z, past, heads, usize::MAX).is_err());
    }
}
