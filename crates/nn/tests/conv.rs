//! `conv2d` against candle's own conv2d (an independent implementation), forward and backward.

use candle_core::{Device, Tensor, Var};
use mvsplat360_nn::{conv2d, conv2d_gemm, conv2d_shift, Conv2dConfig};

fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
    (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
}

type ConvFn = fn(&Tensor, &Tensor, Option<&Tensor>, Conv2dConfig) -> candle_core::Result<Tensor>;

#[test]
fn im2col_matches_candle_forward_and_finite_difference_backward() {
    check(conv2d_gemm, true);
}

#[test]
fn shift_conv_matches_candle_forward_and_finite_difference_backward() {
    check(conv2d_shift, false);
}

fn check(conv: ConvFn, strided: bool) {
    let d = Device::Cpu;
    // (n, c, h, w, co, k, padding, stride, dilation)
    for &(n, c, h, w, co, k, padding, stride, dilation) in &[
        (2, 3, 9, 11, 4, 3, 1, 1, 1),
        (1, 5, 16, 13, 6, 7, 3, 2, 1),
        (3, 4, 8, 8, 2, 1, 0, 1, 1),
        (2, 3, 10, 9, 3, 3, 2, 1, 2),
        (1, 2, 7, 7, 3, 3, 0, 2, 1),
        (2, 3, 5, 6, 4, 3, 0, 1, 1),
    ] {
        if stride != 1 && !strided {
            continue;
        }
        let x = Var::from_tensor(&Tensor::randn(0f32, 1.0, (n, c, h, w), &d).unwrap()).unwrap();
        let wt = Var::from_tensor(&Tensor::randn(0f32, 1.0, (co, c, k, k), &d).unwrap()).unwrap();
        let b = Tensor::randn(0f32, 1.0, co, &d).unwrap();
        let cfg = Conv2dConfig { padding, stride, dilation };
        let ours = conv(x.as_tensor(), wt.as_tensor(), Some(&b), cfg).unwrap();
        let theirs = x.as_tensor().conv2d(wt.as_tensor(), padding, stride, dilation, 1).unwrap().broadcast_add(&b.reshape((1, co, 1, 1)).unwrap()).unwrap();
        assert_eq!(ours.dims(), theirs.dims());
        let tol = 1e-4 * (c * k * k) as f32;
        assert!(max_diff(&ours, &theirs) < tol, "forward {:?}", (n, c, h, w, k, padding, stride, dilation));
        // Backward: L = sum(conv(x, w) * r) is linear in x and in w, so central differences are exact up to
        // rounding and make an independent reference (candle's own conv backward returns a wrongly shaped
        // input gradient for stride 2 with odd sizes, so it cannot serve here).
        let r = Tensor::randn(0f32, 1.0, ours.dims(), &d).unwrap();
        let loss = |xv: &Tensor, wv: &Tensor| -> f64 {
            let o = conv(xv, wv, Some(&b), cfg).unwrap();
            (o * &r).unwrap().sum_all().unwrap().to_dtype(candle_core::DType::F64).unwrap().to_scalar::<f64>().unwrap()
        };
        let grads = (&ours * &r).unwrap().sum_all().unwrap().backward().unwrap();
        for (var, is_x) in [(&x, true), (&wt, false)] {
            let g = grads.get(var.as_tensor()).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let base = var.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let dims = var.as_tensor().dims().to_vec();
            for probe in 0..12 {
                let i = (probe * 7919 + 13) % base.len();
                let step = 0.5f32;
                let at = |delta: f32| {
                    let mut v = base.clone();
                    v[i] += delta;
                    let t = Tensor::from_vec(v, dims.clone(), &d).unwrap();
                    if is_x {
                        loss(&t, wt.as_tensor())
                    } else {
                        loss(x.as_tensor(), &t)
                    }
                };
                let fd = (at(step) - at(-step)) / (2.0 * step as f64);
                assert!(
                    (fd - g[i] as f64).abs() < 2e-3 * fd.abs().max(1.0),
                    "{} grad [{i}] {} vs finite difference {fd} for {:?}",
                    if is_x { "input" } else { "weight" },
                    g[i],
                    (n, c, h, w, k, padding, stride, dilation)
                );
            }
        }
    }
}

#[test]
fn dispatcher_matches_both_paths() {
    let d = Device::Cpu;
    // Stride 1 → shift path; stride 2 with K = 130·9 ≥ 1024 → im2col path; stride 2 with K = 36 → candle;
    // 1×1 → pointwise gemm. All equal candle's conv.
    for (c, k, stride, pad) in [(4usize, 3usize, 1usize, 1usize), (130, 3, 2, 1), (4, 3, 2, 1), (6, 1, 1, 0)] {
        let x = Tensor::randn(0f32, 1.0, (2, c, 8, 7), &d).unwrap();
        let w = Tensor::randn(0f32, 1.0, (5, c, k, k), &d).unwrap();
        let cfg = Conv2dConfig { padding: pad, stride, dilation: 1 };
        let ours = conv2d(&x, &w, None, cfg).unwrap();
        let theirs = x.conv2d(&w, pad, stride, 1, 1).unwrap();
        assert!(max_diff(&ours, &theirs) < 1e-3, "c = {c}, stride = {stride}");
    }
}

/// The shifted-gemm backward against candle's own conv2d backward (conv_transpose2d + conv2d, stride 1) on
/// every entry of both gradients, over shapes with padding below, at and above "same", dilation, several
/// images and non-square maps. Tolerance: 1e-4 relative to the largest gradient entry (f32 sums of ≤ 700
/// products).
#[test]
fn shift_conv_backward_matches_candle_everywhere() {
    let d = Device::Cpu;
    for &(n, c, h, w, co, k, padding, dilation) in
        &[(2, 3, 9, 11, 4, 3, 1, 1), (3, 5, 8, 12, 6, 3, 0, 1), (1, 4, 10, 9, 3, 3, 2, 2), (2, 6, 7, 13, 5, 5, 2, 1), (1, 2, 12, 6, 3, 5, 4, 1)]
    {
        let x = Var::from_tensor(&Tensor::randn(0f32, 1.0, (n, c, h, w), &d).unwrap()).unwrap();
        let wt = Var::from_tensor(&Tensor::randn(0f32, 1.0, (co, c, k, k), &d).unwrap()).unwrap();
        let cfg = Conv2dConfig { padding, stride: 1, dilation };
        let ours = conv2d_shift(x.as_tensor(), wt.as_tensor(), None, cfg).unwrap();
        let r = Tensor::randn(0f32, 1.0, ours.dims(), &d).unwrap();
        let g1 = (&ours * &r).unwrap().sum_all().unwrap().backward().unwrap();
        let theirs = x.as_tensor().conv2d(wt.as_tensor(), padding, 1, dilation, 1).unwrap();
        let g2 = (&theirs * &r).unwrap().sum_all().unwrap().backward().unwrap();
        for (name, v) in [("input", &x), ("weight", &wt)] {
            let a = g1.get(v.as_tensor()).unwrap();
            let b = g2.get(v.as_tensor()).unwrap();
            assert_eq!(a.dims(), b.dims());
            let scale = b.abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap();
            let diff = max_diff(a, b);
            assert!(diff <= 1e-4 * scale, "{name} gradient differs by {diff} (scale {scale}) for {:?}", (n, c, h, w, co, k, padding, dilation));
        }
    }
}

/// The bias gradient of every conv path against its closed form: for L = Σ conv(x, w, b) · r,
/// ∂L/∂b_c = Σ_{n,y,x} r[n, c, y, x] (summed here in f64). Tolerance 1e-4 relative to the largest entry.
#[test]
fn bias_gradient_is_the_per_channel_sum_of_the_output_gradient() {
    let d = Device::Cpu;
    // (n, c, h, w, co, k, padding, stride): stride 1 → shift path, 1×1 → pointwise gemm, stride 2 with
    // K = 130·9 → im2col, stride 2 with K = 27 → candle's conv.
    for &(n, c, h, w, co, k, padding, stride) in &[(2, 3, 9, 11, 4, 3, 1, 1), (3, 6, 5, 7, 5, 1, 0, 1), (1, 130, 8, 7, 3, 3, 1, 2), (2, 3, 8, 9, 6, 3, 1, 2)] {
        let x = Tensor::randn(0f32, 1.0, (n, c, h, w), &d).unwrap();
        let wt = Tensor::randn(0f32, 1.0, (co, c, k, k), &d).unwrap();
        let b = Var::from_tensor(&Tensor::randn(0f32, 1.0, co, &d).unwrap()).unwrap();
        let cfg = Conv2dConfig { padding, stride, dilation: 1 };
        let out = conv2d(&x, &wt, Some(b.as_tensor()), cfg).unwrap();
        let plain = conv2d(&x, &wt, None, cfg).unwrap();
        let want_out = plain.broadcast_add(&b.as_tensor().reshape((1, co, 1, 1)).unwrap()).unwrap();
        assert!(max_diff(&out, &want_out) < 1e-5, "forward {:?}", (n, c, h, w, co, k, stride));
        let r = Tensor::randn(0f32, 1.0, out.dims(), &d).unwrap();
        let grads = (&out * &r).unwrap().sum_all().unwrap().backward().unwrap();
        let got = grads.get(b.as_tensor()).unwrap().to_vec1::<f32>().unwrap();
        let (_, _, ho, wo) = r.dims4().unwrap();
        let rv = r.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for ch in 0..co {
            let want: f64 = (0..n).flat_map(|i| rv[(i * co + ch) * ho * wo..][..ho * wo].iter()).map(|&v| v as f64).sum();
            assert!((got[ch] as f64 - want).abs() < 1e-4 * want.abs().max(1.0), "bias grad [{ch}] {} vs {want} for {:?}", got[ch], (n, c, co, k, stride));
        }
    }
}
