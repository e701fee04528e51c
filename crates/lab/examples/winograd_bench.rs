//! Exploration benchmark (issue 69): `conv2d` (shifted gemms) vs `Winograd3x3` on the VGGT DPT head's 3×3
//! stride-1 convolutions, 5 frames of 518×294. GFLOP/s count the direct convolution's 2·9·C_in·C_out·H·W·N.
//! `cargo run --release -p mvsplat360-lab --example winograd_bench [REPS] [TARGET_TILES...]`: median of REPS
//! (default 3) after one warm-up run, for each block size (default `winograd::TARGET_TILES`).

use std::time::Instant;

use candle_core::{Device, Tensor};
use mvsplat360_nn::conv::{winograd, Winograd3x3, WinogradEpilogue};
use mvsplat360_nn::{conv2d, Conv2dConfig};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

fn time(reps: usize, mut f: impl FnMut() -> Tensor) -> (f64, Tensor) {
    let y = f();
    let t = (0..reps)
        .map(|_| {
            let s = Instant::now();
            std::hint::black_box(f());
            s.elapsed().as_secs_f64()
        })
        .collect();
    (median(t), y)
}

fn main() -> candle_core::Result<()> {
    let args: Vec<usize> = std::env::args().skip(1).map(|a| a.parse().expect("numbers")).collect();
    let reps = args.first().copied().unwrap_or(3);
    let tiles: Vec<usize> = if args.len() > 1 { args[1..].to_vec() } else { vec![winograd::TARGET_TILES] };
    let n = 5;
    // (name, C_in, C_out, H, W)
    let shapes = [
        ("rcu/layer1_rn 84x148", 256, 256, 84, 148),
        ("rcu 42x74", 256, 256, 42, 74),
        ("rcu 21x37", 256, 256, 21, 37),
        ("rcu 11x19", 256, 256, 11, 19),
        ("layer2_rn 42x74", 512, 256, 42, 74),
        ("layer3_rn 21x37", 1024, 256, 21, 37),
        ("layer4_rn 11x19", 1024, 256, 11, 19),
        ("output_conv1 168x296", 256, 128, 168, 296),
        ("output_conv2.0 294x518", 128, 32, 294, 518),
    ];
    let cfg = Conv2dConfig { padding: 1, stride: 1, dilation: 1 };
    println!("threads {}, reps {reps} (median after 1 warm-up)", rayon::current_num_threads());
    for (name, ci, co, h, w) in shapes {
        let d = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (n, ci, h, w), &d)?;
        let wt = (Tensor::randn(0f32, 1.0, (co, ci, 3, 3), &d)? / (9.0 * ci as f64).sqrt())?;
        let b = Tensor::randn(0f32, 0.1, co, &d)?;
        let flop = 2.0 * 9.0 * (ci * co * h * w * n) as f64;
        let (td, yd) = time(reps, || conv2d(&x, &wt, Some(&b), cfg).unwrap());
        let s = Instant::now();
        let wg = Winograd3x3::new(&wt, Some(&b))?;
        let tprep = s.elapsed().as_secs_f64();
        let mut line = format!("{name:24} direct {:7.1} ms {:6.1} GF/s | prep {:5.1} ms", td * 1e3, flop / td / 1e9, tprep * 1e3);
        for &tt in &tiles {
            let (tw, yw) = time(reps, || wg.forward_blocked(&x, WinogradEpilogue::default(), tt).unwrap());
            let diff = (&yw - &yd)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            line += &format!(" | wino[{tt}] {:7.1} ms {:6.1} GF/s {:4.2}x (maxdiff {diff:.1e})", tw * 1e3, flop / tw / 1e9, td / tw);
        }
        println!("{line}");
    }
    Ok(())
}
