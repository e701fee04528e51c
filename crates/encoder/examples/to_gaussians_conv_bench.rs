//! `cargo run --release -p mvsplat360-encoder --example to_gaussians_conv_bench [RUNS]`: the Gaussian head's two
//! full-resolution 3×3 convolutions (DL3DV: 5 views 256×448, 163 → 240 → 120 channels) in f32 (shifted gemm),
//! bf16 (direct, `conv2d_fused_bf16`) and bf16 Winograd F(2×2, 3×3), alternated; fastest of each.

use std::time::Instant;

use candle_core::{Device, Tensor};
use mvsplat360_nn::conv::bf16::{conv2d_fused_bf16, Bf16ConvWeights};
use mvsplat360_nn::conv::Winograd3x3;
use mvsplat360_nn::Conv2dConfig;

fn main() {
    let runs: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(2);
    let dev = Device::Cpu;
    let cfg = Conv2dConfig { padding: 1, stride: 1, dilation: 1 };
    for (ci, co) in [(163usize, 240usize), (240, 120)] {
        let x = Tensor::rand(-1f32, 1f32, (5, ci, 256, 448), &dev).unwrap();
        let w = (Tensor::rand(-1f32, 1f32, (co, ci, 3, 3), &dev).unwrap() * (1.0 / (9.0 * ci as f64).sqrt())).unwrap();
        let b = Tensor::rand(-0.1f32, 0.1f32, co, &dev).unwrap();
        let packed = Bf16ConvWeights::from_conv(&w).unwrap();
        let wino = Winograd3x3::new_bf16(&w, Some(&b)).unwrap();
        let time = |f: &dyn Fn() -> Tensor| {
            let t = Instant::now();
            let y = f();
            let _ = y.sum_all().unwrap().to_scalar::<f32>().unwrap();
            t.elapsed().as_secs_f64() * 1e3
        };
        let f32s = || mvsplat360_nn::conv2d_fused(&x, &w, Some(&b), cfg, Default::default()).unwrap();
        let direct = || conv2d_fused_bf16(&x, &packed, Some(&b), cfg, Default::default()).unwrap();
        let winograd = || wino.forward(&x).unwrap();
        let rel = |a: &Tensor, r: &Tensor| {
            let e = (a - r).unwrap().sqr().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap();
            let n = r.sqr().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap();
            (e / n).sqrt()
        };
        let r = f32s();
        println!("{ci} → {co}: rel. RMS against f32: direct bf16 {:.2e}, Winograd bf16 {:.2e}", rel(&direct(), &r), rel(&winograd(), &r));
        drop(r);
        let mut best = [f64::INFINITY; 3];
        for _ in 0..runs {
            for (i, f) in [&f32s as &dyn Fn() -> Tensor, &direct, &winograd].into_iter().enumerate() {
                best[i] = best[i].min(time(f));
            }
        }
        println!(
            "{ci} → {co}: f32 {:.0} ms, bf16 direct {:.0} ms ({:.2}), bf16 Winograd {:.0} ms ({:.2})",
            best[0],
            best[1],
            best[1] / best[0],
            best[2],
            best[2] / best[0]
        );
    }
}
