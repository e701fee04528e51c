//! The non-CPU path of every op is a composition of candle ops; here each composition runs on CPU tensors and
//! is compared with the CPU kernel, element-wise |a − b| ≤ ATOL + RTOL·|b|. The two differ only in f32
//! summation order and in the kernels' exp/erf approximations (≤ 3e-7 relative), so 1e-5 + 1e-4·|b| is
//! ~10× the spread seen here and far below a wrong tap, index or scale. This is as close as a machine
//! without a GPU gets to checking the CUDA path.

use candle_core::{DType, Device, Tensor, Var};

use crate::{activation, attention, conv, grid_sample, linear, mode, norm, softmax, upsample, warp_correlation};

const ATOL: f32 = 1e-5;
const RTOL: f32 = 1e-4;

#[track_caller]
fn close(what: &str, got: &Tensor, want: &Tensor) {
    assert_eq!(got.dims(), want.dims(), "{what}: shapes");
    let g = got.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
    let w = want.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
    for (i, (a, b)) in g.iter().zip(&w).enumerate() {
        assert!((a - b).abs() <= ATOL + RTOL * b.abs(), "{what}: element {i}: kernel {b}, composed {a}");
    }
}

fn randn(shape: &[usize], std: f32) -> Tensor {
    Tensor::randn(0f32, std, shape, &Device::Cpu).unwrap()
}

#[test]
fn conv_compositions_match_kernels() {
    let x = randn(&[2, 5, 9, 11], 1.0);
    let w = randn(&[7, 5, 3, 3], 0.3);
    let b = randn(&[7], 0.3);
    for (stride, padding, dilation) in [(1, 1, 1), (2, 1, 1), (1, 2, 2)] {
        let cfg = conv::Conv2dConfig { padding, stride, dilation };
        close("conv2d", &conv::conv2d_candle(&x, &w, Some(&b), cfg).unwrap(), &conv::conv2d(&x, &w, Some(&b), cfg).unwrap());
    }
    // The im2col path (K = C·k² ≥ 1024) and the pointwise gemm.
    let xb = randn(&[2, 128, 6, 7], 1.0);
    let wb = randn(&[4, 128, 3, 3], 0.05);
    let cfg = conv::Conv2dConfig { padding: 1, stride: 2, dilation: 1 };
    close("conv2d im2col", &conv::conv2d_candle(&xb, &wb, None, cfg).unwrap(), &conv::conv2d(&xb, &wb, None, cfg).unwrap());
    let wp = randn(&[4, 128, 1, 1], 0.05);
    let cfg = conv::Conv2dConfig::default();
    close("conv2d 1x1", &conv::conv2d_candle(&xb, &wp, None, cfg).unwrap(), &conv::conv2d(&xb, &wp, None, cfg).unwrap());
    // Fused epilogue with upsampling.
    let ib = randn(&[2, 7], 0.3);
    let up = conv::ConvEpilogue { item_bias: Some(&ib), residual: None, scale: Some(0.5), upsample2x: true };
    let res = randn(&[2, 7, 18, 22], 1.0);
    let cfg = conv::Conv2dConfig { padding: 1, stride: 1, dilation: 1 };
    let epi = conv::ConvEpilogue { residual: Some(&res), ..up };
    close("conv2d_fused", &conv::conv2d_fused_composed(&x, &w, Some(&b), cfg, epi, true).unwrap(), &conv::conv2d_fused(&x, &w, Some(&b), cfg, epi).unwrap());
    // Temporal conv over 2 items of 3 frames.
    let xt = randn(&[6, 4, 5, 3], 1.0);
    let wt = randn(&[6, 3 * 4], 0.3);
    let bt = randn(&[6], 0.3);
    let ibt = randn(&[6, 6], 0.3);
    let rt = randn(&[6, 6, 5, 3], 1.0);
    close(
        "temporal_conv",
        &conv::temporal_conv_composed(&xt, &wt, &bt, 3, 3, Some(&ibt), Some(&rt), 0.7).unwrap(),
        &conv::temporal_conv(&xt, &wt, &bt, 3, 3, Some(&ibt), Some(&rt), 0.7).unwrap(),
    );
}

#[test]
fn cpu_only_algorithms_name_themselves_off_the_cpu() {
    let e = mode::NotBuilt { op: "conv2d_shift", device: "CUDA".into() }.to_string();
    assert!(e.starts_with("conv2d_shift: the CUDA path is not built yet"), "{e}");
}

#[test]
fn attention_compositions_match_kernels() {
    let (b, lq, s, c, p) = (4, 37, 53, 16, 2);
    let q = randn(&[b, lq, c], 0.5);
    let k = randn(&[b, s, c], 0.5);
    let v = randn(&[b, s, 12], 1.0);
    let mask =
        attention::RegionMask { q_labels: (0..p * lq).map(|i| ((i * 7) % 3) as u8).collect(), k_labels: (0..p * s).map(|i| ((i * 5) % 3) as u8).collect(), p };
    for m in [None, Some(&mask)] {
        let kernel = attention::fused_attention(&q, &k, &v, m).unwrap();
        close("fused_attention", &attention::fused_attention_composed(&q, &k, &v, m).unwrap(), &kernel);
        // Score budgets below one sequence's lq·s: slices of query rows (uneven last slice), one row at a time.
        for cap in [p * 10 * s, p * s, 1] {
            close(&format!("fused_attention, {cap} scores a slice"), &attention::fused_attention_composed_capped(&q, &k, &v, m, cap).unwrap(), &kernel);
        }
    }
    // Row slices keep gradients: d/dq, d/dk, d/dv of a weighted sum equal those of the unsliced composition.
    let (qv, kv, vv) = (candle_core::Var::from_tensor(&q).unwrap(), candle_core::Var::from_tensor(&k).unwrap(), candle_core::Var::from_tensor(&v).unwrap());
    let w = randn(&[b, lq, 12], 1.0);
    let grads = |cap: usize| {
        let o = attention::fused_attention_composed_capped(&qv, &kv, &vv, Some(&mask), cap).unwrap();
        let g = (o * &w).unwrap().sum_all().unwrap().backward().unwrap();
        [&qv, &kv, &vv].map(|x| g.get(x.as_tensor()).unwrap().clone())
    };
    let (whole, sliced) = (grads(usize::MAX), grads(p * 10 * s));
    for (i, what) in ["d/q", "d/k", "d/v"].iter().enumerate() {
        close(&format!("sliced fused_attention {what}"), &sliced[i], &whole[i]);
    }
    // Multi-head: the small-sequence and the blocked gemm paths; composed in several score blocks.
    for (n, lq, lk, heads, d) in [(3, 14, 14, 2, 16), (2, 70, 300, 2, 8)] {
        let q = randn(&[n, lq, heads * d], 1.0);
        let k = randn(&[n, lk, heads * d], 1.0);
        let v = randn(&[n, lk, heads * d], 1.0);
        close(
            "multi_head_attention",
            &attention::multi_head_attention_composed(&q, &k, &v, heads, lq * lk).unwrap(),
            &attention::multi_head_attention(&q, &k, &v, heads, usize::MAX).unwrap(),
        );
    }
    // Temporal attention in frame-major rows: (b·t, s, c), sequences over t in 2 windows.
    let (bb, t, ss, heads, d) = (2, 6, 5, 2, 8);
    let x = randn(&[bb * t, ss, heads * d], 1.0);
    let tw = t / 2;
    let layout = attention::SeqLayout { count: bb * 2 * ss, len: tw, inner_count: ss, outer: tw * ss, inner: 1, pos: ss };
    close(
        "multi_head_attention_seqs",
        &attention::multi_head_attention_seqs_composed(&x, &x, &x, layout, heads, usize::MAX).unwrap(),
        &attention::multi_head_attention_seqs(&x, &x, &x, layout, heads, usize::MAX).unwrap(),
    );
}

#[test]
fn softmax_and_norm_compositions_match_kernels() {
    let scores = randn(&[6, 5, 37], 3.0);
    let mask = randn(&[3, 5, 37], 1.0).ge(0.5).unwrap().to_dtype(DType::F32).unwrap().affine(-100.0, 0.0).unwrap();
    for m in [None, Some(&mask)] {
        close("masked_softmax", &softmax::masked_softmax_composed(&scores, m).unwrap(), &softmax::masked_softmax(&scores, m).unwrap());
    }
    let x = (randn(&[3, 7, 48], 2.0) + 0.7).unwrap();
    let (w, b) = ((randn(&[48], 0.3) + 1.0).unwrap(), randn(&[48], 0.3));
    close("layer_norm", &norm::layer_norm_composed(&x, &w, &b, 1e-5).unwrap(), &norm::layer_norm(&x, &w, &b, 1e-5).unwrap());
    let x = (randn(&[6, 64, 3, 5], 1.5) + 0.5).unwrap();
    let (w, b) = ((randn(&[64], 0.2) + 1.0).unwrap(), randn(&[64], 0.1));
    for (frames, silu) in [(1, false), (3, true)] {
        close(
            "group_norm",
            &norm::group_norm_composed(&x, 32, frames, &w, &b, 1e-5, silu).unwrap(),
            &norm::group_norm(&x, 32, frames, &w, &b, 1e-5, silu).unwrap(),
        );
    }
    for act in [norm::Act::None, norm::Act::Silu, norm::Act::Gelu] {
        close("group_norm_act", &norm::group_norm_act_composed(&x, &w, &b, 8, 1e-5, act).unwrap(), &norm::group_norm_act(&x, &w, &b, 8, 1e-5, act).unwrap());
    }
}

/// Half-precision inference takes candle's fused LayerNorm for LayerNorm and GroupNorm (frames pooled by a
/// transpose). Reference: the f32 kernel on the same half-rounded inputs, so what differs is four half
/// roundings (normalised value, ×weight, +bias, SiLU; u = 2⁻⁸ bf16, 2⁻¹¹ f16, relative) and f32 statistics:
/// |a − b| ≤ 4u·(1 + |b|). Per-frame instead of pooled statistics, or a group's channels mixed up, move
/// outputs by ≥ 0.1.
#[test]
fn half_precision_norms_match_the_f32_kernels() {
    let x = (randn(&[6, 64, 3, 5], 1.5) + 0.5).unwrap();
    let (w, b) = ((randn(&[64], 0.2) + 1.0).unwrap(), randn(&[64], 0.1));
    let xl = (randn(&[3, 7, 48], 2.0) + 0.7).unwrap();
    let (wl, bl) = ((randn(&[48], 0.3) + 1.0).unwrap(), randn(&[48], 0.3));
    for (dtype, u) in [(DType::BF16, 2f32.powi(-8)), (DType::F16, 2f32.powi(-11))] {
        let half = |t: &Tensor| t.to_dtype(dtype).unwrap();
        let back = |t: &Tensor| half(t).to_dtype(DType::F32).unwrap();
        let check = |what: &str, got: &Tensor, want: &Tensor| {
            assert_eq!(got.dtype(), dtype, "{what}: stays in {dtype:?}");
            let g = got.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
            let w = want.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            for (i, (a, b)) in g.iter().zip(&w).enumerate() {
                assert!((a - b).abs() <= 4.0 * u * (1.0 + b.abs()), "{what} {dtype:?}: element {i}: f32 kernel {b}, half {a}");
            }
        };
        for (frames, silu) in [(1, false), (1, true), (3, true), (6, false)] {
            check(
                &format!("group_norm frames {frames} silu {silu}"),
                &norm::group_norm(&half(&x), 32, frames, &half(&w), &half(&b), 1e-5, silu).unwrap(),
                &norm::group_norm(&back(&x), 32, frames, &back(&w), &back(&b), 1e-5, silu).unwrap(),
            );
        }
        check(
            "layer_norm",
            &norm::layer_norm(&half(&xl), &half(&wl), &half(&bl), 1e-5).unwrap(),
            &norm::layer_norm(&back(&xl), &back(&wl), &back(&bl), 1e-5).unwrap(),
        );
    }
}

#[test]
fn elementwise_and_linear_compositions_match_kernels() {
    let x = randn(&[3, 700], 3.0);
    close("gelu", &x.gelu_erf().unwrap(), &activation::gelu(&x).unwrap());
    close("gelu_inference", &x.gelu_erf().unwrap(), &activation::gelu_inference(&x).unwrap());
    let y = randn(&[3, 700], 1.0);
    let composed = ((&x * 0.3).unwrap() + (&y * 0.7).unwrap()).unwrap();
    close("axpby", &composed, &activation::axpby(&x, 0.3, &y, 0.7).unwrap());
    let x = randn(&[2, 37, 24], 1.0);
    let (w, b) = (randn(&[10, 24], 0.2), randn(&[10], 0.2));
    let r = randn(&[2, 37, 10], 1.0);
    close(
        "linear_fused",
        &linear::linear_fused_composed(&x, &w, Some(&b), 0.3, &[(&r, 0.7)]).unwrap(),
        &linear::linear_fused(&x, &w, Some(&b), 0.3, &[(&r, 0.7)]).unwrap(),
    );
    let (w1, b1, w2, b2) = (randn(&[32, 24], 0.2), randn(&[32], 0.2), randn(&[24, 16], 0.2), randn(&[24], 0.2));
    close(
        "geglu_ff",
        &linear::geglu_ff_composed(&x, &w1, &b1, &w2, &b2, 0.5, &[(&x, 1.0)]).unwrap(),
        &linear::geglu_ff(&x, &w1, &b1, &w2, &b2, 0.5, &[(&x, 1.0)]).unwrap(),
    );
    let xc = randn(&[3, 6, 35], 1.0);
    let (wc, bc) = (randn(&[10, 6], 0.3), randn(&[10], 0.3));
    let tok = linear::linear_from_channels_first(&xc, &wc, &bc).unwrap();
    close("linear_from_channels_first", &linear::linear_from_channels_first_composed(&xc, &wc, &bc).unwrap(), &tok);
    let (w2, b2) = (randn(&[6, 10], 0.3), randn(&[6], 0.3));
    close(
        "linear_to_channels_first",
        &linear::linear_to_channels_first_composed(&tok, &w2, &b2, &xc).unwrap(),
        &linear::linear_to_channels_first(&tok, &w2, &b2, &xc).unwrap(),
    );
}

/// Values and gradients (input and grid) of a loss Σ wgt·f(x, grid) through `f`.
fn value_and_grads(f: impl Fn(&Tensor, &Tensor) -> Tensor, x: &Tensor, g: &Tensor, wgt: &Tensor) -> (Tensor, Tensor, Tensor) {
    let (xv, gv) = (Var::from_tensor(x).unwrap(), Var::from_tensor(g).unwrap());
    let out = f(xv.as_tensor(), gv.as_tensor());
    let grads = out.mul(wgt).unwrap().sum_all().unwrap().backward().unwrap();
    (out, grads.get(xv.as_tensor()).unwrap().clone(), grads.get(gv.as_tensor()).unwrap().clone())
}

#[test]
fn sampling_compositions_match_kernels_values_and_gradients() {
    let (n, c, hi, wi, ho, wo) = (2, 3, 7, 9, 5, 6);
    let x = randn(&[n, c, hi, wi], 1.0);
    // Points inside, on the border and outside [-1, 1].
    let grid = Tensor::rand(-1.2f32, 1.2, (n, ho, wo, 2), &Device::Cpu).unwrap();
    let wgt = randn(&[n, c, ho, wo], 1.0);
    let k = value_and_grads(|a, b| grid_sample::grid_sample(a, b).unwrap(), &x, &grid, &wgt);
    let m = value_and_grads(|a, b| grid_sample::grid_sample_composed(a, b).unwrap(), &x, &grid, &wgt);
    close("grid_sample", &m.0, &k.0);
    close("grid_sample d/input", &m.1, &k.1);
    close("grid_sample d/grid", &m.2, &k.2);

    let wgt = randn(&[n, c, 13, 17], 1.0);
    let up = |f: fn(&Tensor, (usize, usize)) -> candle_core::Result<Tensor>| {
        let xv = Var::from_tensor(&x).unwrap();
        let out = f(xv.as_tensor(), (13, 17)).unwrap();
        let g = out.mul(&wgt).unwrap().sum_all().unwrap().backward().unwrap();
        (out, g.get(xv.as_tensor()).unwrap().clone())
    };
    let (k, m) = (up(upsample::upsample_bilinear), up(upsample::upsample_bilinear_composed));
    close("upsample_bilinear", &m.0, &k.0);
    close("upsample_bilinear d/input", &m.1, &k.1);

    let (d, h, w) = (3, 4, 5);
    let a = randn(&[n, c, h, w], 1.0);
    let b = randn(&[n, c, h, w], 1.0);
    let grid: Vec<f32> = Tensor::rand(-1.1f32, 1.1, n * d * h * w * 2, &Device::Cpu).unwrap().to_vec1().unwrap();
    let wgt = randn(&[n, d, h, w], 1.0);
    let corr = |f: fn(&Tensor, &Tensor, &[f32], usize) -> candle_core::Result<Tensor>| {
        let (av, bv) = (Var::from_tensor(&a).unwrap(), Var::from_tensor(&b).unwrap());
        let out = f(av.as_tensor(), bv.as_tensor(), &grid, d).unwrap();
        let g = out.mul(&wgt).unwrap().sum_all().unwrap().backward().unwrap();
        (out, g.get(av.as_tensor()).unwrap().clone(), g.get(bv.as_tensor()).unwrap().clone())
    };
    let (k, m) = (corr(warp_correlation::warp_correlation), corr(warp_correlation::warp_correlation_composed));
    close("warp_correlation", &m.0, &k.0);
    close("warp_correlation d/reference", &m.1, &k.1);
    close("warp_correlation d/source", &m.2, &k.2);
}
