//! Benchmark (issue 73): f32 `conv2d_fused` vs `conv2d_fused_bf16` and `temporal_conv` vs `temporal_conv_bf16`
//! on the SVD UNet's and its VAE decoder's shapes. GFLOP/s count the direct convolution's 2·taps·C_in·C_out·pixels.
//! `cargo run --release -p mvsplat360-lab --example conv_bf16_bench [RUNS]`: one warm-up pair, then RUNS
//! (default 3) f32/bf16 pairs alternated run by run (the machine is shared: a change of load meets both); the
//! fastest and the median of each, and the fastest bf16 / fastest f32 time.

use std::time::Instant;

use candle_core::{Device, Tensor};
use mvsplat360_nn::bf16::path;
use mvsplat360_nn::conv::bf16::{conv2d_fused_bf16, temporal_conv_bf16, Bf16ConvWeights, Bf16TemporalWeights};
use mvsplat360_nn::conv::temporal_conv;
use mvsplat360_nn::{conv2d_fused, Conv2dConfig, ConvEpilogue};

fn secs(f: impl FnOnce() -> Tensor) -> (f64, Tensor) {
    let s = Instant::now();
    let y = f();
    (s.elapsed().as_secs_f64(), y)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

/// Alternates `f32` and `bf16` runs; prints one line and returns (fastest f32, fastest bf16).
fn compare(name: &str, flop: f64, runs: usize, f32_run: impl Fn() -> Tensor, bf16_run: impl Fn() -> Tensor) -> (f64, f64) {
    let (_, y32) = secs(&f32_run);
    let (_, y16) = secs(&bf16_run);
    let rel = ((&y16 - &y32).unwrap().sqr().unwrap().mean_all().unwrap().to_scalar::<f32>().unwrap()
        / y32.sqr().unwrap().mean_all().unwrap().to_scalar::<f32>().unwrap())
    .sqrt();
    drop((y32, y16));
    let (mut t32, mut t16) = (Vec::new(), Vec::new());
    for _ in 0..runs {
        t32.push(secs(&f32_run).0);
        t16.push(secs(&bf16_run).0);
    }
    let (b32, b16) = (t32.iter().cloned().fold(f64::MAX, f64::min), t16.iter().cloned().fold(f64::MAX, f64::min));
    println!(
        "{name:34} f32 {:8.1} ms (median {:8.1}) {:6.1} GF/s | bf16 {:8.1} ms (median {:8.1}) {:6.1} GF/s | bf16/f32 {:.2} | rel rms {:.1e}",
        b32 * 1e3,
        median(t32) * 1e3,
        flop / b32 / 1e9,
        b16 * 1e3,
        median(t16) * 1e3,
        flop / b16 / 1e9,
        b16 / b32,
        rel
    );
    (b32, b16)
}

fn load() -> String {
    std::fs::read_to_string("/proc/loadavg").unwrap_or_default().split_whitespace().take(3).collect::<Vec<_>>().join(" ")
}

fn main() -> candle_core::Result<()> {
    let runs: usize = std::env::args().nth(1).map(|a| a.parse().expect("RUNS: a number")).unwrap_or(3);
    let d = Device::Cpu;
    println!("threads {}, path {}, runs {runs} (fastest, after a warm-up pair), load {}", rayon::current_num_threads(), path().name(), load());
    // (name, N, C_in, C_out, H, W, k): the UNet's 3×3 convs per level at a 64×112 latent (4 items: 2 frames ×
    // guidance pair would be 28; 4 keeps a run short), the up path's skip-concat input, the VAE decoder's.
    let shapes = [
        ("unet 320 64x112", 4, 320, 320, 64, 112, 3),
        ("unet 640 32x56", 4, 640, 640, 32, 56, 3),
        ("unet 1280 16x28", 4, 1280, 1280, 16, 28, 3),
        ("unet 1280 8x14", 4, 1280, 1280, 8, 14, 3),
        ("unet skip 2560->1280 16x28", 4, 2560, 1280, 16, 28, 3),
        ("unet 1x1 skip 2560->1280 16x28", 4, 2560, 1280, 16, 28, 1),
        ("vae dec 512 64x112", 1, 512, 512, 64, 112, 3),
        ("vae dec 128 512x896", 1, 128, 128, 512, 896, 3),
    ];
    let (mut sum32, mut sum16) = (0.0, 0.0);
    for (name, n, ci, co, h, w, k) in shapes {
        let x = Tensor::randn(0f32, 1.0, (n, ci, h, w), &d)?;
        let wt = (Tensor::randn(0f32, 1.0, (co, ci, k, k), &d)? / ((k * k * ci) as f64).sqrt())?;
        let b = Tensor::randn(0f32, 0.1, co, &d)?;
        let r = Tensor::randn(0f32, 1.0, (n, co, h, w), &d)?;
        let s = Instant::now();
        let wb = Bf16ConvWeights::from_conv(&wt)?;
        let pack = s.elapsed().as_secs_f64();
        let cfg = Conv2dConfig { padding: k / 2, stride: 1, dilation: 1 };
        let epi = ConvEpilogue { residual: Some(&r), scale: Some(0.5), ..Default::default() };
        let flop = 2.0 * (k * k * ci * co * h * w * n) as f64;
        let (a, b16) =
            compare(name, flop, runs, || conv2d_fused(&x, &wt, Some(&b), cfg, epi).unwrap(), || conv2d_fused_bf16(&x, &wb, Some(&b), cfg, epi).unwrap());
        println!(
            "{:34} weights packed in {:.1} ms, {:.1} MiB (f32 {:.1} MiB)",
            "",
            pack * 1e3,
            wb.bytes() as f64 / (1 << 20) as f64,
            (4 * co * ci * k * k) as f64 / (1 << 20) as f64
        );
        sum32 += a;
        sum16 += b16;
    }
    // The downsamplers: 3×3 stride 2.
    for (name, n, c, h, w) in [("unet down 320 64x112 s2", 4, 320, 64, 112), ("unet down 640 32x56 s2", 4, 640, 32, 56)] {
        let x = Tensor::randn(0f32, 1.0, (n, c, h, w), &d)?;
        let wt = (Tensor::randn(0f32, 1.0, (c, c, 3, 3), &d)? / ((9 * c) as f64).sqrt())?;
        let b = Tensor::randn(0f32, 0.1, c, &d)?;
        let wb = Bf16ConvWeights::from_conv(&wt)?;
        let cfg = Conv2dConfig { padding: 1, stride: 2, dilation: 1 };
        let flop = 2.0 * (9 * c * c * (h / 2) * (w / 2) * n) as f64;
        let (a, b16) = compare(
            name,
            flop,
            runs,
            || conv2d_fused(&x, &wt, Some(&b), cfg, ConvEpilogue::default()).unwrap(),
            || conv2d_fused_bf16(&x, &wb, Some(&b), cfg, ConvEpilogue::default()).unwrap(),
        );
        sum32 += a;
        sum16 += b16;
    }
    // Temporal (3, 1, 1) conv: 2 clips of 14 frames.
    let (n, c, h, w, kt, frames) = (28, 320, 64, 112, 3, 14);
    let x = Tensor::randn(0f32, 1.0, (n, c, h, w), &d)?;
    let wt = (Tensor::randn(0f32, 1.0, (c, kt * c), &d)? / ((kt * c) as f64).sqrt())?;
    let b = Tensor::randn(0f32, 0.1, c, &d)?;
    let r = Tensor::randn(0f32, 1.0, (n, c, h, w), &d)?;
    let wb = Bf16TemporalWeights::from_temporal(&wt, kt)?;
    // Taps used: kt per frame but one fewer at each clip edge.
    let taps = (kt * frames - 2) * (n / frames);
    let flop = 2.0 * (taps * c * c * h * w) as f64;
    let (a, b16) = compare(
        "temporal 320 64x112 kt3 x28",
        flop,
        runs,
        || temporal_conv(&x, &wt, &b, kt, frames, None, Some(&r), 0.5).unwrap(),
        || temporal_conv_bf16(&x, &wb, &b, kt, frames, None, Some(&r), 0.5).unwrap(),
    );
    sum32 += a;
    sum16 += b16;
    println!("all shapes: f32 {:.1} ms, bf16 {:.1} ms, bf16/f32 {:.2}; load {}", sum32 * 1e3, sum16 * 1e3, sum16 / sum32, load());
    Ok(())
}
