//! bf16 convolutions on the CPU (issue 73): weights rounded to bf16 and packed once ([`Bf16ConvWeights`],
//! [`Bf16TemporalWeights`]), activations rounded to bf16 (nearest even) while copied into rows of channel
//! pairs, products in `vdpbf16ps` with f32 accumulation (`crate::bf16::conv_kernel`); bias, residual and
//! scale in f32. Same semantics as [`conv2d_fused`] and [`temporal_conv`], inference only.
//!
//! Without AVX512-BF16 (or inside [`crate::bf16::with_bf16_masked`] on the calling thread) the weights are
//! widened to f32 and the f32 kernels run: storage only, never an emulation. Error per output: the module
//! doc of [`crate::bf16`] with K = taps·C, plus the f32 epilogue's roundings.

use candle_core::{DType, Device, Result, Tensor};
use rayon::prelude::*;

use super::{conv2d_fused, epilogue_row, temporal_conv, temporal_dst, with_f32_opt, Conv2dConfig, ConvEpilogue, OutPtr, RawEpilogue, ShiftGeometry};
use crate::bf16::conv_kernel::{matmul_rows, pair_row, Bf16Rows};
use crate::bf16::{bf16_to_f32, path, Bf16Path};

/// Floats (f32 or pair words) for the padded input + the gemm's destination, as the f32 kernel's budget.
const BUDGET: usize = 24 << 20;

/// A conv2d weight (Co, C, kh, kw) in bf16, packed per tap: A = Co rows of kh·kw·⌈C/2⌉ channel pairs, tap-major
/// (an odd C pads each tap with a zero channel).
pub struct Bf16ConvWeights {
    co: usize,
    c: usize,
    kh: usize,
    kw: usize,
    a: Bf16Rows,
}

impl Bf16ConvWeights {
    /// Rounds (nearest even) and packs `w` (Co, C, kh, kw), any dtype or device.
    pub fn from_conv(w: &Tensor) -> Result<Self> {
        let (co, c, kh, kw) = w.dims4()?;
        let v = w.to_device(&Device::Cpu)?.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        let (taps, cpp) = (kh * kw, c.div_ceil(2));
        let a = Bf16Rows::pack(co, taps * cpp, |o, p| {
            let (t, q) = (p / cpp, p % cpp);
            let at = |ci: usize| if ci < c { v[(o * c + ci) * taps + t] } else { 0.0 };
            (at(2 * q), at(2 * q + 1))
        });
        Ok(Self { co, c, kh, kw, a })
    }

    /// (Co, C, kh, kw).
    pub fn dims(&self) -> (usize, usize, usize, usize) {
        (self.co, self.c, self.kh, self.kw)
    }

    /// Bytes held (half of the f32 weight, plus tile and odd-C padding).
    pub fn bytes(&self) -> usize {
        self.a.bytes()
    }

    /// The stored weights widened to f32 (exact), (Co, C, kh, kw) row-major.
    pub fn to_f32(&self) -> Vec<f32> {
        let (taps, cpp) = (self.kh * self.kw, self.c.div_ceil(2));
        let mut out = vec![0f32; self.co * self.c * taps];
        for (i, v) in out.iter_mut().enumerate() {
            let (o, ci, t) = (i / (self.c * taps), i / taps % self.c, i % taps);
            *v = bf16_to_f32((self.a.word(o, t * cpp + ci / 2) >> (16 * (ci & 1))) as u16);
        }
        out
    }

    /// [`Self::to_f32`] as a tensor on `device` in `dtype` (the storage-only path's weight).
    pub fn widened(&self, device: &Device, dtype: DType) -> Result<Tensor> {
        Tensor::from_vec(self.to_f32(), (self.co, self.c, self.kh, self.kw), device)?.to_dtype(dtype)
    }
}

/// A temporal conv weight (Co, kt·C) (tap-major columns, as [`temporal_conv`] takes it) in bf16: A = Co rows of
/// kt·⌈C/2⌉ channel pairs.
pub struct Bf16TemporalWeights {
    co: usize,
    c: usize,
    kt: usize,
    a: Bf16Rows,
}

impl Bf16TemporalWeights {
    /// Rounds (nearest even) and packs `w` (Co, kt·C), any dtype or device.
    pub fn from_temporal(w: &Tensor, kt: usize) -> Result<Self> {
        let (co, ktc) = w.dims2()?;
        if kt == 0 || ktc % kt != 0 {
            candle_core::bail!("temporal conv: weight {:?} is not (Co, {kt}·C)", w.dims());
        }
        let c = ktc / kt;
        let v = w.to_device(&Device::Cpu)?.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        let cpp = c.div_ceil(2);
        let a = Bf16Rows::pack(co, kt * cpp, |o, p| {
            let (t, q) = (p / cpp, p % cpp);
            let at = |ci: usize| if ci < c { v[o * ktc + t * c + ci] } else { 0.0 };
            (at(2 * q), at(2 * q + 1))
        });
        Ok(Self { co, c, kt, a })
    }

    /// (Co, C, kt).
    pub fn dims(&self) -> (usize, usize, usize) {
        (self.co, self.c, self.kt)
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.a.bytes()
    }

    /// The stored weights widened to f32 (exact), (Co, kt·C) row-major.
    pub fn to_f32(&self) -> Vec<f32> {
        let (c, cpp) = (self.c, self.c.div_ceil(2));
        let ktc = self.kt * c;
        let mut out = vec![0f32; self.co * ktc];
        for (i, v) in out.iter_mut().enumerate() {
            let (o, t, ci) = (i / ktc, i % ktc / c, i % c);
            *v = bf16_to_f32((self.a.word(o, t * cpp + ci / 2) >> (16 * (ci & 1))) as u16);
        }
        out
    }

    /// [`Self::to_f32`] as a tensor on `device` in `dtype`.
    pub fn widened(&self, device: &Device, dtype: DType) -> Result<Tensor> {
        Tensor::from_vec(self.to_f32(), (self.co, self.kt * self.c), device)?.to_dtype(dtype)
    }
}

/// Whether the packed products run: AVX512-BF16 on this thread's [`path`] and a CPU input.
fn packed(x: &Tensor) -> bool {
    path() == Bf16Path::Dpbf16 && x.device().is_cpu()
}

fn f32_opt(t: Option<&Tensor>) -> Result<Option<Tensor>> {
    t.map(|t| t.to_dtype(DType::F32)).transpose()
}

/// [`conv2d_fused`] with bf16 weights: `residual + scale·(conv(x, w) + bias + item_bias)` on an optionally
/// nearest-×2 upsampled x, groups 1. Stride 1 runs kh·kw shifted views of one padded pair-format copy of
/// several images (or row bands) side by side in one gemm; other strides gather the taps' pixels (im2col in
/// pair format). x of another float dtype is computed in f32 and the result converted back.
pub fn conv2d_fused_bf16(x: &Tensor, w: &Bf16ConvWeights, bias: Option<&Tensor>, cfg: Conv2dConfig, epi: ConvEpilogue) -> Result<Tensor> {
    conv2d_fused_bf16_budget(x, w, bias, cfg, epi, BUDGET)
}

fn conv2d_fused_bf16_budget(x: &Tensor, w: &Bf16ConvWeights, bias: Option<&Tensor>, cfg: Conv2dConfig, epi: ConvEpilogue, budget: usize) -> Result<Tensor> {
    let (n, c, h, wd) = x.dims4()?;
    let (co, _, kh, kw) = w.dims();
    if c != w.c {
        candle_core::bail!("conv2d: input has {c} channels, weight expects {}", w.c);
    }
    if !packed(x) {
        return conv2d_fused(x, &w.widened(x.device(), x.dtype())?, bias, cfg, epi);
    }
    if cfg.stride == 0 {
        candle_core::bail!("conv2d: stride 0");
    }
    let up = if epi.upsample2x { 2 } else { 1 };
    let (hi, wi) = (h * up, wd * up);
    let (eh, ew) = (cfg.dilation * (kh - 1) + 1, cfg.dilation * (kw - 1) + 1);
    if hi + 2 * cfg.padding < eh || wi + 2 * cfg.padding < ew {
        candle_core::bail!("conv2d: kernel {kh}x{kw} larger than padded input {hi}x{wi}");
    }
    let (ho, wo) = ((hi + 2 * cfg.padding - eh) / cfg.stride + 1, (wi + 2 * cfg.padding - ew) / cfg.stride + 1);
    if let Some(r) = epi.residual {
        if r.dims() != [n, co, ho, wo] {
            candle_core::bail!("conv2d_fused: residual {:?}, output {:?}", r.dims(), [n, co, ho, wo]);
        }
    }
    if let Some(ib) = epi.item_bias {
        if ib.elem_count() != n * co {
            candle_core::bail!("conv2d_fused: item bias {:?}, expected ({n}, {co})", ib.dims());
        }
    }
    let x32 = x.to_dtype(DType::F32)?.contiguous()?;
    let (b32, ib32, r32) = (f32_opt(bias)?, f32_opt(epi.item_bias)?, f32_opt(epi.residual)?);
    let out = with_f32_opt(Some(&x32), |xd| {
        with_f32_opt(b32.as_ref(), |bd| {
            with_f32_opt(ib32.as_ref(), |ibd| {
                with_f32_opt(r32.as_ref(), |rd| {
                    let e = RawEpilogue { bias: bd, item_bias: ibd, residual: rd, scale: epi.scale };
                    let xd = xd.unwrap_or(&[]);
                    if cfg.stride == 1 {
                        let geo = ShiftGeometry::new((n, c, h, wd), (co, kh, kw), cfg.padding, cfg.dilation, up)?;
                        Ok(shift_conv_bf16(xd, w, &geo, &e, budget))
                    } else {
                        Ok(strided_conv_bf16(xd, w, (n, h, wd), cfg, up, (ho, wo), &e, budget))
                    }
                })
            })
        })
    })?;
    Tensor::from_vec(out, (n, co, ho, wo), x.device())?.to_dtype(x.dtype())
}

/// Writes `dst` (rows of `wp` words) = channel pair q of image b, padded by `pad` and upsampled by `up`,
/// rows `y0 − pad ..` of the padded plane (zero outside the input).
#[allow(clippy::too_many_arguments)]
fn fill_pairs(
    x: &[f32],
    (c, h, wd): (usize, usize, usize),
    up: usize,
    pad: usize,
    wp: usize,
    b: usize,
    q: usize,
    y0: usize,
    dst: &mut [u32],
    scratch: &mut Vec<u32>,
) {
    let (hi, wi) = (h * up, wd * up);
    let lo_plane = &x[(b * c + 2 * q) * h * wd..][..h * wd];
    let hi_plane = (2 * q + 1 < c).then(|| &x[(b * c + 2 * q + 1) * h * wd..][..h * wd]);
    for (r, row) in dst.chunks_exact_mut(wp).enumerate() {
        let yy = (y0 + r) as isize - pad as isize;
        if yy < 0 || yy as usize >= hi {
            row.fill(0);
            continue;
        }
        row[..pad].fill(0);
        row[pad + wi..].fill(0);
        let sy = yy as usize / up;
        let (lo, hv) = (&lo_plane[sy * wd..][..wd], hi_plane.map(|p| &p[sy * wd..][..wd]));
        if up == 1 {
            pair_row(lo, hv, &mut row[pad..pad + wi]);
        } else {
            scratch.resize(wd, 0);
            pair_row(lo, hv, scratch);
            for (xx, v) in row[pad..pad + wi].iter_mut().enumerate() {
                *v = scratch[xx / up];
            }
        }
    }
}

/// The bf16 counterpart of the f32 `shift_conv_budget`: the same bands and pieces with the padded copy in
/// pair words (⌈C/2⌉ rows), all kh·kw taps in one gemm over shifted row offsets, the same epilogue.
fn shift_conv_bf16(x: &[f32], w: &Bf16ConvWeights, g: &ShiftGeometry, epi: &RawEpilogue, budget: usize) -> Vec<f32> {
    let ShiftGeometry { n, c, h, w: wd, co, kh, kw, pad, dil, up, wp, ho, wo } = *g;
    let cpp = c.div_ceil(2);
    let halo = dil * (kh - 1);
    let per_row = (cpp + co) * wp;
    let band = if (ho + halo) * per_row <= budget { ho } else { (budget / per_row).saturating_sub(halo).max(1).min(ho) };
    let bands = ho.div_ceil(band);
    let slot = (band + halo) * wp;
    let pieces = n * bands;
    let per = (budget / ((cpp + co) * slot)).clamp(1, pieces);
    let row_len = per * slot;
    let mut out = vec![0f32; n * co * ho * wo];
    let optr = OutPtr(out.as_mut_ptr());
    let mut padded = vec![0u32; cpp * row_len];
    let mut wide = vec![0f32; co * row_len];
    // A's pair (tap, q) meets padded row q shifted by the tap.
    let rows: Vec<usize> = (0..kh * kw * cpp).map(|i| (i % cpp) * row_len + dil * ((i / cpp / kw) * wp + (i / cpp) % kw)).collect();
    let mut p0 = 0;
    while p0 < pieces {
        let np = per.min(pieces - p0);
        padded.par_chunks_mut(row_len).enumerate().for_each_init(Vec::new, |scratch, (q, dst)| {
            for p in 0..np {
                let (b, bi) = ((p0 + p) / bands, (p0 + p) % bands);
                fill_pairs(x, (c, h, wd), up, pad, wp, b, q, bi * band, &mut dst[p * slot..][..slot], scratch);
            }
        });
        let ncols = (np - 1) * slot + (band - 1) * wp + wo;
        matmul_rows(&w.a, 0, &padded, &rows, ncols, &mut wide, row_len, 1.0, false);
        wide.par_chunks(row_len).enumerate().for_each(|(o, wrow)| {
            #[allow(clippy::redundant_locals)] // the whole Send wrapper, not its raw-pointer field (edition 2021 captures)
            let optr = optr;
            for p in 0..np {
                let (b, bi) = ((p0 + p) / bands, (p0 + p) % bands);
                let y0 = bi * band;
                let add = epi.bias.map_or(0.0, |bv| bv[o]) + epi.item_bias.map_or(0.0, |ib| ib[b * co + o]);
                let plane = (b * co + o) * ho * wo;
                for r in 0..band.min(ho - y0) {
                    let y = y0 + r;
                    // SAFETY: output row (b, o, y) is written by this task only.
                    let dst = unsafe { std::slice::from_raw_parts_mut(optr.0.add(plane + y * wo), wo) };
                    epilogue_row(dst, &wrow[p * slot + r * wp..][..wo], add, epi.scale, epi.residual.map(|res| &res[plane + y * wo..][..wo]));
                }
            }
        });
        p0 += np;
    }
    out
}

/// Any stride: per chunk of images, the padded pair-format copy, then each tap's pixels gathered at the
/// stride into rows of (images × output pixels) words (im2col in pair format), one gemm, the epilogue.
#[allow(clippy::too_many_arguments)]
fn strided_conv_bf16(
    x: &[f32],
    w: &Bf16ConvWeights,
    (n, h, wd): (usize, usize, usize),
    cfg: Conv2dConfig,
    up: usize,
    (ho, wo): (usize, usize),
    epi: &RawEpilogue,
    budget: usize,
) -> Vec<f32> {
    let (co, c, kh, kw) = w.dims();
    let (s, pad, dil) = (cfg.stride, cfg.padding, cfg.dilation);
    let cpp = c.div_ceil(2);
    let (hp, wp) = (h * up + 2 * pad, wd * up + 2 * pad);
    let (px, slot, kp) = (ho * wo, hp * wp, kh * kw * cpp);
    let per = (budget / (cpp * slot + (kp + co) * px)).clamp(1, n);
    let (lp, ldb) = (per * slot, per * px);
    let mut out = vec![0f32; n * co * px];
    let mut padded = vec![0u32; cpp * lp];
    let mut cols = vec![0u32; kp * ldb];
    let mut cbuf = vec![0f32; co * ldb];
    let rows: Vec<usize> = (0..kp).map(|r| r * ldb).collect();
    for b0 in (0..n).step_by(per) {
        let nb = per.min(n - b0);
        padded.par_chunks_mut(lp).enumerate().for_each_init(Vec::new, |scratch, (q, dst)| {
            for i in 0..nb {
                fill_pairs(x, (c, h, wd), up, pad, wp, b0 + i, q, 0, &mut dst[i * slot..][..slot], scratch);
            }
        });
        cols.par_chunks_mut(ldb).enumerate().for_each(|(r, dst)| {
            let (t, q) = (r / cpp, r % cpp);
            let (ky, kx) = (t / kw, t % kw);
            for i in 0..nb {
                for oy in 0..ho {
                    let src = &padded[q * lp + i * slot + (oy * s + ky * dil) * wp + kx * dil..];
                    for (ox, d) in dst[i * px + oy * wo..][..wo].iter_mut().enumerate() {
                        *d = src[ox * s];
                    }
                }
            }
        });
        matmul_rows(&w.a, 0, &cols, &rows, nb * px, &mut cbuf, ldb, 1.0, false);
        out[b0 * co * px..(b0 + nb) * co * px].par_chunks_mut(px).enumerate().for_each(|(idx, dst)| {
            let (i, o) = (idx / co, idx % co);
            let b = b0 + i;
            let add = epi.bias.map_or(0.0, |bv| bv[o]) + epi.item_bias.map_or(0.0, |ib| ib[b * co + o]);
            let plane = (b * co + o) * px;
            epilogue_row(dst, &cbuf[o * ldb + i * px..][..px], add, epi.scale, epi.residual.map(|res| &res[plane..][..px]));
        });
    }
    out
}

/// [`temporal_conv`] with bf16 weights: Conv3d (kt, 1, 1), zero padding kt/2 over `frames`-frame clips of
/// frame-major x (B·T, C, H, W); `residual + scale·(conv + bias + item_bias)`. Each input frame is converted
/// to pair rows once; each output frame is one gemm over its valid neighbours' rows (A's pair sub-range at a
/// clip's edges) accumulating into `residual + scale·(bias + item_bias)` with α = scale.
#[allow(clippy::too_many_arguments)]
pub fn temporal_conv_bf16(
    x: &Tensor,
    w: &Bf16TemporalWeights,
    bias: &Tensor,
    kt: usize,
    frames: usize,
    item_bias: Option<&Tensor>,
    residual: Option<&Tensor>,
    scale: f32,
) -> Result<Tensor> {
    let (n, c, h, wd) = x.dims4()?;
    let co = w.co;
    if kt != w.kt || c != w.c || frames == 0 || n % frames != 0 {
        candle_core::bail!("temporal conv: input {:?} with {frames} frames, weight (Co {co}, C {}, kt {}), kt {kt}", x.dims(), w.c, w.kt);
    }
    if !packed(x) {
        return temporal_conv(x, &w.widened(x.device(), x.dtype())?, bias, kt, frames, item_bias, residual, scale);
    }
    let (s, pad, cpp) = (h * wd, kt / 2, c.div_ceil(2));
    let bv = bias.to_dtype(DType::F32)?.to_vec1::<f32>()?;
    let ib = match item_bias {
        Some(t) => Some(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?),
        None => None,
    };
    if bv.len() != co || ib.as_ref().is_some_and(|v| v.len() != n * co) {
        candle_core::bail!("temporal conv: bias {} / item bias {:?} for {n} items of {co} channels", bv.len(), ib.as_ref().map(Vec::len));
    }
    if let Some(r) = residual {
        if r.dims() != [n, co, h, wd] {
            candle_core::bail!("temporal conv: residual {:?}, output {:?}", r.dims(), [n, co, h, wd]);
        }
    }
    let mut dst = with_f32_opt(f32_opt(residual)?.as_ref(), |rd| Ok(temporal_dst((n, co, s), &bv, ib.as_deref(), rd, scale)))?;
    let x32 = x.to_dtype(DType::F32)?.contiguous()?;
    // Pair rows of the kt frames in use, frame f in slot f % kt (kt consecutive frames never share a slot):
    // each frame converted once, just before its first use, into a buffer that stays in L3.
    let mut ring = vec![0u32; kt * cpp * s];
    let mut held = vec![usize::MAX; kt];
    with_f32_opt(Some(&x32), |xd| {
        let xd = xd.unwrap_or(&[]);
        for (item, d) in dst.chunks_mut(co * s).enumerate() {
            let t = item % frames;
            let (k0, k1) = (pad.saturating_sub(t), kt.min(frames + pad - t));
            let first = item + k0 - pad;
            for f in first..first + (k1 - k0) {
                if held[f % kt] != f {
                    ring[f % kt * cpp * s..][..cpp * s].par_chunks_mut(s).enumerate().for_each(|(q, row)| {
                        let hi = (2 * q + 1 < c).then(|| &xd[(f * c + 2 * q + 1) * s..][..s]);
                        pair_row(&xd[(f * c + 2 * q) * s..][..s], hi, row);
                    });
                    held[f % kt] = f;
                }
            }
            // A's pairs from tap k0 on meet frames first.. in their slots.
            let rows: Vec<usize> = (0..(k1 - k0) * cpp).map(|i| ((first + i / cpp) % kt * cpp + i % cpp) * s).collect();
            matmul_rows(&w.a, k0 * cpp, &ring, &rows, s, d, s, scale, true);
        }
        Ok(())
    })?;
    Tensor::from_vec(dst, (n, co, h, wd), x.device())?.to_dtype(x.dtype())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bf16::bench::fill;
    use crate::bf16::{bf16_to_f32_daz, error_bound, f32_to_bf16, with_bf16_masked};

    const U24: f64 = 1.0 / (1u64 << 24) as f64;

    fn t(v: Vec<f32>, shape: &[usize]) -> Tensor {
        Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
    }

    fn v(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    }

    /// One conv case: (n, c, h, w), (co, k), padding, dilation, stride, upsample, epilogue, budget (0: default).
    struct Case {
        x: (usize, usize, usize, usize),
        co: usize,
        k: usize,
        pad: usize,
        dil: usize,
        stride: usize,
        up: bool,
        epi: bool,
        budget: usize,
    }

    /// An operand as the kernel reads it: bf16 (nearest even), denormals as zero.
    fn rd(v: f32) -> f64 {
        bf16_to_f32_daz(f32_to_bf16(v)) as f64
    }

    /// Σ x·w, Σ|x·w| of the unrounded operands, then of the rounded ones.
    #[derive(Clone, Copy, Default)]
    struct Sums([f64; 4]);

    impl Sums {
        fn add(&mut self, x: f32, w: f32) {
            let (p, q) = (x as f64 * w as f64, rd(x) * rd(w));
            self.0[0] += p;
            self.0[1] += p.abs();
            self.0[2] += q;
            self.0[3] += q.abs();
        }
    }

    /// The f64 direct convolution, per output.
    fn direct(x: &[f32], (n, c, h, wd): (usize, usize, usize, usize), w: &[f32], co: usize, k: usize, cs: &Case, (ho, wo): (usize, usize)) -> Vec<Sums> {
        let up = if cs.up { 2 } else { 1 };
        let mut out = vec![Sums::default(); n * co * ho * wo];
        for b in 0..n {
            for o in 0..co {
                for oy in 0..ho {
                    for ox in 0..wo {
                        let mut acc = Sums::default();
                        for ci in 0..c {
                            for ky in 0..k {
                                for kx in 0..k {
                                    let yy = (oy * cs.stride + ky * cs.dil) as isize - cs.pad as isize;
                                    let xx = (ox * cs.stride + kx * cs.dil) as isize - cs.pad as isize;
                                    if yy < 0 || xx < 0 || yy as usize >= h * up || xx as usize >= wd * up {
                                        continue;
                                    }
                                    acc.add(x[((b * c + ci) * h + yy as usize / up) * wd + xx as usize / up], w[((o * c + ci) * k + ky) * k + kx]);
                                }
                            }
                        }
                        out[((b * co + o) * ho + oy) * wo + ox] = acc;
                    }
                }
            }
        }
        out
    }

    /// The epilogue's operands per output: residual, scale, bias + item bias (f64), and the reduction length K.
    struct Epi<'a> {
        r: Option<&'a [f32]>,
        scale: f64,
        b: &'a [f32],
        ib: Option<&'a [f32]>,
        co: usize,
        plane: usize,
        k: usize,
        pairs: usize,
    }

    /// The tolerance of one output against the unrounded operands: |s|·error_bound(K, Σ|xw|) + (blocks + 4)·2⁻²⁴·M,
    /// M = |r| + |s|·(Σ|xw| + |b| + |ib|): the products' model plus the f32 roundings outside it — one per
    /// 256-pair K-block store and three in the epilogue (bias sum, scale, residual), each ≤ 2⁻²⁴·M. Against the
    /// rounded operands only the f32 sums remain: |s|·(K·2⁻²⁴·Σ|x'w'| + 2K·2⁻¹²⁶) + the same outside terms.
    /// Returns (want, tolerance) for both.
    fn model(i: usize, sums: &Sums, e: &Epi) -> [(f64, f64); 2] {
        let [s, sa, sr, sra] = sums.0;
        let (item, o) = (i / e.plane / e.co, i / e.plane % e.co);
        let (b, ib) = (e.b[o] as f64, e.ib.map_or(0.0, |v| v[item * e.co + o] as f64));
        let r = e.r.map_or(0.0, |r| r[i] as f64);
        let outside = |sa: f64| (e.pairs.div_ceil(256) as f64 + 4.0) * U24 * (r.abs() + e.scale.abs() * (sa + b.abs() + ib.abs()));
        let k = e.k as f64;
        [
            (r + e.scale * (s + b + ib), e.scale.abs() * error_bound(e.k, sa) + outside(sa)),
            (r + e.scale * (sr + b + ib), e.scale.abs() * (k * U24 * sra + 2.0 * k * 2f64.powi(-126)) + outside(sra)),
        ]
    }

    /// Every output within both tolerances of [`model`]; the worst |error| / tolerance against the unrounded
    /// operands, or the first output past either.
    fn check(got: &[f32], refs: &[Sums], e: &Epi) -> std::result::Result<f64, String> {
        let mut worst = 0f64;
        for (i, (&g, sums)) in got.iter().zip(refs).enumerate() {
            let [(want, tol), (want_r, tight)] = model(i, sums, e);
            let (d, dr) = ((g as f64 - want).abs(), (g as f64 - want_r).abs());
            if d > tol || g.is_nan() {
                return Err(format!("output {i}: {g} want {want}, |diff| {d} > {tol}"));
            }
            if dr > tight {
                return Err(format!("output {i}: {g}, rounded-operand sum {want_r}, |diff| {dr} > {tight}"));
            }
            worst = worst.max(d / tol);
        }
        Ok(worst)
    }

    fn run_case(cs: &Case, seed: u64) {
        let (n, c, h, wd) = cs.x;
        let (co, k) = (cs.co, cs.k);
        let xv = fill(n * c * h * wd, seed);
        let wv: Vec<f32> = fill(co * c * k * k, seed + 1).into_iter().map(|v| v * 0.5).collect();
        let (x, w) = (t(xv.clone(), &[n, c, h, wd]), t(wv.clone(), &[co, c, k, k]));
        let bw = Bf16ConvWeights::from_conv(&w).unwrap();
        let bias = fill(co, seed + 2);
        let up = if cs.up { 2 } else { 1 };
        let eff = cs.dil * (k - 1) + 1;
        let (ho, wo) = ((h * up + 2 * cs.pad - eff) / cs.stride + 1, (wd * up + 2 * cs.pad - eff) / cs.stride + 1);
        let ib = fill(n * co, seed + 3);
        let res = fill(n * co * ho * wo, seed + 4);
        let (ibt, rt) = (t(ib.clone(), &[n, co]), t(res.clone(), &[n, co, ho, wo]));
        let epi = if cs.epi {
            ConvEpilogue { item_bias: Some(&ibt), residual: Some(&rt), scale: Some(-0.75), upsample2x: cs.up }
        } else {
            ConvEpilogue { upsample2x: cs.up, ..Default::default() }
        };
        let cfg = Conv2dConfig { padding: cs.pad, stride: cs.stride, dilation: cs.dil };
        let bt = t(bias.clone(), &[co]);
        let name = format!("seed {seed} x {:?} co {co} k {k} pad {} dil {} stride {} up {} epi {}", cs.x, cs.pad, cs.dil, cs.stride, cs.up, cs.epi);
        // Masked: the f32 conv of the widened weights, bit for bit.
        let masked = with_bf16_masked(|| conv2d_fused_bf16(&x, &bw, Some(&bt), cfg, epi)).unwrap();
        let f32_of_widened = conv2d_fused(&x, &bw.widened(&Device::Cpu, DType::F32).unwrap(), Some(&bt), cfg, epi).unwrap();
        assert!(
            v(&masked).iter().zip(v(&f32_of_widened)).all(|(a, b)| a.to_bits() == b.to_bits()),
            "{name}: masked path is not the f32 conv of the widened weights"
        );
        if path() != Bf16Path::Dpbf16 {
            return;
        }
        let got =
            if cs.budget > 0 { conv2d_fused_bf16_budget(&x, &bw, Some(&bt), cfg, epi, cs.budget) } else { conv2d_fused_bf16(&x, &bw, Some(&bt), cfg, epi) }
                .unwrap();
        assert_eq!(got.dims(), [n, co, ho, wo], "{name}");
        let refs = direct(&xv, cs.x, &wv, co, k, cs, (ho, wo));
        let e = Epi {
            r: cs.epi.then_some(&res[..]),
            scale: if cs.epi { -0.75 } else { 1.0 },
            b: &bias,
            ib: cs.epi.then_some(&ib[..]),
            co,
            plane: ho * wo,
            k: k * k * c,
            pairs: k * k * c.div_ceil(2),
        };
        let worst = check(&v(&got), &refs, &e).unwrap_or_else(|m| panic!("{name}: {m}"));
        assert!(worst > 0.0, "{name}: no rounding error at all: the bf16 path did not run");
        if cs.budget > 0 {
            // Bands change which columns share a gemm, not any output's sum: bit for bit the default run.
            let plain = conv2d_fused_bf16(&x, &bw, Some(&bt), cfg, epi).unwrap();
            assert!(v(&plain).iter().zip(v(&got)).all(|(a, b)| a.to_bits() == b.to_bits()), "{name}: banded run differs");
        }
        // A result moved 1 % past its tolerance fails the check.
        let mut moved = v(&got);
        let i = moved.len() / 2;
        let [(want, tol), _] = model(i, &refs[i], &e);
        moved[i] = (want + 1.01 * tol) as f32;
        assert!(check(&moved, &refs, &e).is_err(), "{name}: a result 1 % past the tolerance passed");
    }

    #[test]
    fn conv2d_bf16_holds_the_error_model_on_seeds_and_shapes() {
        let case = |x, co, k, pad, dil, stride, up, epi, budget| Case { x, co, k, pad, dil, stride, up, epi, budget };
        let cases = [
            case((2, 1, 7, 9), 3, 3, 1, 1, 1, false, false, 0),
            case((3, 5, 9, 11), 13, 3, 1, 1, 1, true, true, 0),
            case((2, 64, 6, 7), 20, 3, 2, 2, 1, false, true, 0),
            case((2, 33, 8, 37), 25, 1, 0, 1, 1, false, true, 0),
            case((1, 4, 40, 70), 14, 3, 1, 1, 1, false, false, 0),
            case((2, 7, 9, 10), 11, 3, 1, 1, 2, false, true, 0),
            case((1, 6, 5, 7), 5, 3, 1, 1, 2, true, true, 0),
            case((3, 5, 9, 11), 13, 3, 1, 2, 1, true, true, (3 + 13) * 26 * 6),
            case((3, 5, 9, 11), 13, 3, 0, 1, 1, false, true, (3 + 13) * 11 * 4),
            case((3, 6, 9, 11), 12, 3, 1, 1, 2, false, true, 3 * 11 * 13 + (27 + 12) * 20),
        ];
        for seed in [1u64, 2, 3] {
            for cs in &cases {
                run_case(cs, seed);
            }
        }
    }

    /// What a truncating packer computes: operands truncated to bf16 beforehand (then exact in the kernel).
    /// Random activations truncated: off the rounded-operand sums by ≈ 2⁻⁹ relative, far past K·2⁻²⁴. Every
    /// value 1 + 2⁻⁷ − 2⁻²³, both operands truncated: ≈ 2⁻⁶ = 4u relative, past even 2u + u². Nearest even passes.
    #[test]
    fn truncation_is_caught_by_the_conv_error_model() {
        if path() != Bf16Path::Dpbf16 {
            return;
        }
        let (n, c, h, wd, co) = (2, 5, 6, 7, 4);
        let trunc = |x: f32| f32::from_bits(x.to_bits() & 0xffff_0000);
        let same = |x: f32| x;
        let cs = Case { x: (n, c, h, wd), co, k: 3, pad: 1, dil: 1, stride: 1, up: false, epi: false, budget: 0 };
        let zeros = vec![0f32; co];
        let e = Epi { r: None, scale: 1.0, b: &zeros, ib: None, co, plane: h * wd, k: 9 * c, pairs: 9 * c.div_ceil(2) };
        let cfg = Conv2dConfig { padding: 1, stride: 1, dilation: 1 };
        let run = |xv: &[f32], wv: &[f32], fx: &dyn Fn(f32) -> f32, fw: &dyn Fn(f32) -> f32| {
            let x = t(xv.iter().map(|&v| fx(v)).collect(), &[n, c, h, wd]);
            let w = Bf16ConvWeights::from_conv(&t(wv.iter().map(|&v| fw(v)).collect(), &[co, c, 3, 3])).unwrap();
            v(&conv2d_fused_bf16(&x, &w, None, cfg, ConvEpilogue::default()).unwrap())
        };
        for seed in [5u64, 6] {
            let (xv, wv) = (fill(n * c * h * wd, seed), fill(co * c * 9, seed + 1));
            let refs = direct(&xv, cs.x, &wv, co, 3, &cs, (h, wd));
            check(&run(&xv, &wv, &same, &same), &refs, &e).expect("round to nearest even");
            assert!(check(&run(&xv, &wv, &trunc, &same), &refs, &e).is_err(), "seed {seed}: truncated activations passed the model");
        }
        let val = 1.0 + 2f32.powi(-7) - 2f32.powi(-23);
        let (xv, wv) = (vec![val; n * c * h * wd], vec![val; co * c * 9]);
        let refs = direct(&xv, cs.x, &wv, co, 3, &cs, (h, wd));
        check(&run(&xv, &wv, &same, &same), &refs, &e).expect("round to nearest even");
        let truncated = run(&xv, &wv, &trunc, &trunc);
        for (i, (g, sums)) in truncated.iter().zip(&refs).enumerate() {
            let [(want, tol), _] = model(i, sums, &e);
            assert!((*g as f64 - want).abs() > tol, "output {i}: both operands truncated within the unrounded bound");
        }
    }

    #[test]
    fn temporal_bf16_holds_the_error_model_at_clip_edges() {
        // (frames, clips, c, co, h, w)
        let cases = [(1, 2, 5, 7, 3, 5), (2, 1, 6, 13, 4, 9), (14, 1, 3, 5, 2, 3), (14, 2, 8, 33, 3, 11), (3, 1, 180, 12, 2, 3)];
        let kt = 3;
        for seed in [1u64, 2, 3] {
            for &(frames, clips, c, co, h, wd) in &cases {
                let n = frames * clips;
                let s = h * wd;
                let xv = fill(n * c * s, seed);
                let wv: Vec<f32> = fill(co * kt * c, seed + 1).into_iter().map(|v| v * 0.5).collect();
                let (bias, ib, res) = (fill(co, seed + 2), fill(n * co, seed + 3), fill(n * co * s, seed + 4));
                let x = t(xv.clone(), &[n, c, h, wd]);
                let w = t(wv.clone(), &[co, kt * c]);
                let (bt, ibt, rt) = (t(bias.clone(), &[co]), t(ib.clone(), &[n, co]), t(res.clone(), &[n, co, h, wd]));
                let bw = Bf16TemporalWeights::from_temporal(&w, kt).unwrap();
                let name = format!("seed {seed} frames {frames} clips {clips} c {c} co {co} {h}x{wd}");
                let scale = 0.6f32;
                let masked = with_bf16_masked(|| temporal_conv_bf16(&x, &bw, &bt, kt, frames, Some(&ibt), Some(&rt), scale)).unwrap();
                let f32_of_widened = temporal_conv(&x, &bw.widened(&Device::Cpu, DType::F32).unwrap(), &bt, kt, frames, Some(&ibt), Some(&rt), scale).unwrap();
                assert!(
                    v(&masked).iter().zip(v(&f32_of_widened)).all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{name}: masked path is not the f32 conv of the widened weights"
                );
                if path() != Bf16Path::Dpbf16 {
                    continue;
                }
                let got = v(&temporal_conv_bf16(&x, &bw, &bt, kt, frames, Some(&ibt), Some(&rt), scale).unwrap());
                for item in 0..n {
                    let tt = item % frames;
                    let (k0, k1) = (1usize.saturating_sub(tt), kt.min(frames + 1 - tt));
                    let mut refs = vec![Sums::default(); co * s];
                    for o in 0..co {
                        for px in 0..s {
                            for dt in k0..k1 {
                                for ci in 0..c {
                                    refs[o * s + px].add(xv[((item + dt - 1) * c + ci) * s + px], wv[o * kt * c + dt * c + ci]);
                                }
                            }
                        }
                    }
                    let e = Epi {
                        r: Some(&res[item * co * s..][..co * s]),
                        scale: scale as f64,
                        b: &bias,
                        ib: Some(&ib[item * co..][..co]),
                        co,
                        plane: s,
                        k: (k1 - k0) * c,
                        pairs: (k1 - k0) * c.div_ceil(2),
                    };
                    check(&got[item * co * s..][..co * s], &refs, &e).unwrap_or_else(|m| panic!("{name} item {item}: {m}"));
                }
                assert!(got.iter().zip(v(&f32_of_widened)).any(|(a, b)| *a != b), "{name}: bf16 run equals the storage-only one");
            }
        }
    }
}
