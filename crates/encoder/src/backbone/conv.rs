//! The backbone's convolution entry point: the workspace's im2col+gemm conv (falls back to candle's conv2d where
//! that is faster, and on non-CPU devices).

use candle_core::{Result, Tensor};

/// `F.conv2d(x, w, stride=stride, padding=padding)` for `x [N,Cin,H,W]`, `w [Cout,Cin,k,k]`.
pub fn conv2d(x: &Tensor, w: &Tensor, stride: usize, padding: usize) -> Result<Tensor> {
    mvsplat360_nn::conv2d(x, w, None, mvsplat360_nn::Conv2dConfig { padding, stride, dilation: 1 })
}
