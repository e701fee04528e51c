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

/// Largest |got − want| / tol over the elements (≤ 1 passes), with the index where it is reached.
fn worst_ratio(got: &Tensor, want: &Tensor, tol: &[f32]) -> (f32, usize) {
    assert_eq!(got.dims(), want.dims());
    let g = got.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1::<f32>().unwrap();
    let w = want.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    (0..w.len()).map(|i| (if g[i].is_finite() { (g[i] - w[i]).abs() / tol[i] } else { f32::INFINITY }, i)).fold((0.0, 0), |a, b| if b.0 > a.0 { b } else { a })
}

fn rms(t: &Tensor) -> f32 {
    t.sqr().unwrap().mean_all().unwrap().to_scalar::<f32>().unwrap().sqrt()
}

/// Checks `got` (dtype `dt`) against `want`, computed in f32 on the GPU by candle from the same `dt`-rounded
/// inputs. f32: the file's tolerance (cuDNN runs FMA math, no TF32). f16/bf16: cuDNN accumulates the
/// K = C·kh·kw products of rounded inputs in f32 (exact products on tensor cores, or rounded ones in other
/// algorithms: a random walk of K errors of u·|x·w|) and rounds the output — and, where bias and residual are
/// separate passes, each partial sum — to `dt`: |err| ≤ 4u·(|want| + |z| + |b|) + 4u·√K·rms(x)·rms(w)·|scale|,
/// u = 2^-8 (bf16) or 2^-11 (f16). A wrong tap, layout or epilogue errs by ≈ rms(conv) = √K·rms(x)·rms(w),
/// ≥ 1/(4u) = 64 times the second term.
#[allow(clippy::too_many_arguments)]
fn check_cudnn(what: &str, got: &Tensor, want: &Tensor, dt: DType, k: usize, x: &Tensor, w: &Tensor, extra: &Tensor, scale: f32) {
    assert!(got.device().is_cuda() && got.dtype() == dt, "{what}: result on {:?} as {:?}", got.device(), got.dtype());
    let tol: Vec<f32> = if dt == DType::F32 {
        want.flatten_all().unwrap().to_vec1::<f32>().unwrap().iter().map(|v| ATOL + RTOL * v.abs()).collect()
    } else {
        let u = if dt == DType::BF16 { 2f32.powi(-8) } else { 2f32.powi(-11) };
        let walk = 4.0 * u * (k as f32).sqrt() * rms(x) * rms(w) * scale.abs();
        let mag = (want.abs().unwrap() + extra.abs().unwrap()).unwrap();
        mag.flatten_all().unwrap().to_vec1::<f32>().unwrap().iter().map(|m| 4.0 * u * m + walk).collect()
    };
    let (r, i) = worst_ratio(got, want, &tol);
    assert!(r <= 1.0, "{what}: error {r:.2}× the bound at element {i} (bound {:.3e})", tol[i]);
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn cudnn_convolutions_match_candle_at_refiner_shapes() {
    use mvsplat360_nn::conv::cudnn::{try_conv2d, try_temporal};
    let d = gpu();
    let dev = |t: &Tensor, dt: DType| t.to_dtype(dt).unwrap().to_device(&d).unwrap();
    let rounded = |t: &Tensor, dt: DType| t.to_dtype(dt).unwrap().to_dtype(DType::F32).unwrap().to_device(&d).unwrap();
    // (n, c, h, w, co, k, stride, bias, residual): UNet conv_in (8 → 320), its 3×3 convs at 320/640/1280
    // channels and their latent sizes (72×128 at 576×1024), the stride-2 downsample, a 1×1 skip; the VAE
    // decoder's 512 and 128-channel convs with the residual; a residual without bias; a plain conv. Batches are
    // cut to 1–2 frames (the plans do not depend on more).
    let cases = [
        (2, 8, 72, 128, 320, 3, 1, true, false),
        (2, 320, 72, 128, 320, 3, 1, true, true),
        (2, 320, 72, 128, 320, 3, 2, true, false),
        (2, 640, 36, 64, 640, 3, 1, true, true),
        (2, 1280, 9, 16, 1280, 3, 1, true, true),
        (2, 320, 36, 64, 640, 1, 1, true, false),
        (1, 512, 72, 128, 512, 3, 1, true, true),
        (1, 128, 288, 512, 128, 3, 1, true, true),
        (2, 320, 18, 32, 320, 3, 1, false, true),
        (2, 64, 18, 32, 64, 3, 1, false, false),
    ];
    for &(n, c, h, wd, co, k, stride, has_b, has_z) in &cases {
        let kk = c * k * k;
        let x = randn(&[n, c, h, wd], 1.0);
        let w = randn(&[co, c, k, k], 1.0 / (kk as f32).sqrt());
        let b = randn(&[co], 0.5);
        let cfg = conv::Conv2dConfig { padding: k / 2, stride, dilation: 1 };
        let (ho, wo) = ((h + 2 * (k / 2) - k) / stride + 1, (wd + 2 * (k / 2) - k) / stride + 1);
        let z = randn(&[n, co, ho, wo], 1.0);
        let scale = if has_z { 0.7 } else { 1.0 };
        for dt in [DType::F32, DType::BF16, DType::F16] {
            let what = format!("cudnn conv {n}x{c}x{h}x{wd} → {co}, k {k}, stride {stride}, bias {has_b}, residual {has_z}, {dt:?}");
            let (xr, wr, br, zr) = (rounded(&x, dt), rounded(&w, dt), rounded(&b, dt), rounded(&z, dt));
            let mut want = xr.conv2d(&wr, cfg.padding, stride, 1, 1).unwrap();
            if has_b {
                want = want.broadcast_add(&br.reshape((1, co, 1, 1)).unwrap()).unwrap();
            }
            want = (want * scale as f64).unwrap();
            if has_z {
                want = (want + &zr).unwrap();
            }
            let (bd, zd) = (dev(&b, dt), dev(&z, dt));
            let got = try_conv2d(&dev(&x, dt), &dev(&w, dt), has_b.then_some(&bd), has_z.then_some(&zd), scale, cfg).unwrap_or_else(|e| panic!("{what}: {e}"));
            let bmax = if has_b { br.abs().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap() as f64 } else { 0.0 };
            let extra = ((if has_z { zr.abs().unwrap() } else { zr.zeros_like().unwrap() }) + bmax).unwrap();
            check_cudnn(&what, &got, &want, dt, kk, &xr, &wr, &extra, scale);
            // The cached plan again: same result.
            let again = try_conv2d(&dev(&x, dt), &dev(&w, dt), has_b.then_some(&bd), has_z.then_some(&zd), scale, cfg).unwrap();
            check_cudnn(&format!("{what} (cached plan)"), &again, &want, dt, kk, &xr, &wr, &extra, scale);
        }
    }
    // Temporal (kt, 1, 1) conv on frame-major (B·T, C, H, W): the UNet's time_stack at 36×64 (one video of 14
    // frames) and two short videos (the zero padding must not leak across videos), against candle's
    // conv2d on a permuted copy of the same rounded inputs in f32.
    for (videos, frames, c, h, wd, residual) in [(1, 14, 320, 36, 64, true), (2, 5, 64, 9, 16, false)] {
        let (kt, n, co) = (3, videos * frames, c);
        let x = randn(&[n, c, h, wd], 1.0);
        let w = randn(&[co, kt * c], 1.0 / ((kt * c) as f32).sqrt());
        let b = randn(&[co], 0.5);
        let z = randn(&[n, co, h, wd], 1.0);
        let scale = if residual { 0.7 } else { 1.0 };
        for dt in [DType::F32, DType::BF16, DType::F16] {
            let what = format!("cudnn temporal conv {videos}×{frames} frames, {c} ch, {h}x{wd}, residual {residual}, {dt:?}");
            let (xr, wr, br, zr) = (rounded(&x, dt), rounded(&w, dt), rounded(&b, dt), rounded(&z, dt));
            // Reference: candle's conv2d on the (B, C, T, H·W) copy with the (Co, C, kt, 1) kernel (its one padding
            // value pads H·W too: those columns are dropped).
            let s = h * wd;
            let xp = xr.reshape((videos, frames, c, s)).unwrap().permute((0, 2, 1, 3)).unwrap().contiguous().unwrap();
            let w4 = wr.reshape((co, kt, c)).unwrap().permute((0, 2, 1)).unwrap().contiguous().unwrap().reshape((co, c, kt, 1)).unwrap();
            let y = xp.conv2d(&w4, kt / 2, 1, 1, 1).unwrap().narrow(3, kt / 2, s).unwrap().broadcast_add(&br.reshape((1, co, 1, 1)).unwrap()).unwrap();
            let mut want = (y.permute((0, 2, 1, 3)).unwrap().contiguous().unwrap().reshape((n, co, h, wd)).unwrap() * scale as f64).unwrap();
            if residual {
                want = (want + &zr).unwrap();
            }
            let zd = dev(&z, dt);
            let got =
                try_temporal(&dev(&x, dt), &dev(&w, dt), &dev(&b, dt), kt, frames, residual.then_some(&zd), scale).unwrap_or_else(|e| panic!("{what}: {e}"));
            let bmax = br.abs().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap() as f64;
            let extra = ((if residual { zr.abs().unwrap() } else { zr.zeros_like().unwrap() }) + bmax).unwrap();
            check_cudnn(&what, &got, &want, dt, kt * c, &xr, &wr, &extra, scale);
        }
    }
}

/// FlashAttention-2 (feature `flash-attn`, `attention::flash_multi_head_attention[_seqs]`, called directly so
/// that `MVSPLAT360_GPU_OPS` does not matter) against the composed path at the refiner's head size (64, 5 heads).
///
/// Reference: the composed path in f32 on the GPU, from the same f16/bf16-rounded inputs (the composed path in
/// f16/bf16 rounds the scores and the weights too, so it is a noisier reference than the kernel it would check).
/// Error model of the kernel: scores and the softmax in f32 (tensor-core products of rounded inputs are exact,
/// the sums f32); the weights p_j = exp(s_j − max) are rounded to the input dtype before p·V, each by at most a
/// relative u, which moves the output by at most u·Σ_j p_j·|v_j| (the normaliser is summed from the unrounded
/// p_j in f32); the output is rounded once more, u·|o|. So |flash − ref| ≤ u·(|ref| + Σ p|v|), with u = 2^-8
/// (bf16) or 2^-11 (f16); the check allows twice that (second-order terms, fast-math exp2), Σ p|v| taken from
/// the composed path on |v|, plus, in f16, weights below 2^-14 that lose precision as subnormals (≤ 2^-25 each:
/// L·2^-25·max|v|). A wrong head, pixel, row or scale errs by ≈ |o| + Σ p|v|, about 1/(2u) times that.
/// Lengths 300, 150, 77, 37·… are not multiples of the kernel's 128-row tile (its `Is_even_MN = false` variant),
/// 256 is.
#[cfg(feature = "flash-attn")]
#[test]
#[ignore = "needs a CUDA GPU and scripts/build-flash-attn: cargo test --features flash-attn -- --include-ignored"]
fn flash_attention_matches_composed() {
    use attention::{flash_multi_head_attention, flash_multi_head_attention_seqs, multi_head_attention, multi_head_attention_seqs, SeqLayout};
    use mvsplat360_nn::flash_attn::flash_attention;
    let d = gpu();
    let (heads, dh) = (5, 64);
    let inner = heads * dh;
    let dev = |t: &Tensor, dt: DType| t.to_dtype(dt).unwrap().to_device(&d).unwrap();
    let rounded = |t: &Tensor, dt: DType| t.to_dtype(dt).unwrap().to_dtype(DType::F32).unwrap().to_device(&d).unwrap();
    // Checks `got` against the composed f32 `reference(q, k, v)` of the rounded inputs, with the bound above.
    let check = |what: &str, dt: DType, got: &Tensor, qkv: [&Tensor; 3], len: usize, reference: &dyn Fn(&Tensor, &Tensor, &Tensor) -> Tensor| {
        assert!(got.device().is_cuda() && got.dtype() == dt, "{what}: result on {:?} as {:?}", got.device(), got.dtype());
        let [q, k, v] = qkv.map(|t| rounded(t, dt));
        let want = reference(&q, &k, &v);
        let spread = reference(&q, &k, &v.abs().unwrap());
        let u = if dt == DType::BF16 { 2f32.powi(-8) } else { 2f32.powi(-11) };
        let vmax = v.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        let atol = if dt == DType::F16 { len as f32 * 2f32.powi(-25) * vmax } else { 0.0 } + 1e-6;
        let mag = (want.abs().unwrap() + spread).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let tol: Vec<f32> = mag.iter().map(|m| 2.0 * u * m + atol).collect();
        let (r, i) = worst_ratio(got, &want, &tol);
        eprintln!("{what}: worst error {r:.3} of the bound");
        assert!(r <= 1.0, "{what}: error {r:.2}× the bound at element {i} (bound {:.3e})", tol[i]);
    };
    // Scores q·k/8 with std 1.5: softmax neither uniform nor one-hot.
    let qkv = |rows: &[usize], lk_rows: &[usize]| (randn(rows, 1.5), randn(lk_rows, 1.0), randn(lk_rows, 1.0));
    for dt in [DType::BF16, DType::F16] {
        // multi_head_attention: (N, Lq, H·64) × (N, Lk, H·64), self (uneven and whole tiles) and cross (Lq ≠ Lk).
        for (n, lq, lk) in [(2, 300, 300), (3, 256, 256), (2, 150, 77)] {
            let (q, k, v) = qkv(&[n, lq, inner], &[n, lk, inner]);
            let got = flash_multi_head_attention(&dev(&q, dt), &dev(&k, dt), &dev(&v, dt), heads).unwrap().expect("(N, L, H·64) fits the kernel");
            let reference = |q: &Tensor, k: &Tensor, v: &Tensor| multi_head_attention(q, k, v, heads, usize::MAX).unwrap();
            check(&format!("flash multi_head_attention {n}×{lq}×{lk}, {dt:?}"), dt, &got, [&q, &k, &v], lk, &reference);
        }
        // multi_head_attention_seqs: spatial (frames of 300 tokens), windowed (each frame in 2 windows of 150),
        // temporal over frame-major rows (2 videos × 14 frames × 37 pixels, whole and in 2 windows of 7 frames),
        // and temporal with 13 110 pixels, whose 65 550 folded heads exceed the grid limit (two launches).
        let (b, t, s) = (2, 14, 37);
        let temporal = |b: usize, t: usize, s: usize, splits: usize| {
            (b * t * s, SeqLayout { count: b * splits * s, len: t / splits, inner_count: s, outer: t / splits * s, inner: 1, pos: s })
        };
        let cases = [
            ("spatial", 4 * 300, SeqLayout::contiguous(4, 300)),
            ("windowed", 4 * 300, SeqLayout::contiguous(8, 150)),
            ("temporal", temporal(b, t, s, 1).0, temporal(b, t, s, 1).1),
            ("temporal, 2 windows", temporal(b, t, s, 2).0, temporal(b, t, s, 2).1),
            ("temporal, heads past the grid", temporal(1, 3, 13_110, 1).0, temporal(1, 3, 13_110, 1).1),
        ];
        for (what, rows, layout) in cases {
            let (q, k, v) = qkv(&[rows, inner], &[rows, inner]);
            let got = flash_multi_head_attention_seqs(&dev(&q, dt), &dev(&k, dt), &dev(&v, dt), layout, heads).unwrap().expect("layout fits the kernel");
            let reference = |q: &Tensor, k: &Tensor, v: &Tensor| multi_head_attention_seqs(q, k, v, layout, heads, usize::MAX).unwrap();
            check(&format!("flash multi_head_attention_seqs {what} {layout:?}, {dt:?}"), dt, &got, [&q, &k, &v], layout.len, &reference);
        }
        // Strided operands as the op reads them (views into packed (…, H, 2·64) rows, offset 64): no copy needed.
        let (q, k, v) = qkv(&[2, 200, heads, 2 * dh], &[2, 200, heads, 2 * dh]);
        let view = |t: &Tensor| dev(t, dt).narrow(3, dh, dh).unwrap();
        let got = flash_attention(&view(&q), &view(&k), &view(&v), 0.125).unwrap().reshape((2, 200, inner)).unwrap();
        let flat = |t: &Tensor| t.narrow(3, dh, dh).unwrap().contiguous().unwrap().reshape((2, 200, inner)).unwrap();
        let reference = |q: &Tensor, k: &Tensor, v: &Tensor| multi_head_attention(q, k, v, heads, usize::MAX).unwrap();
        check(&format!("flash_attention on strided views, {dt:?}"), dt, &got, [&flat(&q), &flat(&k), &flat(&v)], 200, &reference);
        // What the kernel cannot take is an error (the callers fall back), never a launch: head dim 32, f32, rows
        // 68 elements apart (not 16-byte aligned); layouts that are no (batch, seq, heads, 64) view are None.
        let x = dev(&randn(&[2, 40, 4, 32], 1.0), dt);
        assert!(flash_attention(&x, &x, &x, 0.1).is_err(), "head dim 32");
        let x = randn(&[2, 40, 4, 64], 1.0).to_device(&d).unwrap();
        assert!(flash_attention(&x, &x, &x, 0.1).is_err(), "f32");
        let x = dev(&randn(&[2, 40, 4, 68], 1.0), dt).narrow(3, 0, 64).unwrap();
        assert!(flash_attention(&x, &x, &x, 0.1).is_err(), "unaligned strides");
        let x = dev(&randn(&[60, inner], 1.0), dt);
        let gathered = SeqLayout { count: 3, len: 10, inner_count: 1, outer: 20, inner: 0, pos: 2 };
        assert!(flash_multi_head_attention_seqs(&x, &x, &x, gathered, heads).unwrap().is_none(), "gathered rows");
        let x3 = x.reshape((2, 30, inner)).unwrap();
        assert!(flash_multi_head_attention(&x3, &x3, &x3, 10).unwrap().is_none(), "head dim 32 in the folded form");
    }
}
