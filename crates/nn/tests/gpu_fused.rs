//! The fused kernels of cuda/fused.cu on a CUDA GPU (`MVSPLAT360_GPU_OPS=fused`, set here before the first
//! kernel call reads it) against the CPU f32 path on the same rounded inputs: GroupNorm(+SiLU) with pooled
//! frames and GEGLU, in f32, f16 and bf16. Needs a GPU and the `cuda` feature:
//! `cargo test -p mvsplat360-nn --features cuda --test gpu_fused -- --include-ignored`.
//!
//! Tolerance (element-wise): |gpu − cpu| ≤ 2e-5·(1 + |cpu|) in f32 (f32 statistics chunks, FMA contraction),
//! plus the output's rounding u·|cpu| in f16 / bf16 (u = 2⁻¹¹ / 2⁻⁸) and 2⁻²⁴ for f16's subnormals.
#![cfg(feature = "cuda")]

use candle_core::{DType, Device, Tensor};
use mvsplat360_nn::gpu_ops::{self, GpuOp};
use mvsplat360_nn::{linear, norm};

fn gpu() -> Device {
    // The selection is read once per process; every test of this file sets the same value first.
    std::env::set_var(gpu_ops::ENV, "fused");
    assert!(gpu_ops::enabled(GpuOp::Fused), "{} was read before this test set it", gpu_ops::ENV);
    Device::new_cuda(0).expect("a CUDA GPU (these tests are #[ignore]d without one)")
}

fn unit(dt: DType) -> f32 {
    match dt {
        DType::F16 => 2f32.powi(-11),
        DType::BF16 => 2f32.powi(-8),
        _ => 0.0,
    }
}

#[track_caller]
fn close(what: &str, dt: DType, gpu: &Tensor, cpu: &Tensor) {
    assert_eq!(gpu.dims(), cpu.dims(), "{what}: shapes");
    assert_eq!(gpu.dtype(), dt, "{what}: dtype");
    let g = gpu.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
    let c = cpu.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let sub = if dt == DType::F16 { 2f32.powi(-24) } else { 0.0 };
    let (mut worst, mut at) = (0f32, 0);
    for i in 0..c.len() {
        let tol = 2e-5 * (1.0 + c[i].abs()) + unit(dt) * c[i].abs() + sub;
        let r = (g[i] - c[i]).abs() / tol;
        if !(r <= worst) {
            (worst, at) = (r, i);
        }
    }
    eprintln!("{what} {dt:?}: worst err/tol {worst:.3} at {at}");
    assert!(worst <= 1.0, "{what} {dt:?}: element {at}: gpu {} cpu {}", g[at], c[at]);
}

/// x rounded to `dt`: (the GPU input in `dt`, the same values as CPU f32).
fn rounded(x: &Tensor, dt: DType, d: &Device) -> (Tensor, Tensor) {
    let r = x.to_dtype(dt).unwrap();
    (r.to_device(d).unwrap(), r.to_dtype(DType::F32).unwrap())
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn fused_group_norm_matches_cpu() {
    let d = gpu();
    let cpu = Device::Cpu;
    // (n, c, h, w, groups, frames): a temporal ResBlock's pooled frames (runs over several 4096-chunks) and a
    // spatial one.
    for (n, c, h, w, groups, frames) in [(6, 64, 24, 41, 32, 3), (4, 96, 8, 14, 32, 1)] {
        let x = (Tensor::randn(0f32, 1.0, (n, c, h, w), &cpu).unwrap() + 0.3).unwrap();
        let wt = Tensor::randn(1f32, 0.3, c, &cpu).unwrap();
        let bt = Tensor::randn(0f32, 0.3, c, &cpu).unwrap();
        for dt in [DType::F32, DType::F16, DType::BF16] {
            let (xg, xc) = rounded(&x, dt, &d);
            for silu in [false, true] {
                let got = norm::group_norm(&xg, groups, frames, &wt.to_device(&d).unwrap(), &bt.to_device(&d).unwrap(), 1e-5, silu).unwrap();
                let want = norm::group_norm(&xc, groups, frames, &wt, &bt, 1e-5, silu).unwrap();
                close(&format!("group_norm {n}x{c}x{h}x{w} frames {frames} silu {silu}"), dt, &got, &want);
            }
        }
    }
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn fused_geglu_matches_cpu() {
    let d = gpu();
    let cpu = Device::Cpu;
    let (rows, c, inner, o) = (300, 64, 256, 64);
    let x = Tensor::randn(0f32, 1.0, (3, rows / 3, c), &cpu).unwrap();
    let w1 = Tensor::randn(0f32, 0.15, (2 * inner, c), &cpu).unwrap();
    let b1 = Tensor::randn(0f32, 0.3, 2 * inner, &cpu).unwrap();
    let w2 = Tensor::randn(0f32, 0.1, (o, inner), &cpu).unwrap();
    let b2 = Tensor::randn(0f32, 0.3, o, &cpu).unwrap();
    // The full feed-forward in each dtype against the CPU f32 one on the dtype-rounded operands.
    for dt in [DType::F32, DType::F16, DType::BF16] {
        let r = |t: &Tensor| rounded(t, dt, &d);
        let ((xg, xc), (w1g, w1c), (b1g, b1c), (w2g, w2c), (b2g, b2c)) = (r(&x), r(&w1), r(&b1), r(&w2), r(&b2));
        let got = linear::geglu_ff(&xg, &w1g, &b1g, &w2g, &b2g, 1.0, &[]).unwrap();
        let want = linear::geglu_ff(&xc, &w1c, &b1c, &w2c, &b2c, 1.0, &[]).unwrap();
        close_ff(dt, &got, &want);
    }
}

/// The feed-forward's output: in f16 / bf16 the hidden activation, the gate and the output are each rounded
/// to the dtype, and the second gemm sums `inner` rounded gate values, so the bound is 4u·(|y| + rms y) plus
/// the f32 term.
fn close_ff(dt: DType, gpu: &Tensor, cpu: &Tensor) {
    let g = gpu.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
    let c = cpu.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let rms = (c.iter().map(|v| v * v).sum::<f32>() / c.len() as f32).sqrt();
    let u = unit(dt);
    let (mut worst, mut at) = (0f32, 0);
    for i in 0..c.len() {
        let tol = 2e-5 * (1.0 + c[i].abs()) + 4.0 * u * (c[i].abs() + rms);
        let r = (g[i] - c[i]).abs() / tol;
        if !(r <= worst) {
            (worst, at) = (r, i);
        }
    }
    eprintln!("geglu_ff {dt:?}: worst err/tol {worst:.3} at {at}");
    assert!(worst <= 1.0, "geglu_ff {dt:?}: element {at}: gpu {} cpu {}", g[at], c[at]);
}
