//! Building blocks shared by the model crates (encoder, refiner). candle's CPU conv2d is several times slower
//! than a matrix product of the same size; [`conv2d`] lowers convolutions to one gemm per image.

pub mod conv;

pub use conv::{conv2d, conv2d_fused, conv2d_gemm, conv2d_shift, Conv2d, Conv2dConfig, ConvEpilogue};
