//! `Attention`: packed qkv projection, optional per-head LayerNorm on q and k (QK-norm, PyTorch's default eps
//! 1e-5 — not DINOv2's 1e-6), optional 2D RoPE, scaled dot-product attention, output projection.

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

use super::rope::RopeTables;
use super::{LayerNorm, Linear, TORCH_LN_EPS};
use mvsplat360_nn::rope::{qkv_attention, HeadNorm};

#[derive(Debug, Clone)]
pub struct Attention {
    pub qkv: Linear,
    pub q_norm: Option<LayerNorm>,
    pub k_norm: Option<LayerNorm>,
    pub proj: Linear,
    pub num_heads: usize,
}

impl Attention {
    pub fn new(vb: VarBuilder, dim: usize, num_heads: usize, qkv_bias: bool, proj_bias: bool, qk_norm: bool) -> Result<Self> {
        let head_dim = dim / num_heads;
        let (q_norm, k_norm) = if qk_norm {
            (Some(LayerNorm::new(vb.pp("q_norm"), head_dim, TORCH_LN_EPS)?), Some(LayerNorm::new(vb.pp("k_norm"), head_dim, TORCH_LN_EPS)?))
        } else {
            (None, None)
        };
        Ok(Self { qkv: Linear::new(vb.pp("qkv"), dim, 3 * dim, qkv_bias)?, q_norm, k_norm, proj: Linear::new(vb.pp("proj"), dim, dim, proj_bias)?, num_heads })
    }

    /// The attention's output before `proj`, `(N, L, C)`.
    pub fn attend(&self, x: &Tensor, rope: Option<&RopeTables>) -> Result<Tensor> {
        let qkv = self.qkv.forward(x)?;
        let _p = mvsplat360_nn::prof::scope("vggt.attention");
        qkv_attention(&qkv, self.num_heads, head_norm(&self.q_norm), head_norm(&self.k_norm), rope.map(|r| r.as_arg()))
    }
}

fn head_norm(n: &Option<LayerNorm>) -> Option<HeadNorm<'_>> {
    n.as_ref().map(|n| HeadNorm { weight: &n.weight, bias: &n.bias, eps: n.eps })
}
