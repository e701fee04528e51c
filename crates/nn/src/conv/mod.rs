//! Convolutions. candle's CPU conv2d is several times slower than a gemm of the same size, so CPU f32 runs
//! shifted gemms (stride 1) or im2col + gemm (custom ops that are each other's backward); other devices and
//! dtypes take candle's own conv2d. The refiner's fused epilogues and its (kt, 1, 1) temporal conv live here too.
//! On CUDA with `MVSPLAT360_GPU_OPS=cudnn`, inference (no tensor tracks a gradient) runs on cuDNN with cached
//! plans ([`cudnn`]), bias and residual in the same call; anything it cannot run takes candle's path.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Module, Result, Shape, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

use crate::mode::{cpu_f32, is_cpu_f32, is_differentiable, with_f32};

pub mod bf16;
pub mod cudnn;
pub mod winograd;

pub use winograd::{conv2d_winograd3x3, Winograd3x3, WinogradEpilogue};

/// The cuDNN path applies: CUDA, not differentiable mode, no input records a graph (a `Var` or anything computed
/// from one: the op has no backward), and `MVSPLAT360_GPU_OPS` selects `cudnn`.
fn cudnn_applies(x: &Tensor, rest: &[Option<&Tensor>]) -> bool {
    x.device().is_cuda()
        && !is_differentiable()
        && crate::gpu_ops::enabled(crate::gpu_ops::GpuOp::Cudnn)
        && !x.track_op()
        && rest.iter().flatten().all(|t| !t.track_op())
}

/// `t + scale·item_bias (N, Co)` broadcast over the pixels (cuDNN has no per-image bias).
fn add_item_bias(t: Tensor, item_bias: Option<&Tensor>, scale: f32) -> Result<Tensor> {
    let Some(ib) = item_bias else { return Ok(t) };
    let (n, co) = (t.dim(0)?, t.dim(1)?);
    let ib = ib.reshape((n, co, 1, 1))?;
    let ib = if scale == 1.0 { ib } else { (ib * scale as f64)? };
    t.broadcast_add(&ib)
}

#[derive(Debug, Clone, Copy)]
struct Geometry {
    c: usize,
    h: usize,
    w: usize,
    kh: usize,
    kw: usize,
    stride: usize,
    padding: usize,
    dilation: usize,
    ho: usize,
    wo: usize,
}

impl Geometry {
    fn new(c: usize, h: usize, w: usize, kh: usize, kw: usize, stride: usize, padding: usize, dilation: usize) -> Result<Self> {
        let eff_h = dilation * (kh - 1) + 1;
        let eff_w = dilation * (kw - 1) + 1;
        if h + 2 * padding < eff_h || w + 2 * padding < eff_w {
            candle_core::bail!("conv2d: kernel {kh}x{kw} larger than padded input {h}x{w}");
        }
        let ho = (h + 2 * padding - eff_h) / stride + 1;
        let wo = (w + 2 * padding - eff_w) / stride + 1;
        Ok(Self { c, h, w, kh, kw, stride, padding, dilation, ho, wo })
    }

    fn k(&self) -> usize {
        self.c * self.kh * self.kw
    }

    fn p(&self) -> usize {
        self.ho * self.wo
    }

    /// Input column for output column `ox` at kernel column `kx`, or None in the padding.
    #[inline]
    fn src_x(&self, ox: usize, kx: usize) -> Option<usize> {
        let x = (ox * self.stride + kx * self.dilation) as isize - self.padding as isize;
        (x >= 0 && (x as usize) < self.w).then_some(x as usize)
    }

    #[inline]
    fn src_y(&self, oy: usize, ky: usize) -> Option<usize> {
        let y = (oy * self.stride + ky * self.dilation) as isize - self.padding as isize;
        (y >= 0 && (y as usize) < self.h).then_some(y as usize)
    }
}

/// (N, C, H, W) → (N, Ho·Wo, C·kh·kw): one row per output pixel, columns ordered (c, ky, kx) like a
/// flattened conv weight, so the conv is one tall gemm `cols @ Wᵀ` (gemm is fastest with the pixel count as M).
struct Im2Col(Geometry);
/// Adjoint of [`Im2Col`]: scatter-add the patches back to (N, C, H, W).
struct Col2Im(Geometry);

fn f32_slice<'a>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [f32]> {
    crate::mode::f32_slice(s, l, "conv2d")
}

impl CustomOp1 for Im2Col {
    fn name(&self) -> &'static str {
        "im2col"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let src = f32_slice(s, l)?;
        let n = l.dims()[0];
        let (k, p) = (g.k(), g.p());
        let mut out = vec![0f32; n * p * k];
        // One task per (image, output row): it owns wo·K contiguous outputs.
        out.par_chunks_mut(g.wo * k).enumerate().for_each(|(task, dst)| {
            let b = task / g.ho;
            let oy = task % g.ho;
            let img = &src[b * g.c * g.h * g.w..][..g.c * g.h * g.w];
            for c in 0..g.c {
                let plane = &img[c * g.h * g.w..][..g.h * g.w];
                for ky in 0..g.kh {
                    let y = g.src_y(oy, ky);
                    for kx in 0..g.kw {
                        let col = (c * g.kh + ky) * g.kw + kx;
                        match y {
                            None => (0..g.wo).for_each(|ox| dst[ox * k + col] = 0.0),
                            Some(y) => {
                                let srow = &plane[y * g.w..(y + 1) * g.w];
                                for ox in 0..g.wo {
                                    dst[ox * k + col] = g.src_x(ox, kx).map_or(0.0, |x| srow[x]);
                                }
                            }
                        }
                    }
                }
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((n, p, k))))
    }

    fn bwd(&self, _arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(grad_res.contiguous()?.apply_op1_no_bwd(&Col2Im(self.0))?))
    }
}

impl CustomOp1 for Col2Im {
    fn name(&self) -> &'static str {
        "col2im"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let src = f32_slice(s, l)?;
        let n = l.dims()[0];
        let (k, p) = (g.k(), g.p());
        let mut out = vec![0f32; n * g.c * g.h * g.w];
        // One task per (image, channel) plane: every patch entry of that channel adds into it, no races.
        out.par_chunks_mut(g.h * g.w).enumerate().for_each(|(plane_idx, plane)| {
            let b = plane_idx / g.c;
            let c = plane_idx % g.c;
            let cols = &src[b * p * k..][..p * k];
            for oy in 0..g.ho {
                for ky in 0..g.kh {
                    let Some(y) = g.src_y(oy, ky) else { continue };
                    for kx in 0..g.kw {
                        let col = (c * g.kh + ky) * g.kw + kx;
                        for ox in 0..g.wo {
                            if let Some(x) = g.src_x(ox, kx) {
                                plane[y * g.w + x] += cols[(oy * g.wo + ox) * k + col];
                            }
                        }
                    }
                }
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((n, g.c, g.h, g.w))))
    }

    fn bwd(&self, _arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(grad_res.contiguous()?.apply_op1_no_bwd(&Im2Col(self.0))?))
    }
}

/// Stride-1 convolution as kh·kw gemms over shifted views of one padded copy of each image: for kernel tap
/// (ky, kx) the input pixels form a plain strided matrix (C × pixels) of the padded plane, so no patch matrix
/// is built. Outputs are computed on the padded width and the extra columns dropped.
/// Measured on 2 cores (5 images, 3×3, vs candle's conv2d): 0.30× at 128 ch 64×112, 0.36× at 32 ch 256×448,
/// 0.44× at 320 ch (2 images 64×112).
struct ShiftConv {
    padding: usize,
    dilation: usize,
}

impl CustomOp2 for ShiftConv {
    fn name(&self) -> &'static str {
        "shift-conv2d"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1)?;
        let w = f32_slice(s2, l2)?;
        let (n, c, h, wd) = l1.shape().dims4()?;
        let (co, _, kh, kw) = l2.shape().dims4()?;
        let geo = ShiftGeometry::new((n, c, h, wd), (co, kh, kw), self.padding, self.dilation, 1)?;
        let out = shift_conv_raw(x, w, &geo, &RawEpilogue::default());
        Ok((CpuStorage::F32(out), Shape::from((n, co, geo.ho, geo.wo))))
    }

    fn bwd(&self, x: &Tensor, w: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (_, _, kh, kw) = w.dims4()?;
        let cpu = |t: &Tensor| t.device().is_cpu() && t.dtype() == candle_core::DType::F32;
        if cpu(x) && cpu(w) && cpu(grad) && kh == kw && self.dilation * (kh - 1) >= self.padding {
            return shift_conv_backward(x, w, grad, self.padding, self.dilation).map(|(a, b)| (Some(a), Some(b)));
        }
        // Stride 1: the transposed convolution needs no output padding.
        let grad_x = grad.conv_transpose2d(w, self.padding, 0, 1, self.dilation)?;
        let grad_w = x.transpose(0, 1)?.conv2d(&grad.transpose(0, 1)?, self.padding, self.dilation, 1, 1)?.transpose(0, 1)?;
        let (_, _, kh, kw) = w.dims4()?;
        let grad_w = grad_w.narrow(2, 0, kh)?.narrow(3, 0, kw)?;
        Ok((Some(grad_x), Some(grad_w)))
    }
}

/// Backward of the stride-1 convolution with shifted gemms (candle's `conv_transpose2d` and its conv2d with a
/// whole feature map as kernel take ~10× the forward's time on CPU):
/// grad_x = the same convolution of `grad` with the flipped, transposed kernel and padding `dil·(k−1) − pad`;
/// grad_w[:, :, ky, kx] = Σ_images G · X_(ky,kx)ᵀ, G = grad laid out on the padded width (zeros beyond the
/// output width) and X_(ky,kx) the padded input shifted by the tap, a plain strided matrix.
fn shift_conv_backward(x: &Tensor, w: &Tensor, grad: &Tensor, pad: usize, dil: usize) -> Result<(Tensor, Tensor)> {
    let (n, c, h, wd) = x.dims4()?;
    let (co, _, kh, kw) = w.dims4()?;
    let g = ShiftGeometry::new((n, c, h, wd), (co, kh, kw), pad, dil, 1)?;
    let (ho, wo) = (g.ho, g.wo);
    let gv = grad.contiguous()?.flatten_all()?.to_vec1::<f32>()?;
    let xv = x.contiguous()?.flatten_all()?.to_vec1::<f32>()?;
    let wv = w.contiguous()?.flatten_all()?.to_vec1::<f32>()?;
    // grad_x: flipped kernel, (C, Co, kh, kw).
    let mut wf = vec![0f32; wv.len()];
    for o in 0..co {
        for ci in 0..c {
            for ky in 0..kh {
                for kx in 0..kw {
                    wf[((ci * co + o) * kh + ky) * kw + kx] = wv[((o * c + ci) * kh + (kh - 1 - ky)) * kw + (kw - 1 - kx)];
                }
            }
        }
    }
    let gx_geo = ShiftGeometry::new((n, co, ho, wo), (c, kh, kw), dil * (kh - 1) - pad, dil, 1)?;
    let gx = shift_conv_raw(&gv, &wf, &gx_geo, &RawEpilogue::default());
    // grad_w
    let (hp, wp) = (h + 2 * pad, wd + 2 * pad);
    let extra = dil * (kw - 1);
    let plane = hp * wp + extra;
    let l = ho * wp;
    let taps = kh * kw;
    let mut gw_taps = vec![0f32; taps * co * c];
    let mut xpad = vec![0f32; c * plane];
    let mut gpad = vec![0f32; co * l];
    let threads = rayon::current_num_threads();
    for b in 0..n {
        xpad.par_chunks_mut(plane).enumerate().for_each(|(ci, dst)| {
            let src = &xv[(b * c + ci) * h * wd..][..h * wd];
            for y in 0..h {
                dst[(y + pad) * wp + pad..][..wd].copy_from_slice(&src[y * wd..][..wd]);
            }
        });
        gpad.par_chunks_mut(l).enumerate().for_each(|(o, dst)| {
            let src = &gv[(b * co + o) * ho * wo..][..ho * wo];
            for y in 0..ho {
                dst[y * wp..][..wo].copy_from_slice(&src[y * wo..][..wo]);
            }
        });
        for ky in 0..kh {
            for kx in 0..kw {
                let off = dil * (ky * wp + kx);
                let dst = &mut gw_taps[(ky * kw + kx) * co * c..][..co * c];
                // SAFETY: dst is co × c (row stride c); lhs gpad is co × l (row stride l); rhs[j, ci] =
                // xpad[ci·plane + off + j] with off + l ≤ plane: the last tap's overrun of the padded plane is
                // covered by `extra`, and it multiplies only the zero columns (x ≥ wo) of gpad.
                unsafe {
                    gemm::gemm(
                        co,
                        c,
                        l,
                        dst.as_mut_ptr(),
                        1,
                        c as isize,
                        b > 0,
                        gpad.as_ptr(),
                        1,
                        l as isize,
                        xpad.as_ptr().add(off),
                        plane as isize,
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
        }
    }
    let mut gw = vec![0f32; co * c * taps];
    for t in 0..taps {
        for o in 0..co {
            for ci in 0..c {
                gw[(o * c + ci) * taps + t] = gw_taps[(t * co + o) * c + ci];
            }
        }
    }
    Ok((Tensor::from_vec(gx, (n, c, h, wd), x.device())?, Tensor::from_vec(gw, (co, c, kh, kw), w.device())?))
}

/// Shapes of a stride-1 shifted-gemm convolution, optionally on the nearest-×`up` upsampled input.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ShiftGeometry {
    pub(crate) n: usize,
    pub(crate) c: usize,
    pub(crate) h: usize,
    pub(crate) w: usize,
    pub(crate) co: usize,
    pub(crate) kh: usize,
    pub(crate) kw: usize,
    pub(crate) pad: usize,
    pub(crate) dil: usize,
    pub(crate) up: usize,
    /// padded (upsampled) width, output size
    pub(crate) wp: usize,
    pub(crate) ho: usize,
    pub(crate) wo: usize,
}

impl ShiftGeometry {
    pub(crate) fn new((n, c, h, w): (usize, usize, usize, usize), (co, kh, kw): (usize, usize, usize), pad: usize, dil: usize, up: usize) -> Result<Self> {
        let (hi, wi) = (h * up, w * up);
        let (eh, ew) = (dil * (kh - 1) + 1, dil * (kw - 1) + 1);
        if hi + 2 * pad < eh || wi + 2 * pad < ew {
            candle_core::bail!("conv2d: kernel {kh}x{kw} larger than padded input {hi}x{wi}");
        }
        let wp = wi + 2 * pad;
        Ok(Self { n, c, h, w, co, kh, kw, pad, dil, up, wp, ho: hi + 2 * pad - eh + 1, wo: wp - ew + 1 })
    }
}

/// `out = residual + scale·(conv + bias[o] + item_bias[b, o])` applied while copying the result out.
#[derive(Default)]
pub(crate) struct RawEpilogue<'a> {
    pub(crate) bias: Option<&'a [f32]>,
    pub(crate) item_bias: Option<&'a [f32]>,
    pub(crate) residual: Option<&'a [f32]>,
    pub(crate) scale: Option<f32>,
}

#[derive(Clone, Copy)]
pub(crate) struct OutPtr(pub(crate) *mut f32);
// SAFETY: tasks write disjoint output rows.
unsafe impl Send for OutPtr {}
unsafe impl Sync for OutPtr {}

/// Stride-1 conv as kh·kw gemms over shifted views of a zero-padded, channel-major copy of several
/// images (or row bands of one large image) side by side, so each tap is one wide gemm even for small
/// feature maps; the buffers stay ≈ 96 MiB.
fn shift_conv_raw(x: &[f32], w: &[f32], g: &ShiftGeometry, epi: &RawEpilogue) -> Vec<f32> {
    shift_conv_budget(x, w, g, epi, 24 << 20)
}

/// [`shift_conv_raw`] with `budget` floats for the padded + wide buffers (small in tests to force bands).
fn shift_conv_budget(x: &[f32], w: &[f32], g: &ShiftGeometry, epi: &RawEpilogue, budget: usize) -> Vec<f32> {
    let ShiftGeometry { n, c, h, w: wd, co, kh, kw, pad, dil, up, wp, ho, wo } = *g;
    let halo = dil * (kh - 1);
    let (hi, wi) = (h * up, wd * up);
    #[allow(non_snake_case)]
    let BUDGET = budget;
    let per_row = (c + co) * wp;
    let band = if (ho + halo) * per_row <= BUDGET { ho } else { (BUDGET / per_row).saturating_sub(halo).max(1).min(ho) };
    let bands = ho.div_ceil(band);
    let slot = (band + halo) * wp;
    let pieces = n * bands;
    let per = (BUDGET / ((c + co) * slot)).clamp(1, pieces);
    let mut out = vec![0f32; n * co * ho * wo];
    let optr = OutPtr(out.as_mut_ptr());
    let mut padded = vec![0f32; c * per * slot];
    let mut wide = vec![0f32; co * per * slot];
    let threads = rayon::current_num_threads();
    let mut p0 = 0;
    while p0 < pieces {
        let np = per.min(pieces - p0);
        let row_len = per * slot;
        // Fill: padded[ci, p·slot + r·wp + xx] = input (upsampled) at row y0 + r − pad, col xx − pad, or 0.
        padded.par_chunks_mut(row_len).enumerate().for_each(|(ci, dst)| {
            for p in 0..np {
                let (b, bi) = ((p0 + p) / bands, (p0 + p) % bands);
                let y0 = bi * band;
                let src = &x[(b * c + ci) * h * wd..][..h * wd];
                for r in 0..band + halo {
                    let row = &mut dst[p * slot + r * wp..][..wp];
                    let yy = (y0 + r) as isize - pad as isize;
                    if yy < 0 || yy as usize >= hi {
                        row.fill(0.0);
                        continue;
                    }
                    row[..pad].fill(0.0);
                    row[pad + wi..].fill(0.0);
                    let srow = &src[(yy as usize / up) * wd..][..wd];
                    if up == 1 {
                        row[pad..pad + wi].copy_from_slice(srow);
                    } else {
                        for (xx, v) in row[pad..pad + wi].iter_mut().enumerate() {
                            *v = srow[xx / up];
                        }
                    }
                }
            }
        });
        let ncols = (np - 1) * slot + (band - 1) * wp + wo;
        for ky in 0..kh {
            for kx in 0..kw {
                let shift = dil * (ky * wp + kx);
                // SAFETY: dst is co × ncols with row stride row_len ≥ ncols; lhs reads w[o, ci, ky, kx];
                // rhs reads padded[ci·row_len + shift + j] for j < ncols and shift + ncols ≤ np·slot.
                unsafe {
                    gemm::gemm(
                        co,
                        ncols,
                        c,
                        wide.as_mut_ptr(),
                        1,
                        row_len as isize,
                        !(ky == 0 && kx == 0),
                        w.as_ptr().add(ky * kw + kx),
                        (kh * kw) as isize,
                        (c * kh * kw) as isize,
                        padded.as_ptr().add(shift),
                        1,
                        row_len as isize,
                        1.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::Rayon(threads),
                    );
                }
            }
        }
        wide.par_chunks(row_len).enumerate().for_each(|(o, wrow)| {
            let optr = optr;
            for p in 0..np {
                let (b, bi) = ((p0 + p) / bands, (p0 + p) % bands);
                let y0 = bi * band;
                let rows = band.min(ho - y0);
                let add = epi.bias.map_or(0.0, |bv| bv[o]) + epi.item_bias.map_or(0.0, |ib| ib[b * co + o]);
                let plane = (b * co + o) * ho * wo;
                for r in 0..rows {
                    let y = y0 + r;
                    let src = &wrow[p * slot + r * wp..][..wo];
                    // SAFETY: output row (b, o, y) is written by this task only.
                    let dst = unsafe { std::slice::from_raw_parts_mut(optr.0.add(plane + y * wo), wo) };
                    epilogue_row(dst, src, add, epi.scale, epi.residual.map(|res| &res[plane + y * wo..][..wo]));
                }
            }
        });
        p0 += np;
    }
    out
}

pub(crate) fn epilogue_row(dst: &mut [f32], src: &[f32], add: f32, scale: Option<f32>, res: Option<&[f32]>) {
    match (scale, res) {
        (None, None) => dst.iter_mut().zip(src).for_each(|(d, &s)| *d = s + add),
        (None, Some(r)) => dst.iter_mut().zip(src).zip(r).for_each(|((d, &s), &r)| *d = s + add + r),
        (Some(k), None) => dst.iter_mut().zip(src).for_each(|(d, &s)| *d = k * (s + add)),
        (Some(k), Some(r)) => dst.iter_mut().zip(src).zip(r).for_each(|((d, &s), &r)| *d = k * (s + add) + r),
    }
}

/// What [`conv2d_fused`] adds to the convolution: `residual + scale·(conv + bias + item_bias)`.
#[derive(Debug, Clone, Copy, Default)]
pub struct ConvEpilogue<'a> {
    /// (N, Co): one extra bias per image and channel (e.g. a time embedding).
    pub item_bias: Option<&'a Tensor>,
    /// Same shape as the output.
    pub residual: Option<&'a Tensor>,
    /// Multiplies conv + biases (not the residual); None = 1.
    pub scale: Option<f32>,
    /// Nearest-neighbour ×2 upsampling of the input first (fused into the padded copy).
    pub upsample2x: bool,
}

pub(crate) fn with_f32_opt<R>(t: Option<&Tensor>, f: impl FnOnce(Option<&[f32]>) -> Result<R>) -> Result<R> {
    match t {
        None => f(None),
        Some(t) => {
            let t = t.contiguous()?;
            let (st, l) = t.storage_and_layout();
            match (&*st, l.contiguous_offsets()) {
                (candle_core::Storage::Cpu(CpuStorage::F32(v)), Some((a, b))) => f(Some(&v[a..b])),
                _ => candle_core::bail!("conv2d_fused: expected CPU f32 tensors"),
            }
        }
    }
}

/// [`conv2d_fused`] from tensor ops (records a backward); `candle_conv` forces candle's conv2d on the CPU too.
pub(crate) fn conv2d_fused_composed(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, cfg: Conv2dConfig, epi: ConvEpilogue, candle_conv: bool) -> Result<Tensor> {
    let (n, _, h, wd) = x.dims4()?;
    let co = w.dim(0)?;
    let x = if epi.upsample2x { x.upsample_nearest2d(2 * h, 2 * wd)? } else { x.clone() };
    let mut y = if candle_conv { conv2d_candle(&x, w, bias, cfg)? } else { conv2d(&x, w, bias, cfg)? };
    if let Some(ib) = epi.item_bias {
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

/// Inference-only conv2d (no backward) with the epilogue fused into the output copy. Stride-1 CPU f32
/// convolutions run on the batched shifted-gemm kernel; anything else through [`conv2d`] and tensor ops.
pub fn conv2d_fused(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, cfg: Conv2dConfig, epi: ConvEpilogue) -> Result<Tensor> {
    let (n, c, h, wd) = x.dims4()?;
    let (co, ci, kh, kw) = w.dims4()?;
    if ci != c {
        candle_core::bail!("conv2d: input has {c} channels, weight expects {ci}");
    }
    if cudnn_applies(x, &[Some(w), bias, epi.item_bias, epi.residual]) {
        let x = if epi.upsample2x { x.upsample_nearest2d(2 * h, 2 * wd)? } else { x.clone() };
        let scale = epi.scale.unwrap_or(1.0);
        if let Some(y) = cudnn::conv2d(&x, w, bias, epi.residual, scale, cfg) {
            return add_item_bias(y, epi.item_bias, scale);
        }
    }
    if !cpu_f32(x) || cfg.stride != 1 {
        return conv2d_fused_composed(x, w, bias, cfg, epi, false);
    }
    let geo = ShiftGeometry::new((n, c, h, wd), (co, kh, kw), cfg.padding, cfg.dilation, if epi.upsample2x { 2 } else { 1 })?;
    if let Some(r) = epi.residual {
        if r.dims() != [n, co, geo.ho, geo.wo] {
            candle_core::bail!("conv2d_fused: residual {:?}, output {:?}", r.dims(), [n, co, geo.ho, geo.wo]);
        }
    }
    if let Some(ib) = epi.item_bias {
        if ib.elem_count() != n * co {
            candle_core::bail!("conv2d_fused: item bias {:?}, expected ({n}, {co})", ib.dims());
        }
    }
    let x = x.contiguous()?;
    let w = w.contiguous()?;
    let out = with_f32_opt(Some(&x), |xd| {
        with_f32_opt(Some(&w), |wdat| {
            with_f32_opt(bias, |bd| {
                with_f32_opt(epi.item_bias, |ibd| {
                    with_f32_opt(epi.residual, |rd| {
                        let e = RawEpilogue { bias: bd, item_bias: ibd, residual: rd, scale: epi.scale };
                        Ok(shift_conv_raw(xd.unwrap_or(&[]), wdat.unwrap_or(&[]), &geo, &e))
                    })
                })
            })
        })
    })?;
    Tensor::from_vec(out, (n, co, geo.ho, geo.wo), x.device())
}

/// [`conv2d`] for stride 1 through [`ShiftConv`] (CPU f32 only: [`crate::NotBuilt`] elsewhere).
pub fn conv2d_shift(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, cfg: Conv2dConfig) -> Result<Tensor> {
    crate::mode::require_cpu("conv2d_shift", x)?;
    if cfg.stride != 1 {
        candle_core::bail!("conv2d_shift: stride must be 1, got {}", cfg.stride);
    }
    let (_, c, _, _) = x.dims4()?;
    let (_, ci, _, _) = w.dims4()?;
    if ci != c {
        candle_core::bail!("conv2d: input has {c} channels, weight expects {ci}");
    }
    let out = x.contiguous()?.apply_op2(&w.contiguous()?, ShiftConv { padding: cfg.padding, dilation: cfg.dilation })?;
    add_bias(out, bias)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Conv2dConfig {
    pub padding: usize,
    pub stride: usize,
    pub dilation: usize,
}

impl Default for Conv2dConfig {
    fn default() -> Self {
        Self { padding: 0, stride: 1, dilation: 1 }
    }
}

/// Images per gemm: bounds the im2col buffer (≈ 256 MiB) for large batches such as 14 video frames.
fn images_per_chunk(k: usize, p: usize) -> usize {
    ((64usize << 20) / (k * p).max(1)).max(1)
}

/// `conv2d(x (N,C,H,W), w (Co,C,kh,kw), bias (Co))`, groups = 1, same semantics as candle/PyTorch; picks the
/// faster algorithm for the shape.
pub fn conv2d(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, cfg: Conv2dConfig) -> Result<Tensor> {
    let (_, c, _, _) = x.dims4()?;
    let (_, _, kh, kw) = w.dims4()?;
    // Measured on 2 cores (5 images): stride 1 → shifted gemms (0.3–0.44× candle's time); strided convs →
    // im2col+gemm when K = C·k² ≥ 1024 (0.54× at 2880, 0.72× at 1152), candle's own below (the patch copy
    // dominates there: 0.97–1.28×).
    if cudnn_applies(x, &[Some(w), bias]) {
        if let Some(y) = cudnn::conv2d(x, w, bias, None, 1.0, cfg) {
            return Ok(y);
        }
    }
    let pointwise = kh == 1 && kw == 1 && cfg.stride == 1 && cfg.padding == 0;
    let cpu_f32 = cpu_f32(x);
    if cpu_f32 && cfg.stride == 1 && !pointwise {
        conv2d_shift(x, w, bias, cfg)
    } else if cpu_f32 && (pointwise || c * kh * kw >= 1024) {
        conv2d_gemm(x, w, bias, cfg)
    } else {
        conv2d_candle(x, w, bias, cfg)
    }
}

/// candle's own conv2d plus bias: the path of every non-CPU device.
pub(crate) fn conv2d_candle(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, cfg: Conv2dConfig) -> Result<Tensor> {
    add_bias(x.conv2d(w, cfg.padding, cfg.stride, cfg.dilation, 1)?, bias)
}

/// `out (N, C, H, W) + bias (C)` (no-op without a bias), with a parallel backward for the bias on CPU f32.
pub fn add_bias(out: Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    match bias {
        Some(b) if cpu_f32(&out) && cpu_f32(b) => out.contiguous()?.apply_op2(&b.contiguous()?, ChannelBias),
        Some(b) => out.broadcast_add(&b.reshape((1, (), 1, 1))?),
        None => Ok(out),
    }
}

/// `x (N, C, H, W) + b (C)` on CPU f32. Its backward sums the gradient per channel in parallel: candle's
/// backward of `broadcast_add` reduces over (N, H, W) on one thread with strided reads, which was ≈ 8 % of an
/// encoder training step (the biases of full-resolution convs).
struct ChannelBias;

impl CustomOp2 for ChannelBias {
    fn name(&self) -> &'static str {
        "channel-bias"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1)?;
        let b = f32_slice(s2, l2)?;
        let (_, c, h, w) = l1.shape().dims4()?;
        if b.len() != c {
            candle_core::bail!("conv2d: bias has {} entries for {c} output channels", b.len());
        }
        let plane = h * w;
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(plane).zip(x.par_chunks(plane)).enumerate().for_each(|(i, (dst, src))| {
            let bc = b[i % c];
            dst.iter_mut().zip(src).for_each(|(d, &v)| *d = v + bc);
        });
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(&self, _x: &Tensor, b: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (n, c, h, w) = grad.dims4()?;
        let plane = h * w;
        let sums = with_f32(grad, |g| {
            (0..c)
                .into_par_iter()
                .map(|ch| (0..n).map(|i| g[(i * c + ch) * plane..][..plane].iter().map(|&v| v as f64).sum::<f64>()).sum::<f64>() as f32)
                .collect::<Vec<f32>>()
        })?;
        Ok((Some(grad.clone()), Some(Tensor::from_vec(sums, b.shape(), b.device())?)))
    }
}

/// [`conv2d`] always through im2col + gemm (CPU f32 only: [`crate::NotBuilt`] elsewhere).
pub fn conv2d_gemm(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, cfg: Conv2dConfig) -> Result<Tensor> {
    crate::mode::require_cpu("conv2d_gemm", x)?;
    let (n, c, h, wd) = x.dims4()?;
    let (co, ci, kh, kw) = w.dims4()?;
    if ci != c {
        candle_core::bail!("conv2d: input has {c} channels, weight expects {ci}");
    }
    let g = Geometry::new(c, h, wd, kh, kw, cfg.stride, cfg.padding, cfg.dilation)?;
    let wm = w.reshape((co, g.k()))?;
    let x = x.contiguous()?;
    let pointwise = kh == 1 && kw == 1 && cfg.stride == 1 && cfg.padding == 0;
    let wt = if pointwise { wm.clone() } else { wm.t()? };
    let run = |xb: &Tensor| -> Result<Tensor> {
        let nb = xb.dim(0)?;
        if pointwise {
            // Already a gemm on the NCHW layout; no copy needed.
            return wt.broadcast_left(nb)?.matmul(&xb.reshape((nb, c, h * wd))?)?.reshape((nb, co, g.ho, g.wo));
        }
        let cols = xb.apply_op1(Im2Col(g))?.reshape((nb * g.p(), g.k()))?;
        cols.matmul(&wt)?.reshape((nb, g.ho, g.wo, co))?.permute((0, 3, 1, 2))?.contiguous()
    };
    let per = images_per_chunk(g.k(), g.p());
    let out = if n <= per {
        run(&x)?
    } else {
        let parts = (0..n).step_by(per).map(|s| run(&x.narrow(0, s, per.min(n - s))?)).collect::<Result<Vec<_>>>()?;
        Tensor::cat(&parts, 0)?
    };
    add_bias(out, bias)
}

/// Drop-in for `candle_nn::Conv2d` (same `weight`/`bias` keys), using [`conv2d`].
#[derive(Debug, Clone)]
pub struct Conv2d {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
    pub cfg: Conv2dConfig,
}

impl Conv2d {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, k: usize, cfg: Conv2dConfig, bias: bool) -> Result<Self> {
        let weight = vb.get((c_out, c_in, k, k), "weight")?;
        let bias = if bias { Some(vb.get(c_out, "bias")?) } else { None };
        Ok(Self { weight, bias, cfg })
    }
}

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        conv2d(x, &self.weight, self.bias.as_ref(), self.cfg)
    }
}

/// Conv2d (groups 1) followed by `residual + scale·(conv + bias + item_bias)` on an optionally nearest-×2
/// upsampled input: the fused inference kernel normally, differentiable ops in differentiable mode.
pub fn conv2d_epilogue(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, cfg: Conv2dConfig, epi: ConvEpilogue) -> Result<Tensor> {
    if is_differentiable() {
        return conv2d_fused_composed(x, w, bias, cfg, epi, false);
    }
    if cfg.stride == 1 || epi.item_bias.is_some() || epi.residual.is_some() || epi.upsample2x {
        return conv2d_fused(x, w, bias, cfg, epi);
    }
    conv2d(x, w, bias, cfg)
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
    if cudnn_applies(x, &[Some(w), Some(bias), item_bias, residual]) {
        if let Some(y) = cudnn::temporal(x, w, bias, kt, frames, residual, scale) {
            return add_item_bias(y, item_bias, scale);
        }
    }
    if !is_cpu_f32(x) {
        return temporal_conv_composed(x, w, bias, kt, frames, item_bias, residual, scale);
    }
    let bv = bias.to_vec1::<f32>()?;
    let ib = match item_bias {
        Some(t) => Some(t.flatten_all()?.to_vec1::<f32>()?),
        None => None,
    };
    if let Some(r) = residual {
        if r.elem_count() != n * co * s {
            candle_core::bail!("temporal conv: residual has {} elements, output {}", r.elem_count(), n * co * s);
        }
    }
    let mut dst = with_f32_opt(residual, |rd| Ok(temporal_dst((n, co, s), &bv, ib.as_deref(), rd, scale)))?;
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
                        co,
                        s,
                        (k1 - k0) * c,
                        d.as_mut_ptr(),
                        1,
                        s as isize,
                        true,
                        wd.as_ptr().add(k0 * c),
                        1,
                        (kt * c) as isize,
                        xd.as_ptr().add(first * c * s),
                        1,
                        s as isize,
                        1.0,
                        scale,
                        false,
                        false,
                        false,
                        par,
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

/// The temporal convolutions' destination before their products accumulate into it: for output row (item, o)
/// of `s` values, `residual + scale·(bias[o] + item_bias[item, o])`.
pub(crate) fn temporal_dst((n, co, s): (usize, usize, usize), bias: &[f32], item_bias: Option<&[f32]>, residual: Option<&[f32]>, scale: f32) -> Vec<f32> {
    let mut dst = vec![0f32; n * co * s];
    dst.par_chunks_mut(s.max(1)).enumerate().for_each(|(row, d)| {
        let (item, o) = (row / co, row % co);
        let add = scale * (bias[o] + item_bias.map_or(0.0, |v| v[item * co + o]));
        match residual {
            Some(r) => d.iter_mut().zip(&r[row * s..][..s]).for_each(|(v, &r)| *v = r + add),
            None => d.fill(add),
        }
    });
    dst
}

/// [`temporal_conv`] from tensor ops (records a backward): one matmul per output frame.
#[allow(clippy::too_many_arguments)]
pub(crate) fn temporal_conv_composed(
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
    let co = w.dim(0)?;
    let (s, pad) = (h * wd, kt / 2);
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
    Ok(y)
}

#[cfg(test)]
mod fused_tests {
    use super::*;
    use candle_core::{Device, Tensor};

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    #[test]
    fn fused_conv_matches_candle_with_epilogue_upsample_and_bands() {
        let dev = Device::Cpu;
        let (n, c, co, h, w) = (3, 5, 7, 9, 11);
        let x = Tensor::randn(0f32, 1.0, (n, c, h, w), &dev).unwrap();
        let wt = Tensor::randn(0f32, 0.3, (co, c, 3, 3), &dev).unwrap();
        let b = Tensor::randn(0f32, 0.3, co, &dev).unwrap();
        let ib = Tensor::randn(0f32, 0.3, (n, co), &dev).unwrap();
        for (up, pad, dil) in [(false, 1, 1), (true, 1, 1), (false, 2, 2), (false, 0, 1)] {
            let xin = if up { x.upsample_nearest2d(2 * h, 2 * w).unwrap() } else { x.clone() };
            let plain = xin.conv2d(&wt, pad, 1, dil, 1).unwrap().broadcast_add(&b.reshape((1, co, 1, 1)).unwrap()).unwrap();
            let res = Tensor::randn(0f32, 1.0, plain.dims(), &dev).unwrap();
            let want = ((plain.broadcast_add(&ib.reshape((n, co, 1, 1)).unwrap()).unwrap() * 0.25).unwrap() + &res).unwrap();
            let cfg = Conv2dConfig { padding: pad, stride: 1, dilation: dil };
            let epi = ConvEpilogue { item_bias: Some(&ib), residual: Some(&res), scale: Some(0.25), upsample2x: up };
            let got = conv2d_fused(&x, &wt, Some(&b), cfg, epi).unwrap();
            assert!(max_diff(&got, &want) < 1e-4, "up {up} pad {pad} dil {dil}: {}", max_diff(&got, &want));
            // Tiny buffer budget: one row band at a time, several bands per image.
            let geo = ShiftGeometry::new((n, c, h, w), (co, 3, 3), pad, dil, if up { 2 } else { 1 }).unwrap();
            let xv = x.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let wv = wt.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let banded = shift_conv_budget(&xv, &wv, &geo, &RawEpilogue::default(), (c + co) * geo.wp * (2 + 2 * dil));
            let banded = Tensor::from_vec(banded, plain.dims(), &dev).unwrap();
            let plain_nb = xin.conv2d(&wt, pad, 1, dil, 1).unwrap();
            assert!(max_diff(&banded, &plain_nb) < 1e-4, "banded up {up} pad {pad}: {}", max_diff(&banded, &plain_nb));
        }
    }
}
