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

/// Depth supervision (not in the official recipe; used where a source knows true depth, see `train.depth_weight`):
/// mean |ln d̂ − ln d| over the pixels that see a surface, the ground truth clamped to the model's [near, far]
/// (the encoder cannot place anything outside it). Log depth weighs near and far errors by their ratio, as
/// the cost volume's inverse-depth candidates do. `pred`, `gt`: (V,H,W) ray distances; `gt` infinite = sky.
pub fn depth_log_l1(pred: &Tensor, gt: &Tensor, near: f32, far: f32) -> Result<Tensor> {
    let g = gt.flatten_all()?.to_vec1::<f32>()?;
    let mask: Vec<f32> = g.iter().map(|d| if d.is_finite() { 1.0 } else { 0.0 }).collect();
    let count: f32 = mask.iter().sum();
    if count == 0.0 {
        return Tensor::zeros((), pred.dtype(), pred.device());
    }
    let log_gt: Vec<f32> = g.iter().map(|&d| if d.is_finite() { d.clamp(near, far).ln() } else { 0.0 }).collect();
    let log_gt = Tensor::from_vec(log_gt, gt.shape(), pred.device())?;
    let mask = Tensor::from_vec(mask, gt.shape(), pred.device())?;
    let err = (pred.log()? - log_gt)?.abs()?.mul(&mask)?;
    err.sum_all()? / count as f64
}
