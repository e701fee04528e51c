//! The refiner's half-precision paths (`--dtype f16`, `--dtype bf16`) against its f32 path (itself checked against the official code's
//! fixtures), on tiny random models. The half models get the same weights, rounded.
//!
//! Tolerance: relative L2 error ‖half − f32‖ / ‖f32‖ ≤ 16·u, u = the format's unit roundoff (f16 2⁻¹¹, bf16 2⁻⁸).
//! Error model: a product whose operands are rounded (RMS relative error u/√3 each) is off by a relative RMS
//! ρ ≈ √2·u/√3 ≈ 0.82u when both operands are rounded (bf16) and ≈ 0.58u when only the weights are (f16
//! store). The errors of different layers are independent, and these models renormalise before every product,
//! so relative errors pass through with a gain of about 1: after P products on the longest path the output is
//! off by ≈ √P·ρ. The tiny UNet has P ≈ 150 (≈ 21 per level of res block + transformer, ×7 with the middle and
//! the up path) → ≈ 10u; the VAE and CLIP have far fewer. 16u leaves a 1.6× margin for the gain. Measured
//! 0.2–3 u. An op that overflows or a tensor mixed up gives an error of order 1, ≥ 100× the bound (a layer
//! left unrounded only lowers the error). The error must also be non-zero, which proves that the
//! half-precision path ran.

use candle_core::{DType, Device, Tensor};
use mvsplat360_refiner::clip::{ClipImageEmbedder, ClipVisionConfig};
use mvsplat360_refiner::unet::util::timestep_embedding;
use mvsplat360_refiner::unet::{UNetInputs, VideoUNet, VideoUNetConfig};
use mvsplat360_refiner::vae::{AutoencoderConfig, AutoencoderKL};

fn rel_l2(a: &Tensor, b: &Tensor) -> f64 {
    let a = a.to_dtype(DType::F64).unwrap();
    let b = b.to_dtype(DType::F64).unwrap();
    let num = (&a - &b).unwrap().sqr().unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap().sqrt();
    let den = b.sqr().unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap().sqrt();
    num / den.max(1e-30)
}

/// On the CPU the activations stay f32 and only the products' weights change: f16 stores them in f16 and
/// widens them per call (f32 arithmetic, u = 2⁻¹¹), bf16 packs them for `nn::bf16` (`vdpbf16ps` with
/// AVX512-BF16, activations rounded too; storage only without), u = 2⁻⁸. Both are checked on a GPU by
/// crates/pipeline/tests/gpu.rs.
const HALF: [(DType, f64); 2] = [(DType::F16, 1.0 / 2048.0), (DType::BF16, 1.0 / 256.0)];

/// The dtype a model built "in `dtype`" on the CPU computes in: f32.
fn activations(_dtype: DType) -> DType {
    DType::F32
}

fn check(what: &str, dtype: DType, u: f64, half: &Tensor, full: &Tensor) {
    assert_eq!(half.dtype(), DType::F32, "{what} {dtype:?}: output must come back as f32");
    assert_eq!(half.dims(), full.dims(), "{what} {dtype:?}");
    let e = rel_l2(half, full);
    eprintln!("{what} {dtype:?}: relative L2 error {e:.2e} ({:.2} u)", e / u);
    assert!(e > 0.0, "{what} {dtype:?}: identical to f32, so the half-precision path did not run");
    assert!(e <= 16.0 * u, "{what} {dtype:?}: relative L2 error {e:.2e} > 16u = {:.2e}", 16.0 * u);
}

#[test]
fn unet_in_half_precision_matches_f32() {
    let dev = Device::Cpu;
    let cfg = VideoUNetConfig::tiny();
    let f = 3;
    let x = Tensor::randn(0f32, 1.0, (f, 8, 8, 12), &dev).unwrap();
    let ctx = Tensor::randn(0f32, 1.0, (f, 2, 32), &dev).unwrap();
    let y = timestep_embedding(&[0.02; 3], 32, 10000.0, &dev).unwrap();
    let ts = [0.3f32, -0.2, 0.7];
    let run = |m: &VideoUNet| m.forward(&UNetInputs { x: &x, timesteps: &ts, context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None }).unwrap();
    let full = run(&VideoUNet::random(&cfg, 11, &dev).unwrap());
    for (dtype, u) in HALF {
        let m = VideoUNet::random_as(&cfg, 11, &dev, dtype).unwrap();
        assert_eq!(m.dtype(), activations(dtype));
        let half = run(&m);
        check("UNet", dtype, u, &half, &full);
        if dtype == DType::BF16 && mvsplat360_nn::bf16::hardware_dpbf16() {
            // Masked: the same packed weights, products in f32 (storage only) — within the bound, and not the
            // `vdpbf16ps` result (its activations are rounded too), so the mask reached the dispatch.
            let stored = mvsplat360_nn::bf16::with_bf16_masked(|| run(&m));
            check("UNet (bf16 storage only)", dtype, u, &stored, &full);
            let d = (&stored - &half).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(d > 0.0, "masked run equals the vdpbf16ps run: the mask did not reach the products");
        }
    }
}

/// Heads of 64 (as SVD's): in CPU bf16 the spatial self-attention runs on the packed `[q; k; v]` projection and
/// the fused bf16 attention kernel (the tiny model's heads of 16 take the f32 kernel), same bound.
#[test]
fn unet_with_heads_of_64_in_bf16_matches_f32() {
    let dev = Device::Cpu;
    let cfg = VideoUNetConfig { model_channels: 64, num_head_channels: 64, channel_mult: vec![1], attention_resolutions: vec![1], ..VideoUNetConfig::tiny() };
    let f = 2;
    let x = Tensor::randn(0f32, 1.0, (2 * f, 8, 8, 10), &dev).unwrap();
    let ctx = Tensor::randn(0f32, 1.0, (2 * f, 1, 32), &dev).unwrap();
    let y = timestep_embedding(&[0.02; 4], 32, 10000.0, &dev).unwrap();
    let ts = [0.3f32, -0.2, 0.7, 0.1];
    let run = |m: &VideoUNet| m.forward(&UNetInputs { x: &x, timesteps: &ts, context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None }).unwrap();
    let full = run(&VideoUNet::random(&cfg, 12, &dev).unwrap());
    let m = VideoUNet::random_as(&cfg, 12, &dev, DType::BF16).unwrap();
    let half = run(&m);
    check("UNet, heads of 64", DType::BF16, 1.0 / 256.0, &half, &full);
}

#[test]
fn vae_in_half_precision_matches_f32() {
    let dev = Device::Cpu;
    let cfg = AutoencoderConfig { ch: 32, ch_mult: vec![1, 2], num_res_blocks: 1, ..AutoencoderConfig::default() };
    let img = Tensor::rand(-1f32, 1.0, (2, 3, 8, 12), &dev).unwrap();
    let z = Tensor::randn(0f32, 1.0, (3, 4, 4, 6), &dev).unwrap();
    let full = AutoencoderKL::random(&cfg, 5, &dev).unwrap();
    let (fm, _) = full.encode(&img).unwrap();
    let fd = full.decode(&z, 3).unwrap();
    for (dtype, u) in HALF {
        let m = AutoencoderKL::random_as(&cfg, 5, &dev, dtype).unwrap();
        check("VAE encode (mean)", dtype, u, &m.encode(&img).unwrap().0, &fm);
        check("VAE decode", dtype, u, &m.decode(&z, 3).unwrap(), &fd);
    }
}

#[test]
fn clip_in_half_precision_matches_f32() {
    let dev = Device::Cpu;
    let cfg = ClipVisionConfig { width: 32, layers: 2, heads: 2, mlp_width: 64, patch_size: 8, image_size: 32, output_dim: 32, ..ClipVisionConfig::default() };
    let views = Tensor::rand(0f32, 1.0, (1, 2, 3, 24, 40), &dev).unwrap();
    let full = ClipImageEmbedder::random(&cfg, 3, &dev).unwrap().embed_mean(&views).unwrap();
    for (dtype, u) in HALF {
        let m = ClipImageEmbedder::random_as(&cfg, 3, &dev, dtype).unwrap();
        check("CLIP", dtype, u, &m.embed_mean(&views).unwrap(), &full);
    }
}
