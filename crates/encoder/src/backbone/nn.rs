//! Layers shared by the backbone (weights and their keys); the ops live in `mvsplat360_nn`. Trainable inputs
//! (tensors that track gradients) take composed ops, because candle's fused layer_norm records no backward.

use candle_core::{DType, Module, Result, Tensor, D};
use candle_nn::VarBuilder;

use crate::bf16::{conv_bf16, ConvWeight, LinearWeight};

/// `nn.LayerNorm(d)` with affine parameters (eps 1e-5).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    pub fn new(vb: VarBuilder, d: usize) -> Result<Self> {
        Ok(Self { weight: vb.get(d, "weight")?, bias: vb.get(d, "bias")?, eps: 1e-5 })
    }
}

impl Module for LayerNorm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if x.track_op() || self.weight.track_op() {
            let mean = x.mean_keepdim(D::Minus1)?;
            let xc = x.broadcast_sub(&mean)?;
            let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
            xc.broadcast_div(&(var + self.eps)?.sqrt()?)?.broadcast_mul(&self.weight)?.broadcast_add(&self.bias)
        } else {
            candle_nn::ops::layer_norm(&x.contiguous()?, &self.weight, &self.bias, self.eps as f32)
        }
    }
}

/// 2-D convolution with PyTorch's weight layout `[out, in, kh, kw]` (square kernel, symmetric padding); the
/// weight f32, or packed in bf16 for CPU inference ([`crate::bf16`]).
#[derive(Debug, Clone)]
pub struct Conv2d {
    pub weight: ConvWeight,
    pub bias: Option<Tensor>,
    pub stride: usize,
    pub padding: usize,
}

impl Conv2d {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, k: usize, stride: usize, padding: usize, bias: bool) -> Result<Self> {
        let weight = ConvWeight::F32(vb.get((c_out, c_in, k, k), "weight")?);
        let bias = if bias { Some(vb.get(c_out, "bias")?) } else { None };
        Ok(Self { weight, bias, stride, padding })
    }

    pub fn pack_bf16(&mut self) -> Result<()> {
        self.weight.pack()
    }
}

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match &self.weight {
            ConvWeight::F32(w) => {
                let cfg = mvsplat360_nn::Conv2dConfig { padding: self.padding, stride: self.stride, dilation: 1 };
                mvsplat360_nn::conv2d(x, w, self.bias.as_ref(), cfg)
            }
            ConvWeight::Bf16(w) => conv_bf16(x, w, self.bias.as_ref(), self.stride, self.padding, Default::default()),
        }
    }
}

/// Bias-free linear layer, weight `[out, in]`, applied to the last dimension of any-rank input; the weight
/// f32, or packed in bf16 for CPU inference ([`crate::bf16`]).
#[derive(Debug, Clone)]
pub struct LinearNoBias {
    pub weight: LinearWeight,
}

impl LinearNoBias {
    pub fn new(vb: VarBuilder, d_in: usize, d_out: usize) -> Result<Self> {
        Ok(Self { weight: LinearWeight::F32(vb.get((d_out, d_in), "weight")?) })
    }

    pub fn pack_bf16(&mut self) -> Result<()> {
        self.weight.pack()
    }
}

impl Module for LinearNoBias {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let w = match &self.weight {
            LinearWeight::F32(w) => w,
            LinearWeight::Bf16(w) => return mvsplat360_nn::linear::linear_fused_bf16(x, w, None, 1.0, &[]),
        };
        let dims = x.dims().to_vec();
        let d_in = dims[dims.len() - 1];
        let rows = x.elem_count() / d_in.max(1);
        let y = x.reshape((rows, d_in))?.matmul(&w.t()?)?;
        let mut out = dims;
        let last = out.len() - 1;
        out[last] = w.dim(0)?;
        y.reshape(out)
    }
}

pub fn ensure_f32(x: &Tensor, what: &str) -> Result<()> {
    if x.dtype() != DType::F32 {
        candle_core::bail!("{what}: expected f32, got {:?}", x.dtype())
    }
    Ok(())
}
