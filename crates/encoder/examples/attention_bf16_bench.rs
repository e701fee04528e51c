//! `cargo run --release -p mvsplat360-encoder --example attention_bf16_bench [RUNS]`: the encoder's attention
//! and correlation kernels in f32 and bf16 at the DL3DV shapes (5 views 256×448: feature map 64×112, 2×2
//! windows of 1792 tokens), alternated run by run; fastest of each (the machine is shared).

use std::time::Instant;

use candle_core::{Device, Tensor};
use mvsplat360_encoder::backbone::unimatch::utils::shifted_window_labels;
use mvsplat360_nn::attention::{fused_attention, RegionMask};
use mvsplat360_nn::attention_bf16::fused_attention_bf16;
use mvsplat360_nn::warp_correlation::{warp_correlation, warp_correlation_bf16};

fn rand(shape: &[usize], amp: f64) -> Tensor {
    (Tensor::rand(-1f32, 1f32, shape, &Device::Cpu).unwrap() * amp).unwrap()
}

fn time(f: &dyn Fn() -> Tensor) -> f64 {
    let t = Instant::now();
    let y = f();
    let _ = y.sum_all().unwrap().to_scalar::<f32>().unwrap();
    t.elapsed().as_secs_f64() * 1e3
}

fn main() {
    let runs: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(3);
    let (h, w, k, c) = (64usize, 112usize, 2usize, 128usize);
    let lw = h * w / (k * k);
    let (views, windows) = (5usize, 5 * k * k);
    let mask = |m: usize| {
        let (q_labels, k_labels) = shifted_window_labels(h, w, k, m);
        RegionMask { q_labels, k_labels, p: k * k }
    };
    let (self_mask, cross_mask) = (mask(1), mask(2));
    let q = rand(&[windows, lw, c], 1.0 / (c as f64).sqrt());
    let (ks, vs) = (rand(&[windows, lw, c], 1.0), rand(&[windows, lw, c], 1.0));
    let (kc, vc) = (rand(&[windows, 2 * lw, c], 1.0), rand(&[windows, 2 * lw, c], 1.0));
    // The cost-volume UNet's attention: 4 heads of 32 over 5 views of 16×28 tokens, q and k scaled by 32^-1/4.
    let tok = views * 16 * 28;
    let (qu, ku, vu) = (rand(&[4, tok, 32], 0.42), rand(&[4, tok, 32], 0.42), rand(&[4, tok, 32], 1.0));
    // The cost volume: 5 views × 128 candidates from one neighbour, features 128 × 64×112.
    let (fr, fs) = (rand(&[views, c, h, w], 1.0), rand(&[views, c, h, w], 1.0));
    let grid: Vec<f32> =
        (0..views * 128 * h * w).flat_map(|i| [((i % w) as f32 / w as f32) * 2.1 - 1.05, ((i / w % h) as f32 / h as f32) * 2.0 - 1.0]).collect();
    type Case<'a> = (&'a str, Box<dyn Fn(bool) -> Tensor + 'a>);
    let cases: Vec<Case> = vec![
        (
            "window self-attention, one layer (masked)",
            Box::new(|b| (if b { fused_attention_bf16 } else { fused_attention })(&q, &ks, &vs, Some(&self_mask)).unwrap()),
        ),
        (
            "window cross-attention, one layer (2 key views, masked)",
            Box::new(|b| (if b { fused_attention_bf16 } else { fused_attention })(&q, &kc, &vc, Some(&cross_mask)).unwrap()),
        ),
        ("UNet attention, 4 heads of 32", Box::new(|b| (if b { fused_attention_bf16 } else { fused_attention })(&qu, &ku, &vu, None).unwrap())),
        ("warp correlation, one neighbour", Box::new(|b| (if b { warp_correlation_bf16 } else { warp_correlation })(&fr, &fs, &grid, 128).unwrap())),
    ];
    for (name, f) in &cases {
        let (mut f32s, mut bf16s) = (f64::INFINITY, f64::INFINITY);
        let _ = (time(&|| f(false)), time(&|| f(true)));
        for _ in 0..runs {
            f32s = f32s.min(time(&|| f(false)));
            bf16s = bf16s.min(time(&|| f(true)));
        }
        println!("{name}: f32 {f32s:.1} ms, bf16 {bf16s:.1} ms, bf16/f32 {:.2}", bf16s / f32s);
    }
}
