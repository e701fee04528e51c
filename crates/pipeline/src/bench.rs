//! `mvsplat360 bench scene`: the whole `render` pipeline (encoder → rasterizer → refiner → histogram matching)
//! on a synthetic scene with random weights, per-stage times and peak memory as one JSON line. Defaults are the
//! paper's DL3DV setting (5 views at 448×256, 56 frames, 25 guided steps, official configs).

use std::path::{Path, PathBuf};

use serde_json::json;

use crate::compute::{Compute, DeviceSpec};
use crate::error::{PipelineError, Result};
use crate::model::{self, DataConfig, ModelArgs, ModelConfig, RefinerModelConfig, MODEL_FORMAT};
use crate::render::{self, RefineSettings, RenderRequest, Silent};
use crate::views::{ContextSpec, TargetSpec};
use mvsplat360_nn::bench::median;

#[derive(Debug, Clone)]
pub struct SceneBenchOpts {
    pub device: DeviceSpec,
    /// The refiner's precision.
    pub dtype: candle_core::DType,
    /// The encoder's precision (`--encoder-dtype`).
    pub encoder_dtype: candle_core::DType,
    pub views: usize,
    pub height: u32,
    pub width: u32,
    pub frames: usize,
    pub steps: usize,
    /// Untimed runs first (a GPU's first run also loads kernels and creates handles).
    pub warmup: usize,
    pub runs: usize,
    pub threads: usize,
    /// The tiny model of the tests instead of the official configs.
    pub tiny: bool,
    /// 3DGS only (no refiner).
    pub no_refiner: bool,
}

/// Removes the scratch folder however the bench ends.
struct Scratch(PathBuf);
impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

pub fn run_scene_bench(o: &SceneBenchOpts) -> Result<serde_json::Value> {
    let bad = |msg: String| PipelineError::Flag { flag: "bench scene", msg };
    // Refuse an unusable device before writing the synthetic model; the handle also reads the GPU's peak.
    let compute = Compute { device: o.device, refiner_dtype: o.dtype, encoder_dtype: o.encoder_dtype };
    let device = compute.open()?;
    if o.views < 2 || o.frames == 0 || o.runs == 0 || o.height % 64 != 0 || o.width % 64 != 0 || o.height == 0 || o.width == 0 {
        return Err(bad(format!(
            "need --views ≥ 2, --frames ≥ 1, --runs ≥ 1 and --height/--width positive multiples of 64 (got {}, {}, {}, {}x{})",
            o.views, o.frames, o.runs, o.width, o.height
        )));
    }
    if o.steps == 0 && !o.no_refiner {
        return Err(bad("--steps must be at least 1 (or pass --no-refiner)".into()));
    }
    let dir = std::env::temp_dir().join(format!("mvsplat360-bench-scene-{}", std::process::id()));
    let _scratch = Scratch(dir.clone());
    let werr = |p: &Path, e: &dyn std::fmt::Display| PipelineError::Write { path: p.to_path_buf(), msg: e.to_string() };
    std::fs::create_dir_all(&dir).map_err(|e| werr(&dir, &e))?;

    let cfg = bench_model_config(o);
    let model_dir = dir.join("model");
    model::write_model_dir(&model_dir, &cfg, &model::random_state_dict(&cfg, 7)?)?;
    let scene = dir.join("scene");
    write_synthetic_scene(&scene, o.views, o.width, o.height)?;

    let pool = rayon::ThreadPoolBuilder::new().num_threads(o.threads).build().map_err(|e| bad(e.to_string()))?;
    let mut per_stage: Vec<(String, Vec<f64>)> = Vec::new();
    let mut totals = Vec::new();
    let mut gaussians = 0;
    gpu_peak_mib(&device, true);
    let profile = mvsplat360_nn::prof::is_enabled();
    if profile {
        mvsplat360_nn::prof::sync_with(&device);
    }
    for r in 0..o.warmup + o.runs {
        if r == o.warmup && profile {
            // Only the timed runs are profiled.
            let _ = mvsplat360_nn::prof::take_report();
        }
        let req = RenderRequest {
            scene: scene.clone(),
            scene_key: None,
            context: ContextSpec::Count(o.views),
            targets: TargetSpec::Orbit(o.frames),
            model: ModelArgs { ckpt: Some(model_dir.clone()), compute: compute.clone(), ..Default::default() },
            size: None,
            scene_scale: Some(crate::scale::SceneScale::Auto),
            refine: RefineSettings { steps: o.steps, ..RefineSettings::default() },
            splat: false,
            metrics: false,
            fid_variant: Default::default(),
            weights_dir: None,
            video: false,
            fps: 30,
            out: dir.join(format!("run{r}")),
            resume: false,
        };
        let t = std::time::Instant::now();
        let s = pool.install(|| render::run(&req, &Silent))?;
        let secs = t.elapsed().as_secs_f64();
        let _ = std::fs::remove_dir_all(dir.join(format!("run{r}")));
        if r < o.warmup {
            continue;
        }
        totals.push(secs);
        gaussians = s.gaussians;
        for (name, secs) in s.stage_seconds {
            match per_stage.iter_mut().find(|(n, _)| *n == name) {
                Some((_, v)) => v.push(secs),
                None => per_stage.push((name, vec![secs])),
            }
        }
    }
    let stages: serde_json::Map<String, serde_json::Value> = per_stage.into_iter().map(|(n, v)| (n, json!(median(v)))).collect();
    let mut out = json!({
        "bench": "scene",
        "device": o.device.to_string(),
        "refiner_dtype": o.dtype.as_str(),
        "encoder_dtype": o.encoder_dtype.as_str(),
        "cpu_bf16": compute.cpu_bf16_path().map(|b| b.name()),
        "model": if o.tiny { "tiny" } else { "official DL3DV configs" },
        "refiner": !o.no_refiner,
        "views": o.views,
        "height": o.height,
        "width": o.width,
        "frames": o.frames,
        "steps": if o.no_refiner { 0 } else { o.steps },
        "warmup": o.warmup,
        "runs": o.runs,
        "threads": o.threads,
        "gaussians": gaussians,
        "total_seconds": median(totals),
        "stage_seconds": stages,
        "peak_rss_mib": crate::setup::peak_rss_mib(),
        "gpu_peak_mib": gpu_peak_mib(&device, false),
    });
    if profile {
        // Totals over all runs (encoder stages and refiner modules), inclusive of nested scopes (see mvsplat360_nn::prof).
        let p: serde_json::Map<String, serde_json::Value> =
            mvsplat360_nn::prof::take_report().into_iter().map(|(n, ms, calls)| (n.to_string(), json!({ "ms": ms, "calls": calls }))).collect();
        out["profile"] = serde_json::Value::Object(p);
    }
    Ok(out)
}

/// High-water mark (MiB) of GPU memory in use since the last reset: the device's default memory pool, which
/// candle's buffers come from (stream-ordered allocation). None on the CPU or without memory pools.
#[cfg(feature = "cuda")]
fn gpu_peak_mib(device: &candle_core::Device, reset: bool) -> Option<f64> {
    use candle_core::cuda::cudarc::driver::sys;
    let candle_core::Device::Cuda(d) = device else { return None };
    let ctx = d.cuda_stream().context().clone();
    if !ctx.has_async_alloc() || ctx.bind_to_thread().is_err() {
        return None;
    }
    let attr = sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_USED_MEM_HIGH;
    let mut pool: sys::CUmemoryPool = std::ptr::null_mut();
    let mut v: u64 = 0;
    // SAFETY: plain driver queries on a live context; `v` outlives the calls and is the u64 the attribute holds.
    unsafe {
        if sys::cuDeviceGetDefaultMemPool(&mut pool, ctx.cu_device()) != sys::CUresult::CUDA_SUCCESS {
            return None;
        }
        if reset {
            sys::cuMemPoolSetAttribute(pool, attr, (&mut v as *mut u64).cast());
        }
        if sys::cuMemPoolGetAttribute(pool, attr, (&mut v as *mut u64).cast()) != sys::CUresult::CUDA_SUCCESS {
            return None;
        }
    }
    Some(v as f64 / (1024.0 * 1024.0))
}

#[cfg(not(feature = "cuda"))]
fn gpu_peak_mib(_: &candle_core::Device, _: bool) -> Option<f64> {
    None
}

fn bench_model_config(o: &SceneBenchOpts) -> ModelConfig {
    let mut cfg = if o.tiny {
        model::tiny_config(true)
    } else {
        let data = DataConfig::dl3dv();
        ModelConfig {
            format: MODEL_FORMAT.into(),
            encoder: model::experiment_encoder(&data),
            data,
            refiner: Some(RefinerModelConfig::default()),
            fit: None,
            blend: None,
            scene_scale: None,
        }
    };
    // The scene's photos are written at the model's input size, so no resize happens.
    cfg.data.image_width = o.width;
    cfg.data.image_height = o.height;
    cfg.encoder.num_views = o.views;
    if o.no_refiner {
        cfg.refiner = None;
    }
    cfg
}

/// `views` smooth colour images on a circle of cameras looking at the origin (transforms.json, OpenGL axes).
fn write_synthetic_scene(dir: &Path, views: usize, width: u32, height: u32) -> Result<()> {
    let werr = |p: &Path, e: &dyn std::fmt::Display| PipelineError::Write { path: p.to_path_buf(), msg: e.to_string() };
    let img_dir = dir.join("images");
    std::fs::create_dir_all(&img_dir).map_err(|e| werr(&img_dir, &e))?;
    let f = 0.9 * width as f64;
    let mut frames = Vec::new();
    for i in 0..views {
        let a = std::f64::consts::TAU * i as f64 / views as f64;
        let img = image::RgbImage::from_fn(width, height, |x, y| {
            let (u, v) = (x as f64 / width as f64, y as f64 / height as f64);
            let c = |k: f64| (127.5 + 127.0 * (k * u * 9.0 + (1.0 + k) * v * 7.0 + a * k).sin()) as u8;
            image::Rgb([c(1.0), c(2.0), c(3.0)])
        });
        let p = img_dir.join(format!("{i:03}.png"));
        img.save(&p).map_err(|e| werr(&p, &e))?;
        // Camera at radius 4 looking at the origin; OpenGL convention (x right, y up, looking down −z).
        let eye = [4.0 * a.sin(), 0.0, 4.0 * a.cos()];
        let z = [eye[0] / 4.0, 0.0, eye[2] / 4.0];
        let x = [z[2], 0.0, -z[0]];
        let c2w = [[x[0], 0.0, z[0], eye[0]], [x[1], 1.0, z[1], eye[1]], [x[2], 0.0, z[2], eye[2]], [0.0, 0.0, 0.0, 1.0]];
        frames.push(json!({ "file_path": format!("images/{i:03}.png"), "transform_matrix": c2w }));
    }
    let t = json!({
        "camera_model": "PINHOLE", "fl_x": f, "fl_y": f, "cx": width as f64 / 2.0, "cy": height as f64 / 2.0,
        "w": width, "h": height, "frames": frames,
    });
    let p = dir.join("transforms.json");
    std::fs::write(&p, t.to_string()).map_err(|e| werr(&p, &e))
}

/// `mvsplat360 bench fit`: the test-time fitting of a model folder's Gaussians on a scene's context views, the
/// encoder run once outside the timing.
#[derive(Debug, Clone)]
pub struct FitBenchOpts {
    /// Model folder (its `fit` settings are used; `steps` overrides the step count).
    pub model: PathBuf,
    pub scene: PathBuf,
    pub views: usize,
    pub steps: Option<usize>,
    pub warmup: usize,
    pub runs: usize,
    pub threads: usize,
    pub device: DeviceSpec,
}

pub fn run_fit_bench(o: &FitBenchOpts) -> Result<serde_json::Value> {
    let bad = |msg: String| PipelineError::Flag { flag: "bench fit", msg };
    if o.runs == 0 || o.views < 2 || o.steps == Some(0) {
        let steps = o.steps.map_or("the model's".to_string(), |s| s.to_string());
        return Err(bad(format!("need --runs ≥ 1, --views ≥ 2 and --steps ≥ 1 (got {}, {}, {steps})", o.runs, o.views)));
    }
    let req = RenderRequest {
        scene: o.scene.clone(),
        scene_key: None,
        context: ContextSpec::Count(o.views),
        targets: TargetSpec::Orbit(1),
        model: ModelArgs { ckpt: Some(o.model.clone()), compute: Compute { device: o.device, ..Compute::default() }, fit_steps: o.steps, ..Default::default() },
        size: None,
        scene_scale: Some(crate::scale::SceneScale::Auto),
        refine: RefineSettings::default(),
        splat: false,
        metrics: false,
        fid_variant: Default::default(),
        weights_dir: None,
        video: false,
        fps: 30,
        out: std::env::temp_dir().join("mvsplat360-bench-fit-unused"),
        resume: false,
    };
    let pool = rayon::ThreadPoolBuilder::new().num_threads(o.threads).build().map_err(|e| bad(e.to_string()))?;
    pool.install(|| {
        let p = render::prepare(&req, &Silent)?;
        if p.spec.fit.steps == 0 {
            return Err(bad(format!("{} has no `fit` in its config.json; pass --steps N", o.model.display())));
        }
        let g = render::encode(&p, &Silent)?;
        let gaussians = g.means.dim(0).map_err(crate::error::compute("bench fit"))?;
        let mut secs = Vec::new();
        let mut losses = [f64::NAN; 2];
        for r in 0..o.warmup + o.runs {
            let t = std::time::Instant::now();
            let (_, l) = render::fit_to_context(&p, g.clone(), &Silent)?;
            if r >= o.warmup {
                secs.push(t.elapsed().as_secs_f64());
            }
            losses = l.unwrap_or(losses);
        }
        let steps = p.spec.fit.steps;
        let fastest = secs.iter().copied().fold(f64::INFINITY, f64::min);
        let m = median(secs);
        Ok(json!({
            "bench": "fit",
            "device": o.device.to_string(),
            "model": o.model.display().to_string(),
            "scene": o.scene.display().to_string(),
            "views": o.views,
            "width": p.context_images[0].width,
            "height": p.context_images[0].height,
            "gaussians": gaussians,
            "steps": steps,
            "warmup": o.warmup,
            "runs": o.runs,
            "threads": o.threads,
            "fit_seconds": m,
            "fit_seconds_fastest": fastest,
            "seconds_per_step": m / steps as f64,
            "loss_before": losses[0],
            "loss_after": losses[1],
            "peak_rss_mib": crate::setup::peak_rss_mib(),
        }))
    })
}
