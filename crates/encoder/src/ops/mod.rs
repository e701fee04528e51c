//! Custom tensor ops candle lacks (or lacks a backward for): bilinear `grid_sample` and bilinear / nearest
//! upsampling, both with `align_corners=True` semantics, CPU kernels with rayon and full backward.

pub mod attention;
pub mod grid_sample;
pub mod upsample;
pub mod warp_correlation;

pub use grid_sample::grid_sample;
pub use upsample::{upsample_bilinear, upsample_nearest};
pub use warp_correlation::warp_correlation;
