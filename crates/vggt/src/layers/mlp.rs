//! `Mlp`: fc1 → GELU (erf) → fc2.

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

use super::Linear;

#[derive(Debug, Clone)]
pub struct Mlp {
    pub fc1: Linear,
    pub fc2: Linear,
}

impl Mlp {
    pub fn new(vb: VarBuilder, d_in: usize, hidden: usize, d_out: usize, bias: bool) -> Result<Self> {
        Ok(Self { fc1: Linear::new(vb.pp("fc1"), d_in, hidden, bias)?, fc2: Linear::new(vb.pp("fc2"), hidden, d_out, bias)? })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.fc2.forward(&self.hidden(x)?)
    }

    /// GELU(fc1(x)); a packed `fc1` (bf16 product) or a few rows (see `Linear::fused`) are followed by the same
    /// f32 GELU kernel.
    pub fn hidden(&self, x: &Tensor) -> Result<Tensor> {
        if self.fc1.packed.is_some() || super::few_rows(x) {
            return mvsplat360_nn::activation::gelu_inference(&self.fc1.forward(x)?);
        }
        mvsplat360_nn::linear::linear_gelu(x, &self.fc1.weight, self.fc1.bias.as_ref())
    }
}
