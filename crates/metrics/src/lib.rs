//! Image-quality metrics of the paper's tables: PSNR, SSIM, LPIPS, DISTS, FID (+ loaders of their pretrained
//! weights). Images are f32 (3, H, W) or (N, 3, H, W) in [0, 1].

// Closed-form metrics and folder scoring.
pub mod bench;
pub mod frechet;
pub mod psnr;
pub mod score;
pub mod ssim;

// Networks with pretrained weights (converted from registry packages into a weights folder).
pub mod dists;
pub mod inception;
pub mod lpips;
pub mod weights;

// Reading the packages' checkpoints (pickle / PyTorch / TorchScript) and the network bodies.
pub mod convert;
mod nets;
