//! UniMatch `CNNEncoder` at 1/4 resolution (`num_output_scales = 0` in the official multi-view backbone, which
//! keeps layer3 at stride 1): conv7×7/2 → IN → ReLU → layer1 (64) → layer2 (96, /2) → layer3 (128) → conv1×1.

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

use crate::backbone::nn::Conv2d;
use mvsplat360_nn::norm::instance_norm;

/// `ResidualBlock` with InstanceNorm (no affine) and a strided 1×1 conv + IN shortcut when the shape changes.
#[derive(Debug, Clone)]
pub struct ResidualBlock {
    conv1: Conv2d,
    conv2: Conv2d,
    downsample: Option<Conv2d>,
}

impl ResidualBlock {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, stride: usize) -> Result<Self> {
        let conv1 = Conv2d::new(vb.pp("conv1"), c_in, c_out, 3, stride, 1, false)?;
        let conv2 = Conv2d::new(vb.pp("conv2"), c_out, c_out, 3, 1, 1, false)?;
        let downsample = if stride != 1 || c_in != c_out { Some(Conv2d::new(vb.pp("downsample").pp("0"), c_in, c_out, 1, stride, 0, true)?) } else { None };
        Ok(Self { conv1, conv2, downsample })
    }

    pub fn pack_bf16(&mut self) -> Result<()> {
        self.conv1.pack_bf16()?;
        self.conv2.pack_bf16()?;
        self.downsample.as_mut().map(Conv2d::pack_bf16).transpose()?;
        Ok(())
    }
}

impl Module for ResidualBlock {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = instance_norm(&self.conv1.forward(x)?)?.relu()?;
        let y = instance_norm(&self.conv2.forward(&y)?)?.relu()?;
        let x = match &self.downsample {
            Some(d) => instance_norm(&d.forward(x)?)?,
            None => x.clone(),
        };
        (x + y)?.relu()
    }
}

#[derive(Debug, Clone)]
pub struct CnnEncoder {
    conv1: Conv2d,
    layers: Vec<ResidualBlock>,
    conv2: Conv2d,
}

/// The official widths of the three stages (hard-coded in unimatch's `CNNEncoder`).
pub const FEATURE_DIMS: [usize; 3] = [64, 96, 128];

impl CnnEncoder {
    /// `vb` = `encoder.backbone.backbone`; `dims` = the stages' widths ([`FEATURE_DIMS`] officially).
    pub fn new(vb: VarBuilder, dims: [usize; 3], output_dim: usize) -> Result<Self> {
        let conv1 = Conv2d::new(vb.pp("conv1"), 3, dims[0], 7, 2, 3, false)?;
        let strides = [1, 2, 1];
        let mut layers = Vec::with_capacity(6);
        let mut c_in = dims[0];
        for (i, (&dim, &stride)) in dims.iter().zip(strides.iter()).enumerate() {
            let lvb = vb.pp(format!("layer{}", i + 1));
            layers.push(ResidualBlock::new(lvb.pp("0"), c_in, dim, stride)?);
            layers.push(ResidualBlock::new(lvb.pp("1"), dim, dim, 1)?);
            c_in = dim;
        }
        let conv2 = Conv2d::new(vb.pp("conv2"), dims[2], output_dim, 1, 1, 0, true)?;
        Ok(Self { conv1, layers, conv2 })
    }

    /// Every convolution's weight packed in bf16 (CPU inference; see [`crate::bf16`]).
    pub fn pack_bf16(&mut self) -> Result<()> {
        self.conv1.pack_bf16()?;
        self.layers.iter_mut().try_for_each(ResidualBlock::pack_bf16)?;
        self.conv2.pack_bf16()
    }
}

impl Module for CnnEncoder {
    /// `[N,3,H,W]` (ImageNet-normalised) → `[N,C,H/4,W/4]`.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut x = instance_norm(&self.conv1.forward(x)?)?.relu()?;
        for l in &self.layers {
            x = l.forward(&x)?;
        }
        self.conv2.forward(&x)
    }
}
