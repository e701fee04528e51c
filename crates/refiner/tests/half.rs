//! The refiner's half-precision path (`--dtype f16`) against its f32 path (itself checked against the official code's
//! fixtures), on tiny random models. The half models get the same weights, rounded.
//!
//! Tolerance: relative L2 error ‖half − f32‖ / ‖f32‖ ≤ 16·u, u = the format's unit roundoff (f16 2⁻¹¹).
//! Rounding the weights and activations alone puts an error of about u into every layer, and these models
//! are a few normalised layers deep: measured 1.0–8.1 u over repeated random inputs. An op that overflows in
//! half precision or mixes up a tensor gives an error of order 1, ≥ 100× the bound. The error must also be
//! non-zero, which proves that the half-precision path ran.

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

/// f16 on the CPU in candle's f16 ops; bf16 on the CPU: f32 activations, the products' weights packed in bf16
/// (`nn::bf16`: `vdpbf16ps` with AVX512-BF16, storage only without), u = 2⁻⁸. bf16 on a GPU is checked by
/// crates/pipeline/tests/gpu.rs.
const HALF: [(DType, f64); 2] = [(DType::F16, 1.0 / 2048.0), (DType::BF16, 1.0 / 256.0)];

/// The dtype a model built "in `dtype`" on the CPU computes in: bf16 keeps f32 activations.
fn activations(dtype: DType) -> DType {
    if dtype == DType::BF16 {
        DType::F32
    } else {
        dtype
    }
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
