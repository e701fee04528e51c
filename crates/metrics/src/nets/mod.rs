//! The networks behind LPIPS, DISTS and FID, built from candle ops (convolutions through
//! `mvsplat360_nn::conv2d`, which records a backward), with the pooling written so that it is differentiable
//! for any input size (candle's own pools have no backward unless kernel == stride and the size divides).

pub mod alexnet;
pub mod inception;
pub mod vgg;

use candle_core::{Result, Tensor, D};
use mvsplat360_nn::{conv2d, Conv2dConfig};

/// A convolution with bias; `pad` is (top/bottom, left/right).
#[derive(Debug, Clone)]
pub struct Conv {
    pub weight: Tensor,
    pub bias: Tensor,
    pub stride: usize,
    pub pad: (usize, usize),
}

impl Conv {
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (ph, pw) = self.pad;
        let cfg = |p| Conv2dConfig { padding: p, stride: self.stride, dilation: 1 };
        if ph == pw {
            return conv2d(x, &self.weight, Some(&self.bias), cfg(ph));
        }
        let x = x.pad_with_zeros(2, ph, ph)?.pad_with_zeros(3, pw, pw)?;
        conv2d(&x, &self.weight, Some(&self.bias), cfg(0))
    }

    pub fn forward_relu(&self, x: &Tensor) -> Result<Tensor> {
        self.forward(x)?.relu()
    }
}

/// `x[.., start + stride·i, ..]` for i < count along `dim` (differentiable: narrow / reshape / squeeze).
pub fn strided(x: &Tensor, dim: usize, start: usize, stride: usize, count: usize) -> Result<Tensor> {
    if stride == 1 {
        return x.narrow(dim, start, count);
    }
    let len = x.dim(dim)?;
    let need = start + stride * count;
    // Elements past the end are only ever dropped by the final narrow: pad with anything.
    let x = if need > len { x.pad_with_same(dim, 0, need - len)? } else { x.clone() };
    let x = x.narrow(dim, start, stride * count)?;
    let mut shape = x.dims().to_vec();
    shape[dim] = count;
    shape.insert(dim + 1, stride);
    x.reshape(shape)?.narrow(dim + 1, 0, 1)?.squeeze(dim + 1)
}

fn out_len(len: usize, k: usize, s: usize, pad: usize) -> usize {
    (len + 2 * pad - k) / s + 1
}

/// Max pool along one dim (kernel `k`, stride `s`, `pad` each side, floor mode).
fn max_pool_1d(x: &Tensor, dim: usize, k: usize, s: usize, pad: usize) -> Result<Tensor> {
    let n = out_len(x.dim(dim)?, k, s, pad);
    // Edge replication never changes a max (the replicated value is inside the same window).
    let x = if pad > 0 { x.pad_with_same(dim, pad, pad)? } else { x.clone() };
    if k == s {
        let x = x.narrow(dim, 0, n * k)?;
        let mut shape = x.dims().to_vec();
        shape[dim] = n;
        shape.insert(dim + 1, k);
        return x.reshape(shape)?.max(dim + 1);
    }
    let mut acc = strided(&x, dim, 0, s, n)?;
    for j in 1..k {
        acc = acc.maximum(&strided(&x, dim, j, s, n)?)?;
    }
    Ok(acc)
}

/// 2-D max pool of (N, C, H, W), square kernel, PyTorch semantics (padding counts as −∞, floor mode).
pub fn max_pool2d(x: &Tensor, k: usize, s: usize, pad: usize) -> Result<Tensor> {
    max_pool_1d(&max_pool_1d(x, 3, k, s, pad)?, 2, k, s, pad)
}

/// Separable filter `taps` along one dim with stride `s` and `pad` zeros each side.
fn filter_1d(x: &Tensor, dim: usize, taps: &[f64], s: usize, pad: usize) -> Result<Tensor> {
    let n = out_len(x.dim(dim)?, taps.len(), s, pad);
    let x = if pad > 0 { x.pad_with_zeros(dim, pad, pad)? } else { x.clone() };
    let mut acc = (strided(&x, dim, 0, s, n)? * taps[0])?;
    for (j, &t) in taps.iter().enumerate().skip(1) {
        acc = (acc + (strided(&x, dim, j, s, n)? * t)?)?;
    }
    Ok(acc)
}

/// Depthwise separable filter `taps ⊗ taps` of (N, C, H, W).
pub fn filter2d(x: &Tensor, taps: &[f64], s: usize, pad: usize) -> Result<Tensor> {
    filter_1d(&filter_1d(x, 3, taps, s, pad)?, 2, taps, s, pad)
}

/// Mean over H and W of (N, C, H, W) → (N, C).
pub fn spatial_mean(x: &Tensor) -> Result<Tensor> {
    x.flatten_from(2)?.mean(D::Minus1)
}
