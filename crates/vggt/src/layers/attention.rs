//! `Attention`: packed qkv projection, optional per-head LayerNorm on q and k (QK-norm, PyTorch's default eps
//! 1e-5 — not DINOv2's 1e-6), optional 2D RoPE, scaled dot-product attention, output projection.

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

use super::rope::RopeTables;
use super::{LayerNorm, Linear, TORCH_LN_EPS};
use mvsplat360_nn::rope::{qkv_attention, qkv_attention_bf16, HeadNorm};

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

    /// The attention's output before `proj`, `(N, L, C)`. A trunk packed for bf16 (its `qkv` packed) takes
    /// the attention's products in bf16 too (`qkv_attention_bf16`: f32 where the CPU or the mask rules it out).
    pub fn attend(&self, x: &Tensor, rope: Option<&RopeTables>) -> Result<Tensor> {
        let qkv = self.qkv.forward(x)?;
        let _p = mvsplat360_nn::prof::scope("vggt.attention");
        let attend = if self.qkv.packed.is_some() { qkv_attention_bf16 } else { qkv_attention };
        attend(&qkv, self.num_heads, head_norm(&self.q_norm), head_norm(&self.k_norm), rope.map(|r| r.as_arg()))
    }
}

fn head_norm(n: &Option<LayerNorm>) -> Option<HeadNorm<'_>> {
    n.as_ref().map(|n| HeadNorm { weight: &n.weight, bias: &n.bias, eps: n.eps })
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use std::collections::HashMap;

    /// The trunk's wiring, on heads of 64 (the parity fixtures' heads of 8 never reach the bf16 kernel): with
    /// `qkv` packed the attention is `qkv_attention_bf16` of the packed projection, bit for bit, and where the
    /// CPU has AVX512-BF16 it differs from the f32 attention; unpacked it is `qkv_attention`.
    #[test]
    fn packed_trunk_attends_in_bf16() {
        let dev = Device::Cpu;
        let (dim, heads, l) = (128, 2, 70);
        let r = |shape: &[usize], s: f64| Tensor::randn(0f32, s as f32, shape, &dev).unwrap();
        let t: HashMap<String, Tensor> = [
            ("qkv.weight", r(&[3 * dim, dim], 0.1)),
            ("qkv.bias", r(&[3 * dim], 0.1)),
            ("q_norm.weight", (r(&[64], 0.2) + 1.0).unwrap()),
            ("q_norm.bias", r(&[64], 0.1)),
            ("k_norm.weight", (r(&[64], 0.2) + 1.0).unwrap()),
            ("k_norm.bias", r(&[64], 0.1)),
            ("proj.weight", r(&[dim, dim], 0.1)),
            ("proj.bias", r(&[dim], 0.1)),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let vb = VarBuilder::from_tensors(t, DType::F32, &dev);
        let mut attn = Attention::new(vb, dim, heads, true, true, true).unwrap();
        let x = r(&[2, l, dim], 1.0);
        let bits = |t: Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap().into_iter().map(f32::to_bits).collect::<Vec<_>>();
        let f32_out = bits(attn.attend(&x, None).unwrap());
        let qkv = attn.qkv.forward(&x).unwrap();
        let (qn, kn) = (head_norm(&attn.q_norm), head_norm(&attn.k_norm));
        assert_eq!(f32_out, bits(qkv_attention(&qkv, heads, qn, kn, None).unwrap()), "unpacked: the f32 attention");
        attn.qkv.pack_bf16().unwrap();
        let qkv = attn.qkv.forward(&x).unwrap();
        let (qn, kn) = (head_norm(&attn.q_norm), head_norm(&attn.k_norm));
        let packed = bits(attn.attend(&x, None).unwrap());
        assert_eq!(packed, bits(qkv_attention_bf16(&qkv, heads, qn, kn, None).unwrap()), "packed: the bf16 attention");
        let dpbf16 = mvsplat360_nn::bf16::path() == mvsplat360_nn::bf16::Bf16Path::Dpbf16;
        assert_eq!(packed != bits(qkv_attention(&qkv, heads, qn, kn, None).unwrap()), dpbf16, "bf16 products exactly where the CPU has them");
    }
}
