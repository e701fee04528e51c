//! The hand-written kernels the model crates call: one public function per op, with the device choice inside
//! it, so model code never branches on the device. CPU f32 runs tuned kernels (rayon + gemm, custom ops with
//! backward where training needs one); every other device and dtype runs a composition of candle ops, which
//! works on CUDA tensors. `fallback_tests` checks each composition against its CPU kernel on the CPU.
//!
//! | module | functions | CPU | CUDA (today) |
//! |---|---|---|---|
//! | [`conv`] | `conv2d`, `conv2d_fused`, `conv2d_epilogue`, `temporal_conv`, `Conv2d`, `add_bias` | shifted gemm, im2col + gemm (bias: custom op + backward) | candle `conv2d`, matmuls |
//! | [`attention`] | `fused_attention`, `multi_head_attention`, `multi_head_attention_seqs` | blocked, no score tensor | matmul + softmax + matmul |
//! | [`softmax`] | `softmax_last`, `masked_softmax` | fused masked kernel | candle softmax / composed |
//! | [`norm`] | `layer_norm`, `group_norm`, `group_norm_act`, `instance_norm` | f64 statistics, fused act (`group_norm_act`, `instance_norm`: custom op + backward when tracked) | composed |
//! | [`activation`] | `gelu`, `gelu_inference`, `axpby` | vectorised (gelu: with backward) | candle `gelu_erf`, affine |
//! | [`linear`] | `linear_fused`, `geglu_ff`, `linear_from_channels_first`, `linear_to_channels_first` | gemm, fused epilogue | matmuls |
//! | [`grid_sample`] | `grid_sample` | custom op + backward | 4-tap `gather` (composed) |
//! | [`warp_correlation`] | `warp_correlation` | custom op + backward | `grid_sample` · sum over channels |
//! | [`layout`] | `channels_last` | blocked multi-threaded transpose | candle permute + copy |
//! | [`upsample`] | `upsample_bilinear`, `upsample_nearest` | custom op + backward / candle | `index_select` lerp / candle |
//!
//! The CUDA column is a composition, not a kernel of ours: it materialises what the CPU kernels avoid (the
//! attention scores — in slices of at most 2^26, by batch and then by query rows —, the warped
//! `[N, C, D, h, w]` features). `conv2d_shift` and `conv2d_gemm` (the CPU algorithms by name, for tests and
//! benchmarks) answer [`NotBuilt`] on other devices. On an H200 (2026-11-26) the compositions matched the CPU
//! kernels in `tests/gpu.rs` except where that run notes otherwise (README, GPU).

pub mod activation;
pub mod attention;
pub mod bench;
pub mod conv;
pub mod grid_sample;
pub mod layout;
pub mod linear;
mod math;
pub mod mode;
pub mod norm;
pub mod softmax;
pub mod upsample;
pub mod warp_correlation;

#[cfg(test)]
mod fallback_tests;

pub use conv::{conv2d, conv2d_fused, conv2d_gemm, conv2d_shift, Conv2d, Conv2dConfig, ConvEpilogue};
pub use mode::NotBuilt;
