//! `Block`: `x + ls1(attn(norm1(x)))`, then `x + ls2(mlp(norm2(x)))`. LayerScale (`ls1`, `ls2`: per-channel
//! `gamma`) is folded into `attn.proj` and `mlp.fc2` at load, and each residual sum happens inside the gemm.

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

use super::attention::Attention;
use super::mlp::Mlp;
use super::rope::RopeTables;
use super::LayerNorm;

/// What differs between the blocks VGGT builds: DINOv2's (eps 1e-6, no QK-norm), the aggregator's (eps
/// 1e-5, QK-norm, RoPE) and the camera trunk's (eps 1e-5, neither).
#[derive(Debug, Clone, Copy)]
pub struct BlockSpec {
    pub dim: usize,
    pub num_heads: usize,
    pub mlp_ratio: f64,
    pub qk_norm: bool,
    pub norm_eps: f64,
    /// `init_values` truthy upstream: the block has `ls1.gamma`/`ls2.gamma`.
    pub layer_scale: bool,
    /// Pack the four big linears for the CPU's bf16 product as the block is built ([`Block::pack_bf16`]), so a
    /// model never holds more than one block's f32 weights besides the packed ones.
    pub pack_bf16: bool,
}

#[derive(Debug, Clone)]
pub struct Block {
    pub norm1: LayerNorm,
    pub attn: Attention,
    pub norm2: LayerNorm,
    pub mlp: Mlp,
}

impl Block {
    pub fn new(vb: VarBuilder, s: BlockSpec) -> Result<Self> {
        let norm1 = LayerNorm::new(vb.pp("norm1"), s.dim, s.norm_eps)?;
        let mut attn = Attention::new(vb.pp("attn"), s.dim, s.num_heads, true, true, s.qk_norm)?;
        let norm2 = LayerNorm::new(vb.pp("norm2"), s.dim, s.norm_eps)?;
        // Upstream: `mlp_hidden_dim = int(dim * mlp_ratio)`.
        let mut mlp = Mlp::new(vb.pp("mlp"), s.dim, (s.dim as f64 * s.mlp_ratio) as usize, s.dim, true)?;
        if s.layer_scale {
            attn.proj = attn.proj.scaled_by(&vb.pp("ls1").get(s.dim, "gamma")?)?;
            mlp.fc2 = mlp.fc2.scaled_by(&vb.pp("ls2").get(s.dim, "gamma")?)?;
        }
        let mut b = Self { norm1, attn, norm2, mlp };
        if s.pack_bf16 {
            b.pack_bf16()?;
        }
        Ok(b)
    }

    /// Packs the block's four big linears (attention `qkv` and `proj`, MLP `fc1` and `fc2`, LayerScale already
    /// folded in f32) for `nn`'s bf16 product ([`super::Linear::pack_bf16`]); everything else — the tokens, the
    /// norms, QK-norm, RoPE, attention's own products and softmax, GELU, biases and residual sums — stays f32.
    pub fn pack_bf16(&mut self) -> Result<()> {
        self.attn.qkv.pack_bf16()?;
        self.attn.proj.pack_bf16()?;
        self.mlp.fc1.pack_bf16()?;
        self.mlp.fc2.pack_bf16()
    }

    /// `x (N, L, C)`; `rope`: tables for the L tokens (None: no rotary embedding).
    pub fn forward(&self, x: &Tensor, rope: Option<&RopeTables>) -> Result<Tensor> {
        let a = self.attn.attend(&self.norm1.forward(x)?, rope)?;
        let x = self.attn.proj.forward_add(&a, x)?;
        let h = self.mlp.hidden(&self.norm2.forward(&x)?)?;
        self.mlp.fc2.forward_add(&h, &x)
    }
}
