//! `mvsplat360 bench encoder`: forward time of the encoder with random weights (DL3DV configuration).

use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use serde_json::json;

use crate::backbone::{camera_distances, BackboneMultiview};
use crate::config::EncoderCostVolumeCfg;
use crate::weights::random_tensors;
use mvsplat360_nn::bench::median;

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("bench: {0}")]
    Candle(#[from] candle_core::Error),
    #[error("bench: {0}")]
    Setup(String),
}

pub use mvsplat360_nn::bench::peak_rss_mib;

/// Use `threads` worker threads (0 = all cores) for candle's CPU kernels and rayon. Call before any tensor work.
pub fn set_threads(threads: usize) -> Result<(), BenchError> {
    if threads > 0 {
        std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
        // An already-built global pool (second call in one process) is fine: keep it.
        let _ = rayon::ThreadPoolBuilder::new().num_threads(threads).build_global();
    }
    Ok(())
}

/// Run `f` on a pool of `threads` worker threads (0 = all cores), which candle's CPU kernels and rayon use.
fn on_threads<T: Send>(threads: usize, f: impl FnOnce() -> Result<T, BenchError> + Send) -> Result<T, BenchError> {
    let pool =
        rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|e| BenchError::Setup(format!("cannot build a {threads}-thread pool: {e}")))?;
    pool.install(f)
}

/// Synthetic context: smooth images in [0,1], cameras on an arc looking at the origin, normalised K.
pub fn synthetic_context(b: usize, v: usize, h: usize, w: usize, device: &Device) -> candle_core::Result<[Tensor; 5]> {
    let mut img = Vec::with_capacity(b * v * 3 * h * w);
    for bi in 0..b {
        for vi in 0..v {
            for c in 0..3 {
                for y in 0..h {
                    for x in 0..w {
                        let t = (x as f32 * 0.05 + y as f32 * 0.03 + (vi + bi) as f32 * 0.7 + c as f32).sin();
                        img.push(0.5 + 0.4 * t);
                    }
                }
            }
        }
    }
    let images = Tensor::from_vec(img, (b, v, 3, h, w), device)?;
    let mut ext = Vec::with_capacity(b * v * 16);
    for _ in 0..b {
        for vi in 0..v {
            let ang = -1.0f32 + 2.0 * vi as f32 / (v.max(2) - 1) as f32;
            let c = [2.0 * ang.sin(), 0.05 * vi as f32, -2.0 * ang.cos()];
            // Look at the origin: z = −c/|c|, x = y_world(0,1,0)... OpenCV: y down.
            let n = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
            let z = [-c[0] / n, -c[1] / n, -c[2] / n];
            let down = [0.0f32, 1.0, 0.0];
            let mut x = [down[1] * z[2] - down[2] * z[1], down[2] * z[0] - down[0] * z[2], down[0] * z[1] - down[1] * z[0]];
            let xn = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
            x = [x[0] / xn, x[1] / xn, x[2] / xn];
            let y = [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]];
            ext.extend_from_slice(&[x[0], y[0], z[0], c[0], x[1], y[1], z[1], c[1], x[2], y[2], z[2], c[2], 0.0, 0.0, 0.0, 1.0]);
        }
    }
    let extrinsics = Tensor::from_vec(ext, (b, v, 4, 4), device)?;
    let k = Tensor::new(&[[0.75f32, 0.0, 0.5], [0.0, 1.3, 0.5], [0.0, 0.0, 1.0]], device)?;
    let intrinsics = k.broadcast_as((b, v, 3, 3))?.contiguous()?;
    let near = Tensor::ones((b, v), DType::F32, device)?;
    let far = (Tensor::ones((b, v), DType::F32, device)? * 100.0)?;
    Ok([images, intrinsics, extrinsics, near, far])
}

/// The weights' precision: f32, or bf16 (packed products on the CPU, see [`crate::bf16`]).
fn check_dtype(dtype: DType) -> Result<(), BenchError> {
    match dtype {
        DType::F32 | DType::BF16 => Ok(()),
        d => Err(BenchError::Setup(format!("the encoder runs in f32 or bf16 on the CPU, not {d:?}"))),
    }
}

/// `dtype` and, for bf16, the path its products take on this CPU (as run.json records it).
fn dtype_json(dtype: DType) -> (String, Option<&'static str>) {
    (dtype.as_str().to_string(), (dtype == DType::BF16).then(|| mvsplat360_nn::bf16::path().name()))
}

/// Backbone only (CNN + transformer), for a breakdown of the encoder time.
pub fn run_backbone_bench(views: usize, height: usize, width: usize, threads: usize, runs: usize, dtype: DType) -> Result<serde_json::Value, BenchError> {
    check_dtype(dtype)?;
    on_threads(threads, || backbone_bench(views, height, width, runs, dtype))
}

fn backbone_bench(views: usize, height: usize, width: usize, runs: usize, dtype: DType) -> Result<serde_json::Value, BenchError> {
    let cfg = EncoderCostVolumeCfg { num_views: views, ..Default::default() };
    let dev = Device::Cpu;
    let build = |vb: VarBuilder| BackboneMultiview::new(vb.pp("encoder").pp("backbone"), cfg.d_feature, cfg.num_transformer_layers, cfg.ffn_dim_expansion);
    let weights = random_tensors(0, &dev, build)?;
    let mut model = build(VarBuilder::from_tensors(weights, DType::F32, &dev))?;
    if dtype == DType::BF16 {
        model.pack_bf16()?;
    }
    let [images, _, extrinsics, _, _] = synthetic_context(1, views, height, width, &dev)?;
    let mut times = Vec::new();
    for i in 0..runs.max(1) + 1 {
        let t0 = Instant::now();
        let (_, index) = camera_distances(&extrinsics)?;
        let n = cfg.multiview_trans_nearest_n_views;
        let nn: Vec<Vec<Vec<u32>>> = index.iter().map(|b| b.iter().map(|r| r[..n.min(r.len())].to_vec()).collect()).collect();
        let out = model.forward(&images, cfg.multiview_trans_attn_split, Some(&nn), false)?;
        let _ = out.trans_features.sum_all()?.to_scalar::<f32>()?;
        if i > 0 {
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
    }
    let (dt, path) = dtype_json(dtype);
    Ok(json!({"bench": "encoder_backbone", "views": views, "height": height, "width": width, "dtype": dt, "cpu_bf16": path,
        "threads": rayon::current_num_threads(), "forward_ms": median(times), "peak_mib": peak_rss_mib()}))
}

/// The full encoder (DL3DV configuration, `views` context views, random weights) in `dtype` (f32, or bf16: see
/// [`crate::bf16`]): median forward time over `runs` runs after one warm-up, and the process's peak RSS, on
/// `threads` worker threads (0 = all cores).
pub fn run_encoder_bench(views: usize, height: usize, width: usize, threads: usize, runs: usize, dtype: DType) -> Result<serde_json::Value, BenchError> {
    check_dtype(dtype)?;
    on_threads(threads, || encoder_bench(views, height, width, runs, dtype))
}

fn encoder_bench(views: usize, height: usize, width: usize, runs: usize, dtype: DType) -> Result<serde_json::Value, BenchError> {
    let cfg = EncoderCostVolumeCfg { num_views: views, ..Default::default() };
    let dev = Device::Cpu;
    let build = |vb: VarBuilder| crate::EncoderCostVolume::new(vb.pp("encoder"), &cfg);
    let weights = random_tensors(0, &dev, build)?;
    let mut model = build(VarBuilder::from_tensors(weights, DType::F32, &dev))?;
    if dtype == DType::BF16 {
        model.pack_bf16()?;
    }
    let [images, intrinsics, extrinsics, near, far] = synthetic_context(1, views, height, width, &dev)?;
    let mut times = Vec::new();
    for i in 0..runs.max(1) + 1 {
        if i == 1 {
            // The warm-up's stages are not part of the profile.
            let _ = mvsplat360_nn::prof::take_report();
        }
        let t0 = Instant::now();
        let g = model.forward(&images, &intrinsics, &extrinsics, &near, &far)?;
        let _ = g.means.sum_all()?.to_scalar::<f32>()?;
        if i > 0 {
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
    }
    let (dt, path) = dtype_json(dtype);
    let timed = times.len() as f64;
    let mut out = json!({"bench": "encoder", "views": views, "height": height, "width": width, "dtype": dt, "cpu_bf16": path,
        "threads": rayon::current_num_threads(), "forward_ms": median(times), "peak_mib": peak_rss_mib()});
    if mvsplat360_nn::prof::is_enabled() {
        // Mean ms per timed forward (MVSPLAT360_PROFILE=1); nested scopes are also inside their parents.
        let prof: serde_json::Map<String, serde_json::Value> =
            mvsplat360_nn::prof::take_report().into_iter().map(|(n, ms, calls)| (n.to_string(), json!({ "ms": ms / timed, "calls": calls }))).collect();
        out["profile"] = serde_json::Value::Object(prof);
    }
    Ok(out)
}
