//! Every op on a CUDA GPU against its CPU kernel, values and (where the model trains through it) gradients.
//! Needs a GPU and the `cuda` feature: `cargo test -p mvsplat360-nn --features cuda -- --include-ignored`;
//! without the feature this file compiles to nothing, without a GPU the tests are ignored.
//!
//! Tolerance: |gpu − cpu| ≤ 1e-5 + 1e-4·|cpu| element-wise (f32). The GPU runs candle's ops (cuBLAS without
//! TF32, candle's reductions), so the two differ only in summation order and exp/erf rounding, which
//! src/fallback_tests.rs bounds at this tolerance on the CPU.
#![cfg(feature = "cuda")]

use candle_core::{DType, Device, Tensor, Var};
use mvsplat360_nn::{activation, attention, conv, grid_sample, linear, norm, softmax, upsample, warp_correlation};

const ATOL: f32 = 1e-5;
const RTOL: f32 = 1e-4;

fn gpu() -> Device {
    Device::new_cuda(0).expect("a CUDA GPU (these tests are #[ignore]d without one)")
}

#[track_caller]
fn close(what: &str, gpu: &Tensor, cpu: &Tensor) {
    assert!(gpu.device().is_cuda(), "{what}: the GPU result is not on the GPU");
    assert_eq!(gpu.dims(), cpu.dims(), "{what}: shapes");
    let g = gpu.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
    let c = cpu.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
    let bad: Vec<usize> = (0..c.len()).filter(|&i| (g[i] - c[i]).abs() > ATOL + RTOL * c[i].abs() || !g[i].is_finite()).collect();
    assert!(bad.is_empty(), "{what}: {} of {} elements differ, first {}: cpu {} gpu {}", bad.len(), c.len(), bad[0], c[bad[0]], g[bad[0]]);
}

fn randn(shape: &[usize], std: f32) -> Tensor {
    Tensor::randn(0f32, std, shape, &Device::Cpu).unwrap()
}

fn on(t: &Tensor, d: &Device) -> Tensor {
    t.to_device(d).unwrap()
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn convolutions() {
    let d = gpu();
    let x = randn(&[2, 5, 9, 11], 1.0);
    let w = randn(&[7, 5, 3, 3], 0.3);
    let b = randn(&[7], 0.3);
    for (stride, padding, dilation) in [(1, 1, 1), (2, 1, 1), (1, 2, 2)] {
        let cfg = conv::Conv2dConfig { padding, stride, dilation };
        close("conv2d", &conv::conv2d(&on(&x, &d), &on(&w, &d), Some(&on(&b, &d)), cfg).unwrap(), &conv::conv2d(&x, &w, Some(&b), cfg).unwrap());
    }
    let ib = randn(&[2, 7], 0.3);
    let res = randn(&[2, 7, 18, 22], 1.0);
    let cfg = conv::Conv2dConfig { padding: 1, stride: 1, dilation: 1 };
    let epi = |ib, res| conv::ConvEpilogue { item_bias: Some(ib), residual: Some(res), scale: Some(0.5), upsample2x: true };
    close(
        "conv2d_fused",
        &conv::conv2d_fused(&on(&x, &d), &on(&w, &d), Some(&on(&b, &d)), cfg, epi(&on(&ib, &d), &on(&res, &d))).unwrap(),
        &conv::conv2d_fused(&x, &w, Some(&b), cfg, epi(&ib, &res)).unwrap(),
    );
    let xt = randn(&[6, 4, 5, 3], 1.0);
    let wt = randn(&[6, 3 * 4], 0.3);
    let bt = randn(&[6], 0.3);
    let ibt = randn(&[6, 6], 0.3);
    let rt = randn(&[6, 6, 5, 3], 1.0);
    close(
        "temporal_conv",
        &conv::temporal_conv(&on(&xt, &d), &on(&wt, &d), &on(&bt, &d), 3, 3, Some(&on(&ibt, &d)), Some(&on(&rt, &d)), 0.7).unwrap(),
        &conv::temporal_conv(&xt, &wt, &bt, 3, 3, Some(&ibt), Some(&rt), 0.7).unwrap(),
    );
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn attention_softmax_norms_linear() {
    let d = gpu();
    let (b, lq, s, c, p) = (4, 37, 53, 16, 2);
    let (q, k, v) = (randn(&[b, lq, c], 0.5), randn(&[b, s, c], 0.5), randn(&[b, s, 12], 1.0));
    let mask =
        attention::RegionMask { q_labels: (0..p * lq).map(|i| ((i * 7) % 3) as u8).collect(), k_labels: (0..p * s).map(|i| ((i * 5) % 3) as u8).collect(), p };
    for m in [None, Some(&mask)] {
        close(
            "fused_attention",
            &attention::fused_attention(&on(&q, &d), &on(&k, &d), &on(&v, &d), m).unwrap(),
            &attention::fused_attention(&q, &k, &v, m).unwrap(),
        );
    }
    for (n, lq, lk, heads, dh, max) in [(3, 14, 14, 2, 16, usize::MAX), (2, 70, 300, 2, 8, 70 * 40)] {
        let (q, k, v) = (randn(&[n, lq, heads * dh], 1.0), randn(&[n, lk, heads * dh], 1.0), randn(&[n, lk, heads * dh], 1.0));
        close(
            "multi_head_attention",
            &attention::multi_head_attention(&on(&q, &d), &on(&k, &d), &on(&v, &d), heads, max).unwrap(),
            &attention::multi_head_attention(&q, &k, &v, heads, usize::MAX).unwrap(),
        );
    }
    let scores = randn(&[6, 5, 37], 3.0);
    close("softmax_last", &softmax::softmax_last(&on(&scores, &d)).unwrap(), &softmax::softmax_last(&scores).unwrap());
    let x = (randn(&[6, 64, 3, 5], 1.5) + 0.5).unwrap();
    let (w, bb) = ((randn(&[64], 0.2) + 1.0).unwrap(), randn(&[64], 0.1));
    close(
        "group_norm",
        &norm::group_norm(&on(&x, &d), 32, 3, &on(&w, &d), &on(&bb, &d), 1e-5, true).unwrap(),
        &norm::group_norm(&x, 32, 3, &w, &bb, 1e-5, true).unwrap(),
    );
    close(
        "group_norm_act",
        &norm::group_norm_act(&on(&x, &d), &on(&w, &d), &on(&bb, &d), 8, 1e-5, norm::Act::Gelu).unwrap(),
        &norm::group_norm_act(&x, &w, &bb, 8, 1e-5, norm::Act::Gelu).unwrap(),
    );
    let xl = (randn(&[3, 7, 48], 2.0) + 0.7).unwrap();
    let (wl, bl) = ((randn(&[48], 0.3) + 1.0).unwrap(), randn(&[48], 0.3));
    close("layer_norm", &norm::layer_norm(&on(&xl, &d), &on(&wl, &d), &on(&bl, &d), 1e-5).unwrap(), &norm::layer_norm(&xl, &wl, &bl, 1e-5).unwrap());
    let xa = randn(&[3, 700], 3.0);
    close("gelu", &activation::gelu(&on(&xa, &d)).unwrap(), &activation::gelu(&xa).unwrap());
    let x = randn(&[2, 37, 24], 1.0);
    let (w1, b1, w2, b2) = (randn(&[32, 24], 0.2), randn(&[32], 0.2), randn(&[24, 16], 0.2), randn(&[24], 0.2));
    close(
        "geglu_ff",
        &linear::geglu_ff(&on(&x, &d), &on(&w1, &d), &on(&b1, &d), &on(&w2, &d), &on(&b2, &d), 0.5, &[(&on(&x, &d), 1.0)]).unwrap(),
        &linear::geglu_ff(&x, &w1, &b1, &w2, &b2, 0.5, &[(&x, 1.0)]).unwrap(),
    );
}

/// Output and gradients of Σ wgt·f(inputs) for inputs on `d`.
fn value_and_grads(f: &dyn Fn(&[Tensor]) -> Tensor, inputs: &[Tensor], wgt: &Tensor, d: &Device) -> Vec<Tensor> {
    let vars: Vec<Var> = inputs.iter().map(|t| Var::from_tensor(&on(t, d)).unwrap()).collect();
    let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
    let out = f(&ts);
    let grads = out.mul(&on(wgt, d)).unwrap().sum_all().unwrap().backward().unwrap();
    std::iter::once(out).chain(vars.iter().map(|v| grads.get(v.as_tensor()).unwrap().clone())).collect()
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn sampling_ops_values_and_gradients() {
    let d = gpu();
    let (n, c, hi, wi, ho, wo) = (2, 3, 7, 9, 5, 6);
    let x = randn(&[n, c, hi, wi], 1.0);
    let grid = Tensor::rand(-1.2f32, 1.2, (n, ho, wo, 2), &Device::Cpu).unwrap();
    let wgt = randn(&[n, c, ho, wo], 1.0);
    let f = |t: &[Tensor]| grid_sample::grid_sample(&t[0], &t[1]).unwrap();
    let (g, cpu) = (value_and_grads(&f, &[x.clone(), grid.clone()], &wgt, &d), value_and_grads(&f, &[x.clone(), grid], &wgt, &Device::Cpu));
    for (i, what) in ["grid_sample", "grid_sample d/input", "grid_sample d/grid"].iter().enumerate() {
        close(what, &g[i], &cpu[i]);
    }
    // Bilinear to any size; nearest by one whole factor on both axes (as the models use it; candle's backward
    // refuses unequal factors).
    for (name, f, hw) in [
        ("upsample_bilinear", upsample::upsample_bilinear as fn(&Tensor, (usize, usize)) -> candle_core::Result<Tensor>, (13, 17)),
        ("upsample_nearest", upsample::upsample_nearest, (14, 18)),
    ] {
        let wgt = randn(&[n, c, hw.0, hw.1], 1.0);
        let h = |t: &[Tensor]| f(&t[0], hw).unwrap();
        let (g, cpu) = (value_and_grads(&h, &[x.clone()], &wgt, &d), value_and_grads(&h, &[x.clone()], &wgt, &Device::Cpu));
        close(name, &g[0], &cpu[0]);
        close(&format!("{name} d/input"), &g[1], &cpu[1]);
    }
    let (dd, h, w) = (3, 4, 5);
    let a = randn(&[n, c, h, w], 1.0);
    let b = randn(&[n, c, h, w], 1.0);
    let pts: Vec<f32> = Tensor::rand(-1.1f32, 1.1, n * dd * h * w * 2, &Device::Cpu).unwrap().to_vec1().unwrap();
    let wgt = randn(&[n, dd, h, w], 1.0);
    let f = |t: &[Tensor]| warp_correlation::warp_correlation(&t[0], &t[1], &pts, dd).unwrap();
    let (g, cpu) = (value_and_grads(&f, &[a.clone(), b.clone()], &wgt, &d), value_and_grads(&f, &[a, b], &wgt, &Device::Cpu));
    for (i, what) in ["warp_correlation", "warp_correlation d/reference", "warp_correlation d/source"].iter().enumerate() {
        close(what, &g[i], &cpu[i]);
    }
}
