//! Normalisations. LayerNorm / GroupNorm(+SiLU) for the refiner take f64 statistics on the CPU (candle's
//! fused op uses E[x²]−E[x]² in f32, which loses ~1e-4 on rows with a large mean); the encoder's GroupNorm
//! fuses its activation into one pass. Training on the CPU (tracked inputs, differentiable mode) runs GroupNorm
//! and InstanceNorm as one op with an analytic backward; LayerNorm and other devices use composed ops.

use candle_core::{DType, Result, Tensor, D};
use rayon::prelude::*;

use crate::math::{exp_f32, exp_fast, gelu_scalar, simd_dispatch};
use crate::mode::{cpu_f32, is_cpu_f32, with_f32};

/// LayerNorm over the last dim. CPU f32 path: per-row two-pass statistics in f64 (candle's fused op
/// uses E[x²]−E[x]² in f32, which loses ~1e-4 on rows with a large mean).
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let c = *dims.last().unwrap_or(&1);
    if fused_half(x) {
        let (w, b) = (weight.to_dtype(x.dtype())?, bias.to_dtype(x.dtype())?);
        return candle_nn::ops::layer_norm(&x.contiguous()?, &w, &b, eps as f32);
    }
    if is_cpu_f32(x) {
        let w = weight.to_vec1::<f32>()?;
        let b = bias.to_vec1::<f32>()?;
        let mut out = vec![0f32; x.elem_count()];
        with_f32(x, |data| {
            let rows = (1usize << 14) / c.max(1) + 1;
            out.par_chunks_mut(c * rows).zip(data.par_chunks(c * rows)).for_each(|(dst, src)| layer_norm_rows(src, dst, c, &w, &b, eps));
        })?;
        return Tensor::from_vec(out, dims, x.device());
    }
    layer_norm_composed(x, weight, bias, eps)
}

/// Half-precision inference, any device: candle's fused LayerNorm kernel (statistics as f32 sums, E[x²]−E[x]²,
/// an error far below half precision's rounding) replaces a dozen broadcast ops, each a pass over the tensor
/// (on an H200 the composed GroupNorms were a quarter of a paper-size refiner window). The kernel indexes
/// with i32.
fn fused_half(x: &Tensor) -> bool {
    matches!(x.dtype(), DType::BF16 | DType::F16) && !crate::mode::is_differentiable() && x.elem_count() < i32::MAX as usize
}

/// [`layer_norm`] from tensor ops (differentiable, any device).
pub(crate) fn layer_norm_composed(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    let mean = x.mean_keepdim(D::Minus1)?;
    let xc = x.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    xc.broadcast_div(&(var + eps)?.sqrt()?)?.broadcast_mul(weight)?.broadcast_add(bias)
}

/// GroupNorm on (N, C, ...) with statistics pooled over `frames` consecutive items (frames > 1: a GroupNorm
/// of the (B, C, T, H, W) tensor of a temporal ResBlock), optionally followed by SiLU. CPU f32 fast path (one stats pass, one write pass);
/// in differentiable mode on the CPU one op with an analytic backward; on CUDA with `MVSPLAT360_GPU_OPS=fused`
/// the kernels of cuda/fused.cu; composed ops on other devices.
pub fn group_norm(x: &Tensor, groups: usize, frames: usize, weight: &Tensor, bias: &Tensor, eps: f64, silu: bool) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    let s: usize = dims[2..].iter().product();
    if c % groups != 0 || n % frames != 0 {
        candle_core::bail!("group_norm: {c} channels / {groups} groups or {n} items / {frames} frames not divisible");
    }
    let cg = c / groups;
    let bn = n / frames;
    if is_cpu_f32(x) {
        let w = weight.to_vec1::<f32>()?;
        let b = bias.to_vec1::<f32>()?;
        let mut out = vec![0f32; x.elem_count()];
        with_f32(x, |data| group_norm_cpu(data, &mut out, (bn, frames, groups, cg, c, s), &w, &b, eps, silu))?;
        return Tensor::from_vec(out, dims, x.device());
    }
    if cpu_f32(x) && cpu_f32(weight) && cpu_f32(bias) {
        let y = group_norm_trainable(x, weight, bias, groups, frames, eps)?;
        return if silu { y.silu() } else { Ok(y) };
    }
    #[cfg(feature = "cuda")]
    if crate::fused_cuda::applies(x, &[weight, bias]) {
        if let Some(y) = crate::fused_cuda::group_norm(x, groups, frames, weight, bias, eps, silu)? {
            return Ok(y);
        }
    }
    if fused_half(x) {
        return group_norm_fused_half(x, groups, frames, weight, bias, eps, silu);
    }
    group_norm_composed(x, groups, frames, weight, bias, eps, silu)
}

/// `x (N, C, S)·weight[c] + bias[c]`, optionally followed by SiLU: the end of both non-kernel GroupNorm paths.
fn channel_affine(x: &Tensor, weight: &Tensor, bias: &Tensor, silu: bool) -> Result<Tensor> {
    let c = x.dim(1)?;
    let y = x.broadcast_mul(&weight.reshape((1, c, 1))?)?.broadcast_add(&bias.reshape((1, c, 1))?)?;
    if silu {
        y.silu()
    } else {
        Ok(y)
    }
}

/// [`group_norm`] in half precision: each (item, group) as one row of the fused LayerNorm (frames moved next to
/// each other first when pooled), then the per-channel affine and SiLU.
fn group_norm_fused_half(x: &Tensor, groups: usize, frames: usize, weight: &Tensor, bias: &Tensor, eps: f64, silu: bool) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    let s: usize = dims[2..].iter().product();
    let (cg, bn) = (c / groups, n / frames);
    let len = frames * cg * s;
    let rows = if frames == 1 {
        x.reshape((n * groups, len))?
    } else {
        x.reshape((bn, frames, groups, cg * s))?.transpose(1, 2)?.contiguous()?.reshape((bn * groups, len))?
    };
    let (ones, zeros) = (Tensor::ones(len, x.dtype(), x.device())?, Tensor::zeros(len, x.dtype(), x.device())?);
    let xn = candle_nn::ops::layer_norm(&rows.contiguous()?, &ones, &zeros, eps as f32)?;
    let xn = if frames == 1 { xn } else { xn.reshape((bn, groups, frames, cg * s))?.transpose(1, 2)?.contiguous()? };
    let y = channel_affine(&xn.reshape((n, c, s))?, &weight.to_dtype(x.dtype())?, &bias.to_dtype(x.dtype())?, silu)?;
    y.reshape(dims)
}

/// [`group_norm`] from tensor ops (differentiable, any device).
pub(crate) fn group_norm_composed(x: &Tensor, groups: usize, frames: usize, weight: &Tensor, bias: &Tensor, eps: f64, silu: bool) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    let s: usize = dims[2..].iter().product();
    let (cg, bn) = (c / groups, n / frames);
    let xr = x.reshape((bn, frames, groups, cg * s))?;
    let mean = xr.mean_keepdim(3)?.mean_keepdim(1)?;
    let xc = xr.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(3)?.mean_keepdim(1)?;
    let xn = xc.broadcast_div(&(var + eps)?.sqrt()?)?.reshape((n, c, s))?;
    let y = channel_affine(&xn, weight, bias, silu)?;
    y.reshape(dims)
}

/// CPU GroupNorm(+SiLU): statistics per (item, group, pooled over frames) in f64, then one fused
/// scale/shift(/SiLU) pass.
#[allow(clippy::too_many_arguments)]
fn group_norm_cpu(
    data: &[f32],
    out: &mut [f32],
    (bn, frames, groups, cg, c, s): (usize, usize, usize, usize, usize, usize),
    w: &[f32],
    b: &[f32],
    eps: f64,
    silu: bool,
) {
    let stats: Vec<(f32, f32)> = (0..bn * groups)
        .into_par_iter()
        .map(|idx| {
            let (bi, g) = (idx / groups, idx % groups);
            let mut sum = 0f64;
            let mut sq = 0f64;
            for t in 0..frames {
                let base = ((bi * frames + t) * c + g * cg) * s;
                let (s1, s2) = sum_sq(&data[base..base + cg * s]);
                sum += s1;
                sq += s2;
            }
            let cnt = (frames * cg * s) as f64;
            let mean = sum / cnt;
            let var = (sq / cnt - mean * mean).max(0.0);
            (mean as f32, (1.0 / (var + eps).sqrt()) as f32)
        })
        .collect();
    out.par_chunks_mut(s).enumerate().for_each(|(row, dst)| {
        let item = row / c;
        let ch = row % c;
        let bi = item / frames;
        let (mean, rstd) = stats[bi * groups + ch / cg];
        let a = rstd * w[ch];
        let o = b[ch] - mean * a;
        scale_shift_silu(&data[row * s..(row + 1) * s], dst, a, o, silu);
    });
}

simd_dispatch! {
    /// (Σx, Σx²) in f64, accumulated per block of 64 values in f32 lanes.
    fn sum_sq(x: &[f32]) -> (f64, f64) {
        let (mut s1, mut s2) = (0f64, 0f64);
        for blk in x.chunks(64) {
            let mut a = [0f32; 16];
            let mut q = [0f32; 16];
            let mut it = blk.chunks_exact(16);
            for c in &mut it {
                for i in 0..16 {
                    a[i] += c[i];
                    q[i] = c[i].mul_add(c[i], q[i]);
                }
            }
            for &v in it.remainder() {
                a[0] += v;
                q[0] = v.mul_add(v, q[0]);
            }
            s1 += a.iter().map(|&v| v as f64).sum::<f64>();
            s2 += q.iter().map(|&v| v as f64).sum::<f64>();
        }
        (s1, s2)
    }
}

simd_dispatch! {
    fn scale_shift_silu(src: &[f32], dst: &mut [f32], a: f32, o: f32, silu: bool) {
        if silu {
            for (d, &v) in dst.iter_mut().zip(src) {
                let y = v.mul_add(a, o);
                *d = y / (1.0 + exp_f32(-y));
            }
        } else {
            for (d, &v) in dst.iter_mut().zip(src) {
                *d = v.mul_add(a, o);
            }
        }
    }
}

simd_dispatch! {
    fn layer_norm_rows(src: &[f32], dst: &mut [f32], c: usize, w: &[f32], b: &[f32], eps: f64) {
        for (s, d) in src.chunks_exact(c).zip(dst.chunks_exact_mut(c)) {
            let mean = s.iter().map(|&v| v as f64).sum::<f64>() / c as f64;
            let var = s.iter().map(|&v| (v as f64 - mean) * (v as f64 - mean)).sum::<f64>() / c as f64;
            let rstd = (1.0 / (var + eps).sqrt()) as f32;
            let m = mean as f32;
            for i in 0..c {
                d[i] = ((s[i] - m) * rstd).mul_add(w[i], b[i]);
            }
        }
    }
}

/// Activation fused after [`group_norm_act`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Act {
    None,
    Silu,
    Gelu,
}

/// `d = act(a·s + b)`.
#[inline(always)]
fn affine_act_impl(d: &mut [f32], s: &[f32], a: f32, b: f32, act: Act) {
    match act {
        Act::None => d.iter_mut().zip(s).for_each(|(o, &v)| *o = a * v + b),
        Act::Silu => d.iter_mut().zip(s).for_each(|(o, &v)| {
            let y = a * v + b;
            *o = y / (1.0 + exp_fast(-y));
        }),
        Act::Gelu => d.iter_mut().zip(s).for_each(|(o, &v)| *o = gelu_scalar(a * v + b)),
    }
}

/// AVX2 build of [`affine_act_impl`] (no FMA: bit-identical to the portable path).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn affine_act_avx2(d: &mut [f32], s: &[f32], a: f32, b: f32, act: Act) {
    affine_act_impl(d, s, a, b, act)
}

fn affine_act(d: &mut [f32], s: &[f32], a: f32, b: f32, act: Act) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is available on this CPU.
        return unsafe { affine_act_avx2(d, s, a, b, act) };
    }
    affine_act_impl(d, s, a, b, act)
}

/// `act(GroupNorm(groups)(x))` on `[N, C, ...]` (the encoder's UNets; statistics as the official f32 ones, in
/// f64 here). Inference (CPU f32, nothing tracks gradients) runs one fused pass per (image, group); tracked CPU
/// inputs one op with an analytic backward, then the activation.
pub fn group_norm_act(x: &Tensor, weight: &Tensor, bias: &Tensor, groups: usize, eps: f64, act: Act) -> Result<Tensor> {
    let fused = cpu_f32(x) && weight.dtype() == DType::F32 && !(x.track_op() || weight.track_op() || bias.track_op());
    if !fused {
        if cpu_f32(x) && cpu_f32(weight) && cpu_f32(bias) {
            return apply_act(&group_norm_trainable(x, weight, bias, groups, 1, eps)?, act);
        }
        return group_norm_act_composed(x, weight, bias, groups, eps, act);
    }
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    let x = x.contiguous()?;
    let s = x.elem_count() / (n * c).max(1);
    let (wv, bv) = (weight.to_vec1::<f32>()?, bias.to_vec1::<f32>()?);
    let mut out = vec![0f32; x.elem_count()];
    with_f32(&x, |src| GroupNormOp { groups, frames: 1, eps }.normalize(src, &mut out, (n, c, s), &wv, &bv, act))?;
    Tensor::from_vec(out, dims, x.device())
}

/// [`group_norm_act`] from tensor ops in f32 (differentiable, any device).
pub(crate) fn group_norm_act_composed(x: &Tensor, weight: &Tensor, bias: &Tensor, groups: usize, eps: f64, act: Act) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    let in_dtype = x.dtype();
    let xg = x.to_dtype(DType::F32)?.reshape((n, groups, ()))?;
    let mean = xg.mean_keepdim(D::Minus1)?;
    let xc = xg.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    let xn = xc.broadcast_div(&(var + eps)?.sqrt()?)?.reshape(dims.as_slice())?;
    let mut pshape = vec![1usize; dims.len()];
    pshape[1] = c;
    let w = weight.to_dtype(DType::F32)?.reshape(pshape.as_slice())?;
    let b = bias.to_dtype(DType::F32)?.reshape(pshape.as_slice())?;
    let y = xn.broadcast_mul(&w)?.broadcast_add(&b)?.to_dtype(in_dtype)?;
    apply_act(&y, act)
}

fn apply_act(y: &Tensor, act: Act) -> Result<Tensor> {
    match act {
        Act::None => Ok(y.clone()),
        Act::Silu => y.silu(),
        Act::Gelu => crate::activation::gelu(y),
    }
}

/// GroupNorm (affine, no activation; statistics pooled over `frames` consecutive items) on CPU f32 as one op
/// with an analytic backward: the composed form records ~10 full-size ops whose backward (candle's broadcast
/// reductions run on one thread) took ≈ 10 % of an encoder training step. Statistics in f64 as the inference
/// kernel.
fn group_norm_trainable(x: &Tensor, weight: &Tensor, bias: &Tensor, groups: usize, frames: usize, eps: f64) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    if c % groups != 0 || n % frames != 0 || weight.elem_count() != c || bias.elem_count() != c {
        candle_core::bail!(
            "group_norm: {c} channels, {groups} groups, {n} items, {frames} frames, {} weights, {} biases",
            weight.elem_count(),
            bias.elem_count()
        );
    }
    let x3 = x.contiguous()?.reshape((n, c, ()))?;
    x3.apply_op3(&weight.contiguous()?.flatten_all()?, &bias.contiguous()?.flatten_all()?, GroupNormOp { groups, frames, eps })?.reshape(dims)
}

/// On (N, C, S): one block per (image, group), an image being `frames` consecutive items; a block is `frames`
/// contiguous runs of C/groups · S values. Parallel passes go over the (item, group) runs.
struct GroupNormOp {
    groups: usize,
    frames: usize,
    eps: f64,
}

impl GroupNormOp {
    /// (mean, 1/std) per block.
    fn stats(&self, x: &[f32], (n, c, s): (usize, usize, usize)) -> Vec<(f64, f64)> {
        let run = c / self.groups * s;
        let blocks = n / self.frames * self.groups;
        let runs = |blk: usize| {
            let (bi, gi) = (blk / self.groups, blk % self.groups);
            (0..self.frames).map(move |f| ((bi * self.frames + f) * self.groups + gi) * run)
        };
        (0..blocks)
            .into_par_iter()
            .map(|blk| {
                let len = (run * self.frames) as f64;
                let sum: f64 = runs(blk).flat_map(|o| x[o..o + run].chunks(4096)).map(|ch| ch.iter().map(|&v| v as f64).sum::<f64>()).sum();
                let mean = sum / len;
                let var: f64 =
                    runs(blk).flat_map(|o| x[o..o + run].chunks(4096)).map(|ch| ch.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>()).sum::<f64>() / len;
                (mean, 1.0 / (var + self.eps).sqrt())
            })
            .collect()
    }

    /// `act(x̂·w + b)` into `out`: statistics per block, then one scale/shift(/act) pass per channel.
    #[allow(clippy::too_many_arguments)]
    fn normalize(&self, x: &[f32], out: &mut [f32], (n, c, s): (usize, usize, usize), w: &[f32], b: &[f32], act: Act) {
        let cg = c / self.groups;
        let stats = self.stats(x, (n, c, s));
        out.par_chunks_mut(cg * s).zip(x.par_chunks(cg * s)).enumerate().for_each(|(t, (dst, xs))| {
            let (mean, rstd) = stats[self.block(t)];
            for ci in 0..cg {
                let ch = (t % self.groups) * cg + ci;
                let a = (w[ch] as f64 * rstd) as f32;
                let sh = (b[ch] as f64 - mean * w[ch] as f64 * rstd) as f32;
                affine_act(&mut dst[ci * s..(ci + 1) * s], &xs[ci * s..(ci + 1) * s], a, sh, act);
            }
        });
    }

    /// The block of (item, group) run number `t`.
    fn block(&self, t: usize) -> usize {
        let (item, gi) = (t / self.groups, t % self.groups);
        item / self.frames * self.groups + gi
    }
}

impl candle_core::CustomOp3 for GroupNormOp {
    fn name(&self) -> &'static str {
        "group-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
        s3: &candle_core::CpuStorage,
        l3: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = crate::mode::f32_slice(s1, l1, "group_norm")?;
        let w = crate::mode::f32_slice(s2, l2, "group_norm")?;
        let b = crate::mode::f32_slice(s3, l3, "group_norm")?;
        let mut out = vec![0f32; x.len()];
        self.normalize(x, &mut out, l1.shape().dims3()?, w, b, Act::None);
        Ok((candle_core::CpuStorage::F32(out), l1.shape().clone()))
    }

    /// x̂ = (x − μ)·r, y = x̂·w + b per channel; with ĝ = dy·w and means over the block:
    /// dx = r·(ĝ − mean ĝ − x̂·mean(ĝ·x̂)), dw = Σ dy·x̂, db = Σ dy (sums over items and pixels).
    fn bwd(&self, x: &Tensor, w: &Tensor, b: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (n, c, s) = x.dims3()?;
        let cg = c / self.groups;
        let wv = w.to_vec1::<f32>()?;
        let mut dx = vec![0f32; n * c * s];
        let (mut dw, mut db) = (vec![0f32; c], vec![0f32; c]);
        with_f32(x, |xv| {
            with_f32(grad, |gv| {
                let stats = self.stats(xv, (n, c, s));
                // Per (item, channel): (Σ dy·x̂, Σ dy).
                let mut partial = vec![(0f64, 0f64); n * c];
                partial.par_chunks_mut(cg).enumerate().for_each(|(t, part)| {
                    let (mean, rstd) = stats[self.block(t)];
                    let (xs, gs) = (&xv[t * cg * s..][..cg * s], &gv[t * cg * s..][..cg * s]);
                    for (ci, p) in part.iter_mut().enumerate() {
                        let (mut dyx, mut dy) = (0f64, 0f64);
                        for (&xi, &gi) in xs[ci * s..(ci + 1) * s].iter().zip(&gs[ci * s..(ci + 1) * s]) {
                            dyx += gi as f64 * (xi as f64 - mean) * rstd;
                            dy += gi as f64;
                        }
                        *p = (dyx, dy);
                    }
                });
                // Per block: (mean ĝ, mean ĝ·x̂).
                let mut means = vec![(0f64, 0f64); stats.len()];
                for (t, part) in partial.chunks(cg).enumerate() {
                    let m = &mut means[self.block(t)];
                    for (ci, &(dyx, dy)) in part.iter().enumerate() {
                        let wc = wv[(t % self.groups) * cg + ci] as f64;
                        m.0 += wc * dy;
                        m.1 += wc * dyx;
                    }
                }
                let len = (cg * s * self.frames) as f64;
                dx.par_chunks_mut(cg * s).enumerate().for_each(|(t, dxs)| {
                    let (mean, rstd) = stats[self.block(t)];
                    let (mg, mgx) = (means[self.block(t)].0 / len, means[self.block(t)].1 / len);
                    let (xs, gs) = (&xv[t * cg * s..][..cg * s], &gv[t * cg * s..][..cg * s]);
                    for ci in 0..cg {
                        let wc = wv[(t % self.groups) * cg + ci] as f64;
                        let rows = dxs[ci * s..(ci + 1) * s].iter_mut().zip(&xs[ci * s..(ci + 1) * s]).zip(&gs[ci * s..(ci + 1) * s]);
                        for ((d, &xi), &gi) in rows {
                            let xh = (xi as f64 - mean) * rstd;
                            *d = (rstd * (gi as f64 * wc - mg - xh * mgx)) as f32;
                        }
                    }
                });
                for ch in 0..c {
                    let (a, bsum) = (0..n).fold((0f64, 0f64), |(a, bs), i| (a + partial[i * c + ch].0, bs + partial[i * c + ch].1));
                    dw[ch] = a as f32;
                    db[ch] = bsum as f32;
                }
            })
        })??;
        Ok((
            Some(Tensor::from_vec(dx, (n, c, s), x.device())?),
            Some(Tensor::from_vec(dw, w.shape(), w.device())?),
            Some(Tensor::from_vec(db, b.shape(), b.device())?),
        ))
    }
}

/// `nn.InstanceNorm2d(c)` as used by the UniMatch CNN: no affine parameters, no running stats, eps 1e-5.
pub fn instance_norm(x: &Tensor) -> Result<Tensor> {
    let (n, c, h, w) = x.dims4()?;
    if cpu_f32(x) {
        let (ones, zeros) = (Tensor::ones(c, DType::F32, x.device())?, Tensor::zeros(c, DType::F32, x.device())?);
        return group_norm_trainable(x, &ones, &zeros, c, 1, 1e-5);
    }
    let xf = x.reshape((n, c, h * w))?;
    let mean = xf.mean_keepdim(D::Minus1)?;
    let xc = xf.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    xc.broadcast_div(&(var + 1e-5)?.sqrt()?)?.reshape((n, c, h, w))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn group_norm_fast_path_matches_composed_ops() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (6, 64, 3, 5), &dev).unwrap();
        let w = Tensor::randn(1f32, 0.2, 64, &dev).unwrap();
        let b = Tensor::randn(0f32, 0.1, 64, &dev).unwrap();
        for frames in [1, 3] {
            let fast = group_norm(&x, 32, frames, &w, &b, 1e-5, true).unwrap();
            let slow = group_norm(&x.to_dtype(DType::F64).unwrap(), 32, frames, &w.to_dtype(DType::F64).unwrap(), &b.to_dtype(DType::F64).unwrap(), 1e-5, true)
                .unwrap()
                .to_dtype(DType::F32)
                .unwrap();
            let d = (fast - slow).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(d < 1e-5, "frames {frames}: {d}");
        }
    }
}
