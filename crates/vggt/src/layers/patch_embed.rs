//! `PatchEmbed`: a `patch × patch` convolution with stride `patch` (`proj`), flattened to tokens. Patches do
//! not overlap, so it runs as one gemm over the unfolded patches (channel, row, column order = the kernel's).

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

use super::Linear;

#[derive(Debug, Clone)]
pub struct PatchEmbed {
    /// `proj.weight (C, 3, p, p)` viewed as `(C, 3·p·p)`.
    pub proj: Linear,
    pub patch_size: usize,
    pub in_chans: usize,
}

impl PatchEmbed {
    pub fn new(vb: VarBuilder, patch_size: usize, in_chans: usize, embed_dim: usize) -> Result<Self> {
        let p = patch_size;
        let w = vb.pp("proj").get((embed_dim, in_chans, p, p), "weight")?;
        let b = vb.pp("proj").get(embed_dim, "bias")?;
        Ok(Self { proj: Linear { weight: w.reshape((embed_dim, in_chans * p * p))?, bias: Some(b), packed: None }, patch_size, in_chans })
    }

    /// `x (N, 3, H, W)` with H and W multiples of the patch → `(N, (H/p)·(W/p), C)`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (n, c, hh, ww) = x.dims4()?;
        let p = self.patch_size;
        if c != self.in_chans || hh % p != 0 || ww % p != 0 {
            candle_core::bail!("patch embed: input {:?} is not {} channels of multiples of {p}", x.dims(), self.in_chans);
        }
        let (h, w) = (hh / p, ww / p);
        let cols = x.reshape((n, c, h, p, w, p))?.permute((0, 2, 4, 1, 3, 5))?.contiguous()?.reshape((n, h * w, c * p * p))?;
        self.proj.forward(&cols)
    }
}
