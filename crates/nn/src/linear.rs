//! Linear layers with their bias, residual and blend folded into the gemm's destination, the GEGLU
//! feed-forward in row chunks, and projections that read a channels-first layout through gemm strides.
//! CPU f32 outside differentiable mode; composed matmuls otherwise.

use candle_core::{CpuStorage, Result, Storage, Tensor};
use rayon::prelude::*;

use crate::math::{gelu_f32, simd_dispatch, LANES};
use crate::mode::{is_cpu_f32, with_f32};

/// dst (rows × o) = beta·(x (rows × k) @ wᵀ (w: o × k)) [+ dst when `accumulate`].
pub(crate) fn gemm_xwt(x: &[f32], rows: usize, k: usize, w: &[f32], o: usize, dst: &mut [f32], accumulate: bool, beta: f32) {
    debug_assert!(x.len() >= rows * k && w.len() >= o * k && dst.len() >= rows * o);
    if rows == 0 || o == 0 {
        return;
    }
    let threads = rayon::current_num_threads();
    let par = if threads > 1 && rows * o * k > 1 << 16 { gemm::Parallelism::Rayon(threads) } else { gemm::Parallelism::None };
    // SAFETY: the asserted lengths cover every index gemm touches.
    unsafe {
        gemm::gemm(
            rows,
            o,
            k,
            dst.as_mut_ptr(),
            1,
            o as isize,
            accumulate,
            x.as_ptr(),
            1,
            k as isize,
            w.as_ptr(),
            k as isize,
            1,
            1.0,
            beta,
            false,
            false,
            false,
            par,
        );
    }
}

/// `scale·(x @ wᵀ + bias) + Σ cᵢ·addᵢ` over the last dim of x, in one gemm whose destination starts as
/// the bias/addend sum (no separate bias, residual or blend passes). Adds have the output's shape.
pub fn linear_fused(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
    linear_fused_impl(x, w, bias, scale, adds, false)
}

fn linear_fused_impl(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, scale: f32, adds: &[(&Tensor, f32)], few_rows: bool) -> Result<Tensor> {
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
        return linear_fused_composed(x, w, bias, scale, adds);
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
    let product = if few_rows { xwt_few_rows } else { gemm_xwt };
    with_f32(x, |xd| with_f32(w, |wd| product(xd, rows, k, wd, o, &mut dst, accumulate, scale)))??;
    Tensor::from_vec(dst, od, x.device())
}

/// Inputs of at most this many rows take [`xwt_few_rows`] in [`linear_fused_few_rows`].
pub const FEW_ROWS: usize = 8;

/// [`linear_fused`] for inputs of at most [`FEW_ROWS`] rows (VGGT's camera head: 5 tokens through weights of
/// 2048 × 8192): each weight row is streamed from memory once and dotted with every input row, where the gemm
/// would first pack the whole weight (per call: the head's 4 × 4 blocks read 3.4 GB of weights). More rows, or
/// another device or dtype: `linear_fused`. The sums run in another order than the gemm's (16 lanes, then
/// across), so the results differ from `linear_fused` by rounding; callers opt in.
pub fn linear_fused_few_rows(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
    let k = *x.dims().last().unwrap_or(&1);
    let few = x.elem_count() / k.max(1) <= FEW_ROWS;
    linear_fused_impl(x, w, bias, scale, adds, few)
}

/// As `gemm_xwt` for few rows: output columns in parallel chunks, each weight row read once.
fn xwt_few_rows(x: &[f32], rows: usize, k: usize, w: &[f32], o: usize, dst: &mut [f32], accumulate: bool, beta: f32) {
    const CH: usize = 32;
    if rows == 0 || o == 0 {
        return;
    }
    let mut t = vec![0f32; o * rows];
    t.par_chunks_mut(CH * rows).enumerate().for_each(|(ci, tc)| {
        let j0 = ci * CH;
        let jn = tc.len() / rows;
        few_rows_dots(&x[..rows * k], rows, k, &w[j0 * k..(j0 + jn) * k], tc);
    });
    for r in 0..rows {
        let d = &mut dst[r * o..(r + 1) * o];
        for (j, v) in d.iter_mut().enumerate() {
            let p = beta * t[j * rows + r];
            *v = if accumulate { *v + p } else { p };
        }
    }
}

simd_dispatch! {
    /// `out[j·rows + r] = x_r · w_j` for the weight rows of `w` (each `k` long).
    fn few_rows_dots(x: &[f32], rows: usize, k: usize, w: &[f32], out: &mut [f32]) {
        for (j, wr) in w.chunks_exact(k).enumerate() {
            for r in 0..rows {
                let xr = &x[r * k..(r + 1) * k];
                let mut acc = [0f32; LANES];
                let (mut xa, mut wa) = (xr.chunks_exact(LANES), wr.chunks_exact(LANES));
                for (a, b) in (&mut xa).zip(&mut wa) {
                    for i in 0..LANES {
                        acc[i] = a[i].mul_add(b[i], acc[i]);
                    }
                }
                let mut s = 0f32;
                for (a, b) in xa.remainder().iter().zip(wa.remainder()) {
                    s = a.mul_add(*b, s);
                }
                out[j * rows + r] = s + acc.iter().sum::<f32>();
            }
        }
    }
}

/// `GELU(x @ wᵀ + bias)` (erf GELU, as `nn.GELU()`): on CPU f32 the activation runs in place on the gemm's output
/// (no second buffer); elsewhere candle's ops.
pub fn linear_gelu(x: &Tensor, w: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let k = *dims.last().unwrap_or(&1);
    let (o, wk) = w.dims2()?;
    if wk != k {
        candle_core::bail!("linear: input width {k}, weight {:?}", w.dims());
    }
    if !is_cpu_f32(x) {
        return linear_fused_composed(x, w, bias, 1.0, &[])?.gelu_erf();
    }
    let rows = x.elem_count() / k.max(1);
    let mut od = dims;
    if let Some(l) = od.last_mut() {
        *l = o;
    }
    let mut dst = vec![0f32; rows * o];
    let bias_v = match bias {
        Some(b) => Some(b.to_vec1::<f32>()?),
        None => None,
    };
    if bias_v.is_some() {
        init_rows(&mut dst, o, bias_v.as_deref(), 1.0, &[])?;
    }
    with_f32(x, |xd| with_f32(w, |wd| gemm_xwt(xd, rows, k, wd, o, &mut dst, bias_v.is_some(), 1.0)))??;
    dst.par_chunks_mut(1 << 14).for_each(crate::activation::gelu_inplace);
    Tensor::from_vec(dst, od, x.device())
}

/// [`linear_fused`] from tensor ops (differentiable, any device).
pub(crate) fn linear_fused_composed(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
    let mut od = x.dims().to_vec();
    let k = *od.last().unwrap_or(&1);
    let rows = x.elem_count() / k.max(1);
    if let Some(l) = od.last_mut() {
        *l = w.dim(0)?;
    }
    let mut y = x.reshape((rows, k))?.matmul(&w.t()?)?;
    if let Some(b) = bias {
        y = y.broadcast_add(b)?;
    }
    let mut y = (y.reshape(od)? * scale as f64)?;
    for (a, c) in adds {
        y = (y + (*a * *c as f64)?)?;
    }
    Ok(y)
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

simd_dispatch! {
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

simd_dispatch! {
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
        return geglu_ff_composed(x, w1, b1, w2, b2, scale, adds);
    }
    let b1v = b1.to_vec1::<f32>()?;
    let b2v = b2.to_vec1::<f32>()?;
    let mut dst = vec![0f32; rows * o];
    init_rows(&mut dst, o, Some(&b2v), scale, adds)?;
    with_f32(x, |xd| {
        with_f32(w1, |w1d| {
            with_f32(w2, |w2d| {
                geglu_chunked(
                    xd,
                    (rows, c, inner, o),
                    &b1v,
                    1.0,
                    &mut dst,
                    |x, m, h| gemm_xwt(x, m, c, w1d, hidden2, h, false, 1.0),
                    |g, m, d| gemm_xwt(g, m, inner, w2d, o, d, true, scale),
                )
            })
        })
    })???;
    Tensor::from_vec(dst, od, x.device())
}

/// The GEGLU feed-forward's body in row chunks, so the 2·inner-wide hidden activation stays ≈ 64 MiB:
/// `first(x rows, m, h)` writes the first projection, the gate (bias, GELU, product, times `gate_scale`
/// unless 1) makes g, `second(g, m, dst rows)` accumulates the output projection.
#[allow(clippy::too_many_arguments)]
fn geglu_chunked(
    xd: &[f32],
    (rows, c, inner, o): (usize, usize, usize, usize),
    b1v: &[f32],
    gate_scale: f32,
    dst: &mut [f32],
    mut first: impl FnMut(&[f32], usize, &mut [f32]),
    mut second: impl FnMut(&[f32], usize, &mut [f32]),
) {
    let hidden2 = 2 * inner;
    let chunk = ((16usize << 20) / hidden2.max(1)).max(64).min(rows.max(1));
    let mut hbuf = vec![0f32; chunk * hidden2];
    let mut gbuf = vec![0f32; chunk * inner];
    let mut r0 = 0;
    while r0 < rows {
        let m = chunk.min(rows - r0);
        first(&xd[r0 * c..(r0 + m) * c], m, &mut hbuf[..m * hidden2]);
        let per = (m / rayon::current_num_threads().max(1) / 4).max(1);
        hbuf[..m * hidden2].par_chunks(per * hidden2).zip(gbuf[..m * inner].par_chunks_mut(per * inner)).for_each(|(h, g)| {
            geglu_rows(h, b1v, g, inner);
            if gate_scale != 1.0 {
                g.iter_mut().for_each(|v| *v *= gate_scale);
            }
        });
        second(&gbuf[..m * inner], m, &mut dst[r0 * o..(r0 + m) * o]);
        r0 += m;
    }
}

/// [`geglu_ff`] from tensor ops (differentiable, any device).
#[allow(clippy::too_many_arguments)]
pub(crate) fn geglu_ff_composed(x: &Tensor, w1: &Tensor, b1: &Tensor, w2: &Tensor, b2: &Tensor, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
    let mut od = x.dims().to_vec();
    let c = *od.last().unwrap_or(&1);
    let rows = x.elem_count() / c.max(1);
    let inner = w1.dim(0)? / 2;
    if let Some(l) = od.last_mut() {
        *l = w2.dim(0)?;
    }
    let h = x.reshape((rows, c))?.matmul(&w1.t()?)?;
    let gated = match geglu_gate_fused(&h, b1)? {
        Some(g) => g,
        None => {
            let h = h.broadcast_add(b1)?;
            let a = h.narrow(1, 0, inner)?;
            let g = h.narrow(1, inner, inner)?.gelu_erf()?;
            (a * g)?
        }
    };
    let y = gated.matmul(&w2.t()?)?.broadcast_add(b2)?.reshape(od)?;
    let mut y = (y * scale as f64)?;
    for (a, cf) in adds {
        y = (y + (*a * *cf as f64)?)?;
    }
    Ok(y)
}

/// `(h₁ + b₁)·gelu_erf(h₂ + b₂)` of the first projection h (rows, 2·inner) in one kernel (bias add, split,
/// GELU and product fused) where [`crate::fused_cuda`] applies; `None` otherwise.
fn geglu_gate_fused(h: &Tensor, b1: &Tensor) -> Result<Option<Tensor>> {
    #[cfg(feature = "cuda")]
    if crate::fused_cuda::applies(h, &[b1]) {
        return crate::fused_cuda::geglu(h, b1);
    }
    let _ = (h, b1);
    Ok(None)
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
        return linear_from_channels_first_composed(x, w, b);
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
                        s,
                        o,
                        c,
                        d.as_mut_ptr(),
                        1,
                        o as isize,
                        true,
                        xd.as_ptr().add(i * c * s),
                        s as isize,
                        1,
                        wd.as_ptr(),
                        c as isize,
                        1,
                        1.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::Rayon(threads),
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
        return linear_to_channels_first_composed(h, w, b, residual);
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
                        o,
                        s,
                        k,
                        d.as_mut_ptr(),
                        1,
                        s as isize,
                        true,
                        wd.as_ptr(),
                        1,
                        k as isize,
                        hd.as_ptr().add(i * s * k),
                        k as isize,
                        1,
                        1.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::Rayon(threads),
                    );
                }
            }
        })
    })??;
    Tensor::from_vec(dst, (n, o, s), h.device())
}

/// [`linear_from_channels_first`] from tensor ops (differentiable, any device).
pub(crate) fn linear_from_channels_first_composed(x: &Tensor, w: &Tensor, b: &Tensor) -> Result<Tensor> {
    let (n, c, s) = x.dims3()?;
    let o = w.dim(0)?;
    x.transpose(1, 2)?.contiguous()?.reshape((n * s, c))?.matmul(&w.t()?)?.broadcast_add(b)?.reshape((n, s, o))
}

/// [`linear_to_channels_first`] from tensor ops (differentiable, any device).
pub(crate) fn linear_to_channels_first_composed(h: &Tensor, w: &Tensor, b: &Tensor, residual: &Tensor) -> Result<Tensor> {
    let (n, s, k) = h.dims3()?;
    let o = w.dim(0)?;
    let y = h.reshape((n * s, k))?.matmul(&w.t()?)?.broadcast_add(b)?.reshape((n, s, o))?.transpose(1, 2)?;
    y + residual.reshape((n, o, s))?
}

/// [`linear_fused`] with bf16 weights (issue 73, inference only, opt-in): `scale·(x @ wᵀ + bias) + Σ cᵢ·addᵢ`,
/// the product by [`crate::bf16::matmul_bf16`] — `vdpbf16ps` where the CPU has AVX512-BF16 (activations rounded
/// to bf16 while packed, f32 accumulation), otherwise storage only (the bf16 weights widened, f32 arithmetic).
/// x, bias and adds are CPU f32; `w` is [`Bf16Weights::from_linear`]. The f32 [`linear_fused`] is untouched.
pub fn linear_fused_bf16(x: &Tensor, w: &crate::bf16::Bf16Weights, bias: Option<&Tensor>, scale: f32, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let k = *dims.last().unwrap_or(&1);
    let o = w.n();
    if w.k() != k {
        candle_core::bail!("linear (bf16): input width {k}, weight {o}×{}", w.k());
    }
    if !crate::mode::cpu_f32(x) {
        candle_core::bail!("linear (bf16): the input must be a CPU f32 tensor (got {:?} on {:?})", x.dtype(), x.device());
    }
    let rows = x.elem_count() / k.max(1);
    let mut od = dims;
    if let Some(l) = od.last_mut() {
        *l = o;
    }
    for (a, _) in adds {
        if a.elem_count() != rows * o {
            candle_core::bail!("linear (bf16): addend {:?} does not match output {od:?}", a.dims());
        }
    }
    let bias_v = match bias {
        Some(b) => Some(b.to_vec1::<f32>()?),
        None => None,
    };
    let mut dst = vec![0f32; rows * o];
    let accumulate = bias_v.is_some() || !adds.is_empty();
    if accumulate {
        init_rows(&mut dst, o, bias_v.as_deref(), scale, adds)?;
    }
    if scale == 1.0 {
        with_f32(x, |xd| crate::bf16::matmul_bf16(xd, rows, k, w, &mut dst, accumulate))?;
    } else {
        let mut prod = vec![0f32; rows * o];
        with_f32(x, |xd| crate::bf16::matmul_bf16(xd, rows, k, w, &mut prod, false))?;
        dst.par_chunks_mut(1 << 14).zip(prod.par_chunks(1 << 14)).for_each(|(d, p)| {
            for (d, p) in d.iter_mut().zip(p) {
                *d += scale * p;
            }
        });
    }
    Tensor::from_vec(dst, od, x.device())
}

/// A bf16 weight widened to an f32 `(out, in)` tensor: the storage-only path's operand, made once per call.
fn widened(w: &crate::bf16::Bf16Weights) -> Result<Tensor> {
    let (k, n) = (w.k(), w.n());
    let kn = w.to_f32_kn();
    let mut nk = vec![0f32; n * k];
    if k > 0 {
        nk.par_chunks_mut(k).enumerate().for_each(|(o, row)| {
            for (kk, v) in row.iter_mut().enumerate() {
                *v = kn[kk * n + o];
            }
        });
    }
    Tensor::from_vec(nk, (n, k), &candle_core::Device::Cpu)
}

fn bf16_products() -> bool {
    crate::bf16::path() == crate::bf16::Bf16Path::Dpbf16
}

/// [`geglu_ff`] with bf16 weights (`--dtype bf16` on the CPU, inference only): both products by
/// [`crate::bf16::matmul_bf16`], the bias, GELU gate, scale and addends in f32; without AVX512-BF16 the weights
/// are widened once and [`geglu_ff`] runs (storage only). `scale` multiplies the gated activations before they
/// are rounded, which leaves the error model's relative bound as it is.
#[allow(clippy::too_many_arguments)]
pub fn geglu_ff_bf16(
    x: &Tensor,
    w1: &crate::bf16::Bf16Weights,
    b1: &Tensor,
    w2: &crate::bf16::Bf16Weights,
    b2: &Tensor,
    scale: f32,
    adds: &[(&Tensor, f32)],
) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let c = *dims.last().unwrap_or(&1);
    let (hidden2, inner, o) = (w1.n(), w1.n() / 2, w2.n());
    if w1.k() != c || w2.k() != inner || hidden2 % 2 != 0 {
        candle_core::bail!("feed-forward (bf16): input width {c}, weights {}x{} and {}x{}", w1.n(), w1.k(), w2.n(), w2.k());
    }
    if !crate::mode::cpu_f32(x) {
        candle_core::bail!("feed-forward (bf16): the input must be a CPU f32 tensor (got {:?} on {:?})", x.dtype(), x.device());
    }
    if !bf16_products() {
        return geglu_ff(x, &widened(w1)?, b1, &widened(w2)?, b2, scale, adds);
    }
    let rows = x.elem_count() / c.max(1);
    let mut od = dims;
    if let Some(l) = od.last_mut() {
        *l = o;
    }
    let b1v = b1.to_vec1::<f32>()?;
    let b2v = b2.to_vec1::<f32>()?;
    let mut dst = vec![0f32; rows * o];
    init_rows(&mut dst, o, Some(&b2v), scale, adds)?;
    with_f32(x, |xd| {
        geglu_chunked(
            xd,
            (rows, c, inner, o),
            &b1v,
            scale,
            &mut dst,
            |x, m, h| {
                crate::bf16::matmul_bf16(x, m, c, w1, h, false);
            },
            |g, m, d| {
                crate::bf16::matmul_bf16(g, m, inner, w2, d, true);
            },
        )
    })?;
    Tensor::from_vec(dst, od, x.device())
}

/// [`linear_from_channels_first`] with bf16 weights: each item's (C, S) block is transposed to token rows,
/// then multiplied by [`crate::bf16::matmul_bf16`] (storage only without AVX512-BF16, weights widened once).
pub fn linear_from_channels_first_bf16(x: &Tensor, w: &crate::bf16::Bf16Weights, b: &Tensor) -> Result<Tensor> {
    let (n, c, s) = x.dims3()?;
    let o = w.n();
    if w.k() != c {
        candle_core::bail!("linear (bf16): {c} channels, weight {o}x{}", w.k());
    }
    if !crate::mode::cpu_f32(x) {
        candle_core::bail!("linear (bf16): the input must be a CPU f32 tensor (got {:?} on {:?})", x.dtype(), x.device());
    }
    if !bf16_products() {
        return linear_from_channels_first(x, &widened(w)?, b);
    }
    let bv = b.to_vec1::<f32>()?;
    let mut dst = vec![0f32; n * s * o];
    dst.par_chunks_mut(1 << 14).for_each(|d| init_chunk(d, 0, o, Some(&bv), 1.0, &[]));
    let mut tokens = vec![0f32; s * c];
    with_f32(x, |xd| {
        for (i, d) in dst.chunks_mut(s * o).enumerate() {
            let item = &xd[i * c * s..(i + 1) * c * s];
            tokens.par_chunks_mut(c).enumerate().for_each(|(j, row)| {
                for (ch, v) in row.iter_mut().enumerate() {
                    *v = item[ch * s + j];
                }
            });
            crate::bf16::matmul_bf16(&tokens, s, c, w, d, true);
        }
    })?;
    Tensor::from_vec(dst, (n, s, o), x.device())
}

/// [`linear_to_channels_first`] with bf16 weights: token rows multiplied by [`crate::bf16::matmul_bf16`], then
/// transposed into the channels-first output with bias and residual (storage only without AVX512-BF16).
pub fn linear_to_channels_first_bf16(h: &Tensor, w: &crate::bf16::Bf16Weights, b: &Tensor, residual: &Tensor) -> Result<Tensor> {
    let (n, s, k) = h.dims3()?;
    let o = w.n();
    if w.k() != k || residual.elem_count() != n * o * s {
        candle_core::bail!("linear (bf16): tokens {:?}, weight {o}x{}, residual {:?}", h.dims(), w.k(), residual.dims());
    }
    if !crate::mode::cpu_f32(h) {
        candle_core::bail!("linear (bf16): the input must be a CPU f32 tensor (got {:?} on {:?})", h.dtype(), h.device());
    }
    if !bf16_products() {
        return linear_to_channels_first(h, &widened(w)?, b, residual);
    }
    let bv = b.to_vec1::<f32>()?;
    let mut dst = with_f32(residual, |r| r.to_vec())?;
    let mut prod = vec![0f32; s * o];
    with_f32(h, |hd| {
        for (i, d) in dst.chunks_mut(o * s).enumerate() {
            crate::bf16::matmul_bf16(&hd[i * s * k..(i + 1) * s * k], s, k, w, &mut prod, false);
            d.par_chunks_mut(s).enumerate().for_each(|(oo, row)| {
                let bb = bv[oo];
                for (j, v) in row.iter_mut().enumerate() {
                    *v += prod[j * o + oo] + bb;
                }
            });
        }
    })?;
    Tensor::from_vec(dst, (n, o, s), h.device())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

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

    /// The few-rows product against an f64 reference: per output |err| ≤ (k + 3)·u·Σ|terms| (k products and
    /// sums in f32, the bias, addend and scale), several seeds, row counts and widths (k not a multiple of 16);
    /// a 1 % change fails it; more rows than FEW_ROWS take the gemm.
    #[test]
    fn few_rows_linear_matches_f64() {
        let dev = Device::Cpu;
        let u = f32::EPSILON as f64 / 2.0;
        for (seed, (rows, k, o)) in [(1, 19, 40), (5, 64, 33), (8, 300, 70), (3, 1, 5)].into_iter().enumerate() {
            let mut st = seed as u64 * 7919 + 1;
            let mut rnd = |n: usize| -> Vec<f32> {
                (0..n)
                    .map(|_| {
                        st = st.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                        (st >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
                    })
                    .collect()
            };
            let (xv, wv, bv, rv) = (rnd(rows * k), rnd(o * k), rnd(o), rnd(rows * o));
            let x = Tensor::from_vec(xv.clone(), (1, rows, k), &dev).unwrap();
            let w = Tensor::from_vec(wv.clone(), (o, k), &dev).unwrap();
            let b = Tensor::from_vec(bv.clone(), o, &dev).unwrap();
            let r = Tensor::from_vec(rv.clone(), (1, rows, o), &dev).unwrap();
            let got = linear_fused_few_rows(&x, &w, Some(&b), 0.5, &[(&r, 1.0)]).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let mut moved = 0;
            for i in 0..rows {
                for j in 0..o {
                    let terms: Vec<f64> = (0..k).map(|t| xv[i * k + t] as f64 * wv[j * k + t] as f64).collect();
                    let want = 0.5 * (terms.iter().sum::<f64>() + bv[j] as f64) + rv[i * o + j] as f64;
                    let mag = 0.5 * (terms.iter().map(|t| t.abs()).sum::<f64>() + (bv[j] as f64).abs()) + (rv[i * o + j] as f64).abs();
                    let bound = (k as f64 + 3.0) * u * mag;
                    let g = got[i * o + j] as f64;
                    assert!((g - want).abs() <= bound, "rows {rows} k {k}: ({i}, {j}) {g} vs {want}, bound {bound}");
                    moved += usize::from((g * 1.01 - want).abs() > bound);
                }
            }
            assert!(moved * 10 > rows * o * 9, "rows {rows} k {k}: the bound cannot see a 1 % error");
        }
        // Empty shapes: no rows, no outputs.
        assert_eq!(
            linear_fused_few_rows(
                &Tensor::zeros((0, 4), candle_core::DType::F32, &dev).unwrap(),
                &Tensor::zeros((3, 4), candle_core::DType::F32, &dev).unwrap(),
                None,
                1.0,
                &[]
            )
            .unwrap()
            .dims(),
            &[0, 3]
        );
        assert_eq!(
            linear_fused_few_rows(
                &Tensor::zeros((2, 4), candle_core::DType::F32, &dev).unwrap(),
                &Tensor::zeros((0, 4), candle_core::DType::F32, &dev).unwrap(),
                None,
                1.0,
                &[]
            )
            .unwrap()
            .dims(),
            &[2, 0]
        );
        // Past FEW_ROWS: the gemm path, same results as linear_fused.
        let x = Tensor::randn(0f32, 1.0, (FEW_ROWS + 1, 24), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.2, (10, 24), &dev).unwrap();
        let a = linear_fused_few_rows(&x, &w, None, 1.0, &[]).unwrap();
        let b = linear_fused(&x, &w, None, 1.0, &[]).unwrap();
        assert_eq!(a.to_vec2::<f32>().unwrap(), b.to_vec2::<f32>().unwrap());
    }

    #[test]
    fn channels_first_linears_match_permuted_matmuls() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (3, 6, 35), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.3, (10, 6), &dev).unwrap();
        let b = Tensor::randn(0f32, 0.3, 10, &dev).unwrap();
        let tok = linear_from_channels_first(&x, &w, &b).unwrap();
        let want = x
            .transpose(1, 2)
            .unwrap()
            .contiguous()
            .unwrap()
            .reshape((105, 6))
            .unwrap()
            .matmul(&w.t().unwrap())
            .unwrap()
            .broadcast_add(&b)
            .unwrap()
            .reshape((3, 35, 10))
            .unwrap();
        let d = (&tok - &want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-5, "to tokens: {d}");
        let w2 = Tensor::randn(0f32, 0.3, (6, 10), &dev).unwrap();
        let b2 = Tensor::randn(0f32, 0.3, 6, &dev).unwrap();
        let back = linear_to_channels_first(&tok, &w2, &b2, &x).unwrap();
        let want = (tok
            .reshape((105, 10))
            .unwrap()
            .matmul(&w2.t().unwrap())
            .unwrap()
            .broadcast_add(&b2)
            .unwrap()
            .reshape((3, 35, 6))
            .unwrap()
            .transpose(1, 2)
            .unwrap()
            + &x)
            .unwrap();
        let d = (back - want).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-5, "to channels-first: {d}");
    }

    /// `linear_fused_bf16`: bias, scale and addends as `linear_fused`, the product within the error model (the
    /// f32 bias/addend sum adds its own f32 rounding); masked, the storage-only path.
    #[test]
    fn channels_first_bf16_projections_hold_the_error_model() {
        let fill = crate::bf16::bench::fill;
        let dev = Device::Cpu;
        for (seed, n, c, s, o) in [(1u64, 2usize, 33usize, 45usize, 37usize), (2, 1, 64, 130, 20), (3, 3, 7, 1, 9)] {
            let x = Tensor::from_vec(fill(n * c * s, seed), (n, c, s), &dev).unwrap();
            let w = Tensor::from_vec(fill(o * c, seed + 10), (o, c), &dev).unwrap();
            let b = Tensor::from_vec(fill(o, seed + 20), o, &dev).unwrap();
            let wb = crate::bf16::Bf16Weights::from_linear(&w).unwrap();
            let (xv, wv, bv) =
                (x.flatten_all().unwrap().to_vec1::<f32>().unwrap(), w.flatten_all().unwrap().to_vec1::<f32>().unwrap(), b.to_vec1::<f32>().unwrap());
            // from channels-first: out[i, j, oo] = Σ_ch x[i, ch, j]·w[oo, ch] + b[oo].
            for masked in [false, true] {
                let run = || linear_from_channels_first_bf16(&x, &wb, &b).unwrap();
                let got = if masked { crate::bf16::with_bf16_masked(run) } else { run() }.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let mut worst = 0f64;
                for i in 0..n {
                    for j in 0..s {
                        for oo in 0..o {
                            let terms = (0..c).map(|ch| xv[(i * c + ch) * s + j] as f64 * wv[oo * c + ch] as f64);
                            let (exact, sa) = terms.fold((bv[oo] as f64, 0.0), |(e, a), t| (e + t, a + t.abs()));
                            let bound = crate::bf16::error_bound(c, sa) + 4.0 * 2f64.powi(-24) * (exact.abs() + bv[oo].abs() as f64);
                            let d = (got[(i * s + j) * o + oo] as f64 - exact).abs();
                            assert!(d <= bound, "from channels-first, seed {seed}, masked {masked}: |diff| {d} > {bound}");
                            worst = worst.max(d / bound);
                        }
                    }
                }
                assert!(worst > 0.0, "bf16 result exact everywhere: the weights were not rounded");
            }
            // to channels-first: h (n, s, c) tokens → out[i, oo, j] = Σ_ch h[i, j, ch]·w[oo, ch] + b[oo] + r[i, oo, j].
            let h = Tensor::from_vec(fill(n * s * c, seed + 30), (n, s, c), &dev).unwrap();
            let r = Tensor::from_vec(fill(n * o * s, seed + 40), (n, o, s), &dev).unwrap();
            let (hv, rv) = (h.flatten_all().unwrap().to_vec1::<f32>().unwrap(), r.flatten_all().unwrap().to_vec1::<f32>().unwrap());
            for masked in [false, true] {
                let run = || linear_to_channels_first_bf16(&h, &wb, &b, &r).unwrap();
                let got = if masked { crate::bf16::with_bf16_masked(run) } else { run() }.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                for i in 0..n {
                    for oo in 0..o {
                        for j in 0..s {
                            let terms = (0..c).map(|ch| hv[(i * s + j) * c + ch] as f64 * wv[oo * c + ch] as f64);
                            let rest = bv[oo] as f64 + rv[(i * o + oo) * s + j] as f64;
                            let (exact, sa) = terms.fold((rest, 0.0), |(e, a), t| (e + t, a + t.abs()));
                            let bound = crate::bf16::error_bound(c, sa) + 4.0 * 2f64.powi(-24) * (exact.abs() + rest.abs() + sa);
                            let d = (got[(i * o + oo) * s + j] as f64 - exact).abs();
                            assert!(d <= bound, "to channels-first, seed {seed}, masked {masked}: |diff| {d} > {bound}");
                        }
                    }
                }
            }
        }
    }

    /// The bf16 GEGLU feed-forward against an f64 evaluation of the unrounded operands, within the first
    /// product's bound carried through the gate and the second product's own bound (first order):
    /// δg ≤ |gelu(v)|·B_a + |a|·G'·B_v (+ B_a·G'·B_v), G' = max|gelu'| < 1.13, then the output's error ≤
    /// scale·(Σ|w₂|·δg + bound₂(Σ|g·w₂|)).
    #[test]
    fn geglu_bf16_holds_the_propagated_error_model() {
        let fill = crate::bf16::bench::fill;
        let dev = Device::Cpu;
        let gelu = |v: f64| 0.5 * v * (1.0 + libm_erf(v / std::f64::consts::SQRT_2));
        // Mixed signs, and non-negative operands: without cancellation Σ|a·b| = |Σa·b|, so the bound is within a
        // few u of the result and a wrong scale or bias of a few per cent fails it.
        for (seed, rows, c, inner, o, scale, positive) in
            [(5u64, 37usize, 24usize, 40usize, 24usize, 1.0f32, false), (6, 70, 33, 17, 9, 0.75, false), (7, 20, 16, 12, 8, 0.75, true)]
        {
            let fill = |n: usize, sd: u64| -> Vec<f32> { fill(n, sd).into_iter().map(|v| if positive { v.abs() } else { v }).collect() };
            let x = Tensor::from_vec(fill(rows * c, seed), (rows, c), &dev).unwrap();
            let w1 = Tensor::from_vec(fill(2 * inner * c, seed + 1), (2 * inner, c), &dev).unwrap();
            let b1 = Tensor::from_vec(fill(2 * inner, seed + 2), 2 * inner, &dev).unwrap();
            let w2 = Tensor::from_vec(fill(o * inner, seed + 3), (o, inner), &dev).unwrap();
            let b2 = Tensor::from_vec(fill(o, seed + 4), o, &dev).unwrap();
            let add = Tensor::from_vec(fill(rows * o, seed + 5), (rows, o), &dev).unwrap();
            let (p1, p2) = (crate::bf16::Bf16Weights::from_linear(&w1).unwrap(), crate::bf16::Bf16Weights::from_linear(&w2).unwrap());
            let v = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let (xv, w1v, b1v, w2v, b2v, av) = (v(&x), v(&w1), v(&b1), v(&w2), v(&b2), v(&add));
            for masked in [false, true] {
                let run = || geglu_ff_bf16(&x, &p1, &b1, &p2, &b2, scale, &[(&add, 0.5)]).unwrap();
                let got = v(&if masked { crate::bf16::with_bf16_masked(run) } else { run() });
                for r in 0..rows {
                    let mut g = vec![0f64; inner];
                    let mut dg = vec![0f64; inner];
                    for j in 0..inner {
                        let dot = |row: usize| -> (f64, f64) {
                            (0..c).fold((b1v[row] as f64, 0.0), |(e, a), p| {
                                let t = xv[r * c + p] as f64 * w1v[row * c + p] as f64;
                                (e + t, a + t.abs())
                            })
                        };
                        let ((a, sa), (gv, sg)) = (dot(j), dot(inner + j));
                        let (ba, bg) = (crate::bf16::error_bound(c, sa), crate::bf16::error_bound(c, sg));
                        g[j] = a * gelu(gv);
                        dg[j] = gelu(gv).abs() * ba + (a.abs() + ba) * 1.13 * bg + 2f64.powi(-22) * g[j].abs();
                    }
                    for oo in 0..o {
                        let (mut exact, mut sa, mut prop) = (b2v[oo] as f64, 0.0, 0.0);
                        for j in 0..inner {
                            let wj = w2v[oo * inner + j] as f64;
                            exact += g[j] * wj;
                            sa += ((g[j].abs() + dg[j]) * wj).abs();
                            prop += wj.abs() * dg[j];
                        }
                        let want = scale as f64 * exact + 0.5 * av[r * o + oo] as f64;
                        let bound = scale as f64 * (prop + crate::bf16::error_bound(inner, sa)) + 8.0 * 2f64.powi(-24) * (want.abs() + sa + 1.0);
                        let d = (got[r * o + oo] as f64 - want).abs();
                        assert!(d <= bound, "seed {seed}, masked {masked}: [{r},{oo}] |diff| {d} > {bound}");
                    }
                }
            }
        }
    }

    /// erf to double precision (Abramowitz–Stegun 7.1.26 is too coarse here): its Taylor series for |x| < 3,
    /// the continued fraction of erfc beyond.
    fn libm_erf(x: f64) -> f64 {
        if x.abs() < 3.0 {
            let (mut term, mut sum, x2) = (x, x, x * x);
            for n in 1..200 {
                term *= -x2 / n as f64;
                let t = term / (2 * n + 1) as f64;
                sum += t;
                if t.abs() < 1e-17 * sum.abs() {
                    break;
                }
            }
            return 2.0 / std::f64::consts::PI.sqrt() * sum;
        }
        let a = x.abs();
        let mut f = 0.0;
        for n in (1..60).rev() {
            f = (n as f64 / 2.0) / (a + f);
        }
        let erfc = (-a * a).exp() / std::f64::consts::PI.sqrt() / (a + f);
        (1.0 - erfc).copysign(x)
    }

    #[test]
    fn linear_bf16_matches_linear_fused_within_the_model() {
        let (rows, k, o) = (37usize, 129usize, 45usize);
        let x = Tensor::from_vec(crate::bf16::bench::fill(rows * k, 21), (rows, k), &Device::Cpu).unwrap();
        let w = Tensor::from_vec(crate::bf16::bench::fill(o * k, 22), (o, k), &Device::Cpu).unwrap();
        let b = Tensor::from_vec(crate::bf16::bench::fill(o, 23), o, &Device::Cpu).unwrap();
        let add = Tensor::from_vec(crate::bf16::bench::fill(rows * o, 24), (rows, o), &Device::Cpu).unwrap();
        let wb = crate::bf16::Bf16Weights::from_linear(&w).unwrap();
        let want = linear_fused(&x, &w, Some(&b), 0.5, &[(&add, 2.0)]).unwrap().to_vec2::<f32>().unwrap();
        let xs = x.to_vec2::<f32>().unwrap();
        let ws = w.to_vec2::<f32>().unwrap();
        for masked in [false, true] {
            let got = if masked {
                crate::bf16::with_bf16_masked(|| linear_fused_bf16(&x, &wb, Some(&b), 0.5, &[(&add, 2.0)]))
            } else {
                linear_fused_bf16(&x, &wb, Some(&b), 0.5, &[(&add, 2.0)])
            }
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
            for i in 0..rows {
                for j in 0..o {
                    let sa: f64 = (0..k).map(|p| (xs[i][p] as f64 * ws[j][p] as f64).abs()).sum();
                    // 0.5·(product error) + both results' f32 roundings of the epilogue (a few ulps of 3 terms).
                    let bound =
                        0.5 * (crate::bf16::error_bound(k, sa) + k as f64 * 2f64.powi(-24) * sa) + 8.0 * 2f64.powi(-24) * (want[i][j].abs() as f64 + 4.0);
                    let d = (got[i][j] - want[i][j]).abs() as f64;
                    assert!(d <= bound, "masked {masked}: [{i},{j}] {} vs {} (|diff| {d} > {bound})", got[i][j], want[i][j]);
                }
            }
        }
        let bad = Tensor::zeros((3, 7), candle_core::DType::F32, &Device::Cpu).unwrap();
        assert!(linear_fused_bf16(&bad, &wb, None, 1.0, &[]).is_err(), "width mismatch refused");
    }
}
