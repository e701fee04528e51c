//! `render` end to end on a CUDA GPU (feature `cuda`) against the same run on the CPU: the bundled scene, a
//! tiny random model with refiner. Needs a GPU: `cargo test -p mvsplat360-pipeline --features cuda --test gpu
//! -- --include-ignored`.
//!
//! Tolerance on the written 8-bit frames: every channel within 2 levels and the mean difference below 0.05
//! levels in f32 (the stages agree to ~1e-4 relative, so only values next to a rounding boundary flip one
//! level); in bf16 within 8 levels at the 99th percentile (the refiner's half-precision error, see
//! crates/refiner/tests/half.rs, on a random model whose output is near-flat).
//!
//! The test-time fit of the shipped model (`fit_on_gpu_matches_cpu`): Adam steps every Gaussian at the full rate
//! whatever its gradient's size, so float-order differences (and on the GPU the atomicAdd order, which differs from
//! run to run) let barely visible Gaussians walk apart. The GPU fit must land where the CPU fit does by what the
//! fit is for — its loss within 2 %, the targets' PSNR against their photos within 0.1 dB — and each frame must be
//! closer to the CPU's fitted frame than the unfitted frame is, by 3 dB. Measured on an H200 (2026-11-27) with the
//! constant-rate recipe: loss 0.011247 vs 0.011230, PSNR 17.32 vs 17.35 (unfitted 16.49), frames 27.8–36.9 dB
//! from the CPU's and 28.6–39.0 dB from a second GPU run, where the unfitted ones are 19.9–25.4 dB (a first bound
//! of 30 dB, taken from 29 against 30 CPU steps, was too tight); with the cosine-decayed one shipped since: loss
//! 0.012227 vs 0.012211, PSNR 17.20 vs 17.12, frames 28.3–39.8 dB from the CPU's, 32.6–45.0 dB between GPU runs.
//!
//! The shipped model's blender (`blend_on_gpu_matches_cpu`): the same inputs through its CNN on both devices,
//! every output within 1e-4 (f32 convolutions summed in another order; outputs are colours of order 1).
#![cfg(feature = "cuda")]

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use mvsplat360_pipeline::blend::BlendNet;
use mvsplat360_pipeline::compute::{Compute, DeviceSpec};
use mvsplat360_pipeline::model::{self, ModelArgs};
use mvsplat360_pipeline::render::{self, RefineSettings, RenderRequest, Silent};
use mvsplat360_pipeline::views::{ContextSpec, TargetSpec};

fn render_on(model_dir: &Path, out: &Path, compute: Compute) {
    render_views(model_dir, out, compute, vec![0, 6, 12, 18], vec![1, 4, 7], None, false);
}

fn render_views(model_dir: &Path, out: &Path, compute: Compute, context: Vec<usize>, targets: Vec<usize>, fit_steps: Option<usize>, metrics: bool) {
    let req = RenderRequest {
        scene: PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../assets/woodbox"),
        scene_key: None,
        context: ContextSpec::Views(context),
        targets: TargetSpec::Views(targets),
        model: ModelArgs { ckpt: Some(model_dir.to_path_buf()), compute, fit_steps, ..Default::default() },
        size: None,
        scene_scale: Some(mvsplat360_pipeline::scale::SceneScale::None),
        refine: RefineSettings { steps: 2, window: 3, ..RefineSettings::default() },
        splat: false,
        metrics,
        fid_variant: Default::default(),
        weights_dir: None,
        video: false,
        fps: 8,
        out: out.to_path_buf(),
        resume: false,
    };
    render::run(&req, &Silent).unwrap();
}

/// Per-channel absolute differences of two PNGs.
fn diffs(a: &Path, b: &Path) -> Vec<u8> {
    let (a, b) = (image::open(a).unwrap().to_rgb8(), image::open(b).unwrap().to_rgb8());
    a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| x.abs_diff(*y)).collect()
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn render_on_gpu_matches_cpu() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = model::tiny_config(true);
    let m = tmp.path().join("tiny");
    model::write_model_dir(&m, &cfg, &model::random_state_dict(&cfg, 3).unwrap()).unwrap();
    let cpu = tmp.path().join("cpu");
    render_on(&m, &cpu, Compute::default());
    let gpu = tmp.path().join("gpu");
    render_on(&m, &gpu, Compute { device: DeviceSpec::Cuda(0), refiner_dtype: DType::F32, ..Default::default() });
    let half = tmp.path().join("bf16");
    render_on(&m, &half, Compute { device: DeviceSpec::Cuda(0), refiner_dtype: DType::BF16, ..Default::default() });
    for dir in ["gsplat", "refined", "final"] {
        for i in 0..3 {
            let f = format!("frames/{dir}/{i:04}.png");
            let mut d = diffs(&gpu.join(&f), &cpu.join(&f));
            let mean = d.iter().map(|&x| x as f64).sum::<f64>() / d.len() as f64;
            d.sort_unstable();
            // Renders and refined frames agree everywhere. Histogram matching is a step function of each value's
            // rank, so a refined value that moves by 1e-6 across a quantile of the render can land on a
            // neighbouring quantile's colour — far away where the render's histogram has gaps (seen: 52 levels
            // on a few pixels of a random model's frame). There only all but 1% of pixels must agree (0.1% was
            // crossed on an H200 in 2026-11: 99.9th percentile 3 levels, mean 0.010, with refined frames within 2).
            let (q, what) = if dir == "final" { (d[d.len() * 99 / 100], "99th percentile") } else { (d[d.len() - 1], "max") };
            assert!(q <= 2 && mean < 0.05, "{f}: f32 GPU vs CPU {what} {q} levels, mean {mean:.3}");
            if dir == "final" {
                // bf16 moves refined values by a few levels (checked above), which histogram matching turns
                // into jumps between the colours of a random model's gappy histogram (seen on an H200:
                // 99th percentile 41 levels), so final frames are compared in f32 only.
                continue;
            }
            let mut d = diffs(&half.join(&f), &cpu.join(&f));
            d.sort_unstable();
            let p99 = d[d.len() * 99 / 100];
            assert!(p99 <= 8, "{f}: bf16 GPU vs f32 CPU, 99th percentile {p99} levels");
        }
    }
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// PSNR (dB) between two 8-bit PNGs.
fn psnr(a: &Path, b: &Path) -> f64 {
    let (a, b) = (image::open(a).unwrap().to_rgb8(), image::open(b).unwrap().to_rgb8());
    let mse = a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| (*x as f64 - *y as f64).powi(2)).sum::<f64>() / a.as_raw().len() as f64;
    10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn fit_on_gpu_matches_cpu() {
    let tmp = tempfile::tempdir().unwrap();
    let shipped = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../assets/models/default");
    let (context, targets) = (vec![0, 5, 10, 15, 20], vec![2, 7, 12, 17, 22]);
    let run = |name: &str, compute: Compute, steps: Option<usize>| {
        let out = tmp.path().join(name);
        render_views(&shipped, &out, compute, context.clone(), targets.clone(), steps, true);
        out
    };
    let cpu = run("cpu", Compute::default(), None);
    let gpu = run("gpu", Compute { device: DeviceSpec::Cuda(0), refiner_dtype: DType::F32, ..Default::default() }, None);
    let again = run("gpu-again", Compute { device: DeviceSpec::Cuda(0), refiner_dtype: DType::F32, ..Default::default() }, None);
    let unfitted = run("unfitted", Compute::default(), Some(0));
    let loss = |d: &Path| {
        let l = &json(&d.join("run.json"))["settings"]["fit_loss"];
        [l[0].as_f64().expect("a fit ran"), l[1].as_f64().unwrap()]
    };
    let mean_psnr = |d: &Path| json(&d.join("metrics.json"))["psnr"].as_f64().unwrap();
    let ([c0, c1], [g0, g1]) = (loss(&cpu), loss(&gpu));
    let (pc, pg, pu) = (mean_psnr(&cpu), mean_psnr(&gpu), mean_psnr(&unfitted));
    let frames: Vec<(f64, f64, f64)> = (0..targets.len())
        .map(|i| {
            let f = format!("frames/gsplat/{i:04}.png");
            (psnr(&gpu.join(&f), &cpu.join(&f)), psnr(&unfitted.join(&f), &cpu.join(&f)), psnr(&again.join(&f), &gpu.join(&f)))
        })
        .collect();
    let [_, a1] = loss(&again);
    eprintln!("fit loss CPU {c0:.6} -> {c1:.6}, GPU {g0:.6} -> {g1:.6} (again: {a1:.6}); target PSNR CPU {pc:.3}, GPU {pg:.3}, unfitted {pu:.3}");
    eprintln!("per frame PSNR (GPU vs CPU fitted, unfitted vs CPU fitted, GPU vs GPU again): {frames:.2?}");
    assert!((g0 - c0).abs() <= 1e-3 * c0, "loss before fitting: GPU {g0} vs CPU {c0}");
    assert!(g1 < 0.5 * g0 && c1 < 0.5 * c0, "the fit did not lower the loss: GPU {g0} -> {g1}, CPU {c0} -> {c1}");
    assert!((g1 - c1).abs() <= 0.02 * c1, "loss after fitting: GPU {g1} vs CPU {c1}");
    assert!((pg - pc).abs() <= 0.1, "target PSNR: GPU {pg:.3} vs CPU {pc:.3} dB");
    for (i, (g, u, _)) in frames.iter().enumerate() {
        assert!(*g >= u + 3.0, "frame {i}: GPU vs CPU fitted {g:.2} dB, unfitted vs fitted {u:.2} dB");
    }
}

#[test]
#[ignore = "needs a CUDA GPU: cargo test --features cuda -- --include-ignored"]
fn blend_on_gpu_matches_cpu() {
    let shipped = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../assets/models/default");
    let (s, weights) = model::read_model_dir(&shipped).unwrap().blend.expect("the shipped model has a blender");
    let gpu = Device::new_cuda(0).unwrap();
    let (on_cpu, on_gpu) = (BlendNet::load(&weights, &s, &Device::Cpu).unwrap(), BlendNet::load(&weights, &s, &gpu).unwrap());
    let x = Tensor::rand(0f32, 1f32, (3, s.channels(), 64, 128), &Device::Cpu).unwrap();
    let a = on_cpu.forward(&x).unwrap();
    let b = on_gpu.forward(&x.to_device(&gpu).unwrap()).unwrap().to_device(&Device::Cpu).unwrap();
    let d = (&a - &b).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
    let m = a.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
    eprintln!("blender GPU vs CPU: max |difference| {d:.3e} (outputs up to {m:.3})");
    assert!(m > 0.1 && d <= 1e-4, "blender GPU vs CPU: max |difference| {d:e}, outputs up to {m}");
}
