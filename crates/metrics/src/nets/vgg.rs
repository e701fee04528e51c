//! torchvision VGG16 `features` (ImageNet weights), as used by LPIPS-vgg and DISTS.

use candle_core::{Device, Result, Tensor};

use super::Conv;
use crate::weights::{MetricsWeightsError, Weights};

/// torchvision `vgg16().features` indices of the 13 convolutions.
pub const VGG16_CONVS: [usize; 13] = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28];
/// Output channels of those convolutions.
pub const VGG16_CHANNELS: [usize; 13] = [64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512];

/// Convolutions (3×3, padding 1) of each stage; a stage ends at relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
pub const STAGES: [std::ops::Range<usize>; 5] = [0..2, 2..4, 4..7, 7..10, 10..13];

#[derive(Debug, Clone)]
pub struct Vgg16 {
    convs: Vec<Conv>,
}

impl Vgg16 {
    pub(crate) fn load(w: &Weights, device: &Device) -> std::result::Result<Self, MetricsWeightsError> {
        let mut convs = Vec::with_capacity(13);
        let mut cin = 3;
        for (&idx, &co) in VGG16_CONVS.iter().zip(&VGG16_CHANNELS) {
            let weight = w.get(&format!("features.{idx}.weight"), &[co, cin, 3, 3])?.to_device(device)?;
            let bias = w.get(&format!("features.{idx}.bias"), &[co])?.to_device(device)?;
            convs.push(Conv { weight, bias, stride: 1, pad: (1, 1) });
            cin = co;
        }
        Ok(Self { convs })
    }

    /// The convs (+ ReLU) of stage `s` (no pooling).
    pub fn stage(&self, s: usize, x: &Tensor) -> Result<Tensor> {
        let mut h = x.clone();
        for c in &self.convs[STAGES[s].clone()] {
            h = c.forward_relu(&h)?;
        }
        Ok(h)
    }

    /// relu1_2 … relu5_3 with 2×2 max pools between the stages (torchvision / LPIPS).
    pub fn features(&self, x: &Tensor) -> Result<Vec<Tensor>> {
        let mut out: Vec<Tensor> = Vec::with_capacity(5);
        for s in 0..5 {
            let input = match out.last() {
                None => x.clone(),
                Some(prev) => super::max_pool2d(prev, 2, 2, 0)?,
            };
            out.push(self.stage(s, &input)?);
        }
        Ok(out)
    }
}
