//! End-to-end encoder parity against the official PyTorch `EncoderCostVolume` (fixtures/encoder), plus the tiny
//! configuration with random weights (shapes, conversion to splat Gaussians, gradients to every Var).
//!
//! Tolerances (fixture README, ≈5× the f32-vs-f64 noise of the reference itself), normalised error
//! e = max|Δ| / max(1, max|ref|): e ≤ 2e-4 for opacities and both SH; e ≤ 2e-3 for depths, means, scales,
//! rotations and covariances (depth = 1/disparity amplifies f32 noise near the far plane); disparity 1/depth
//! max-abs ≤ 1e-4.

use candle_core::{DType, Device, Tensor};
use mvsplat360_encoder::{to_splat_gaussians, EncoderCostVolume, EncoderCostVolumeCfg};
use mvsplat360_testkit as tk;

fn check(name: &str, a: &Tensor, e: &Tensor, tol: f64) {
    let (d, m) = tk::max_abs_diff(a, e);
    eprintln!("{name}: max abs {d:.3e}, max|ref| {m:.3e}, e {:.3e} (tol {tol:.0e})", d / m.max(1.0));
    tk::assert_close_norm(name, a, e, tol);
}

#[test]
fn encoder_matches_official_outputs() {
    let inputs = tk::load("encoder/inputs.safetensors");
    let outputs = tk::load("encoder/outputs.safetensors");
    let images = tk::get(&inputs, "context.image");
    let (_, v, _, _, _) = images.dims5().unwrap();
    let cfg = EncoderCostVolumeCfg { num_views: v, ..Default::default() };
    // Strict: zero missing and zero unexpected `encoder.*` keys, or this fails with the key list.
    let enc = EncoderCostVolume::load(tk::fixture("encoder/state_dict.safetensors"), &cfg, &Device::Cpu)
        .unwrap_or_else(|e| panic!("{e}"));
    let g = enc
        .forward(
            images,
            tk::get(&inputs, "context.intrinsics"),
            tk::get(&inputs, "context.extrinsics"),
            tk::get(&inputs, "context.near"),
            tk::get(&inputs, "context.far"),
        )
        .unwrap();
    check("gaussians.opacities", &g.opacities, tk::get(&outputs, "gaussians.opacities"), 2e-4);
    check("gaussians.harmonics", &g.harmonics, tk::get(&outputs, "gaussians.harmonics"), 2e-4);
    check("gaussians.feature_harmonics", &g.feature_harmonics, tk::get(&outputs, "gaussians.feature_harmonics"), 2e-4);
    check("gaussians.rotations", &g.rotations, tk::get(&outputs, "gaussians.rotations"), 2e-3);
    check("gaussians.scales", &g.scales, tk::get(&outputs, "gaussians.scales"), 2e-3);
    check("gaussians.means", &g.means, tk::get(&outputs, "gaussians.means"), 2e-3);
    check("gaussians.covariances", &g.covariances, tk::get(&outputs, "gaussians.covariances"), 2e-3);
    let want_depths = tk::get(&outputs, "depths");
    check("depths", &g.depths, want_depths, 2e-3);
    let disp = g.depths.recip().unwrap();
    let want_disp = want_depths.recip().unwrap();
    let (d, _) = tk::max_abs_diff(&disp, &want_disp);
    eprintln!("disparity (1/depths): max abs {d:.3e} (tol 1e-4)");
    assert!(d <= 1e-4, "disparity max abs {d:.3e} > 1e-4");

    // Per-batch conversion to the splat crate's type keeps every value (view-major Gaussian order).
    let splat = to_splat_gaussians(&g).unwrap();
    assert_eq!(splat.len(), 1);
    tk::assert_close("splat.means", &splat[0].means, &g.means.squeeze(0).unwrap(), 0.0);
    tk::assert_close("splat.harmonics", &splat[0].harmonics, &g.harmonics.squeeze(0).unwrap(), 0.0);
}

#[test]
fn wrong_view_count_or_size_is_a_clear_error() {
    let cfg = EncoderCostVolumeCfg::tiny();
    let dev = Device::Cpu;
    let w = mvsplat360_encoder::weights::random_tensors(1, &dev, |vb| EncoderCostVolume::new(vb.pp("encoder"), &cfg)).unwrap();
    let enc = EncoderCostVolume::new(candle_nn::VarBuilder::from_tensors(w, DType::F32, &dev).pp("encoder"), &cfg).unwrap();
    let [im, k, e, n, f] = mvsplat360_encoder::bench::synthetic_context(1, cfg.num_views, 40, 32, &dev).unwrap();
    let err = enc.forward(&im, &k, &e, &n, &f).err().expect("40 rows is not a valid size").to_string();
    assert!(err.contains("multiple of"), "{err}");
    let [im, k, e, n, f] = mvsplat360_encoder::bench::synthetic_context(1, cfg.num_views + 1, 32, 32, &dev).unwrap();
    let err = enc.forward(&im, &k, &e, &n, &f).err().expect("view count differs from num_views").to_string();
    assert!(err.contains("num_views"), "{err}");
}

/// Tiny config, random weights: output shapes, probability ranges, and a non-zero gradient for every trainable
/// Var (biases of the CNN's 1×1 shortcut convs excepted: InstanceNorm cancels them exactly, so their gradient
/// must vanish instead).
#[test]
fn tiny_encoder_shapes_and_gradients() {
    use candle_nn::{VarBuilder, VarMap};
    let dev = Device::Cpu;
    let cfg = EncoderCostVolumeCfg::tiny();
    let varmap = VarMap::new();
    let enc = EncoderCostVolume::new(VarBuilder::from_varmap(&varmap, DType::F32, &dev).pp("encoder"), &cfg).unwrap();
    let init = mvsplat360_encoder::weights::random_tensors(5, &dev, |vb| EncoderCostVolume::new(vb.pp("encoder"), &cfg)).unwrap();
    for (name, var) in varmap.data().lock().unwrap().iter() {
        var.set(&init[name]).unwrap();
    }
    let (h, w) = (32, 32);
    let v = cfg.num_views;
    let [im, k, e, n, f] = mvsplat360_encoder::bench::synthetic_context(1, v, h, w, &dev).unwrap();
    let g = enc.forward(&im, &k, &e, &n, &f).unwrap();
    let n_g = v * h * w;
    assert_eq!(g.means.dims(), &[1, n_g, 3]);
    assert_eq!(g.covariances.dims(), &[1, n_g, 3, 3]);
    assert_eq!(g.harmonics.dims(), &[1, n_g, 3, 25]);
    assert_eq!(g.feature_harmonics.dims(), &[1, n_g, 4, 9]);
    assert_eq!(g.opacities.dims(), &[1, n_g]);
    assert_eq!(g.depths.dims(), &[1, v, h, w, 1, 1]);
    let op: Vec<f32> = g.opacities.flatten_all().unwrap().to_vec1().unwrap();
    assert!(op.iter().all(|&o| (0.0..=1.0).contains(&o)));
    let d: Vec<f32> = g.depths.flatten_all().unwrap().to_vec1().unwrap();
    assert!(d.iter().all(|&x| x >= cfg.near * 0.999 && x <= cfg.far * 1.001), "depths outside [near, far]");

    let mut loss = Tensor::zeros((), DType::F32, &dev).unwrap();
    for t in [&g.means, &g.covariances, &g.harmonics, &g.feature_harmonics, &g.opacities] {
        let wts = Tensor::randn(0f32, 1.0, t.dims(), &dev).unwrap();
        loss = (loss + (t * wts).unwrap().sum_all().unwrap()).unwrap();
    }
    let grads = loss.backward().unwrap();
    let data = varmap.data().lock().unwrap();
    let mut zero = Vec::new();
    for (name, var) in data.iter() {
        let gmax = grads
            .get(var.as_tensor())
            .map(|g| g.abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap())
            .unwrap_or(0.0);
        if name.contains("backbone.backbone.") && name.contains("downsample.0.bias") {
            assert!(gmax < 1e-3, "{name}: InstanceNorm should cancel this bias, |grad| {gmax}");
        } else if !(gmax > 0.0 && gmax.is_finite()) {
            zero.push(format!("{name} ({gmax})"));
        }
    }
    assert!(zero.is_empty(), "Vars without gradient: {zero:?}");
}
