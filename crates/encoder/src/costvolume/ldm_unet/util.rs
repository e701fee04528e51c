//! Layers shared by the UNet and the depth predictor (`ldm_unet/util.py`); their ops live in
//! `mvsplat360_nn` (GroupNorm + activation in `norm::group_norm_act`).

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;
use mvsplat360_nn::ConvEpilogue;

use crate::bf16::{conv_bf16, ConvWeight};

/// `nn.Conv2d(c_in, c_out, k, stride, padding)` with bias, PyTorch weight layout `[out, in, k, k]`; the weight
/// f32, or packed in bf16 for CPU inference ([`crate::bf16`]).
#[derive(Debug, Clone)]
pub struct Conv2d {
    pub weight: ConvWeight,
    pub bias: Tensor,
    pub stride: usize,
    pub padding: usize,
}

impl Conv2d {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, k: usize, stride: usize, padding: usize) -> Result<Self> {
        Ok(Self { weight: ConvWeight::F32(vb.get((c_out, c_in, k, k), "weight")?), bias: vb.get(c_out, "bias")?, stride, padding })
    }

    pub fn pack_bf16(&mut self) -> Result<()> {
        self.weight.pack()
    }

    /// `conv(nearest×2(x))`: packed weights fuse the upsampling into the convolution's input copy; f32 as
    /// the official code composes it.
    pub fn forward_up2(&self, x: &Tensor) -> Result<Tensor> {
        match &self.weight {
            ConvWeight::Bf16(w) => conv_bf16(x, w, Some(&self.bias), self.stride, self.padding, ConvEpilogue { upsample2x: true, ..Default::default() }),
            ConvWeight::F32(_) => {
                let (_, _, h, w) = x.dims4()?;
                self.forward(&mvsplat360_nn::upsample::upsample_nearest(x, (2 * h, 2 * w))?)
            }
        }
    }

    /// "Same" 3×3 convolution (stride 1, padding 1).
    pub fn same3(vb: VarBuilder, c_in: usize, c_out: usize) -> Result<Self> {
        Self::new(vb, c_in, c_out, 3, 1, 1)
    }
}

/// Largest im2col buffer (values) one convolution call may need; bigger ones run per image, then per band of
/// output rows. At DL3DV size the full-resolution Gaussian head would otherwise allocate ~5 GB at once.
const IM2COL_BUDGET: usize = 48 << 20;

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_budget(x, IM2COL_BUDGET)
    }
}

impl Conv2d {
    fn forward_budget(&self, x: &Tensor, budget: usize) -> Result<Tensor> {
        let weight = match &self.weight {
            ConvWeight::F32(w) => w,
            // The bf16 kernel bands its own buffers.
            ConvWeight::Bf16(w) => return conv_bf16(x, w, Some(&self.bias), self.stride, self.padding, Default::default()),
        };
        let (n, cin, h, w) = x.dims4()?;
        let (_, _, k, _) = weight.dims4()?;
        let (s, pd) = (self.stride, self.padding);
        if h + 2 * pd < k || w + 2 * pd < k {
            candle_core::bail!("conv2d: kernel {k} larger than padded input {h}x{w}");
        }
        let ho = (h + 2 * pd - k) / s + 1;
        let wo = (w + 2 * pd - k) / s + 1;
        if s == 1 {
            // The shifted-gemm kernel bands large inputs itself (no im2col buffer): no splitting here, and
            // for inference the bias is fused into its output copy.
            let cfg = mvsplat360_nn::Conv2dConfig { padding: pd, stride: 1, dilation: 1 };
            return if x.track_op() || weight.track_op() || self.bias.track_op() {
                mvsplat360_nn::conv2d(x, weight, Some(&self.bias), cfg)
            } else {
                mvsplat360_nn::conv2d_fused(x, weight, Some(&self.bias), cfg, Default::default())
            };
        }
        let per_row = wo * cin * k * k;
        let y = if n * ho * per_row <= budget || k == 1 {
            conv2d(x, weight, s, pd)?
        } else if ho * per_row <= budget {
            let per = (budget / (ho * per_row)).max(1);
            let parts = (0..n).step_by(per).map(|i| conv2d(&x.narrow(0, i, per.min(n - i))?, weight, s, pd)).collect::<Result<Vec<_>>>()?;
            Tensor::cat(&parts, 0)?
        } else {
            // Bands of output rows over the zero-padded input (differentiable: pad/narrow/cat).
            let xp = x.pad_with_zeros(2, pd, pd)?.pad_with_zeros(3, pd, pd)?;
            let rows = (budget / per_row).max(1);
            let mut per_image = Vec::with_capacity(n);
            for i in 0..n {
                let xi = xp.narrow(0, i, 1)?;
                let mut bands = Vec::new();
                let mut r0 = 0;
                while r0 < ho {
                    let r1 = (r0 + rows).min(ho);
                    let band = xi.narrow(2, r0 * s, (r1 - 1) * s + k - r0 * s)?;
                    bands.push(conv2d(&band, weight, s, 0)?);
                    r0 = r1;
                }
                per_image.push(Tensor::cat(&bands, 2)?);
            }
            Tensor::cat(&per_image, 0)?
        };
        mvsplat360_nn::conv::add_bias(y, Some(&self.bias))
    }
}

/// `nn.Conv1d(c_in, c_out, 1)` on `[N, C, T]` (weight `[out, in, 1]`), as one matrix product; packed in bf16
/// it runs as a 1×1 convolution of `[N, C, 1, T]`.
#[derive(Debug, Clone)]
pub struct Conv1x1 {
    pub weight: ConvWeight,
    pub bias: Tensor,
}

impl Conv1x1 {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize) -> Result<Self> {
        Ok(Self { weight: ConvWeight::F32(vb.get((c_out, c_in, 1), "weight")?), bias: vb.get(c_out, "bias")? })
    }

    pub fn pack_bf16(&mut self) -> Result<()> {
        if let ConvWeight::F32(w) = &self.weight {
            crate::bf16::refuse_var(w)?;
            let mut c = ConvWeight::F32(w.unsqueeze(3)?);
            c.pack()?;
            self.weight = c;
        }
        Ok(())
    }
}

impl Module for Conv1x1 {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (n, c, t) = x.dims3()?;
        match &self.weight {
            ConvWeight::F32(w) => {
                let w = w.squeeze(2)?;
                w.broadcast_left(n)?.matmul(&x.contiguous()?)?.broadcast_add(&self.bias.reshape((1, (), 1))?)
            }
            ConvWeight::Bf16(w) => {
                let y = conv_bf16(&x.reshape((n, c, 1, t))?, w, Some(&self.bias), 1, 0, Default::default())?;
                y.reshape((n, (), t))
            }
        }
    }
}

pub use mvsplat360_nn::norm::Act;

/// `nn.GroupNorm(groups, channels)` (eps 1e-5) on `[N, C, ...]`.
#[derive(Debug, Clone)]
pub struct GroupNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    groups: usize,
    eps: f64,
}

impl GroupNorm {
    pub fn new(vb: VarBuilder, groups: usize, channels: usize) -> Result<Self> {
        if groups == 0 || channels % groups != 0 {
            candle_core::bail!("GroupNorm at `{}`: {channels} channels not divisible into {groups} groups", vb.prefix());
        }
        Ok(Self { weight: vb.get(channels, "weight")?, bias: vb.get(channels, "bias")?, groups, eps: 1e-5 })
    }

    /// The UNet's `normalization(channels)`: 8 groups when divisible, else 4.
    pub fn unet(vb: VarBuilder, channels: usize) -> Result<Self> {
        Self::new(vb, if channels % 8 == 0 { 8 } else { 4 }, channels)
    }

    /// `act(GN(x))`.
    pub fn forward_act(&self, x: &Tensor, act: Act) -> Result<Tensor> {
        let _prof = mvsplat360_nn::prof::scope("encoder.groupnorm");
        mvsplat360_nn::norm::group_norm_act(x, &self.weight, &self.bias, self.groups, self.eps, act)
    }
}

/// `F.conv2d(x, w, stride=stride, padding=padding)` without bias.
fn conv2d(x: &Tensor, w: &Tensor, stride: usize, padding: usize) -> Result<Tensor> {
    mvsplat360_nn::conv2d(x, w, None, mvsplat360_nn::Conv2dConfig { padding, stride, dilation: 1 })
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn banded_convolution_equals_direct() {
        let dev = Device::Cpu;
        for &(stride, padding) in &[(1usize, 1usize), (2, 1)] {
            let weight = Tensor::randn(0f32, 0.3, (5, 3, 3, 3), &dev).unwrap();
            let conv = Conv2d { weight: ConvWeight::F32(weight.clone()), bias: Tensor::randn(0f32, 0.3, 5, &dev).unwrap(), stride, padding };
            let x = Tensor::randn(0f32, 1.0, (2, 3, 11, 9), &dev).unwrap();
            // Independent reference: candle's own convolution plus bias (stride 1 takes the shifted-gemm path,
            // stride 2 the banded im2col path).
            let direct = x.conv2d(&weight, padding, stride, 1, 1).unwrap().broadcast_add(&conv.bias.reshape((1, (), 1, 1)).unwrap()).unwrap();
            for budget in [1usize, 100, 400] {
                let banded = conv.forward_budget(&x, budget).unwrap();
                let e = (&banded - &direct).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
                assert!(e < 1e-5, "stride {stride} budget {budget}: max diff {e}");
            }
        }
    }
}
