//! Exploration benchmark (issue 69): `nn::rope::qkv_attention` on VGGT-1B's attention shapes (16 heads of 64):
//! global (1 sequence of 5 × 782 tokens) and frame (5 sequences of 782). GFLOP/s count the two products
//! (4·n·l²·c). `cargo run --release -p mvsplat360-lab --example attention_bench [REPS]`: median of REPS (default
//! 3) after one warm-up run, wall time and the process's CPU time (so a busy machine shows). Each shape runs
//! `qkv_attention` (f32) and `qkv_attention_bf16` (bf16 products where the CPU has AVX512-BF16), alternated.

use std::time::Instant;

use candle_core::{Device, Tensor};
use mvsplat360_nn::rope::{qkv_attention, qkv_attention_bf16, HeadNorm, Rope2dTables};

type AttentionFn = fn(&Tensor, usize, Option<HeadNorm>, Option<HeadNorm>, Option<Rope2dTables>) -> candle_core::Result<Tensor>;

fn cpu_s() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let f: Vec<&str> = s.rsplit(')').next().unwrap_or("").split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

fn main() -> anyhow::Result<()> {
    let reps: usize = std::env::args().nth(1).map(|a| a.parse()).transpose()?.unwrap_or(3).max(1);
    let heads = 16;
    let c = heads * 64;
    for (name, n, l) in [("global", 1usize, 3910usize), ("frame", 5, 782)] {
        let mut x = 5u64;
        let v: Vec<f32> = (0..n * l * 3 * c)
            .map(|_| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((x >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * 2.0
            })
            .collect();
        let qkv = Tensor::from_vec(v, (n, l, 3 * c), &Device::Cpu)?;
        let kernels: [(&str, AttentionFn); 2] = [("f32", qkv_attention), ("bf16", qkv_attention_bf16)];
        for (_, f) in &kernels {
            f(&qkv, heads, None, None, None)?;
        }
        let mut walls = vec![Vec::with_capacity(reps); 2];
        let mut cpus = [0f64; 2];
        for _ in 0..reps {
            for (i, (_, f)) in kernels.iter().enumerate() {
                let (c0, t) = (cpu_s(), Instant::now());
                f(&qkv, heads, None, None, None)?;
                walls[i].push(t.elapsed().as_secs_f64());
                cpus[i] += cpu_s() - c0;
            }
        }
        for (i, (kind, _)) in kernels.iter().enumerate() {
            walls[i].sort_by(|a, b| a.total_cmp(b));
            let w = walls[i][reps / 2];
            let flops = 4.0 * (n * l * l * c) as f64;
            println!(
                "{name} {kind}: n {n} l {l}: {w:.3} s ({:.0} GFLOP/s), cpu {:.3} s per run, {} threads",
                flops / w / 1e9,
                cpus[i] / reps as f64,
                rayon::current_num_threads()
            );
        }
    }
    Ok(())
}
