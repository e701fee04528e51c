//! Building blocks of the official `vggt/layers/`: attention with QK-norm and 2D RoPE, the pre-norm block
//! with LayerScale, the MLP, DINOv2's patch embedding and vision transformer.

pub mod attention;
pub mod block;
pub mod mlp;
pub mod patch_embed;
pub mod rope;
pub mod vision_transformer;

use candle_core::{DType, Result, Tensor};
use candle_nn::VarBuilder;

/// `nn.Linear` (weight `(out, in)`), run through `nn`'s fused gemm, or through `nn`'s bf16 product when its
/// weight was packed by [`Linear::pack_bf16`].
#[derive(Debug, Clone)]
pub struct Linear {
    /// `(out, in)`; empty once packed (the packed copy is the only weight kept: no f32 or bf16 tensor beside it).
    pub weight: Tensor,
    pub bias: Option<Tensor>,
    /// The weight in bf16, packed once at load for `vdpbf16ps` ([`mvsplat360_nn::bf16`]); None: the f32 gemm
    /// (or candle's ops on other dtypes and devices).
    pub packed: Option<PackedBf16>,
}

/// A linear layer's weight packed for `nn`'s bf16 product (shared by clones of the layer).
#[derive(Clone)]
pub struct PackedBf16(pub std::sync::Arc<mvsplat360_nn::bf16::Bf16Weights>);

impl std::fmt::Debug for PackedBf16 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PackedBf16({}×{})", self.0.n(), self.0.k())
    }
}

/// At most `nn::linear::FEW_ROWS` rows (the camera head's tokens).
pub(crate) fn few_rows(x: &Tensor) -> bool {
    let k = *x.dims().last().unwrap_or(&1);
    x.elem_count() / k.max(1) <= mvsplat360_nn::linear::FEW_ROWS
}

impl Linear {
    pub fn new(vb: VarBuilder, d_in: usize, d_out: usize, bias: bool) -> Result<Self> {
        let weight = vb.get((d_out, d_in), "weight")?;
        let bias = if bias { Some(vb.get(d_out, "bias")?) } else { None };
        Ok(Self { weight, bias, packed: None })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.fused(x, &[])
    }

    /// `residual + self(x)` with the sum done in the gemm's destination.
    pub fn forward_add(&self, x: &Tensor, residual: &Tensor) -> Result<Tensor> {
        self.fused(x, &[(residual, 1.0)])
    }

    /// `x @ Wᵀ + b + Σ cᵢ·addᵢ`: the packed bf16 product on a CPU f32 input when packed (bias and addends in
    /// f32), the f32 gemm otherwise (a packed layer's bf16 weight widened to the input's dtype there).
    pub(crate) fn fused(&self, x: &Tensor, adds: &[(&Tensor, f32)]) -> Result<Tensor> {
        match &self.packed {
            Some(p) if x.device().is_cpu() && x.dtype() == DType::F32 && !mvsplat360_nn::mode::is_differentiable() => {
                mvsplat360_nn::linear::linear_fused_bf16(x, &p.0, self.bias.as_ref(), 1.0, adds)
            }
            Some(_) => {
                let w = self.weight_f32()?.to_device(x.device())?.to_dtype(x.dtype())?;
                let b = self.bias.as_ref().map(|b| b.to_dtype(x.dtype())).transpose()?;
                mvsplat360_nn::linear::linear_fused(x, &w, b.as_ref(), 1.0, adds)
            }
            // The camera head's 5 tokens: the weight streamed once instead of packed by the gemm.
            None if few_rows(x) => mvsplat360_nn::linear::linear_fused_few_rows(x, &self.weight, self.bias.as_ref(), 1.0, adds),
            None => mvsplat360_nn::linear::linear_fused(x, &self.weight, self.bias.as_ref(), 1.0, adds),
        }
    }

    /// Packs the weight (any dtype; f32 here, after any folding, so it is rounded to bf16 once) for `nn`'s bf16
    /// product and drops the weight tensor (the packed copy is the weight; the bias stays as it is).
    pub fn pack_bf16(&mut self) -> Result<()> {
        if self.packed.is_some() {
            return Ok(());
        }
        self.packed = Some(PackedBf16(std::sync::Arc::new(mvsplat360_nn::bf16::Bf16Weights::from_linear(&self.weight)?)));
        self.weight = Tensor::zeros(0, DType::F32, self.weight.device())?;
        Ok(())
    }

    /// The weight `(out, in)` in f32: the tensor, or the packed bf16 values widened (exact; a fallback's copy).
    pub fn weight_f32(&self) -> Result<Tensor> {
        match &self.packed {
            Some(p) => Tensor::from_vec(p.0.to_f32_kn(), (p.0.k(), p.0.n()), &candle_core::Device::Cpu)?.t()?.contiguous(),
            None => self.weight.to_dtype(DType::F32),
        }
    }

    /// The layer followed by a per-channel scale (`LayerScale`), folded into the weights once at load:
    /// `γ ⊙ (W x + b) = (diag(γ) W) x + γ ⊙ b`.
    pub fn scaled_by(&self, gamma: &Tensor) -> Result<Self> {
        let w = if self.packed.is_some() { self.weight_f32()?.to_device(gamma.device())? } else { self.weight.clone() };
        let weight = w.to_dtype(gamma.dtype())?.broadcast_mul(&gamma.unsqueeze(1)?)?;
        let bias = self.bias.as_ref().map(|b| b * gamma).transpose()?;
        let mut out = Self { weight, bias, packed: None };
        if self.packed.is_some() {
            out.pack_bf16()?;
        }
        Ok(out)
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
