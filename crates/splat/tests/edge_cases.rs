//! Degenerate inputs: nothing may panic or produce NaN.

use candle_core::{DType, Device, Tensor};
use mvsplat360_splat::cpu::{self, CovInput, GradMode, PixelGrads, RasterInputs, RasterSettings};
use mvsplat360_splat::{render, Gaussians, RasterCamera, RenderOptions};

fn cam(w: usize, h: usize) -> RasterCamera {
    let mut v = [[0f32; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    RasterCamera { viewmatrix: v, fx: w as f32, fy: h as f32, cx: w as f32 / 2.0, cy: h as f32 / 2.0, width: w, height: h, near: 0.1, far: 100.0 }
}

/// Gaussians: in view, behind the camera, at the near cull, far outside the frustum, zero opacity,
/// zero covariance, NaN covariance, rank-1 covariance, huge covariance, negative-definite covariance.
fn run(w: usize, h: usize, mode: GradMode) {
    let means: Vec<f32> = vec![
        0.0, 0.0, 2.0, //
        0.0, 0.0, -2.0, //
        0.0, 0.0, 0.19, //
        100.0, 0.0, 2.0, //
        0.1, 0.0, 2.0, //
        0.0, 0.1, 2.0, //
        0.0, 0.0, 3.0, //
        0.05, 0.05, 2.5, //
        0.0, 0.0, 5.0, //
        0.0, 0.0, 4.0, //
    ];
    let n = means.len() / 3;
    let mut cov = vec![];
    for i in 0..n {
        let c: [f32; 6] = match i {
            5 => [0.0; 6],
            6 => [f32::NAN; 6],
            7 => [1.0, 1.0, 1.0, 1.0, 1.0, 1.0],
            8 => [1e12, 0.0, 0.0, 1e12, 0.0, 1e12],
            9 => [-0.01, 0.0, 0.0, -0.01, 0.0, -0.01],
            _ => [0.01, 0.0, 0.0, 0.01, 0.0, 0.01],
        };
        cov.extend_from_slice(&c);
    }
    let mut opac = vec![0.8f32; n];
    opac[4] = 0.0;
    let sh = vec![0.3f32; n * 16 * 3];
    let feat = vec![0.5f32; n * 4];
    let inp =
        RasterInputs { means: &means, cov: CovInput::Cov3d(&cov), opacities: &opac, sh: &sh, sh_coeffs: 16, sh_degree: 3, features: &feat, num_features: 4 };
    let st = RasterSettings { camera: cam(w, h), background: [1.0, 0.0, 0.5] };
    let out = cpu::forward(&inp, &st).unwrap();
    for v in [&out.rgb, &out.features, &out.alpha, &out.depth, &out.final_t] {
        assert!(v.iter().all(|x| x.is_finite()), "non-finite image");
    }
    assert_eq!(out.radii[1], 0, "behind the camera must be culled");
    assert_eq!(out.radii[2], 0, "z <= 0.2 must be culled");
    assert_eq!(out.radii[3], 0, "outside the frustum must be culled");
    let hw = w * h;
    let ones = vec![1f32; 4 * hw];
    let pg = PixelGrads { rgb: &ones[..3 * hw], features: &ones, alpha: Some(&ones[..hw]), depth: Some(&ones[..hw]) };
    let g = cpu::backward(&inp, &st, &out, &pg, mode).unwrap();
    for v in [&g.means, &g.cov3d, &g.opacities, &g.sh, &g.features, &g.means2d_ndc] {
        assert!(v.iter().all(|x| x.is_finite()), "non-finite gradient");
    }
    for i in [1, 2, 3] {
        assert!(g.means[3 * i..3 * i + 3].iter().all(|&x| x == 0.0), "culled Gaussian {i} got a gradient");
    }
    // Scale/rotation path with a zero quaternion and zero scales.
    let scales = vec![0f32; 3 * n];
    let quats = vec![0f32; 4 * n];
    let inp2 = RasterInputs { cov: CovInput::ScaleRot { scales: &scales, quats: &quats }, ..inp };
    let out2 = cpu::forward(&inp2, &st).unwrap();
    assert!(out2.rgb.iter().all(|x| x.is_finite()));
    let g2 = cpu::backward(&inp2, &st, &out2, &pg, mode).unwrap();
    assert!(g2.scales.unwrap().iter().chain(g2.quats.unwrap().iter()).all(|x| x.is_finite()));
}

#[test]
fn degenerate_gaussians_official() {
    run(40, 24, GradMode::Official);
}

#[test]
fn degenerate_gaussians_exact() {
    run(40, 24, GradMode::Exact);
}

#[test]
fn one_by_one_image() {
    run(1, 1, GradMode::Official);
    run(1, 1, GradMode::Exact);
}

#[test]
fn empty_scene_gives_background() {
    let st = RasterSettings { camera: cam(17, 5), background: [0.25, 0.5, 0.75] };
    let inp = RasterInputs { means: &[], cov: CovInput::Cov3d(&[]), opacities: &[], sh: &[], sh_coeffs: 1, sh_degree: 0, features: &[], num_features: 3 };
    let out = cpu::forward(&inp, &st).unwrap();
    assert!(out.rgb[..85].iter().all(|&x| x == 0.25));
    assert!(out.rgb[170..].iter().all(|&x| x == 0.75));
    assert!(out.features.iter().all(|&x| x == 0.0));
    assert!(out.final_t.iter().all(|&x| x == 1.0));

    let dev = Device::Cpu;
    let g = Gaussians {
        means: Tensor::zeros((0, 3), DType::F32, &dev).unwrap(),
        covariances: Tensor::zeros((0, 3, 3), DType::F32, &dev).unwrap(),
        opacities: Tensor::zeros(0, DType::F32, &dev).unwrap(),
        harmonics: Tensor::zeros((0, 3, 25), DType::F32, &dev).unwrap(),
        feature_harmonics: Tensor::zeros((0, 4, 9), DType::F32, &dev).unwrap(),
    };
    let r = render(&g, &cam(17, 5), &RenderOptions { background: [0.25, 0.5, 0.75], ..Default::default() }).unwrap();
    assert_eq!(r.rgb.dims(), &[3, 5, 17]);
    assert_eq!(r.features.dims(), &[4, 5, 17]);
    let v = r.rgb.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert_eq!(v[0], 0.25);
    assert_eq!(v[3 * 85 - 1], 0.75);
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let st = RasterSettings { camera: cam(8, 8), background: [0.0; 3] };
    let inp = RasterInputs {
        means: &[0.0; 5],
        cov: CovInput::Cov3d(&[0.0; 6]),
        opacities: &[1.0],
        sh: &[0.0; 3],
        sh_coeffs: 1,
        sh_degree: 0,
        features: &[],
        num_features: 0,
    };
    assert!(cpu::forward(&inp, &st).is_err());
    let mut c = cam(0, 8);
    c.width = 0;
    let inp = RasterInputs { means: &[0.0; 3], ..inp };
    assert!(cpu::forward(&inp, &RasterSettings { camera: c, background: [0.0; 3] }).is_err());
}
