//! `DinoVisionTransformer` as the aggregator uses it (`dinov2_vitl14_reg` for VGGT-1B): patch embedding, a
//! class token, the positional embedding of the training grid (interpolated to other grids), register tokens
//! after the class token, blocks with LayerScale and LayerNorm eps 1e-6, a final norm; the aggregator takes
//! the normalised patch tokens (`x_norm_patchtokens`).

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

use super::block::{Block, BlockSpec};
use super::patch_embed::PatchEmbed;
use super::{LayerNorm, DINO_LN_EPS};

#[derive(Debug, Clone)]
pub struct DinoVisionTransformer {
    pub patch_embed: PatchEmbed,
    pub cls_token: Tensor,
    /// `(1, 1 + M², C)` for the `M × M` training grid.
    pub pos_embed: Tensor,
    pub register_tokens: Option<Tensor>,
    pub blocks: Vec<Block>,
    pub norm: LayerNorm,
    pub grid: usize,
    pub embed_dim: usize,
}

impl DinoVisionTransformer {
    pub fn new(
        vb: VarBuilder,
        img_size: usize,
        patch_size: usize,
        embed_dim: usize,
        depth: usize,
        num_heads: usize,
        mlp_ratio: f64,
        num_register_tokens: usize,
        pack_bf16: bool,
    ) -> Result<Self> {
        let grid = img_size / patch_size;
        let spec = BlockSpec { dim: embed_dim, num_heads, mlp_ratio, qk_norm: false, norm_eps: DINO_LN_EPS, layer_scale: true, pack_bf16 };
        let blocks = (0..depth).map(|i| Block::new(vb.pp("blocks").pp(i), spec)).collect::<Result<Vec<_>>>()?;
        // Unused at inference (masked pre-training), but part of the state dict: requested so strict loading
        // accounts for it.
        let _mask_token = vb.get((1, embed_dim), "mask_token")?;
        Ok(Self {
            patch_embed: PatchEmbed::new(vb.pp("patch_embed"), patch_size, 3, embed_dim)?,
            cls_token: vb.get((1, 1, embed_dim), "cls_token")?,
            pos_embed: vb.get((1, grid * grid + 1, embed_dim), "pos_embed")?,
            register_tokens: if num_register_tokens > 0 { Some(vb.get((1, num_register_tokens, embed_dim), "register_tokens")?) } else { None },
            blocks,
            norm: LayerNorm::new(vb.pp("norm"), embed_dim, DINO_LN_EPS)?,
            grid,
            embed_dim,
        })
    }

    /// `interpolate_pos_encoding` for an `H × W` input: the training grid's embedding as it is when the input
    /// is square with that grid (upstream's `npatch == N and w == h`), else the patch part resized to
    /// `(H/p, W/p)` by antialiased bicubic interpolation (PyTorch's `antialias=True`: Keys' a = −0.5, support
    /// widened by the downscale) — offset 0, as the aggregator builds it. `(1, 1 + h·w, C)`.
    pub fn interpolate_pos_encoding(&self, hh: usize, ww: usize) -> Result<Tensor> {
        let p = self.patch_embed.patch_size;
        let (h, w) = (hh / p, ww / p);
        if h * w == self.grid * self.grid && hh == ww {
            return Ok(self.pos_embed.clone());
        }
        let c = self.embed_dim;
        let m = self.grid;
        let dev = self.pos_embed.device();
        // Upstream interpolates in float32 whatever the model's dtype (`pos_embed.float()`).
        let patch = self.pos_embed.narrow(1, 1, m * m)?.reshape((m * m, c))?.t()?.to_dtype(candle_core::DType::F32)?.contiguous()?.to_vec2::<f32>()?;
        let mut out = Vec::with_capacity(h * w * c);
        let planes: Vec<Vec<f32>> = patch.iter().map(|plane| interpolate_bicubic_aa(plane, m, m, h, w)).collect();
        for i in 0..h * w {
            for plane in &planes {
                out.push(plane[i]);
            }
        }
        let patch = Tensor::from_vec(out, (1, h * w, c), dev)?.to_dtype(self.pos_embed.dtype())?;
        Tensor::cat(&[&self.pos_embed.narrow(1, 0, 1)?, &patch], 1)
    }

    /// `x (N, 3, H, W)` normalised images → the final-norm patch tokens `(N, h·w, C)`.
    pub fn forward_patch_tokens(&self, x: &Tensor) -> Result<Tensor> {
        let (n, _, hh, ww) = x.dims4()?;
        let tokens = self.patch_embed.forward(x)?;
        let c = self.embed_dim;
        let cls = self.cls_token.broadcast_as((n, 1, c))?;
        let mut x = Tensor::cat(&[&cls, &tokens], 1)?.broadcast_add(&self.interpolate_pos_encoding(hh, ww)?)?;
        if let Some(r) = &self.register_tokens {
            let r = r.broadcast_as((n, r.dim(1)?, c))?;
            let rest = x.dim(1)? - 1;
            x = Tensor::cat(&[&x.narrow(1, 0, 1)?, &r, &x.narrow(1, 1, rest)?], 1)?;
        }
        for b in &self.blocks {
            x = b.forward(&x, None)?;
        }
        let x = self.norm.forward(&x)?;
        let skip = 1 + self.register_tokens.as_ref().map_or(0, |r| r.dim(1).unwrap_or(0));
        let len = x.dim(1)? - skip;
        x.narrow(1, skip, len)
    }
}

/// Keys' cubic convolution kernel with a = −0.5 (PyTorch's antialiased bicubic, Pillow's BICUBIC).
fn cubic_aa(x: f64) -> f64 {
    const A: f64 = -0.5;
    let x = x.abs();
    if x < 1.0 {
        ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
    } else if x < 2.0 {
        ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A
    } else {
        0.0
    }
}

/// Per output index along one axis: the first input index and the normalised weights (PyTorch's
/// `_compute_weights_aa`, align_corners = False: centre `s·(i + ½)`, support `2·max(s, 1)`, window
/// `[⌊centre − support + ½⌋, ⌊centre + support + ½⌋)` clipped to the input, taps at
/// `(j − centre + ½) / max(s, 1)`).
fn aa_taps(input: usize, output: usize) -> Vec<(usize, Vec<f64>)> {
    let scale = input as f64 / output as f64;
    let (support, inv) = if scale >= 1.0 { (2.0 * scale, 1.0 / scale) } else { (2.0, 1.0) };
    (0..output)
        .map(|i| {
            let center = scale * (i as f64 + 0.5);
            let xmin = ((center - support + 0.5) as i64).max(0) as usize;
            let xmax = ((center + support + 0.5) as i64).min(input as i64).max(xmin as i64) as usize;
            let mut w: Vec<f64> = (xmin..xmax).map(|j| cubic_aa((j as f64 - center + 0.5) * inv)).collect();
            let total: f64 = w.iter().sum();
            if total != 0.0 {
                w.iter_mut().for_each(|v| *v /= total);
            }
            (xmin, w)
        })
        .collect()
}

/// `F.interpolate(x, size=(h, w), mode="bicubic", antialias=True)` of one `(hi, wi)` plane, separable
/// (rows of the width pass first, then columns), row-major `(h, w)` out.
pub fn interpolate_bicubic_aa(src: &[f32], hi: usize, wi: usize, h: usize, w: usize) -> Vec<f32> {
    let tx = aa_taps(wi, w);
    let ty = aa_taps(hi, h);
    let mut mid = vec![0f64; hi * w];
    for r in 0..hi {
        for (o, (x0, ws)) in tx.iter().enumerate() {
            mid[r * w + o] = ws.iter().enumerate().map(|(j, k)| k * src[r * wi + x0 + j] as f64).sum();
        }
    }
    let mut out = vec![0f32; h * w];
    for (o, (y0, ws)) in ty.iter().enumerate() {
        for c in 0..w {
            out[o * w + c] = ws.iter().enumerate().map(|(j, k)| k * mid[(y0 + j) * w + c]).sum::<f64>() as f32;
        }
    }
    out
}
