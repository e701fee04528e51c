//! The encoder in bf16 on the CPU (`--encoder-dtype bf16`, issue 73): every linear and convolution weight packed
//! once in bf16 ([`EncoderCostVolume::pack_bf16`](crate::EncoderCostVolume::pack_bf16); the f32 weight is
//! dropped, but for the Gaussian head's two kernels, ≈ 0.6 MB, kept as its Winograd kernel's fallback),
//! activations f32 and rounded to bf16 only inside the products (`vdpbf16ps`, f32 sums; storage only without
//! AVX512-BF16 — `mvsplat360_nn::bf16` decides per call).
//!
//! In bf16: the CNN's convolutions (7×7/2, 3×3 stride 1 and 2, the 1×1 shortcuts and output), the transformer's
//! q/k/v/merge projections and MLP, every convolution of the cost-volume and depth-refinement UNets and heads
//! (stride 1 and 2, the ×2-upsampling ones; the Gaussian head's two full-resolution 3×3 ones as bf16 Winograd
//! F(2×2, 3×3), `mvsplat360_nn::conv::Winograd3x3::new_bf16`), the UNets' attention qkv / proj_out (1×1), and
//! attention's own products q·kᵀ and weights·v (the transformer's shifted windows with their region mask, heads
//! of 128; the UNets' heads of 32: `mvsplat360_nn::attention_bf16`, softmax in f32).
//!
//! Kept f32, and why:
//! - InstanceNorm, LayerNorm, GroupNorm: means and variances over thousands of values, where bf16's 8 bits
//!   would lose the small differences a norm divides by.
//! - Softmax (max, exp, sums, the region mask's −100): it sums exponentials that span many octaves.
//! - The cost volume's geometry and warp (the bilinear tap weights): the sampling grid is sub-pixel geometry.
//!   Its channel dot products are bf16 (`mvsplat360_nn::warp_correlation::warp_correlation_bf16`, features
//!   rounded once, f32 sums).
//! - The depth head's softmax over candidates, the disparity → depth (1/x), upsampling, GELU/SiLU/sigmoid.
//! - The Gaussian adapter (means from depth along rays, covariances, SH rotation): it places the Gaussians.
//!
//! Inference only: packing refuses trainable weights (`Var`s), so training and the test-time fit stay f32.

use std::sync::Arc;

use candle_core::{Result, Tensor};
use mvsplat360_nn::bf16::Bf16Weights;
use mvsplat360_nn::conv::bf16::{conv2d_fused_bf16, Bf16ConvWeights};
use mvsplat360_nn::{Conv2dConfig, ConvEpilogue};

/// A linear layer's `(out, in)` weight: f32, or packed once in bf16.
#[derive(Clone)]
pub enum LinearWeight {
    F32(Tensor),
    Bf16(Arc<Bf16Weights>),
}

/// A convolution's `(Co, C, kh, kw)` weight: f32, or packed once in bf16.
#[derive(Clone)]
pub enum ConvWeight {
    F32(Tensor),
    Bf16(Arc<Bf16ConvWeights>),
}

impl std::fmt::Debug for LinearWeight {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LinearWeight::F32(t) => write!(f, "F32({:?})", t.dims()),
            LinearWeight::Bf16(w) => write!(f, "Bf16({}x{})", w.n(), w.k()),
        }
    }
}

impl std::fmt::Debug for ConvWeight {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ConvWeight::F32(t) => write!(f, "F32({:?})", t.dims()),
            ConvWeight::Bf16(w) => write!(f, "Bf16({:?})", w.dims()),
        }
    }
}

pub(crate) fn refuse_var(w: &Tensor) -> Result<()> {
    if w.is_variable() {
        // A packed weight has no gradient: training must never reach this.
        candle_core::bail!("bf16 packing is for inference: this encoder holds trainable weights (Vars)");
    }
    Ok(())
}

impl LinearWeight {
    /// Packs an f32 weight in bf16 (no-op when already packed).
    pub fn pack(&mut self) -> Result<()> {
        if let LinearWeight::F32(w) = self {
            refuse_var(w)?;
            *self = LinearWeight::Bf16(Arc::new(Bf16Weights::from_linear(w)?));
        }
        Ok(())
    }

    pub fn is_bf16(&self) -> bool {
        matches!(self, LinearWeight::Bf16(_))
    }
}

impl ConvWeight {
    /// Packs an f32 weight in bf16 (no-op when already packed).
    pub fn pack(&mut self) -> Result<()> {
        if let ConvWeight::F32(w) = self {
            refuse_var(w)?;
            *self = ConvWeight::Bf16(Arc::new(Bf16ConvWeights::from_conv(w)?));
        }
        Ok(())
    }

    /// `(Co, C, kh, kw)`.
    pub fn dims(&self) -> Result<(usize, usize, usize, usize)> {
        match self {
            ConvWeight::F32(w) => w.dims4(),
            ConvWeight::Bf16(w) => Ok(w.dims()),
        }
    }

    pub fn is_bf16(&self) -> bool {
        matches!(self, ConvWeight::Bf16(_))
    }
}

/// `residual + conv(x) + bias` on packed weights, stride and padding as given (the caller handles f32).
pub(crate) fn conv_bf16(x: &Tensor, w: &Bf16ConvWeights, bias: Option<&Tensor>, stride: usize, padding: usize, epi: ConvEpilogue) -> Result<Tensor> {
    conv2d_fused_bf16(x, w, bias, Conv2dConfig { padding, stride, dilation: 1 }, epi)
}
