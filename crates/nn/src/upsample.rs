//! Upsampling with PyTorch semantics: bilinear with `align_corners=True` (CPU custom op with backward; candle's
//! `upsample_bilinear2d` has none, so other devices gather rows and columns with `index_select`) and nearest
//! (candle's op, which has a backward for integer factors).

use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Source index pair and weight of the upper neighbour, per output position (align_corners=True:
/// src = dst·(in−1)/(out−1), independent of any scale factor).
fn axis_taps(n_in: usize, n_out: usize) -> Vec<(usize, usize, f32)> {
    let scale = if n_out > 1 { (n_in as f32 - 1.0) / (n_out as f32 - 1.0) } else { 0.0 };
    (0..n_out)
        .map(|o| {
            let src = scale * o as f32;
            let i0 = (src.floor() as usize).min(n_in - 1);
            let i1 = (i0 + 1).min(n_in - 1);
            (i0, i1, src - i0 as f32)
        })
        .collect()
}

#[derive(Debug, Clone, Copy)]
struct UpsampleBilinear {
    ho: usize,
    wo: usize,
}

impl CustomOp1 for UpsampleBilinear {
    fn name(&self) -> &'static str {
        "upsample_bilinear_align_corners"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, c, hi, wi) = l.shape().dims4()?;
        let x = crate::mode::f32_slice(s, l, "upsample_bilinear")?;
        let (ho, wo) = (self.ho, self.wo);
        let ty = axis_taps(hi, ho);
        let tx = axis_taps(wi, wo);
        let mut out = vec![0f32; n * c * ho * wo];
        out.par_chunks_mut((ho * wo).max(1)).enumerate().for_each(|(nc, o)| {
            let src = &x[nc * hi * wi..(nc + 1) * hi * wi];
            for (yo, &(y0, y1, fy)) in ty.iter().enumerate() {
                let r0 = &src[y0 * wi..(y0 + 1) * wi];
                let r1 = &src[y1 * wi..(y1 + 1) * wi];
                let orow = &mut o[yo * wo..(yo + 1) * wo];
                for (v, &(x0, x1, fx)) in orow.iter_mut().zip(&tx) {
                    let top = (1.0 - fx) * r0[x0] + fx * r0[x1];
                    let bot = (1.0 - fx) * r1[x0] + fx * r1[x1];
                    *v = (1.0 - fy) * top + fy * bot;
                }
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((n, c, ho, wo))))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(upsample_bilinear_backward(arg.dims4()?, grad_res)?))
    }
}

/// Adjoint of [`upsample_bilinear`]: `grad_out [N,C,Ho,Wo]` → gradient w.r.t. the input of shape `in_dims`.
fn upsample_bilinear_backward(in_dims: (usize, usize, usize, usize), grad_out: &Tensor) -> Result<Tensor> {
    let (n, c, hi, wi) = in_dims;
    let (_, _, ho, wo) = grad_out.dims4()?;
    let g = grad_out.flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()?;
    let ty = axis_taps(hi, ho);
    let tx = axis_taps(wi, wo);
    let mut gin = vec![0f32; n * c * hi * wi];
    gin.par_chunks_mut((hi * wi).max(1)).enumerate().for_each(|(nc, gp)| {
        let go = &g[nc * ho * wo..(nc + 1) * ho * wo];
        for (yo, &(y0, y1, fy)) in ty.iter().enumerate() {
            for (xo, &(x0, x1, fx)) in tx.iter().enumerate() {
                let v = go[yo * wo + xo];
                gp[y0 * wi + x0] += (1.0 - fy) * (1.0 - fx) * v;
                gp[y0 * wi + x1] += (1.0 - fy) * fx * v;
                gp[y1 * wi + x0] += fy * (1.0 - fx) * v;
                gp[y1 * wi + x1] += fy * fx * v;
            }
        }
    });
    Tensor::from_vec(gin, (n, c, hi, wi), grad_out.device())?.to_dtype(grad_out.dtype())
}

/// `F.interpolate(x, size=(ho, wo), mode="bilinear", align_corners=True)` for `x [N,C,H,W]`; differentiable.
/// With `align_corners=True` PyTorch's result depends only on the sizes, so a scale factor s maps to
/// `(⌊H·s⌋, ⌊W·s⌋)`.
pub fn upsample_bilinear(x: &Tensor, out_hw: (usize, usize)) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    if h == 0 || w == 0 || out_hw.0 == 0 || out_hw.1 == 0 {
        candle_core::bail!("upsample_bilinear: empty input {:?} or output {out_hw:?}", x.dims());
    }
    if !crate::mode::cpu_f32(x) {
        return upsample_bilinear_composed(x, out_hw);
    }
    x.contiguous()?.apply_op1(UpsampleBilinear { ho: out_hw.0, wo: out_hw.1 })
}

/// [`upsample_bilinear`] from `index_select` and lerps (columns first, like the kernel); differentiable.
pub(crate) fn upsample_bilinear_composed(x: &Tensor, (ho, wo): (usize, usize)) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    let lerp = |x: &Tensor, dim: usize, taps: Vec<(usize, usize, f32)>| -> Result<Tensor> {
        let len = taps.len();
        let dev = x.device();
        let i0 = Tensor::from_vec(taps.iter().map(|t| t.0 as u32).collect::<Vec<_>>(), len, dev)?;
        let i1 = Tensor::from_vec(taps.iter().map(|t| t.1 as u32).collect::<Vec<_>>(), len, dev)?;
        let mut shape = [1usize; 4];
        shape[dim] = len;
        let f = Tensor::from_vec(taps.iter().map(|t| t.2).collect::<Vec<_>>(), &shape[..], dev)?.to_dtype(x.dtype())?;
        x.index_select(&i0, dim)?.broadcast_mul(&f.affine(-1.0, 1.0)?)? + x.index_select(&i1, dim)?.broadcast_mul(&f)?
    };
    lerp(&lerp(x, 3, axis_taps(w, wo))?, 2, axis_taps(h, ho))
}

/// `F.interpolate(x, scale_factor=s, mode="nearest")` for an integer factor `s` (`out_hw` = s·(H, W)).
/// candle's op records a backward for integer, uniform factors.
pub fn upsample_nearest(x: &Tensor, out_hw: (usize, usize)) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    if h == 0 || w == 0 || out_hw.0 % h != 0 || out_hw.1 % w != 0 {
        candle_core::bail!("upsample_nearest: {:?} → {out_hw:?} is not an integer upscaling", x.dims());
    }
    x.upsample_nearest2d(out_hw.0, out_hw.1)
}
