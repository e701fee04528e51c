//! Depth-predictor parity against the official PyTorch encoder (fixtures/encoder, README "Intermediates"), fed
//! with the fixture's own backbone features so it does not depend on the backbone port.
//! Tolerances: an error model (intermediates relative to each tensor's max; the Gaussians by tests/common/mod.rs),
//! checked on fixtures of 3 seeds × 2 sizes (scripts/fixtures/check-parity-seeds).

use candle_core::{DType, Device, IndexOp, Tensor};
use mvsplat360_encoder::config::EncoderCostVolumeCfg;
use mvsplat360_encoder::costvolume::{DepthPredictorInput, DepthPredictorMultiView};
use mvsplat360_encoder::weights::load_strict;
use mvsplat360_testkit::{self as tk, Tol};

mod common;

/// Intermediates: |ours − official| ≤ INTER × max|official| of that tensor. Scale-relative, not element-wise: the
/// cost volume (up to ~140), the UNets and the heads are sums of many terms, so an entry near zero carries the
/// absolute noise of the tensor's scale. Measured worst: 7.3e-6 (pdf max, whose max is ~1), ≤ 5e-6 elsewhere,
/// on 7 fixtures (shared + seeds 0–2 × 32×64, 48×80) → 2e-5 (2.7×).
const INTER: f64 = 2e-5;
/// Depth predictor → adapter, end to end: the model of tests/common. Measured (fed the official backbone
/// features) on 9 fixtures (shared + seeds 0–3 × 32×64, 48×80): disparity τ 3.6e-6, rotations 2.2e-5, opacities
/// 1.25e-6, SH 1.7e-5 of the block max (degree 4: the Wigner-D difference, see adapter.rs) → τ 1e-5, q 6e-5,
/// o 4e-6, σ 5e-5 (≥ 2.7×); ρ 1e-6 (≈ 16 u) covers the final products.
const TOL: common::GaussianTol = common::GaussianTol { disparity: 1e-5, rounding: 1e-6, rotation: 6e-5, opacity: 4e-6, sh: 5e-5 };

#[test]
fn depth_predictor_matches_official_intermediates() {
    let inputs = tk::load("encoder/inputs.safetensors");
    let inter = tk::load("encoder/intermediates.safetensors");
    let outputs = tk::load("encoder/outputs.safetensors");
    let images = tk::get(&inputs, "context.image");
    let cfg = EncoderCostVolumeCfg { num_views: images.dim(1).unwrap(), ..Default::default() };
    let model =
        load_strict(tk::fixture("encoder/state_dict.safetensors"), "encoder.depth_predictor.", &Device::Cpu, |vb| DepthPredictorMultiView::new(vb, &cfg))
            .unwrap();
    let index = tk::get(&inter, "encoder.cameras_dist_index").to_dtype(DType::U32).unwrap();
    let inp = DepthPredictorInput {
        features_cnn: tk::get(&inter, "backbone.cnn_features"),
        features_trans: tk::get(&inter, "backbone.trans_features"),
        images,
        intrinsics: tk::get(&inputs, "context.intrinsics"),
        extrinsics: tk::get(&inputs, "context.extrinsics"),
        near: tk::get(&inputs, "context.near"),
        far: tk::get(&inputs, "context.far"),
        cameras_dist_index: &index,
    };
    let out = model.forward_with_intermediates(&inp).unwrap();
    let it = out.intermediates.as_ref().unwrap();
    let mut fails: Vec<String> = Vec::new();
    let mut check = |name: &str, a: &Tensor, e: &Tensor, tol: Tol| fails.extend(tk::check(name, a, e, tol));
    // Both sides: 1/far + linspace·(1/near − 1/far) in f32.
    check("depth.disparity_candidates", &it.disparity_candidates.i(0).unwrap(), tk::get(&inter, "depth.disparity_candidates"), Tol::of_max(1e-6));
    for (name, t) in [
        ("depth.cost_volume", &it.cost_volume),
        ("depth.corr_refine_net.out", &it.corr_refine_net_out),
        ("depth.cost_volume_refined", &it.cost_volume_refined),
        ("depth.depth_head_lowres.out", &it.depth_head_lowres_out),
        ("depth.pdf_max_lowres", &it.pdf_max_lowres),
        ("depth.coarse_disparity_lowres", &it.coarse_disparity_lowres),
        ("depth.fullres_disparity", &it.fullres_disparity),
        ("depth.pdf_max_fullres", &it.pdf_max_fullres),
        ("depth.proj_feature.out", &it.proj_feature_out),
        ("depth.refine_unet.out", &it.refine_unet_out),
        ("depth.to_disparity.out", &it.to_disparity_out),
    ] {
        check(name, t, tk::get(&inter, name), Tol::of_max(INTER));
    }
    // raw Gaussians [B,V,C,H,W] vs the fixture's (v b) layout (B = 1 here).
    let (b, v, c, h, w) = out.raw_gaussians.dims5().unwrap();
    let raw_vb = out.raw_gaussians.permute((1, 0, 2, 3, 4)).unwrap().reshape((v * b, c, h, w)).unwrap();
    check("depth.to_gaussians.out", &raw_vb, tk::get(&inter, "depth.to_gaussians.out"), Tol::of_max(INTER));
    let dens = tk::get(&inter, "adapter.in.opacities").reshape((b, v, h, w)).unwrap();
    check("densities", &out.densities, &dens, Tol::abs(TOL.opacity));

    // Depth predictor → adapter, end to end against the official Gaussians (depths and disparity included).
    let g = mvsplat360_encoder::common::gaussians_from_prediction(&cfg, &out, inp.extrinsics, inp.intrinsics, (h, w)).unwrap();
    common::check_gaussians("end-to-end ", &g, &outputs, TOL, &mut fails);
    tk::assert_no_failures("depth predictor vs official", &fails);
}

/// Every trainable parameter of the depth predictor and the input features receive a non-zero, finite gradient
/// through the depth predictor and the Gaussian adapter (tiny config, random weights). This is what would
/// catch an op without a backward (candle's fused softmax/norms silently drop gradients).
#[test]
fn depth_predictor_and_adapter_backpropagate_to_every_parameter() {
    use candle_core::Var;
    use candle_nn::{VarBuilder, VarMap};
    use mvsplat360_encoder::common::gaussians_from_prediction;

    let cfg = EncoderCostVolumeCfg::tiny();
    let dev = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
    let model = DepthPredictorMultiView::new(vb, &cfg).unwrap();
    // Random weights (VarMap's default init is zero): small normals, unit-ish norm weights.
    {
        let data = varmap.data().lock().unwrap();
        let mut names: Vec<_> = data.keys().cloned().collect();
        names.sort();
        for name in &names {
            let var = &data[name];
            let std = if name.ends_with(".weight") && var.rank() > 1 {
                let fan_in: usize = var.dims()[1..].iter().product();
                1.0 / (fan_in as f64).sqrt()
            } else {
                0.1
            };
            let mean = if var.rank() == 1 && name.ends_with(".weight") { 1.0 } else { 0.0 };
            var.set(&Tensor::randn(mean as f32, std as f32, var.shape(), &dev).unwrap()).unwrap();
        }
    }
    let (b, v, c, h, w) = (1, cfg.num_views, cfg.d_feature, 4, 8);
    let up = cfg.downscale_factor;
    let f_trans = Var::from_tensor(&Tensor::randn(0f32, 1.0, (b, v, c, h, w), &dev).unwrap()).unwrap();
    let f_cnn = Var::from_tensor(&Tensor::randn(0f32, 1.0, (b, v, c, h, w), &dev).unwrap()).unwrap();
    let images = Tensor::rand(0f32, 1.0, (b, v, 3, h * up, w * up), &dev).unwrap();
    // Cameras on an arc looking roughly forward (+z), c2w.
    let mut ext = Vec::new();
    for i in 0..v {
        let a = 0.15 * i as f32;
        let (ca, sa) = (a.cos(), a.sin());
        ext.extend_from_slice(&[ca, 0.0, sa, 0.4 * i as f32, 0.0, 1.0, 0.0, 0.05 * i as f32, -sa, 0.0, ca, 0.0, 0.0, 0.0, 0.0, 1.0]);
    }
    let extrinsics = Tensor::from_vec(ext, (b, v, 4, 4), &dev).unwrap();
    let k = Tensor::new(&[[0.8f32, 0.0, 0.5], [0.0, 1.6, 0.5], [0.0, 0.0, 1.0]], &dev).unwrap();
    let intrinsics = k.broadcast_as((b, v, 3, 3)).unwrap().contiguous().unwrap();
    let near = Tensor::full(1f32, (b, v), &dev).unwrap();
    let far = Tensor::full(100f32, (b, v), &dev).unwrap();
    // Nearest views by index distance (column 0 = self).
    let mut idx = Vec::new();
    for i in 0..v {
        let mut order: Vec<u32> = (0..v as u32).collect();
        order.sort_by_key(|&j| ((j as i64 - i as i64).abs(), j));
        idx.extend(order);
    }
    let index = Tensor::from_vec(idx, (b, v, v), &dev).unwrap();
    let inp = DepthPredictorInput {
        features_cnn: f_cnn.as_tensor(),
        features_trans: f_trans.as_tensor(),
        images: &images,
        intrinsics: &intrinsics,
        extrinsics: &extrinsics,
        near: &near,
        far: &far,
        cameras_dist_index: &index,
    };
    let pred = model.forward(&inp).unwrap();
    let g = gaussians_from_prediction(&cfg, &pred, &extrinsics, &intrinsics, (h * up, w * up)).unwrap();
    let weighted = |t: &Tensor| -> Tensor {
        let r = Tensor::randn(0f32, 1.0, t.shape(), &dev).unwrap();
        t.mul(&r).unwrap().sum_all().unwrap()
    };
    let loss = [weighted(&g.means), weighted(&g.covariances), weighted(&g.harmonics), weighted(&g.feature_harmonics), weighted(&g.opacities)]
        .into_iter()
        .reduce(|a, b| (a + b).unwrap())
        .unwrap();
    let grads = loss.backward().unwrap();
    let data = varmap.data().lock().unwrap();
    let mut missing = Vec::new();
    for (name, var) in data.iter() {
        match grads.get(var.as_tensor()) {
            Some(gr) => {
                let m = gr.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
                if !(m > 0.0 && m.is_finite()) {
                    missing.push(format!("{name} (max |grad| {m})"));
                }
            }
            None => missing.push(format!("{name} (no grad)")),
        }
    }
    for (name, var) in [("features_trans", &f_trans), ("features_cnn", &f_cnn)] {
        let gr = grads.get(var.as_tensor()).unwrap_or_else(|| panic!("{name}: no gradient"));
        assert!(gr.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap() > 0.0, "{name}: zero gradient");
    }
    missing.sort();
    assert!(missing.is_empty(), "{} of {} parameters get no gradient: {missing:?}", missing.len(), data.len());
}
