//! The CUDA rasterizer on a real GPU (feature `cuda-raster`; run on a CUDA machine with
//! `cargo test -p mvsplat360-splat --features cuda-raster --test cuda_device`): forward images, per-Gaussian
//! buffers and every gradient against the CPU path and the golden fixtures, both covariance paths and both
//! gradient modes. Without the feature this file compiles to nothing. The kernels' logic is also checked
//! without a GPU by tests/cuda_emulated.rs.
//!
//! Tolerances: images 1e-4 abs, gradients 1e-4 × max |ref| (nvcc contracts into FMA and atomicAdd order
//! varies, so results differ from the CPU path by rounding), radii / tiles_touched exact except where FMA
//! moves a radius across an integer (≤ 0.1 % of Gaussians), n_contrib ≤ 0.1 % of pixels.
#![cfg(feature = "cuda-raster")]

use mvsplat360_splat::cpu::{self, GradMode, PixelGrads};
use mvsplat360_splat::cuda::CudaRasterizer;

mod common;
use common::{check_abs, check_rel, count_diff, CovPath, Fixture};

fn run(file: &str) {
    let fx = Fixture::load(file);
    let gpu = CudaRasterizer::new(0).expect("a CUDA device (this test needs a GPU)");
    let hw = fx.settings.camera.width * fx.settings.camera.height;
    let ones = vec![0.25f32; hw];
    for path in [CovPath::Cov3d, CovPath::ScaleRot] {
        eprintln!("--- {file} via {path:?}");
        let inp = fx.inputs(path);
        let cpu_out = cpu::forward(&inp, &fx.settings).unwrap();
        let out = gpu.forward(&inp, &fx.settings).unwrap();
        let n = inp.len();
        let bad_r = count_diff(&out.radii, &cpu_out.radii);
        assert!(bad_r * 1000 <= n, "radii differ for {bad_r} of {n} Gaussians");
        let bad_t = count_diff(&out.tiles_touched, &cpu_out.tiles_touched);
        assert!(bad_t * 1000 <= n, "tiles_touched differ for {bad_t} of {n} Gaussians");
        check_abs("rgb vs CPU", &out.rgb, &cpu_out.rgb, 1e-4);
        check_abs("features vs CPU", &out.features, &cpu_out.features, 1e-4);
        check_abs("alpha vs CPU", &out.alpha, &cpu_out.alpha, 1e-4);
        check_abs("depth vs CPU", &out.depth, &cpu_out.depth, 1e-4);
        check_abs("rgb vs fixture", &out.rgb, &fx.planar("rgb"), 1e-4);
        check_abs("features vs fixture", &out.features, &fx.planar("feat"), 1e-4);
        let bad_c = count_diff(&out.n_contrib, &cpu_out.n_contrib);
        assert!(bad_c * 1000 <= hw, "n_contrib differs at {bad_c} of {hw} pixels");

        for mode in [GradMode::Official, GradMode::Exact] {
            let pg = PixelGrads { rgb: &fx.w1, features: &fx.w2, alpha: Some(&ones), depth: Some(&ones) };
            let want = cpu::backward(&inp, &fx.settings, &cpu_out, &pg, mode).unwrap();
            let g = gpu.backward(&out, &pg, mode).unwrap();
            let tol = 1e-4;
            check_rel("grad means", &g.means, &want.means, tol);
            check_rel("grad opacities", &g.opacities, &want.opacities, tol);
            check_rel("grad sh", &g.sh, &want.sh, tol);
            check_rel("grad features", &g.features, &want.features, tol);
            check_rel("grad means2d_ndc", &g.means2d_ndc, &want.means2d_ndc, tol);
            match path {
                CovPath::Cov3d => check_rel("grad cov3d", &g.cov3d, &want.cov3d, tol),
                CovPath::ScaleRot => {
                    check_rel("grad scales", g.scales.as_ref().unwrap(), want.scales.as_ref().unwrap(), tol);
                    check_rel("grad quats", g.quats.as_ref().unwrap(), want.quats.as_ref().unwrap(), tol);
                }
            }
            if mode == GradMode::Official {
                check_rel("grad means vs fixture", &g.means, &fx.f("grad_means"), tol);
                check_rel("grad sh vs fixture", &g.sh, &fx.f("grad_sh"), tol);
            }
        }
    }
}

#[test]
fn gpu_matches_cpu_and_fixture_small() {
    run("small.safetensors");
}

#[test]
fn gpu_matches_cpu_and_fixture_medium() {
    run("medium.safetensors");
}

/// The candle op's packed path (`forward_packed` / `backward_packed`: one row per Gaussian, unpacked and
/// packed by kernels) against the per-field host path above: the forward is deterministic, so images and
/// radii must be identical; gradients (atomics) within 1e-4 × max.
#[test]
fn packed_path_matches_host_path() {
    let fx = Fixture::load("small.safetensors");
    let gpu = CudaRasterizer::new(0).expect("a CUDA device (this test needs a GPU)");
    let inp = fx.inputs(CovPath::Cov3d);
    let (n, k, nf) = (inp.len(), fx.sh_coeffs, fx.nf);
    let d = 10 + 3 * k + nf;
    let mut packed = Vec::with_capacity(n * d);
    for i in 0..n {
        packed.extend_from_slice(&fx.means[3 * i..3 * i + 3]);
        packed.extend_from_slice(&fx.cov3d[6 * i..6 * i + 6]);
        packed.push(fx.opacities[i]);
        packed.extend_from_slice(&fx.sh[3 * k * i..3 * k * (i + 1)]);
        packed.extend_from_slice(&fx.features[nf * i..nf * (i + 1)]);
    }
    let stream = gpu.stream().clone();
    let down = |s: &cudarc::driver::CudaSlice<f32>| -> Vec<f32> {
        let v = stream.clone_dtoh(s).unwrap();
        stream.synchronize().unwrap();
        v
    };
    let dev_packed = stream.clone_htod(&packed).unwrap();
    let (out, radii, state) = gpu.forward_packed(&dev_packed.slice(..), n, k, nf, fx.sh_degree, &fx.settings).unwrap();
    let out = down(&out);
    let host = gpu.forward(&inp, &fx.settings).unwrap();
    let hw = fx.settings.camera.width * fx.settings.camera.height;
    assert_eq!(out.len(), (5 + nf) * hw);
    assert!(out[..3 * hw] == host.rgb[..], "rgb");
    assert!(out[3 * hw..(3 + nf) * hw] == host.features[..], "features");
    assert!(out[(3 + nf) * hw..(4 + nf) * hw] == host.alpha[..], "alpha");
    assert!(out[(4 + nf) * hw..] == host.depth[..], "depth");
    assert_eq!(radii, host.radii);

    let quarter = vec![0.25f32; hw];
    let grad_out: Vec<f32> = [&fx.w1[..], &fx.w2[..], &quarter[..], &quarter[..]].concat();
    let dev_grad = stream.clone_htod(&grad_out).unwrap();
    for mode in [GradMode::Official, GradMode::Exact] {
        let g = down(&gpu.backward_packed(&state, &dev_grad.slice(..), mode).unwrap());
        assert_eq!(g.len(), n * d);
        let pg = PixelGrads { rgb: &fx.w1, features: &fx.w2, alpha: Some(&quarter), depth: Some(&quarter) };
        let want = gpu.backward(&host, &pg, mode).unwrap();
        let col = |c0: usize, cw: usize| -> Vec<f32> { (0..n).flat_map(|i| g[i * d + c0..i * d + c0 + cw].to_vec()).collect() };
        check_rel("packed grad means", &col(0, 3), &want.means, 1e-4);
        check_rel("packed grad cov3d", &col(3, 6), &want.cov3d, 1e-4);
        check_rel("packed grad opacities", &col(9, 1), &want.opacities, 1e-4);
        check_rel("packed grad sh", &col(10, 3 * k), &want.sh, 1e-4);
        check_rel("packed grad features", &col(10 + 3 * k, nf), &want.features, 1e-4);
    }
}
