//! `render` end to end on a CUDA GPU (feature `cuda`) against the same run on the CPU: the bundled scene, a
//! tiny random model with refiner. Needs a GPU: `cargo test -p mvsplat360-pipeline --features cuda --test gpu
//! -- --include-ignored`.
//!
//! Tolerance on the written 8-bit frames: every channel within 2 levels and the mean difference below 0.05
//! levels in f32 (the stages agree to ~1e-4 relative, so only values next to a rounding boundary flip one
//! level); in bf16 within 8 levels at the 99th percentile (the refiner's half-precision error, see
//! crates/refiner/tests/half.rs, on a random model whose output is near-flat).
#![cfg(feature = "cuda")]

use std::path::{Path, PathBuf};

use candle_core::DType;
use mvsplat360_pipeline::compute::{Compute, DeviceSpec};
use mvsplat360_pipeline::model::{self, ModelArgs};
use mvsplat360_pipeline::render::{self, RefineSettings, RenderRequest, Silent};
use mvsplat360_pipeline::views::{ContextSpec, TargetSpec};

fn render_on(model_dir: &Path, out: &Path, compute: Compute) {
    let req = RenderRequest {
        scene: PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../assets/woodbox"),
        scene_key: None,
        context: ContextSpec::Views(vec![0, 6, 12, 18]),
        targets: TargetSpec::Views(vec![1, 4, 7]),
        model: ModelArgs { ckpt: Some(model_dir.to_path_buf()), compute, ..Default::default() },
        size: None,
        scene_scale: Default::default(),
        refine: RefineSettings { steps: 2, window: 3, ..RefineSettings::default() },
        splat: false,
        metrics: false,
        weights_dir: None,
        video: false,
        fps: 8,
        out: out.to_path_buf(),
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
    render_on(&m, &gpu, Compute { device: DeviceSpec::Cuda(0), refiner_dtype: DType::F32 });
    let half = tmp.path().join("bf16");
    render_on(&m, &half, Compute { device: DeviceSpec::Cuda(0), refiner_dtype: DType::BF16 });
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
