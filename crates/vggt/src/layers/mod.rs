//! Building blocks of the official `vggt/layers/`: attention with QK-norm and 2D RoPE, the pre-norm block
//! with LayerScale, the MLP, DINOv2's patch embedding and vision transformer.

pub mod attention;
pub mod block;
pub mod mlp;
pub mod patch_embed;
pub mod rope;
pub mod vision_transformer;

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

/// `nn.Linear` (weight `(out, in)`), run through `nn`'s fused gemm.
#[derive(Debug, Clone)]
pub struct Linear {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
}

impl Linear {
    pub fn new(vb: VarBuilder, d_in: usize, d_out: usize, bias: bool) -> Result<Self> {
        let weight = vb.get((d_out, d_in), "weight")?;
        let bias = if bias { Some(vb.get(d_out, "bias")?) } else { None };
        Ok(Self { weight, bias })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        mvsplat360_nn::linear::linear_fused(x, &self.weight, self.bias.as_ref(), 1.0, &[])
    }

    /// `residual + self(x)` with the sum done in the gemm's destination.
    pub fn forward_add(&self, x: &Tensor, residual: &Tensor) -> Result<Tensor> {
        mvsplat360_nn::linear::linear_fused(x, &self.weight, self.bias.as_ref(), 1.0, &[(residual, 1.0)])
    }

    /// The layer followed by a per-channel scale (`LayerScale`), folded into the weights once at load:
    /// `γ ⊙ (W x + b) = (diag(γ) W) x + γ ⊙ b`.
    pub fn scaled_by(&self, gamma: &Tensor) -> Result<Self> {
        let weight = self.weight.broadcast_mul(&gamma.unsqueeze(1)?)?;
        let bias = self.bias.as_ref().map(|b| b * gamma).transpose()?;
        Ok(Self { weight, bias })
    }
}

/// `nn.LayerNorm(dim, eps)` with its affine parameters (`elementwise_affine=False`: unit weight, zero bias).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    pub eps: f64,
}

impl LayerNorm {
    pub fn new(vb: VarBuilder, dim: usize, eps: f64) -> Result<Self> {
        Ok(Self { weight: vb.get(dim, "weight")?, bias: vb.get(dim, "bias")?, eps })
    }

    pub fn no_affine(dim: usize, eps: f64, dev: &candle_core::Device) -> Result<Self> {
        Ok(Self { weight: Tensor::ones(dim, candle_core::DType::F32, dev)?, bias: Tensor::zeros(dim, candle_core::DType::F32, dev)?, eps })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        mvsplat360_nn::norm::layer_norm(x, &self.weight, &self.bias, self.eps)
    }
}

/// PyTorch's `nn.LayerNorm` default eps (the aggregator's, the camera head's and the DPT heads' norms).
pub const TORCH_LN_EPS: f64 = 1e-5;
/// DINOv2's `partial(nn.LayerNorm, eps=1e-6)` (its blocks and final norm) and the camera head's adaLN norm.
pub const DINO_LN_EPS: f64 = 1e-6;
