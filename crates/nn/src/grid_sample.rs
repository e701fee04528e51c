//! `F.grid_sample(input, grid, mode="bilinear", padding_mode="zeros", align_corners=True)` (candle has none), a
//! custom op with backward for the input and the grid on CPU f32; other devices gather the 4 taps with
//! candle ops (differentiable the same way).
//!
//! The 4 taps of every output point are computed once per image and shared by all channels; each (image,
//! channel) plane is then a cache-resident gather, run in parallel with rayon.

use candle_core::{CpuStorage, CustomOp2, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Bilinear taps of one sample point: flat indices into an `Hi×Wi` plane and their weights (0 outside).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Taps {
    pub(crate) idx: [u32; 4],
    pub(crate) w: [f32; 4],
}

/// Pixel coordinate of a normalised grid value with `align_corners=True`.
#[inline]
pub(crate) fn unnormalize(g: f32, size: usize) -> f32 {
    (g + 1.0) * 0.5 * (size as f32 - 1.0)
}

#[inline]
pub(crate) fn taps_at(ix: f32, iy: f32, hi: usize, wi: usize) -> Taps {
    let x0 = ix.floor();
    let y0 = iy.floor();
    let fx = ix - x0;
    let fy = iy - y0;
    let (x0, y0) = (x0 as i64, y0 as i64);
    let corners = [(x0, y0, (1.0 - fx) * (1.0 - fy)), (x0 + 1, y0, fx * (1.0 - fy)), (x0, y0 + 1, (1.0 - fx) * fy), (x0 + 1, y0 + 1, fx * fy)];
    let mut t = Taps::default();
    for (k, &(x, y, w)) in corners.iter().enumerate() {
        // NaN/inf coordinates fall through as out of bounds (zero contribution).
        if x >= 0 && y >= 0 && (x as usize) < wi && (y as usize) < hi && w.is_finite() {
            t.idx[k] = (y as usize * wi + x as usize) as u32;
            t.w[k] = w;
        }
    }
    t
}

#[derive(Debug, Clone, Copy)]
struct Dims {
    n: usize,
    c: usize,
    hi: usize,
    wi: usize,
    ho: usize,
    wo: usize,
}

fn check(input: &Tensor, grid: &Tensor) -> Result<Dims> {
    let (n, c, hi, wi) = input.dims4()?;
    let (ng, ho, wo, two) = grid.dims4()?;
    if ng != n || two != 2 {
        candle_core::bail!("grid_sample: input {:?} needs grid [N={n},Ho,Wo,2], got {:?}", input.dims(), grid.dims());
    }
    if hi * wi > u32::MAX as usize {
        candle_core::bail!("grid_sample: input plane {hi}x{wi} too large");
    }
    Ok(Dims { n, c, hi, wi, ho, wo })
}

fn contiguous_f32<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    crate::mode::f32_slice(s, l, &format!("grid_sample {what}"))
}

fn all_taps(grid: &[f32], d: Dims) -> Vec<Taps> {
    let p = d.ho * d.wo;
    let mut taps = vec![Taps::default(); d.n * p];
    taps.par_chunks_mut(p.max(1)).enumerate().for_each(|(ni, row)| {
        let g = &grid[ni * p * 2..(ni + 1) * p * 2];
        for (i, t) in row.iter_mut().enumerate() {
            *t = taps_at(unnormalize(g[2 * i], d.wi), unnormalize(g[2 * i + 1], d.hi), d.hi, d.wi);
        }
    });
    taps
}

struct GridSample;

impl CustomOp2 for GridSample {
    fn name(&self) -> &'static str {
        "grid_sample_bilinear_zeros_align_corners"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, c, hi, wi) = l1.shape().dims4()?;
        let (_, ho, wo, _) = l2.shape().dims4()?;
        let d = Dims { n, c, hi, wi, ho, wo };
        let input = contiguous_f32(s1, l1, "input")?;
        let grid = contiguous_f32(s2, l2, "grid")?;
        let taps = all_taps(grid, d);
        let p = ho * wo;
        let plane_in = hi * wi;
        let mut out = vec![0f32; n * c * p];
        out.par_chunks_mut(p.max(1)).enumerate().for_each(|(nc, o)| {
            let ni = nc / c.max(1);
            let src = &input[nc * plane_in..(nc + 1) * plane_in];
            let tp = &taps[ni * p..(ni + 1) * p];
            for (y, t) in o.iter_mut().zip(tp) {
                *y = t.w[0] * src[t.idx[0] as usize] + t.w[1] * src[t.idx[1] as usize] + t.w[2] * src[t.idx[2] as usize] + t.w[3] * src[t.idx[3] as usize];
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((n, c, ho, wo))))
    }

    fn bwd(&self, input: &Tensor, grid: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (gi, gg) = grid_sample_backward(input, grid, grad_res)?;
        Ok((Some(gi), Some(gg)))
    }
}

/// Gradients of [`grid_sample`] w.r.t. input `[N,C,Hi,Wi]` and grid `[N,Ho,Wo,2]` (not differentiable itself).
fn grid_sample_backward(input: &Tensor, grid: &Tensor, grad_out: &Tensor) -> Result<(Tensor, Tensor)> {
    let d = check(input, grid)?;
    let dev = input.device();
    let inp = input.flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()?;
    let grd = grid.flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()?;
    let go = grad_out.flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()?;
    let taps = all_taps(&grd, d);
    let p = d.ho * d.wo;
    let plane_in = d.hi * d.wi;

    // Input gradient: each (image, channel) plane scatters only into itself, so planes run in parallel.
    let mut gin = vec![0f32; d.n * d.c * plane_in];
    gin.par_chunks_mut(plane_in.max(1)).enumerate().for_each(|(nc, gplane)| {
        let ni = nc / d.c.max(1);
        let g = &go[nc * p..(nc + 1) * p];
        let tp = &taps[ni * p..(ni + 1) * p];
        for (&gv, t) in g.iter().zip(tp) {
            for k in 0..4 {
                gplane[t.idx[k] as usize] += t.w[k] * gv;
            }
        }
    });

    // Grid gradient: d out / d ix = Σ_y-rows wy·(v(x0+1) − v(x0)), likewise for iy; chain with (size−1)/2.
    let mut ggrid = vec![0f32; d.n * p * 2];
    let sx = (d.wi as f32 - 1.0) * 0.5;
    let sy = (d.hi as f32 - 1.0) * 0.5;
    ggrid.par_chunks_mut(d.wo * 2).enumerate().for_each(|(row, gg)| {
        let ni = row / d.ho.max(1);
        for xo in 0..d.wo {
            let pi = (row % d.ho.max(1)) * d.wo + xo;
            let gx = grd[(ni * p + pi) * 2];
            let gy = grd[(ni * p + pi) * 2 + 1];
            let ix = unnormalize(gx, d.wi);
            let iy = unnormalize(gy, d.hi);
            if !ix.is_finite() || !iy.is_finite() {
                continue;
            }
            let x0 = ix.floor();
            let y0 = iy.floor();
            let fx = ix - x0;
            let fy = iy - y0;
            let (x0, y0) = (x0 as i64, y0 as i64);
            let inb = |x: i64, y: i64| x >= 0 && y >= 0 && (x as usize) < d.wi && (y as usize) < d.hi;
            let off = |x: i64, y: i64| if inb(x, y) { Some(y as usize * d.wi + x as usize) } else { None };
            let (o00, o10, o01, o11) = (off(x0, y0), off(x0 + 1, y0), off(x0, y0 + 1), off(x0 + 1, y0 + 1));
            let (mut dx, mut dy) = (0f32, 0f32);
            for ci in 0..d.c {
                let plane = &inp[(ni * d.c + ci) * plane_in..(ni * d.c + ci + 1) * plane_in];
                let v = |o: Option<usize>| o.map_or(0.0, |o| plane[o]);
                let (v00, v10, v01, v11) = (v(o00), v(o10), v(o01), v(o11));
                let g = go[(ni * d.c + ci) * p + pi];
                dx += g * ((v10 - v00) * (1.0 - fy) + (v11 - v01) * fy);
                dy += g * ((v01 - v00) * (1.0 - fx) + (v11 - v10) * fx);
            }
            gg[2 * xo] = dx * sx;
            gg[2 * xo + 1] = dy * sy;
        }
    });
    Ok((
        Tensor::from_vec(gin, (d.n, d.c, d.hi, d.wi), dev)?.to_dtype(input.dtype())?,
        Tensor::from_vec(ggrid, (d.n, d.ho, d.wo, 2), dev)?.to_dtype(grid.dtype())?,
    ))
}

/// Bilinear sampling of `input [N,C,Hi,Wi]` at `grid [N,Ho,Wo,2]` (x, y in [-1,1], align_corners=True; points
/// outside read zeros) → `[N,C,Ho,Wo]`. Differentiable w.r.t. both arguments.
pub fn grid_sample(input: &Tensor, grid: &Tensor) -> Result<Tensor> {
    check(input, grid)?;
    if !(crate::mode::cpu_f32(input) && crate::mode::cpu_f32(grid)) {
        return grid_sample_composed(input, grid);
    }
    input.contiguous()?.apply_op2(&grid.contiguous()?, GridSample)
}

/// [`grid_sample`] from candle ops: per corner, a `gather` of the flattened planes times its bilinear weight
/// (zero outside the image). The floor is taken on a detached copy, so gradients reach the grid through the
/// fractional parts, as in the kernel's backward.
pub(crate) fn grid_sample_composed(input: &Tensor, grid: &Tensor) -> Result<Tensor> {
    let Dims { n, c, hi, wi, ho, wo } = check(input, grid)?;
    let p = ho * wo;
    let g = grid.reshape((n, p, 2))?;
    let ix = g.narrow(2, 0, 1)?.reshape((n, p))?.affine(0.5, 0.5)?.affine(wi as f64 - 1.0, 0.0)?;
    let iy = g.narrow(2, 1, 1)?.reshape((n, p))?.affine(0.5, 0.5)?.affine(hi as f64 - 1.0, 0.0)?;
    let (x0, y0) = (ix.detach().floor()?, iy.detach().floor()?);
    let (fx, fy) = ((&ix - &x0)?, (&iy - &y0)?);
    let (gx, gy) = (fx.affine(-1.0, 1.0)?, fy.affine(-1.0, 1.0)?);
    let planes = input.reshape((n, c, hi * wi))?;
    let zero = fx.zeros_like()?;
    let mut out: Option<Tensor> = None;
    for (dx, dy, wx, wy) in [(0.0, 0.0, &gx, &gy), (1.0, 0.0, &fx, &gy), (0.0, 1.0, &gx, &fy), (1.0, 1.0, &fx, &fy)] {
        let (xc, yc) = ((&x0 + dx)?, (&y0 + dy)?);
        let inside = xc.ge(0.0)?.mul(&xc.lt(wi as f64)?)?.mul(&yc.ge(0.0)?)?.mul(&yc.lt(hi as f64)?)?;
        let idx = (yc.clamp(0.0, hi as f64 - 1.0)?.affine(wi as f64, 0.0)? + xc.clamp(0.0, wi as f64 - 1.0)?)?;
        let idx = idx.to_dtype(DType::U32)?.unsqueeze(1)?.broadcast_as((n, c, p))?.contiguous()?;
        let w = inside.where_cond(&wx.mul(wy)?, &zero)?.unsqueeze(1)?;
        let term = planes.gather(&idx, 2)?.broadcast_mul(&w)?;
        out = Some(match out {
            None => term,
            Some(o) => (o + term)?,
        });
    }
    out.expect("four corners").reshape((n, c, ho, wo))
}
