//! torchvision AlexNet `features` (ImageNet weights), as used by LPIPS-alex.

use candle_core::{Device, Result, Tensor};

use super::Conv;
use crate::weights::{MetricsWeightsError, Weights};

/// torchvision `alexnet().features` indices of the 5 convolutions, and their (out channels, kernel).
pub const ALEXNET_CONVS: [usize; 5] = [0, 3, 6, 8, 10];
pub const ALEXNET_SHAPES: [(usize, usize); 5] = [(64, 11), (192, 5), (384, 3), (256, 3), (256, 3)];

/// (stride, padding) of the five convolutions.
const GEOMETRY: [(usize, usize); 5] = [(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)];

#[derive(Debug, Clone)]
pub struct AlexNet {
    convs: Vec<Conv>,
}

impl AlexNet {
    pub(crate) fn load(w: &Weights, device: &Device) -> std::result::Result<Self, MetricsWeightsError> {
        let mut convs = Vec::with_capacity(5);
        let mut cin = 3;
        for ((&idx, &(co, k)), &(stride, pad)) in ALEXNET_CONVS.iter().zip(&ALEXNET_SHAPES).zip(&GEOMETRY) {
            let weight = w.get(&format!("features.{idx}.weight"), &[co, cin, k, k])?.to_device(device)?;
            let bias = w.get(&format!("features.{idx}.bias"), &[co])?.to_device(device)?;
            convs.push(Conv { weight, bias, stride, pad: (pad, pad) });
            cin = co;
        }
        Ok(Self { convs })
    }

    /// The five ReLU outputs (3×3 stride-2 max pools after the first two).
    pub fn features(&self, x: &Tensor) -> Result<Vec<Tensor>> {
        let r1 = self.convs[0].forward_relu(x)?;
        let r2 = self.convs[1].forward_relu(&super::max_pool2d(&r1, 3, 2, 0)?)?;
        let r3 = self.convs[2].forward_relu(&super::max_pool2d(&r2, 3, 2, 0)?)?;
        let r4 = self.convs[3].forward_relu(&r3)?;
        let r5 = self.convs[4].forward_relu(&r4)?;
        Ok(vec![r1, r2, r3, r4, r5])
    }
}
