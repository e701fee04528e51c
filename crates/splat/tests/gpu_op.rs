//! The candle op on GPU tensors (feature `cuda`): the CUDA kernels run on candle's stream and the images stay
//! on the GPU; images, radii and every gradient (through `loss.backward()`, both gradient modes) against the
//! same op on the CPU. Needs a GPU: `cargo test -p mvsplat360-splat --features cuda -- --include-ignored`.
//!
//! Also with zero feature channels (the test-time fit renders RGB only).
//!
//! Tolerances as tests/cuda_device.rs: images 1e-4 abs; gradients element-wise 3e-5·max|cpu| + 1e-4·|cpu|
//! (FMA contraction and atomicAdd order, see tests/cuda_emulated.rs); radii equal except where FMA moves a
//! radius across an integer (≤ 0.1 % of Gaussians).
#![cfg(feature = "cuda")]

use candle_core::{Device, Tensor, Var};
use mvsplat360_splat::cpu::GradMode;
use mvsplat360_splat::{render, sh, Gaussians, RenderOptions};
use mvsplat360_testkit::{get, load};

mod common;
use common::camera;

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_device(&Device::Cpu).unwrap().to_vec1::<f32>().unwrap()
}

/// Images, radii and gradients (means, covariances, opacities, SH, feature SH) of Σ W·image on `dev`; with
/// `features` false the Gaussians have zero feature channels (the feature image and gradient are then empty).
fn run(file: &str, dev: &Device, mode: GradMode, features: bool) -> (Vec<Vec<f32>>, Vec<u32>, Vec<Vec<f32>>) {
    let m = load(file);
    let cam = camera(&m);
    let n = get(&m, "means").dim(0).unwrap();
    let cov6 = get(&m, "cov3d").to_vec2::<f32>().unwrap();
    let full: Vec<f32> = cov6.iter().flat_map(|c| [c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5]]).collect();
    let fh = ((get(&m, "features") - 0.5).unwrap() / sh::C0 as f64).unwrap().unsqueeze(2).unwrap();
    let fh = if features { fh } else { fh.narrow(1, 0, 0).unwrap() };
    let var = |t: &Tensor| Var::from_tensor(&t.to_device(dev).unwrap()).unwrap();
    let vars = [
        var(get(&m, "means")),
        var(&Tensor::from_vec(full, (n, 3, 3), &Device::Cpu).unwrap()),
        var(get(&m, "opacities")),
        var(&get(&m, "sh").transpose(1, 2).unwrap().contiguous().unwrap()),
        var(&fh),
    ];
    let g = Gaussians {
        means: vars[0].as_tensor().clone(),
        covariances: vars[1].as_tensor().clone(),
        opacities: vars[2].as_tensor().clone(),
        harmonics: vars[3].as_tensor().clone(),
        feature_harmonics: vars[4].as_tensor().clone(),
    };
    let bg = get(&m, "background").to_vec1::<f32>().unwrap();
    let opts = RenderOptions { background: [bg[0], bg[1], bg[2]], grad_mode: mode, ..Default::default() };
    let out = render(&g, &cam, &opts).unwrap();
    for t in [&out.rgb, &out.features, &out.alpha, &out.depth] {
        assert!(t.device().same_device(dev), "{file}: an image left the device");
    }
    let w = |name: &str| get(&m, name).permute((2, 0, 1)).unwrap().to_device(dev).unwrap();
    let mut loss =
        ((&out.rgb * &w("W1")).unwrap().sum_all().unwrap() + out.alpha.sum_all().unwrap() + (&out.depth * 0.01).unwrap().sum_all().unwrap()).unwrap();
    if features {
        loss = (loss + (&out.features * &w("W2")).unwrap().sum_all().unwrap()).unwrap();
    } else {
        assert_eq!(out.features.dim(0).unwrap(), 0, "{file}: a feature image from Gaussians without features");
    }
    let grads = loss.backward().unwrap();
    let images = [&out.rgb, &out.features, &out.alpha, &out.depth].iter().map(|t| values(t)).collect();
    let radii = out.radii.to_device(&Device::Cpu).unwrap().to_vec1::<u32>().unwrap();
    let gr = vars
        .iter()
        .enumerate()
        .map(|(i, v)| match grads.get(v.as_tensor()) {
            Some(g) => values(g),
            // An empty Var may get no gradient at all.
            None if i == 4 && !features => Vec::new(),
            None => panic!("{file}: a Var without gradient"),
        })
        .collect();
    (images, radii, gr)
}

fn compare(file: &str, features: bool) {
    let gpu = Device::new_cuda(0).expect("a CUDA GPU (this test is #[ignore]d without one)");
    for mode in [GradMode::Official, GradMode::Exact] {
        let (ci, cr, cg) = run(file, &Device::Cpu, mode, features);
        let (gi, gr, gg) = run(file, &gpu, mode, features);
        for (name, (a, b)) in ["rgb", "features", "alpha", "depth"].iter().zip(gi.iter().zip(&ci)) {
            assert_eq!(a.len(), b.len(), "{file} {mode:?} {name}: sizes differ");
            let d = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
            assert!(d <= 1e-4, "{file} {mode:?} {name}: max |gpu − cpu| {d:.2e} > 1e-4");
        }
        let moved = gr.iter().zip(&cr).filter(|(a, b)| a != b).count();
        assert!(moved * 1000 <= cr.len(), "{file} {mode:?}: {moved} of {} radii differ", cr.len());
        for (name, (a, b)) in ["means", "covariances", "opacities", "harmonics", "feature_harmonics"].iter().zip(gg.iter().zip(&cg)) {
            assert_eq!(a.len(), b.len(), "{file} {mode:?} grad {name}: sizes differ");
            let max = b.iter().fold(0f32, |m, x| m.max(x.abs()));
            let bad = a.iter().zip(b).filter(|(x, y)| (*x - *y).abs() > 3e-5 * max + 1e-4 * y.abs()).count();
            assert!(bad == 0, "{file} {mode:?} grad {name}: {bad} of {} entries out of tolerance", b.len());
        }
    }
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn gpu_op_matches_cpu_small() {
    compare("rasterizer/small.safetensors", true);
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn gpu_op_matches_cpu_medium() {
    compare("rasterizer/medium.safetensors", true);
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn gpu_op_matches_cpu_without_feature_channels() {
    compare("rasterizer/small.safetensors", false);
}
