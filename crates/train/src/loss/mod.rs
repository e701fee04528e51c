//! Training losses, with the official formulas and weights.

pub mod diffusion;

use candle_core::{Result, Tensor};
use mvsplat360_metrics::lpips::Lpips;

/// Official `LossMse`: mean over all pixels, channels and target views of (render − target)².
pub fn mse(pred: &Tensor, gt: &Tensor) -> Result<Tensor> {
    (pred - gt)?.sqr()?.mean_all()
}

/// Official `LossLpips`: VGG LPIPS on images in [0, 1] (normalised to [−1, 1] inside), mean over target views.
pub fn lpips(net: &Lpips, pred: &Tensor, gt: &Tensor) -> Result<Tensor> {
    net.forward(pred, gt)?.mean_all()
}
