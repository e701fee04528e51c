//! Fused plane-sweep correlation: `out[n,d,p] = Σ_c ref[n,c,p] · grid_sample(src, grid)[n,c,d·h+y,x]` for a
//! fixed (gradient-free) sampling grid `[N, D·h, w, 2]`. Equals `(ref.unsqueeze(2) * warped).sum(1)` of the
//! official cost volume without materialising the `[N, C, D, h, w]` warped features (gigabytes at DL3DV size).
//! Backward w.r.t. both feature maps; the grid is a constant, as under the official `torch.no_grad()`. Other
//! devices run that composition itself (grid_sample, product, channel sum).

use std::sync::Arc;

use candle_core::{CpuStorage, CustomOp2, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use crate::grid_sample::{taps_at, unnormalize, Taps};

#[derive(Clone)]
struct WarpCorrelation {
    /// `[N·D·P]` taps into the `h×w` source plane.
    taps: Arc<Vec<Taps>>,
    d: usize,
}

/// `[N, C, P]` → `[N, P, C]` (channels contiguous for the gathers).
fn to_nhwc(x: &[f32], n: usize, c: usize, p: usize) -> Vec<f32> {
    let mut out = vec![0f32; n * p * c];
    out.par_chunks_mut((p * c).max(1)).enumerate().for_each(|(ni, o)| {
        let xs = &x[ni * c * p..(ni + 1) * c * p];
        for ci in 0..c {
            for pi in 0..p {
                o[pi * c + ci] = xs[ci * p + pi];
            }
        }
    });
    out
}

fn from_nhwc(x: &[f32], n: usize, c: usize, p: usize) -> Vec<f32> {
    let mut out = vec![0f32; n * c * p];
    out.par_chunks_mut((c * p).max(1)).enumerate().for_each(|(ni, o)| {
        let xs = &x[ni * p * c..(ni + 1) * p * c];
        for pi in 0..p {
            for ci in 0..c {
                o[ci * p + pi] = xs[pi * c + ci];
            }
        }
    });
    out
}

/// Bilinear sample of one C-vector (the official order: interpolate each channel, then dot).
#[inline]
fn sample_into(buf: &mut [f32], src: &[f32], t: &Taps, c: usize) {
    let rows = [&src[t.idx[0] as usize * c..][..c], &src[t.idx[1] as usize * c..][..c], &src[t.idx[2] as usize * c..][..c], &src[t.idx[3] as usize * c..][..c]];
    for (ci, b) in buf.iter_mut().enumerate() {
        *b = t.w[0] * rows[0][ci] + t.w[1] * rows[1][ci] + t.w[2] * rows[2][ci] + t.w[3] * rows[3][ci];
    }
}

fn slice<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    crate::mode::f32_slice(s, l, &format!("warp_correlation {what}"))
}

impl CustomOp2 for WarpCorrelation {
    fn name(&self) -> &'static str {
        "warp_correlation"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, c, h, w) = l1.shape().dims4()?;
        let p = h * w;
        let d = self.d;
        let r = to_nhwc(slice(s1, l1, "reference features")?, n, c, p);
        let s = to_nhwc(slice(s2, l2, "source features")?, n, c, p);
        let mut out = vec![0f32; n * d * p];
        out.par_chunks_mut(p.max(1)).enumerate().for_each(|(nd, o)| {
            let ni = nd / d.max(1);
            let src = &s[ni * p * c..(ni + 1) * p * c];
            let rf = &r[ni * p * c..(ni + 1) * p * c];
            let taps = &self.taps[nd * p..(nd + 1) * p];
            let mut buf = vec![0f32; c];
            for (pi, (y, t)) in o.iter_mut().zip(taps).enumerate() {
                sample_into(&mut buf, src, t, c);
                *y = buf.iter().zip(&rf[pi * c..(pi + 1) * c]).map(|(a, b)| a * b).sum();
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((n, d, h, w))))
    }

    fn bwd(&self, reference: &Tensor, source: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (n, c, h, w) = reference.dims4()?;
        let p = h * w;
        let d = self.d;
        let flat = |t: &Tensor| -> Result<Vec<f32>> { t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>() };
        let r = to_nhwc(&flat(reference)?, n, c, p);
        let s = to_nhwc(&flat(source)?, n, c, p);
        let go = flat(grad_res)?;
        // d/d ref[n,p,:] = Σ_d go[n,d,p] · sampled(n,d,p)
        let mut gr = vec![0f32; n * p * c];
        gr.par_chunks_mut(c.max(1)).enumerate().for_each(|(np, g)| {
            let (ni, pi) = (np / p.max(1), np % p.max(1));
            let src = &s[ni * p * c..(ni + 1) * p * c];
            let mut buf = vec![0f32; c];
            for di in 0..d {
                let gv = go[(ni * d + di) * p + pi];
                if gv == 0.0 {
                    continue;
                }
                sample_into(&mut buf, src, &self.taps[(ni * d + di) * p + pi], c);
                for (a, b) in g.iter_mut().zip(&buf) {
                    *a += gv * b;
                }
            }
        });
        // d/d src[n,q,:] = Σ over taps hitting q of go·w·ref[n,p,:]; each image scatters into its own slab.
        let mut gs = vec![0f32; n * p * c];
        gs.par_chunks_mut((p * c).max(1)).enumerate().for_each(|(ni, g)| {
            let rf = &r[ni * p * c..(ni + 1) * p * c];
            for di in 0..d {
                for pi in 0..p {
                    let gv = go[(ni * d + di) * p + pi];
                    if gv == 0.0 {
                        continue;
                    }
                    let t = &self.taps[(ni * d + di) * p + pi];
                    let rv = &rf[pi * c..(pi + 1) * c];
                    for k in 0..4 {
                        let wk = t.w[k] * gv;
                        if wk != 0.0 {
                            let dst = &mut g[t.idx[k] as usize * c..(t.idx[k] as usize + 1) * c];
                            for (a, b) in dst.iter_mut().zip(rv) {
                                *a += wk * b;
                            }
                        }
                    }
                }
            }
        });
        let dev = reference.device();
        Ok((
            Some(Tensor::from_vec(from_nhwc(&gr, n, c, p), (n, c, h, w), dev)?.to_dtype(reference.dtype())?),
            Some(Tensor::from_vec(from_nhwc(&gs, n, c, p), (n, c, h, w), dev)?.to_dtype(source.dtype())?),
        ))
    }
}

/// `Σ_c reference[n,c,y,x] · grid_sample(source, grid)[n,c,d·h+y,x]` → `[N, D, h, w]`, with `grid` given flat as
/// `[N, D·h, w, 2]` (bilinear, zeros, align_corners=True; constant, no gradient). Differentiable w.r.t. both
/// feature maps `[N, C, h, w]`.
pub fn warp_correlation(reference: &Tensor, source: &Tensor, grid: &[f32], num_candidates: usize) -> Result<Tensor> {
    let (n, _, h, w) = reference.dims4()?;
    if source.dims() != reference.dims() {
        candle_core::bail!("warp_correlation: reference {:?} and source {:?} differ", reference.dims(), source.dims());
    }
    let d = num_candidates;
    let p = h * w;
    if grid.len() != n * d * p * 2 {
        candle_core::bail!("warp_correlation: grid has {} values, expected N·D·h·w·2 = {}", grid.len(), n * d * p * 2);
    }
    if !(crate::mode::cpu_f32(reference) && crate::mode::cpu_f32(source)) {
        return warp_correlation_composed(reference, source, grid, d);
    }
    let mut taps = vec![Taps::default(); n * d * p];
    taps.par_chunks_mut(p.max(1)).enumerate().for_each(|(nd, row)| {
        let g = &grid[nd * p * 2..(nd + 1) * p * 2];
        for (i, t) in row.iter_mut().enumerate() {
            *t = taps_at(unnormalize(g[2 * i], w), unnormalize(g[2 * i + 1], h), h, w);
        }
    });
    reference.contiguous()?.apply_op2(&source.contiguous()?, WarpCorrelation { taps: Arc::new(taps), d })
}

/// [`warp_correlation`] as the official composition: warp all `D` candidates, multiply, sum over channels
/// (materialises `[N, C, D, h, w]`).
pub(crate) fn warp_correlation_composed(reference: &Tensor, source: &Tensor, grid: &[f32], d: usize) -> Result<Tensor> {
    let (n, c, h, w) = reference.dims4()?;
    let g = Tensor::from_slice(grid, (n, d * h, w, 2), reference.device())?.to_dtype(source.dtype())?;
    let warped = crate::grid_sample::grid_sample_composed(source, &g)?.reshape((n, c, d, h, w))?;
    warped.broadcast_mul(&reference.unsqueeze(2)?)?.sum(1)
}
