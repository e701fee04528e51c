//! The candle wrapper: `loss.backward()` through `render` reaches every `Var` with the core's gradients
//! (checked against the golden fixture, which the core matches), and the feature SH evaluation is differentiable.

use candle_core::{DType, Device, Tensor, Var};
use mvsplat360_splat::{render, sh, Gaussians, RenderOptions};
use mvsplat360_testkit::{assert_close, assert_close_rel_max, get, load};

mod common;
use common::camera;

#[test]
fn autograd_matches_fixture_gradients() {
    check_against_fixture(false);
}

/// Constant colours and features (as test-time fitting renders them) travel inside the op instead of the packed
/// autograd input; the geometry's gradients must not change.
#[test]
fn constant_colours_keep_the_geometry_gradients() {
    check_against_fixture(true);
}

fn check_against_fixture(constant_colours: bool) {
    let m = load("rasterizer/small.safetensors");
    let cam = camera(&m);
    let dev = Device::Cpu;
    let n = get(&m, "means").dim(0).unwrap();
    let cov6 = get(&m, "cov3d").to_vec2::<f32>().unwrap();
    let full: Vec<f32> = cov6.iter().flat_map(|c| [c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5]]).collect();
    // Feature SH of degree 0 whose evaluation (C0·h + 0.5) reproduces the fixture's features.
    let fh = ((get(&m, "features") - 0.5).unwrap() / sh::C0 as f64).unwrap().unsqueeze(2).unwrap();
    let means = Var::from_tensor(get(&m, "means")).unwrap();
    let covs = Var::from_tensor(&Tensor::from_vec(full, (n, 3, 3), &dev).unwrap()).unwrap();
    let opac = Var::from_tensor(get(&m, "opacities")).unwrap();
    let harm = Var::from_tensor(&get(&m, "sh").transpose(1, 2).unwrap().contiguous().unwrap()).unwrap();
    let feat = Var::from_tensor(&fh).unwrap();
    let (harmonics, feature_harmonics) =
        if constant_colours { (harm.as_tensor().detach(), feat.as_tensor().detach()) } else { (harm.as_tensor().clone(), feat.as_tensor().clone()) };
    let g = Gaussians {
        means: means.as_tensor().clone(),
        covariances: covs.as_tensor().clone(),
        opacities: opac.as_tensor().clone(),
        harmonics,
        feature_harmonics,
    };
    let bg = get(&m, "background").to_vec1::<f32>().unwrap();
    let opts = RenderOptions { background: [bg[0], bg[1], bg[2]], ..Default::default() };
    let out = render(&g, &cam, &opts).unwrap();
    let w1 = get(&m, "W1").permute((2, 0, 1)).unwrap();
    let w2 = get(&m, "W2").permute((2, 0, 1)).unwrap();
    assert_close("rgb", &out.rgb, &get(&m, "rgb").permute((2, 0, 1)).unwrap(), 1e-4);
    assert_close("feat", &out.features, &get(&m, "feat").permute((2, 0, 1)).unwrap(), 1e-4);
    let radii = out.radii.to_dtype(DType::I64).unwrap();
    assert_eq!(radii.to_vec1::<i64>().unwrap(), get(&m, "radii").to_dtype(DType::I64).unwrap().to_vec1::<i64>().unwrap());
    let loss = ((&out.rgb * &w1).unwrap().sum_all().unwrap() + (&out.features * &w2).unwrap().sum_all().unwrap()).unwrap();
    let grads = loss.backward().unwrap();
    let gr = |v: &Var| grads.get(v.as_tensor()).expect("no gradient reached a Var").clone();
    let tol = 1e-4;
    assert_close_rel_max("grad_means", &gr(&means), get(&m, "grad_means"), tol);
    assert_close_rel_max("grad_opacities", &gr(&opac), get(&m, "grad_opacities"), tol);
    if constant_colours {
        assert!(grads.get(harm.as_tensor()).is_none() && grads.get(feat.as_tensor()).is_none(), "a gradient reached a constant");
    } else {
        assert_close_rel_max("grad_sh", &gr(&harm).transpose(1, 2).unwrap(), get(&m, "grad_sh"), tol);
        let gf = (gr(&feat).squeeze(2).unwrap() / sh::C0 as f64).unwrap();
        assert_close_rel_max("grad_features", &gf, get(&m, "grad_features"), tol);
    }
    // The official wrapper reads the upper triangle only: that is where the cov3d gradient lands.
    let gc = gr(&covs).reshape((n, 9)).unwrap();
    let upper = gc.index_select(&Tensor::new(&[0u32, 1, 2, 4, 5, 8], &dev).unwrap(), 1).unwrap();
    assert_close_rel_max("grad_cov3d", &upper, get(&m, "grad_cov3d"), tol);
    let lower = gc.index_select(&Tensor::new(&[3u32, 6, 7], &dev).unwrap(), 1).unwrap();
    assert_eq!(lower.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap(), 0.0);
}

#[test]
fn feature_sh_matches_closed_form_and_is_differentiable() {
    let dev = Device::Cpu;
    let dirs_v: Vec<f32> = vec![0.6, 0.0, 0.8, 0.0, -1.0, 0.0];
    let dirs = Var::from_tensor(&Tensor::from_vec(dirs_v.clone(), (2, 3), &dev).unwrap()).unwrap();
    let coeffs: Vec<f32> = (0..2 * 2 * 9).map(|i| (i as f32 * 0.37).sin()).collect();
    let shv = Var::from_tensor(&Tensor::from_vec(coeffs.clone(), (2, 2, 9), &dev).unwrap()).unwrap();
    let out = sh::eval_feature_sh(shv.as_tensor(), dirs.as_tensor()).unwrap();
    let got = out.to_vec2::<f32>().unwrap();
    for i in 0..2 {
        let mut b = [0f32; 16];
        sh::basis([dirs_v[3 * i], dirs_v[3 * i + 1], dirs_v[3 * i + 2]], 2, &mut b);
        for c in 0..2 {
            let want: f32 = (0..9).map(|k| b[k] * coeffs[(i * 2 + c) * 9 + k]).sum::<f32>() + 0.5;
            assert!((got[i][c] - want).abs() < 1e-6, "feature SH {i},{c}: {} vs {want}", got[i][c]);
        }
    }
    let grads = out.sum_all().unwrap().backward().unwrap();
    let gd = grads.get(dirs.as_tensor()).expect("no gradient to directions");
    assert!(gd.abs().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap() > 0.0);
    // d/dcoeff = basis value.
    let gs = grads.get(shv.as_tensor()).unwrap().to_vec3::<f32>().unwrap();
    assert!((gs[0][0][0] - sh::C0).abs() < 1e-6);
}
