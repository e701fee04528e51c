//! CPU f32 kernels for the inference hot spots of the UNet, VAE and CLIP: attention without head
//! transposes (flash-style query blocks, one small score buffer per task), softmax/GELU with vectorised
//! exp/erf, and linear layers whose bias, residual and blend are folded into the gemm's destination.
//! Each entry point has a composed-candle fallback for other devices/dtypes.

use candle_core::{CpuStorage, DType, Result, Storage, Tensor};
use rayon::prelude::*;

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

const LANES: usize = 16;

/// e^x for x ≤ 88 in f32 (Cephes `expf` polynomial, ≈1 ulp); inputs below −87 give ≈1e-38 instead of 0.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
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
pub fn erf_f32(x: f32) -> f32 {
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
pub fn gelu_f32(x: f32) -> f32 {
    0.5 * x * (1.0 + erf_f32(x * std::f32::consts::FRAC_1_SQRT_2))
}

#[inline(always)]
fn row_max(row: &[f32]) -> f32 {
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
    let m = row_max(row);
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

simd_dispatch_impl! {
    fn softmax_rows_unnormalised(s: &mut [f32], cols: usize, sums: &mut [f32]) {
        for (row, sum) in s.chunks_exact_mut(cols).zip(sums.iter_mut()) {
            *sum = exp_shift_sum(row);
        }
    }
}

simd_dispatch_impl! {
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

#[derive(Clone, Copy)]
struct SendPtr(*mut f32);
// SAFETY: every task writes a disjoint set of output elements.
unsafe impl Send for SendPtr {}
unsafe impl Sync for SendPtr {}

/// One attention operand: data, row length (elements), sequence layout.
#[derive(Clone, Copy)]
pub struct AttnOperand<'a> {
    pub data: &'a [f32],
    pub row_len: usize,
    pub col_offset: usize,
}

simd_dispatch_impl! {
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
pub fn attention_raw(
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
                    q.data, ql.row(g, 0) * q.row_len + q.col_offset + h * d, q.row_len, ql.pos * q.row_len, lq,
                    k.data, kl.row(g, 0) * k.row_len + k.col_offset + h * d, k.row_len, kl.pos * k.row_len, lk,
                    v.data, kl.row(g, 0) * v.row_len + v.col_offset + h * d, v.row_len, kl.pos * v.row_len,
                    optr, ql.row(g, 0) * out_row_len + h * d, out_row_len, ql.pos * out_row_len, d, scale, s,
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
                m, lk, d,
                scores.as_mut_ptr(), 1, lk as isize, false,
                q.data.as_ptr().add(qoff), 1, (ql.pos * q.row_len) as isize,
                k.data.as_ptr().add(koff), (kl.pos * k.row_len) as isize, 1,
                0.0, scale, false, false, false, gemm::Parallelism::None,
            );
        }
        softmax_rows_unnormalised(scores, lk, sums);
        unsafe {
            gemm::gemm(
                m, d, lk,
                optr.0.add(ooff), 1, (ql.pos * out_row_len) as isize, false,
                scores.as_ptr(), 1, lk as isize,
                v.data.as_ptr().add(voff), 1, (kl.pos * v.row_len) as isize,
                0.0, 1.0, false, false, false, gemm::Parallelism::None,
            );
        }
        scale_rows(unsafe { optr.0.add(ooff) }, m, d, ql.pos * out_row_len, sums);
    });
}

thread_local! {
    static DIFFERENTIABLE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Switch this thread's differentiable mode (returns the previous setting). While on, every fast kernel of
/// the refiner (UNet, VAE, CLIP) takes its composed candle-op path, so the forward records a backward graph
/// (inputs and `Var` weights receive gradients); off (the default) is the inference fast path, unchanged.
/// Thread-local: the model calls made from this thread are affected, other threads are not.
pub fn set_differentiable(on: bool) -> bool {
    DIFFERENTIABLE.with(|d| d.replace(on))
}

/// Whether differentiable mode is on for this thread (see [`set_differentiable`]).
pub fn is_differentiable() -> bool {
    DIFFERENTIABLE.with(|d| d.get())
}

/// Differentiable mode for a scope: on while the guard lives, then back to the previous setting.
#[must_use = "differentiable mode ends when the guard is dropped"]
pub struct DifferentiableGuard(bool);

/// Turn differentiable mode on until the returned guard is dropped.
pub fn differentiable() -> DifferentiableGuard {
    DifferentiableGuard(set_differentiable(true))
}

impl Drop for DifferentiableGuard {
    fn drop(&mut self) {
        set_differentiable(self.0);
    }
}

/// True when the fast CPU kernels apply: a CPU f32 tensor outside differentiable mode.
pub fn is_cpu_f32(t: &Tensor) -> bool {
    t.device().is_cpu() && t.dtype() == DType::F32 && !is_differentiable()
}

/// Softmax over the last dim from ops that all record a backward (`candle_nn::ops::softmax_last_dim`
/// records none in candle 0.11.1); the row max is subtracted as a constant.
pub fn softmax_last_dim_differentiable(x: &Tensor) -> Result<Tensor> {
    let m = x.max_keepdim(candle_core::D::Minus1)?.detach();
    let e = x.broadcast_sub(&m)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(candle_core::D::Minus1)?)
}

/// Conv2d (groups 1) followed by `residual + scale·(conv + bias + item_bias)` on an optionally nearest-×2
/// upsampled input: the fused inference kernel normally, differentiable ops in differentiable mode.
pub fn conv2d_epilogue(
    x: &Tensor,
    w: &Tensor,
    bias: Option<&Tensor>,
    cfg: mvsplat360_nn::Conv2dConfig,
    epi: mvsplat360_nn::ConvEpilogue,
) -> Result<Tensor> {
    if !is_differentiable() {
        if cfg.stride == 1 || epi.item_bias.is_some() || epi.residual.is_some() || epi.upsample2x {
            return mvsplat360_nn::conv2d_fused(x, w, bias, cfg, epi);
        }
        return mvsplat360_nn::conv2d(x, w, bias, cfg);
    }
    let x = if epi.upsample2x {
        let (_, _, h, wd) = x.dims4()?;
        x.upsample_nearest2d(2 * h, 2 * wd)?
    } else {
        x.clone()
    };
    // `mvsplat360_nn::conv2d`: shifted gemm / im2col custom ops with backward, or candle's conv2d.
    let mut y = mvsplat360_nn::conv2d(&x, w, bias, cfg)?;
    if let Some(ib) = epi.item_bias {
        let (n, co, _, _) = y.dims4()?;
        y = y.broadcast_add(&ib.reshape((n, co, 1, 1))?)?;
    }
    if let Some(k) = epi.scale {
        y = (y * k as f64)?;
    }
    if let Some(r) = epi.residual {
        y = (y + r)?;
    }
    Ok(y)
}

/// Run `f` on the contiguous f32 data of a CPU tensor (no copy when already contiguous).
pub fn with_f32<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> R) -> Result<R> {
    let t = if t.is_contiguous() { t.clone() } else { t.contiguous()? };
    let (st, l) = t.storage_and_layout();
    match &*st {
        Storage::Cpu(CpuStorage::F32(v)) => match l.contiguous_offsets() {
            Some((a, b)) => Ok(f(&v[a..b])),
            None => candle_core::bail!("kernels: tensor not contiguous"),
        },
        _ => candle_core::bail!("kernels: expected a CPU f32 tensor"),
    }
}

/// Scaled dot-product attention on (N, L, H·d) tensors, heads folded, output (N, Lq, H·d).
pub fn attention_tensors(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize) -> Result<Tensor> {
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

/// dst (rows × o) = beta·(x (rows × k) @ wᵀ (w: o × k)) [+ dst when `accumulate`].
pub fn gemm_xwt(x: &[f32], rows: usize, k: usize, w: &[f32], o: usize, dst: &mut [f32], accumulate: bool, beta: f32) {
    debug_assert!(x.len() >= rows * k && w.len() >= o * k && dst.len() >= rows * o);
    if rows == 0 || o == 0 {
        return;
    }
    let threads = rayon::current_num_threads();
    let par = if threads > 1 && rows * o * k > 1 << 16 { gemm::Parallelism::Rayon(threads) } else { gemm::Parallelism::None };
    // SAFETY: the asserted lengths cover every index gemm touches.
    unsafe {
        gemm::gemm(
            rows, o, k,
            dst.as_mut_ptr(), 1, o as isize, accumulate,
            x.as_ptr(), 1, k as isize,
            w.as_ptr(), k as isize, 1,
            1.0, beta, false, false, false, par,
        );
    }
}

/// `scale·(x @ wᵀ + bias) + Σ cᵢ·addᵢ` over the last dim of x, in one gemm whose destination starts as
/// the bias/addend sum (no separate bias, residual or blend passes). Adds have the output's shape.
pub fn linear_fused(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let k = *dims.last().unwrap_or(&1);
    let (o, wk) = w.dims2()?;
    if wk != k {
        candle_core::bail!("linear: input width {k}, weight {:?}", w.dims());
    }
    let rows = x.elem_count() / k.max(1);
    let mut od = dims;
    if let Some(l) = od.last_mut() {
        *l = o;
    }
    if !is_cpu_f32(x) {
        let mut y = x.reshape((rows, k))?.matmul(&w.t()?)?;
        if let Some(b) = bias {
            y = y.broadcast_add(b)?;
        }
        let mut y = (y.reshape(od)? * scale as f64)?;
        for (a, c) in adds {
            y = (y + (*a * *c as f64)?)?;
        }
        return Ok(y);
    }
    for (a, _) in adds {
        if a.elem_count() != rows * o {
            candle_core::bail!("linear: addend {:?} does not match output {od:?}", a.dims());
        }
    }
    let mut dst = vec![0f32; rows * o];
    let bias_v = match bias {
        Some(b) => Some(b.to_vec1::<f32>()?),
        None => None,
    };
    let accumulate = bias_v.is_some() || !adds.is_empty();
    if accumulate {
        init_rows(&mut dst, o, bias_v.as_deref(), scale, adds)?;
    }
    with_f32(x, |xd| with_f32(w, |wd| gemm_xwt(xd, rows, k, wd, o, &mut dst, accumulate, scale)))??;
    Tensor::from_vec(dst, od, x.device())
}

/// dst[r, j] = scale·bias[j] + Σ cᵢ·addᵢ[r, j] (one parallel pass).
fn init_rows(dst: &mut [f32], o: usize, bias: Option<&[f32]>, scale: f32, adds: &[(&Tensor, f32)]) -> Result<()> {
    let datas: Vec<Tensor> = adds.iter().map(|(a, _)| if a.is_contiguous() { Ok((*a).clone()) } else { a.contiguous() }).collect::<Result<_>>()?;
    let guards: Vec<_> = datas.iter().map(|t| t.storage_and_layout()).collect();
    let mut slices: Vec<(&[f32], f32)> = Vec::with_capacity(adds.len());
    for ((st, l), (_, c)) in guards.iter().zip(adds) {
        match (&**st, l.contiguous_offsets()) {
            (Storage::Cpu(CpuStorage::F32(v)), Some((a, b))) => slices.push((&v[a..b], *c)),
            _ => candle_core::bail!("linear: addend must be a CPU f32 tensor"),
        }
    }
    const CH: usize = 1 << 14;
    let chunk = (CH / o.max(1)).max(1) * o;
    dst.par_chunks_mut(chunk).enumerate().for_each(|(ci, d)| {
        let start = ci * chunk;
        init_chunk(d, start, o, bias, scale, &slices);
    });
    Ok(())
}

simd_dispatch_impl! {
    fn init_chunk(d: &mut [f32], start: usize, o: usize, bias: Option<&[f32]>, scale: f32, adds: &[(&[f32], f32)]) {
        match bias {
            Some(b) => {
                for row in d.chunks_mut(o) {
                    for (x, &bv) in row.iter_mut().zip(b) {
                        *x = scale * bv;
                    }
                }
            }
            None => d.fill(0.0),
        }
        for (a, c) in adds {
            let a = &a[start..start + d.len()];
            if *c == 1.0 {
                for (x, &y) in d.iter_mut().zip(a) {
                    *x += y;
                }
            } else {
                for (x, &y) in d.iter_mut().zip(a) {
                    *x = c.mul_add(y, *x);
                }
            }
        }
    }
}

simd_dispatch_impl! {
    /// out[r, j] = (h[r, j] + b[j]) · gelu(h[r, inner + j] + b[inner + j]).
    fn geglu_rows(h: &[f32], b: &[f32], out: &mut [f32], inner: usize) {
        for (hr, orow) in h.chunks_exact(2 * inner).zip(out.chunks_exact_mut(inner)) {
            let (a, g) = hr.split_at(inner);
            let (ba, bg) = b.split_at(inner);
            for j in 0..inner {
                orow[j] = (a[j] + ba[j]) * gelu_f32(g[j] + bg[j]);
            }
        }
    }
}

simd_dispatch_impl! {
    fn gelu_inplace(x: &mut [f32]) {
        for v in x {
            *v = gelu_f32(*v);
        }
    }
}

/// GEGLU feed-forward `w2·geglu(w1·x + b1) + b2`, times `scale`, plus addends; rows processed in
/// chunks so the 2·inner-wide hidden activation stays ≈ 64 MiB, results written in place.
#[allow(clippy::too_many_arguments)]
pub fn geglu_ff(x: &Tensor, w1: &Tensor, b1: &Tensor, w2: &Tensor, b2: &Tensor, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let c = *dims.last().unwrap_or(&1);
    let rows = x.elem_count() / c.max(1);
    let (hidden2, _) = w1.dims2()?;
    let inner = hidden2 / 2;
    let (o, _) = w2.dims2()?;
    let mut od = dims;
    if let Some(l) = od.last_mut() {
        *l = o;
    }
    if !is_cpu_f32(x) {
        let h = x.reshape((rows, c))?.matmul(&w1.t()?)?.broadcast_add(b1)?;
        let a = h.narrow(1, 0, inner)?;
        let g = h.narrow(1, inner, inner)?.gelu_erf()?;
        let y = (a * g)?.matmul(&w2.t()?)?.broadcast_add(b2)?.reshape(od)?;
        let mut y = (y * scale as f64)?;
        for (a, cf) in adds {
            y = (y + (*a * *cf as f64)?)?;
        }
        return Ok(y);
    }
    let b1v = b1.to_vec1::<f32>()?;
    let b2v = b2.to_vec1::<f32>()?;
    let mut dst = vec![0f32; rows * o];
    init_rows(&mut dst, o, Some(&b2v), scale, adds)?;
    let chunk = ((16usize << 20) / hidden2.max(1)).max(64).min(rows.max(1));
    let mut hbuf = vec![0f32; chunk * hidden2];
    let mut gbuf = vec![0f32; chunk * inner];
    with_f32(x, |xd| {
        with_f32(w1, |w1d| {
            with_f32(w2, |w2d| {
                let mut r0 = 0;
                while r0 < rows {
                    let m = chunk.min(rows - r0);
                    gemm_xwt(&xd[r0 * c..(r0 + m) * c], m, c, w1d, hidden2, &mut hbuf[..m * hidden2], false, 1.0);
                    let per = (m / rayon::current_num_threads().max(1) / 4).max(1);
                    hbuf[..m * hidden2]
                        .par_chunks(per * hidden2)
                        .zip(gbuf[..m * inner].par_chunks_mut(per * inner))
                        .for_each(|(h, g)| geglu_rows(h, &b1v, g, inner));
                    gemm_xwt(&gbuf[..m * inner], m, inner, w2d, o, &mut dst[r0 * o..(r0 + m) * o], true, scale);
                    r0 += m;
                }
            })
        })
    })???;
    Tensor::from_vec(dst, od, x.device())
}

/// Exact-erf GELU (vectorised on CPU f32).
pub fn gelu(x: &Tensor) -> Result<Tensor> {
    if !is_cpu_f32(x) {
        return x.gelu_erf();
    }
    let mut v = with_f32(x, |d| d.to_vec())?;
    v.par_chunks_mut(1 << 14).for_each(gelu_inplace);
    Tensor::from_vec(v, x.dims(), x.device())
}

/// `a·ca + b·cb` in one pass (same shapes).
pub fn axpby(a: &Tensor, ca: f32, b: &Tensor, cb: f32) -> Result<Tensor> {
    if !is_cpu_f32(a) || a.dims() != b.dims() {
        return (a * ca as f64)? + (b * cb as f64)?;
    }
    let mut out = vec![0f32; a.elem_count()];
    with_f32(a, |ad| {
        with_f32(b, |bd| {
            out.par_chunks_mut(1 << 14).zip(ad.par_chunks(1 << 14)).zip(bd.par_chunks(1 << 14)).for_each(|((o, x), y)| {
                axpby_chunk(o, x, ca, y, cb)
            })
        })
    })??;
    Tensor::from_vec(out, a.dims(), a.device())
}

simd_dispatch_impl! {
    fn axpby_chunk(o: &mut [f32], x: &[f32], ca: f32, y: &[f32], cb: f32) {
        for ((o, &x), &y) in o.iter_mut().zip(x).zip(y) {
            *o = ca.mul_add(x, cb * y);
        }
    }
}

/// Per item of x (N, C, S) (channels-first): tokens (N, S, O) = xᵢᵀ·Wᵀ + b, reading the channels-first
/// layout through gemm strides (no permute copy).
pub fn linear_from_channels_first(x: &Tensor, w: &Tensor, b: &Tensor) -> Result<Tensor> {
    let (n, c, s) = x.dims3()?;
    let (o, wc) = w.dims2()?;
    if wc != c {
        candle_core::bail!("linear: {c} channels, weight {:?}", w.dims());
    }
    if !is_cpu_f32(x) {
        return x.transpose(1, 2)?.contiguous()?.reshape((n * s, c))?.matmul(&w.t()?)?.broadcast_add(b)?.reshape((n, s, o));
    }
    let bv = b.to_vec1::<f32>()?;
    let mut dst = vec![0f32; n * s * o];
    dst.par_chunks_mut(1 << 14).for_each(|d| init_chunk(d, 0, o, Some(&bv), 1.0, &[]));
    let threads = rayon::current_num_threads();
    with_f32(x, |xd| {
        with_f32(w, |wd| {
            for (i, d) in dst.chunks_mut(s * o).enumerate() {
                // SAFETY: lhs (s × c) element (j, k) = x[i, k, j]; all indices inside item i.
                unsafe {
                    gemm::gemm(
                        s, o, c,
                        d.as_mut_ptr(), 1, o as isize, true,
                        xd.as_ptr().add(i * c * s), s as isize, 1,
                        wd.as_ptr(), c as isize, 1,
                        1.0, 1.0, false, false, false, gemm::Parallelism::Rayon(threads),
                    );
                }
            }
        })
    })??;
    Tensor::from_vec(dst, (n, s, o), x.device())
}

/// Per item of tokens h (N, S, K): channels-first (N, O, S) = W·hᵢᵀ + b + residual (N, O, S).
pub fn linear_to_channels_first(h: &Tensor, w: &Tensor, b: &Tensor, residual: &Tensor) -> Result<Tensor> {
    let (n, s, k) = h.dims3()?;
    let (o, wk) = w.dims2()?;
    if wk != k || residual.elem_count() != n * o * s {
        candle_core::bail!("linear: tokens {:?}, weight {:?}, residual {:?}", h.dims(), w.dims(), residual.dims());
    }
    if !is_cpu_f32(h) {
        let y = h.reshape((n * s, k))?.matmul(&w.t()?)?.broadcast_add(b)?.reshape((n, s, o))?.transpose(1, 2)?;
        return y + residual.reshape((n, o, s))?;
    }
    let bv = b.to_vec1::<f32>()?;
    let mut dst = with_f32(residual, |r| r.to_vec())?;
    dst.par_chunks_mut(s).enumerate().for_each(|(row, d)| {
        let bb = bv[row % o];
        for v in d {
            *v += bb;
        }
    });
    let threads = rayon::current_num_threads();
    with_f32(h, |hd| {
        with_f32(w, |wd| {
            for (i, d) in dst.chunks_mut(o * s).enumerate() {
                // SAFETY: rhs (k × s) element (kk, j) = h[i, j, kk]; all indices inside item i.
                unsafe {
                    gemm::gemm(
                        o, s, k,
                        d.as_mut_ptr(), 1, s as isize, true,
                        wd.as_ptr(), 1, k as isize,
                        hd.as_ptr().add(i * s * k), k as isize, 1,
                        1.0, 1.0, false, false, false, gemm::Parallelism::Rayon(threads),
                    );
                }
            }
        })
    })??;
    Tensor::from_vec(dst, (n, o, s), h.device())
}

/// Conv3d with kernel (kt, 1, 1), zero padding (kt/2, 0, 0) on frame-major x (B·T, Cin, H, W), weight
/// (Cout, kt·Cin) (tap-major columns): each output frame is ONE gemm over its stacked valid neighbour frames,
/// which are contiguous in memory; the destination starts as `residual + scale·(bias + item_bias)`.
#[allow(clippy::too_many_arguments)]
pub fn temporal_conv(
    x: &Tensor,
    w: &Tensor,
    bias: &Tensor,
    kt: usize,
    frames: usize,
    item_bias: Option<&Tensor>,
    residual: Option<&Tensor>,
    scale: f32,
) -> Result<Tensor> {
    let (n, c, h, wd) = x.dims4()?;
    let (co, ktc) = w.dims2()?;
    if ktc != kt * c || frames == 0 || n % frames != 0 {
        candle_core::bail!("temporal conv: input {:?} with {frames} frames, weight {:?}, kt {kt}", x.dims(), w.dims());
    }
    let s = h * wd;
    let pad = kt / 2;
    if !is_cpu_f32(x) {
        let xs = x.reshape((n, c, s))?;
        let mut outs = Vec::with_capacity(n);
        for item in 0..n {
            let t = item % frames;
            let (k0, k1) = (pad.saturating_sub(t), kt.min(frames + pad - t));
            let wk = w.reshape((co, kt, c))?.narrow(1, k0, k1 - k0)?.reshape((co, (k1 - k0) * c))?;
            let src = xs.narrow(0, item + k0 - pad, k1 - k0)?.reshape(((k1 - k0) * c, s))?;
            outs.push(wk.matmul(&src)?.broadcast_add(&bias.reshape((co, 1))?)?);
        }
        let mut y = Tensor::stack(&outs, 0)?.reshape((n, co, h, wd))?;
        if let Some(ib) = item_bias {
            y = y.broadcast_add(&ib.reshape((n, co, 1, 1))?)?;
        }
        y = (y * scale as f64)?;
        if let Some(r) = residual {
            y = (y + r)?;
        }
        return Ok(y);
    }
    let bv = bias.to_vec1::<f32>()?;
    let ib = match item_bias {
        Some(t) => Some(t.flatten_all()?.to_vec1::<f32>()?),
        None => None,
    };
    let mut dst = match residual {
        Some(r) => with_f32(r, |d| d.to_vec())?,
        None => vec![0f32; n * co * s],
    };
    if dst.len() != n * co * s {
        candle_core::bail!("temporal conv: residual has {} elements, output {}", dst.len(), n * co * s);
    }
    dst.par_chunks_mut(s).enumerate().for_each(|(row, d)| {
        let (item, o) = (row / co, row % co);
        let add = scale * (bv[o] + ib.as_ref().map_or(0.0, |v| v[item * co + o]));
        for v in d {
            *v += add;
        }
    });
    let threads = rayon::current_num_threads();
    let small = s * co < 1 << 16;
    with_f32(x, |xd| {
        with_f32(w, |wd| {
            let run = |item: usize, d: &mut [f32], par: gemm::Parallelism| {
                let t = item % frames;
                let (k0, k1) = (pad.saturating_sub(t), kt.min(frames + pad - t));
                let first = item + k0 - pad;
                // SAFETY: lhs = columns k0·c..k1·c of w (row stride kt·c); rhs = frames first..first+k1−k0,
                // contiguous ((k1−k0)·c × s); dst = this item's (co × s) output.
                unsafe {
                    gemm::gemm(
                        co, s, (k1 - k0) * c,
                        d.as_mut_ptr(), 1, s as isize, true,
                        wd.as_ptr().add(k0 * c), 1, (kt * c) as isize,
                        xd.as_ptr().add(first * c * s), 1, s as isize,
                        1.0, scale, false, false, false, par,
                    );
                }
            };
            if small {
                dst.par_chunks_mut(co * s).enumerate().for_each(|(i, d)| run(i, d, gemm::Parallelism::None));
            } else {
                dst.chunks_mut(co * s).enumerate().for_each(|(i, d)| run(i, d, gemm::Parallelism::Rayon(threads)));
            }
        })
    })??;
    Tensor::from_vec(dst, (n, co, h, wd), x.device())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

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
        // erf against its Taylor series near 0 and its known values.
        assert!((erf_f32(0.5) - 0.520_499_9).abs() < 2e-7);
        assert!((erf_f32(-1.0) + 0.842_700_8).abs() < 2e-7);
        assert!((erf_f32(2.0) - 0.995_322_3).abs() < 2e-7);
        assert!(erf_f32(0.0).abs() < 2e-7);
        let x = Tensor::arange(-600i64, 600, &Device::Cpu).unwrap().to_dtype(DType::F32).unwrap().affine(0.01, 0.0).unwrap();
        let d = (gelu(&x).unwrap() - x.gelu_erf().unwrap()).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-6, "gelu vs candle gelu_erf: {d}");
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
    fn fused_linear_and_geglu_match_composed_ops() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 37, 24), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.2, (10, 24), &dev).unwrap();
        let b = Tensor::randn(0f32, 0.2, 10, &dev).unwrap();
        let r = Tensor::randn(0f32, 1.0, (2, 37, 10), &dev).unwrap();
        let got = linear_fused(&x, &w, Some(&b), 0.3, &[(&r, 0.7)]).unwrap();
        let lin = x.reshape((74, 24)).unwrap().matmul(&w.t().unwrap()).unwrap().broadcast_add(&b).unwrap().reshape((2, 37, 10)).unwrap();
        let want = ((lin * 0.3).unwrap() + (&r * 0.7).unwrap()).unwrap();
        let diff = (got - want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(diff < 1e-5, "linear: {diff}");
        let w1 = Tensor::randn(0f32, 0.2, (32, 24), &dev).unwrap();
        let b1 = Tensor::randn(0f32, 0.2, 32, &dev).unwrap();
        let w2 = Tensor::randn(0f32, 0.2, (24, 16), &dev).unwrap();
        let b2 = Tensor::randn(0f32, 0.2, 24, &dev).unwrap();
        let got = geglu_ff(&x, &w1, &b1, &w2, &b2, 1.0, &[(&x, 1.0)]).unwrap();
        let h = x.reshape((74, 24)).unwrap().matmul(&w1.t().unwrap()).unwrap().broadcast_add(&b1).unwrap();
        let g = (h.narrow(1, 0, 16).unwrap() * h.narrow(1, 16, 16).unwrap().gelu_erf().unwrap()).unwrap();
        let want = (g.matmul(&w2.t().unwrap()).unwrap().broadcast_add(&b2).unwrap().reshape((2, 37, 24)).unwrap() + &x).unwrap();
        let diff = (got - want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(diff < 1e-5, "geglu: {diff}");
    }

    #[test]
    fn channels_first_linears_match_permuted_matmuls() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (3, 6, 35), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.3, (10, 6), &dev).unwrap();
        let b = Tensor::randn(0f32, 0.3, 10, &dev).unwrap();
        let tok = linear_from_channels_first(&x, &w, &b).unwrap();
        let want = x.transpose(1, 2).unwrap().contiguous().unwrap().reshape((105, 6)).unwrap().matmul(&w.t().unwrap()).unwrap().broadcast_add(&b).unwrap().reshape((3, 35, 10)).unwrap();
        let d = (&tok - &want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-5, "to tokens: {d}");
        let w2 = Tensor::randn(0f32, 0.3, (6, 10), &dev).unwrap();
        let b2 = Tensor::randn(0f32, 0.3, 6, &dev).unwrap();
        let back = linear_to_channels_first(&tok, &w2, &b2, &x).unwrap();
        let want = (tok.reshape((105, 10)).unwrap().matmul(&w2.t().unwrap()).unwrap().broadcast_add(&b2).unwrap().reshape((3, 35, 6)).unwrap().transpose(1, 2).unwrap() + &x).unwrap();
        let d = (back - want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-5, "to channels-first: {d}");
    }
}
