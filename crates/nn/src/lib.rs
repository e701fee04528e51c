//! The hand-written kernels the model crates call: one public function per op, with the device choice inside
//! it, so model code never branches on the device. CPU f32 runs tuned kernels (rayon + gemm, custom ops with
//! backward where training needs one); every other device and dtype runs a composition of candle ops, which
//! works on CUDA tensors. `fallback_tests` checks each composition against its CPU kernel on the CPU.
//!
//! | module | functions | CPU | CUDA (today) |
//! |---|---|---|---|
//! | [`conv`] | `conv2d`, `conv2d_fused`, `conv2d_epilogue`, `temporal_conv`, `Conv2d`, `add_bias` | shifted gemm, im2col + gemm (bias: custom op + backward) | candle `conv2d`, matmuls; with `cudnn`: cuDNN with cached plans ([`conv::cudnn`]: tensor-op math in f16/bf16, no TF32 in f32; bias + residual in the call; temporal conv as a (kt, 1) conv on a strided view) |
//! | [`attention`] | `fused_attention`, `multi_head_attention`, `multi_head_attention_seqs` | blocked, no score tensor | matmul + softmax + matmul; `multi_head_attention[_seqs]` with feature `flash-attn` and `flash`: FlashAttention-2 forward (`flash_attn`; f16/bf16, head dim 64, inference only; scripts/build-flash-attn) |
//! | [`softmax`] | `softmax_last`, `masked_softmax` | fused masked kernel | candle softmax / composed |
//! | [`norm`] | `layer_norm`, `group_norm`, `group_norm_act`, `instance_norm` | f64 statistics, fused act (`group_norm_act`, `instance_norm`: custom op + backward when tracked) | composed; `group_norm` with `fused`: cuda/fused.cu (chunk statistics, f64 merge, apply + SiLU) |
//! | [`activation`] | `gelu`, `gelu_inference`, `axpby` | vectorised (gelu: with backward) | candle `gelu_erf`, affine |
//! | [`linear`] | `linear_fused`, `geglu_ff`, `linear_from_channels_first`, `linear_to_channels_first` | gemm, fused epilogue | matmuls; `geglu_ff` with `fused`: bias + split + GELU + product in one kernel (cuda/fused.cu) |
//! | [`grid_sample`] | `grid_sample` | custom op + backward | 4-tap `gather` (composed) |
//! | [`warp_correlation`] | `warp_correlation` | custom op + backward | `grid_sample` · sum over channels |
//! | [`layout`] | `channels_last` | blocked multi-threaded transpose | candle permute + copy |
//! | [`bf16`] | `matmul_bf16`, `Bf16Weights`, `linear::linear_fused_bf16`, `rope::qkv_attention_bf16`, `attention_bf16::fused_attention_bf16`, `warp_correlation::warp_correlation_bf16` (opt-in, inference) | AVX512-BF16 `vdpbf16ps` gemm, fused attention (heads of 64; of 32/64/128 with a region mask) and the correlation's channel dot products (runtime-detected); without it storage only (bf16 weights widened, f32 gemm) or the f32 kernel | — (CPU only) |
//! | [`conv::bf16`] | `conv2d_fused_bf16`, `temporal_conv_bf16`, `Bf16ConvWeights`, `Bf16TemporalWeights`, `conv::winograd::Winograd3x3::new_bf16` (opt-in, inference) | AVX512-BF16 gemm of weights packed once × activations in channel-pair rows (a tap's shifted view, a clip's frames: row offsets); without it storage only (weights widened, the f32 convs) | — (CPU only; elsewhere the f32 path on the widened weights) |
//! | [`upsample`] | `upsample_bilinear`, `upsample_nearest` | custom op + backward / candle | `index_select` lerp / candle |
//!
//! The CUDA column is a composition, not a kernel of ours, unless `MVSPLAT360_GPU_OPS` selects one ([`gpu_ops`];
//! `fused`: GroupNorm and GEGLU, inference only, checked on the CPU by `tests/cuda_emulated.rs`): it materialises what the CPU kernels avoid (the
//! attention scores — in slices of at most 2^26, by batch and then by query rows —, the warped
//! `[N, C, D, h, w]` features). `conv2d_shift` and `conv2d_gemm` (the CPU algorithms by name, for tests and
//! benchmarks) answer [`NotBuilt`] on other devices. On an H200 (2026-11-26) the compositions matched the CPU
//! kernels in `tests/gpu.rs` except where that run notes otherwise (docs/gpu.md).

pub mod activation;
pub mod attention;
mod attention64;
mod attention64_bf16;
pub mod attention_bf16;
pub mod bench;
pub mod bf16;
pub mod conv;
#[cfg(feature = "flash-attn")]
pub mod flash_attn;
#[cfg(feature = "cuda")]
mod fused_cuda;
pub mod gpu_ops;
pub mod grid_sample;
pub mod layout;
pub mod linear;
mod math;
pub mod mode;
pub mod norm;
pub mod prof;
pub mod rope;
pub mod softmax;
pub mod upsample;
pub mod warp_correlation;

#[cfg(test)]
mod fallback_tests;

pub use conv::{conv2d, conv2d_fused, conv2d_gemm, conv2d_shift, Conv2d, Conv2dConfig, ConvEpilogue};
pub use mode::NotBuilt;
