//! `render`: posed photos → Gaussians → 3DGS renders (RGB + latent features) at every target → SVD refiner over
//! temporal windows → colour-histogram matching → frames, videos, cameras and a run record.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use mvsplat360_camera::Camera;
use mvsplat360_dataset::{ImageF32, Scene};
use mvsplat360_encoder::encoder_costvolume::{camera_tensors, to_splat_gaussians, EncoderCostVolume};
use mvsplat360_refiner::clip::ClipImageEmbedder;
use mvsplat360_refiner::refiner::{seeded_noise, Refiner, RefinerConfig};
use mvsplat360_refiner::sampling::SamplerConfig;
use mvsplat360_refiner::unet::VideoUNet;
use mvsplat360_refiner::vae::AutoencoderKL;
use mvsplat360_splat::camera::RasterCamera;
use mvsplat360_splat::op::{render as rasterize, RenderOptions};
use mvsplat360_splat::Gaussians;
use serde_json::json;

use crate::error::{check_finite, compute, flag, PipelineError, Result};
use crate::model::{ModelArgs, ModelSpec};
use crate::output::{self, write_json, write_png};
use crate::preprocess::{InputSize, Preprocess};
use crate::scale::SceneTransform;
use crate::views::{ContextSpec, TargetSpec, ViewChoice};

pub use crate::progress::{Progress, Silent};

/// Refiner sampling settings; defaults = the official DL3DV evaluation.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RefineSettings {
    pub steps: usize,
    pub guidance_min: f32,
    pub guidance_max: f32,
    pub seed: u64,
    /// Frames per temporal window (14).
    pub window: usize,
    /// All frames in one UNet call with temporal attention split into windows (the official video mode).
    pub video_mode: bool,
    /// Frames per VAE decode call (1 = the official setting).
    pub vae_chunk: usize,
}

impl Default for RefineSettings {
    fn default() -> Self {
        Self { steps: 25, guidance_min: 1.0, guidance_max: 2.5, seed: 0, window: 14, video_mode: false, vae_chunk: 1 }
    }
}

/// Everything `render` needs.
#[derive(Debug, Clone)]
pub struct RenderRequest {
    pub scene: PathBuf,
    pub scene_key: Option<String>,
    pub context: ContextSpec,
    pub targets: TargetSpec,
    pub model: ModelArgs,
    /// Model input size; None = the model's own.
    pub size: Option<InputSize>,
    /// Scene units → model units (`--scene-scale`); None = the model's own setting ([`crate::scale::resolve`]).
    pub scene_scale: Option<crate::scale::SceneScale>,
    pub refine: RefineSettings,
    /// Also write `gaussians.splat`.
    pub splat: bool,
    /// Score against `frames/gt` into `metrics.json` when the targets have photos: `frames/refined` (the
    /// paper's figures) with `frames/final` as a second row under `"final"`, or `frames/final` without a refiner.
    pub metrics: bool,
    /// Whose FID (default pytorch-fid, the paper's).
    pub fid_variant: mvsplat360_metrics::inception::FidVariant,
    /// Where the metric networks' weights are (`--weights-dir`; then the env var, then the default folder).
    pub weights_dir: Option<PathBuf>,
    /// Write `video.mp4` / `compare.mp4`.
    pub video: bool,
    pub fps: u32,
    pub out: PathBuf,
    /// Continue an interrupted render in `out`: its finished refined windows are kept (`render --resume`).
    pub resume: bool,
}

/// What a finished run reports.
#[derive(Debug, Clone)]
pub struct RenderSummary {
    pub out: PathBuf,
    pub frames: usize,
    pub gaussians: usize,
    pub refined: bool,
    pub stage_seconds: Vec<(String, f64)>,
    pub peak_mib: Option<f64>,
}

/// Everything checked and prepared before any heavy work.
pub struct Prepared {
    pub scene: Scene,
    pub spec: ModelSpec,
    pub choice: ViewChoice,
    pub pre: Preprocess,
    pub transform: SceneTransform,
    /// The scene scaling that applied and why ([`crate::scale::resolve`]).
    pub scene_scale: (crate::scale::SceneScale, &'static str),
    /// Preprocessed context photos and cameras (model space).
    pub context_images: Vec<ImageF32>,
    pub context_cameras: Vec<Camera>,
    /// Target cameras (model space, preprocessed size) and their preprocessed photos where they are views.
    pub target_cameras: Vec<Camera>,
    pub target_photos: Vec<Option<ImageF32>>,
    /// Where the model runs (opened once per run: tensors of two opened GPUs never mix).
    pub device: Device,
    /// The refiner's precision (`--dtype`).
    pub refiner_dtype: DType,
    /// The refiner's initial noise (`eval --noise`), shape [`Refiner::noise_shape`] of one window; None = drawn
    /// from `--seed`.
    pub noise: Option<Tensor>,
}

/// Open every image of the scene and check it against its camera (size, decodability), in parallel.
pub fn check_scene_images(scene: &Scene) -> Result<()> {
    use rayon::prelude::*;
    (0..scene.len()).into_par_iter().try_for_each(|i| scene.check_image(i).map_err(PipelineError::from))
}

/// Read the scene, resolve the model and the views, validate everything, preprocess context and targets.
pub fn prepare(req: &RenderRequest, progress: &dyn Progress) -> Result<Prepared> {
    let scene = mvsplat360_dataset::read_scene_with(&req.scene, req.scene_key.as_deref())?;
    progress.begin("checking images", 0);
    check_scene_images(&scene)?;
    progress.end();
    let spec = crate::model::resolve(&req.model)?;
    let choice = crate::views::choose(&scene, &req.context, &req.targets)?;
    if req.refine.window == 0 {
        return Err(flag("--window", "must be at least 1"));
    }
    if req.refine.vae_chunk == 0 {
        return Err(flag("--vae-chunk", "must be at least 1"));
    }
    if req.video && !(1..=crate::video::MAX_FPS).contains(&req.fps) {
        return Err(flag("--fps", format!("must be 1..={} (or --no-video), got {}", crate::video::MAX_FPS, req.fps)));
    }
    if spec.refiner.is_some() && req.refine.steps == 0 {
        return Err(flag("--steps", "must be at least 1 (or use --refiner none)"));
    }
    let size = req.size.unwrap_or(InputSize::Fixed { width: spec.data.image_width, height: spec.data.image_height });
    let pre = Preprocess { size, multiple: spec.encoder.image_multiple() as u32 };
    let used: Vec<usize> = choice.context.iter().copied().chain(choice.targets.iter().filter_map(|t| t.view)).collect();
    pre.check_sizes(&scene, &used)?;
    let mut context_images = Vec::new();
    let mut context_cameras_raw = Vec::new();
    for &i in &choice.context {
        let (img, cam) = pre.view(&scene.image(i)?, &scene.cameras[i])?;
        context_images.push(img);
        context_cameras_raw.push(cam);
    }
    let scene_scale = crate::scale::resolve(req.scene_scale, crate::scale::pose_engine_scale(&req.scene), spec.scene_scale);
    let (transform, warning) = crate::scale::scene_transform(scene_scale.0, &context_cameras_raw, spec.data.near, spec.data.far);
    if let Some(w) = warning {
        progress.note(&format!("warning: {w}"));
    }
    let context_cameras: Vec<Camera> = context_cameras_raw.iter().map(|c| transform.apply(c)).collect();
    let mut target_cameras = Vec::new();
    let mut target_photos = Vec::new();
    for t in &choice.targets {
        match t.view {
            Some(i) => {
                let (img, cam) = pre.view(&scene.image(i)?, &scene.cameras[i])?;
                target_cameras.push(transform.apply(&cam));
                target_photos.push(Some(img));
            }
            None => {
                // Generated cameras take the context's preprocessed intrinsics and size.
                let mut cam = pre.camera(&t.camera)?;
                let c0 = &context_cameras[0];
                (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) = (c0.fx, c0.fy, c0.cx, c0.cy, c0.width, c0.height);
                target_cameras.push(transform.apply(&cam));
                target_photos.push(None);
            }
        }
    }
    let device = req.model.compute.open()?;
    let refiner_dtype = req.model.compute.refiner_dtype;
    Ok(Prepared {
        scene,
        spec,
        choice,
        pre,
        transform,
        scene_scale,
        context_images,
        context_cameras,
        target_cameras,
        target_photos,
        device,
        refiner_dtype,
        noise: None,
    })
}

/// Run the encoder on the preprocessed context → one scene's Gaussians (model space).
pub fn encode(p: &Prepared, progress: &dyn Progress) -> Result<Gaussians> {
    let dev = p.device.clone();
    let v = p.context_images.len();
    let mut cfg = p.spec.encoder.clone();
    cfg.num_views = v;
    // "All views" configs (RE10K) store usize::MAX.
    cfg.costvolume_nearest_n_views = cfg.costvolume_nearest_n_views.min(v);
    cfg.multiview_trans_nearest_n_views = cfg.multiview_trans_nearest_n_views.min(v);
    let (w, h) = (p.context_images[0].width as usize, p.context_images[0].height as usize);
    let data: Vec<f32> = p.context_images.iter().flat_map(|im| im.data.iter().copied()).collect();
    let images = Tensor::from_vec(data, (1, v, 3, h, w), &dev).map_err(compute("encoder input"))?;
    let k_norm: Vec<[f64; 4]> = p.context_cameras.iter().map(|c| c.normalized_intrinsics()).collect();
    let c2w: Vec<[[f64; 4]; 4]> = p.context_cameras.iter().map(|c| c.c2w).collect();
    let (intr, extr) = camera_tensors(&k_norm, &c2w, &dev).map_err(compute("encoder input"))?;
    let near = Tensor::full(cfg.near, (1, v), &dev).map_err(compute("encoder input"))?;
    let far = Tensor::full(cfg.far, (1, v), &dev).map_err(compute("encoder input"))?;
    progress.note(&format!("loading encoder weights from {}", p.spec.encoder_file.display()));
    let encoder = EncoderCostVolume::load_as(&p.spec.encoder_file, &cfg, &dev, p.spec.encoder_dtype)
        .map_err(|e| PipelineError::Model { path: p.spec.encoder_file.clone(), msg: e.to_string() })?;
    progress.begin("encoder", 1);
    let g = encoder.forward(&images, &intr, &extr, &near, &far).map_err(compute("encoder"))?;
    progress.advance(1);
    progress.end();
    let g = to_splat_gaussians(&g).map_err(compute("encoder"))?.remove(0);
    check_finite("encoder (Gaussian means)", &g.means)?;
    check_finite("encoder (Gaussian opacities)", &g.opacities)?;
    Ok(g)
}

/// The model's test-time fitting of `g` to the context photos (see [`crate::fit`]), when its step count is not 0:
/// the fitted Gaussians and the fitting loss before and after.
pub fn fit_to_context(p: &Prepared, g: Gaussians, progress: &dyn Progress) -> Result<(Gaussians, Option<[f64; 2]>)> {
    if p.spec.fit.steps == 0 {
        return Ok((g, None));
    }
    let (near, far) = (p.spec.encoder.near, p.spec.encoder.far);
    let (f, losses) = crate::fit::fit(&g, &p.context_cameras, &p.context_images, near, far, &p.spec.fit, progress)?;
    Ok((f, Some(losses)))
}

/// Rasterize RGB and the latent features at every camera: (rgb (3,H,W), features (C,H,W)) per target.
pub fn rasterize_targets(g: &Gaussians, cams: &[Camera], near: f32, far: f32, progress: &dyn Progress) -> Result<Vec<(Tensor, Tensor)>> {
    progress.begin("rasterizing", cams.len() as u64);
    let mut out = Vec::with_capacity(cams.len());
    for c in cams {
        let r = rasterize(g, &RasterCamera::from_camera(c, near, far), &RenderOptions::default()).map_err(compute("rasterizer"))?;
        check_finite("rasterizer", &r.rgb)?;
        out.push((r.rgb, r.features));
        progress.advance(1);
    }
    progress.end();
    Ok(out)
}

/// One target's 3DGS stage output.
pub struct StageFrame {
    /// The rasterized Gaussians' RGB (3,H,W) and latent features (C,H,W).
    pub rgb: Tensor,
    pub features: Tensor,
    /// The learned blender's frame (3,H,W), when the model has one (see [`crate::blend`]).
    pub blended: Option<Tensor>,
}

impl StageFrame {
    /// What the stage hands on: the blended frame if there is one, else the render.
    pub fn output(&self) -> &Tensor {
        self.blended.as_ref().unwrap_or(&self.rgb)
    }
}

/// The 3DGS stage at every target: the rasterized Gaussians and, when the model has a learned blender, its blend
/// of them with the context photos.
pub fn frames_3dgs(p: &Prepared, g: &Gaussians, progress: &dyn Progress) -> Result<Vec<StageFrame>> {
    let (near, far) = (p.spec.encoder.near, p.spec.encoder.far);
    let Some((s, weights)) = &p.spec.blend else {
        let r = rasterize_targets(g, &p.target_cameras, near, far, progress)?;
        return Ok(r.into_iter().map(|(rgb, features)| StageFrame { rgb, features, blended: None }).collect());
    };
    let net = crate::blend::BlendNet::load(weights, s, &p.device)?;
    progress.begin("rasterizing and blending", p.target_cameras.len() as u64);
    let mut out = Vec::with_capacity(p.target_cameras.len());
    for c in &p.target_cameras {
        let (r, x) = blend_input(p, g, s, c)?;
        let (h, w) = (c.height as usize, c.width as usize);
        let y = net.blend_all(&[x], s, h, w, &p.device, 1)?.remove(0);
        check_finite("blend", &y)?;
        out.push(StageFrame { rgb: r.rgb, features: r.features, blended: Some(y) });
        progress.advance(1);
    }
    progress.end();
    Ok(out)
}

fn host_vec(t: &Tensor) -> Result<Vec<f32>> {
    t.flatten_all().and_then(|t| t.to_vec1()).map_err(compute("rasterizer"))
}

/// The rasterized Gaussians at `c` and the learned blender's input for them (`crate::blend::candidates`, layout
/// `s`): what `frames_3dgs` blends, and what `mvsplat360
/// train-blend` stores to train a blender on.
pub fn blend_input(p: &Prepared, g: &Gaussians, s: &crate::blend::BlendSettings, c: &Camera) -> Result<(mvsplat360_splat::RenderOutput, Vec<f32>)> {
    let (near, far) = (p.spec.encoder.near, p.spec.encoder.far);
    let r = rasterize(g, &RasterCamera::from_camera(c, near, far), &RenderOptions::default()).map_err(compute("rasterizer"))?;
    check_finite("rasterizer", &r.rgb)?;
    let rgb = host_vec(&r.rgb.clamp(0f32, 1f32).map_err(compute("rasterizer"))?)?;
    let photos: Vec<&[f32]> = p.context_images.iter().map(|im| im.data.as_slice()).collect();
    let x = crate::blend::candidates(s, c, &rgb, &host_vec(&r.alpha)?, &host_vec(&r.depth)?, &p.context_cameras, &photos, near as f64, far as f64);
    Ok((r, x))
}

/// Refiner modules loaded from one weights file.
struct RefinerModules {
    refiner: Refiner,
    vae: AutoencoderKL,
}

/// CLIP context token (1, 1, D) of the context views; the CLIP tower is dropped before the UNet is loaded.
fn clip_context(p: &Prepared, weights: &Path, progress: &dyn Progress) -> Result<Tensor> {
    let (cfg, _) = p.spec.refiner.as_ref().ok_or_else(|| flag("--refiner", "no refiner configured"))?;
    progress.note(&format!("loading CLIP image embedder from {}", weights.display()));
    let clip = ClipImageEmbedder::load_as(weights, None, &cfg.clip, &p.device, p.refiner_dtype)
        .map_err(|e| PipelineError::Model { path: weights.to_path_buf(), msg: e.to_string() })?;
    let v = p.context_images.len();
    let (w, h) = (p.context_images[0].width as usize, p.context_images[0].height as usize);
    let data: Vec<f32> = p.context_images.iter().flat_map(|im| im.data.iter().copied()).collect();
    let views = Tensor::from_vec(data, (1, v, 3, h, w), &p.device).map_err(compute("CLIP"))?;
    let ctx = clip.embed_mean(&views).map_err(compute("CLIP"))?;
    check_finite("CLIP", &ctx)?;
    Ok(ctx)
}

fn load_refiner(p: &Prepared, weights: &Path, s: &RefineSettings, num_splits: Option<usize>, progress: &dyn Progress) -> Result<RefinerModules> {
    let (cfg, _) = p.spec.refiner.as_ref().ok_or_else(|| flag("--refiner", "no refiner configured"))?;
    progress.note(&format!("loading the video UNet and VAE from {}", weights.display()));
    let merr = |e: &dyn std::fmt::Display| PipelineError::Model { path: weights.to_path_buf(), msg: e.to_string() };
    let unet = VideoUNet::load_as(weights, None, &cfg.unet, &p.device, p.refiner_dtype).map_err(|e| merr(&e))?;
    let vae = AutoencoderKL::load_as(weights, None, &cfg.vae, &p.device, p.refiner_dtype).map_err(|e| merr(&e))?;
    let sampler = SamplerConfig { num_steps: s.steps, min_scale: s.guidance_min, max_scale: s.guidance_max, num_splits, ..SamplerConfig::default() };
    let rc = RefinerConfig { sampler, scale_factor: cfg.vae.scale_factor as f32, decode_chunk: Some(s.vae_chunk), ..RefinerConfig::default() };
    Ok(RefinerModules { refiner: Refiner::new(unet, rc), vae })
}

/// The temporal windows over `n` frames: (start, real frames); every window is padded to `window` frames by
/// repeating its last frame, as the official code does.
pub fn windows(n: usize, window: usize) -> Vec<(usize, usize)> {
    (0..n).step_by(window.max(1)).map(|s| (s, window.min(n - s))).collect()
}

/// Refine all frames: windows of `s.window` frames (or one video-mode call), one initial noise reused;
/// `weights` is the refiner safetensors ([`crate::model::refiner_safetensors`]). Frames are (3,H,W) in [0, 1].
pub fn refine_frames(p: &Prepared, feats: &[Tensor], weights: &Path, s: &RefineSettings, progress: &dyn Progress) -> Result<Vec<Tensor>> {
    refine_frames_timed(p, feats, weights, s, progress, &mut Vec::new(), None)
}

/// [`refine_frames`], adding the time of its parts to `times` (`refine.clip`, `refine.load`, `refine.sampling`,
/// `refine.decode`). `saved_windows`: a folder where each window's frames are saved as it finishes and read back
/// instead of refined again (a resumed render; not in video mode).
pub fn refine_frames_timed(
    p: &Prepared,
    feats: &[Tensor],
    weights: &Path,
    s: &RefineSettings,
    progress: &dyn Progress,
    times: &mut Vec<(String, f64)>,
    saved_windows: Option<&Path>,
) -> Result<Vec<Tensor>> {
    let t = Instant::now();
    let ctx = clip_context(p, weights, progress)?;
    times.push(("refine.clip".into(), t.elapsed().as_secs_f64()));
    let t = Instant::now();
    let n = feats.len();
    // Video mode: one call over all frames (padded to whole attention groups), temporal attention split into
    // groups of `s.window` frames; convolutions, positional embedding and the guidance ramp span all frames.
    let (window, splits) = if s.video_mode { (n.div_ceil(s.window) * s.window, Some(n.div_ceil(s.window))) } else { (s.window, None) };
    let m = load_refiner(p, weights, s, splits, progress)?;
    times.push(("refine.load".into(), t.elapsed().as_secs_f64()));
    let (mut t_sample, mut t_decode) = (0.0, 0.0);
    let wins = windows(n, window);
    progress.begin("refining", (wins.len() * s.steps) as u64);
    let (c, h, w) = feats[0].dims3().map_err(compute("refiner"))?;
    let shape = m.refiner.noise_shape(&[1, window, c, h, w]);
    // One noise for every window (the official sampler draws it once per video).
    let noise = match &p.noise {
        Some(n) if n.dims() != shape.as_slice() => {
            return Err(PipelineError::Compute {
                stage: "refiner",
                msg: format!("the given initial noise is {:?}, this run needs {shape:?} (window × 4 × latent height × latent width)", n.dims()),
            })
        }
        Some(n) => n.to_dtype(DType::F32).and_then(|n| n.to_device(&p.device)).map_err(compute("refiner"))?,
        None => seeded_noise(s.seed, &shape, &p.device).map_err(compute("refiner"))?,
    };
    let mut out = Vec::with_capacity(n);
    let saved_windows = saved_windows.filter(|_| !s.video_mode);
    for (start, len) in wins {
        let saved = saved_windows.map(|d| crate::txn::window_file(d, start));
        if let Some(f) = saved.as_ref().filter(|f| f.exists()) {
            if let Some(frames) = load_window(f, len, &p.device) {
                out.extend(frames);
                progress.advance(s.steps as u64);
                continue;
            }
            progress.note(&format!("--resume: {} cannot be read; refining that window again", f.display()));
        }
        let mut fr: Vec<&Tensor> = feats[start..start + len].iter().collect();
        while fr.len() < window {
            fr.push(fr[fr.len() - 1]);
        }
        let x = Tensor::stack(&fr, 0).and_then(|t| t.unsqueeze(0)).map_err(compute("refiner"))?;
        let concat = m.refiner.concat_features(&x).map_err(compute("refiner"))?;
        let mut step = |_: &mvsplat360_refiner::sampling::StepRecord| progress.advance(1);
        let t = Instant::now();
        let lat = m.refiner.sample_latents(&ctx, &concat, &noise, window, Some(&mut step)).map_err(compute("refiner (UNet)"))?;
        check_finite("refiner (UNet)", &lat)?;
        t_sample += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let frames = m.refiner.decode(&m.vae, &lat, window).map_err(compute("refiner (VAE decode)"))?;
        check_finite("refiner (VAE decode)", &frames)?;
        t_decode += t.elapsed().as_secs_f64();
        let frames = frames.get(0).and_then(|f| f.narrow(0, 0, len)).map_err(compute("refiner"))?;
        if let Some(f) = &saved {
            // In the refiner's own dtype: read back, the frames are the same bits.
            let host = frames.to_device(&Device::Cpu).and_then(|t| t.contiguous()).map_err(compute("refiner"))?;
            crate::output::atomic_write(f, |tmp| {
                candle_core::safetensors::save(&std::collections::HashMap::from([("frames".to_string(), host)]), tmp).map_err(|e| e.to_string())
            })?;
        }
        for i in 0..len {
            out.push(frames.get(i).map_err(compute("refiner"))?);
        }
    }
    progress.end();
    times.push(("refine.sampling".into(), t_sample));
    times.push(("refine.decode".into(), t_decode));
    Ok(out)
}

/// A refined window saved by an interrupted render: its `len` frames, or None when unreadable (refined again).
fn load_window(path: &Path, len: usize, dev: &Device) -> Option<Vec<Tensor>> {
    let t = candle_core::safetensors::load(path, &Device::Cpu).ok()?.remove("frames")?;
    if t.dims().first() != Some(&len) || t.dims().len() != 4 {
        return None;
    }
    let t = t.to_device(dev).ok()?;
    (0..len).map(|i| t.get(i).ok()).collect()
}

/// Colour-histogram matching of each refined frame to its 3DGS render, on 8-bit images as the official
/// post-processing does (`match_histograms` on the saved PNGs).
pub fn histogram_match(refined: &ImageF32, gsplat: &ImageF32) -> Result<ImageF32> {
    let a = refined.to_rgb8();
    let b = gsplat.to_rgb8();
    let m = mvsplat360_refiner::histogram::match_histograms_u8(a.as_raw(), b.as_raw(), 3).map_err(compute("histogram matching"))?;
    let img = image::RgbImage::from_raw(refined.width, refined.height, m)
        .ok_or_else(|| PipelineError::Compute { stage: "histogram matching", msg: "size mismatch".into() })?;
    Ok(ImageF32::from_rgb8(&img))
}

fn frame_name(i: usize) -> String {
    format!("{i:04}.png")
}

fn camera_json(c: &Camera, role: &str, view: Option<usize>, scene: &Scene) -> serde_json::Value {
    json!({
        "role": role,
        "view": view,
        "name": view.map(|i| scene.view_names[i].clone()),
        "c2w": c.c2w,
        "K": [[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]],
        "width": c.width,
        "height": c.height,
    })
}

const FNV_START: u64 = 0xcbf29ce484222325;

/// FNV-1a of `b`, continuing from `h`.
fn fnv1a(mut h: u64, b: &[u8]) -> u64 {
    for &x in b {
        h ^= x as u64;
        h = h.wrapping_mul(0x100000001b3);
    }
    h
}

/// FNV-1a over the scene's camera data and image bytes' sizes and names (cheap, stable input fingerprint).
fn fingerprint(p: &Prepared) -> String {
    let mut h = FNV_START;
    let mut eat = |b: &[u8]| h = fnv1a(h, b);
    for (i, c) in p.scene.cameras.iter().enumerate() {
        eat(p.scene.view_names[i].as_bytes());
        for v in c.c2w.iter().flatten().chain([c.fx, c.fy, c.cx, c.cy].iter()) {
            eat(&v.to_le_bytes());
        }
    }
    for im in &p.context_images {
        for v in &im.data {
            eat(&v.to_le_bytes());
        }
    }
    format!("{h:016x}")
}

/// What this render is, for `--resume` ([`crate::txn::ResumeKey`]): input pixels and cameras, the model (its
/// flags, description and the weight files' size and time), the settings, the targets, device and dtype.
fn resume_key(req: &RenderRequest, p: &Prepared, refiner: Option<&Path>) -> crate::txn::ResumeKey {
    let hash = |v: &serde_json::Value| format!("{:016x}", fnv1a(FNV_START, v.to_string().as_bytes()));
    let file = |f: &Path| match std::fs::metadata(f) {
        Ok(m) => {
            json!([f.display().to_string(), m.len(), m.modified().ok().and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map(|d| d.as_nanos() as u64)])
        }
        Err(_) => json!(f.display().to_string()),
    };
    let weights: Vec<serde_json::Value> = [req.model.ckpt.as_deref(), req.model.encoder.as_deref(), refiner].into_iter().flatten().map(file).collect();
    let targets: Vec<serde_json::Value> = p.target_cameras.iter().map(|c| json!([c.c2w, c.fx, c.fy, c.cx, c.cy, c.width, c.height])).collect();
    let noise = p.noise.as_ref().and_then(|n| n.flatten_all().and_then(|t| t.to_dtype(DType::F32)).and_then(|t| t.to_vec1::<f32>()).ok());
    let settings = json!({
        "refine": req.refine,
        "fit": p.spec.fit,
        "blend": p.spec.blend.as_ref().map(|(b, _)| b),
        "preprocess": p.pre,
        "scene_scale": p.scene_scale.0,
        "noise": noise,
    });
    [
        ("input", fingerprint(p)),
        (
            "model",
            hash(&json!([
                format!("{:?}", req.model.ckpt),
                format!("{:?}", req.model.encoder),
                format!("{:?}", req.model.refiner),
                req.model.experiment,
                p.spec.description,
                weights
            ])),
        ),
        ("settings", hash(&settings)),
        ("targets", hash(&json!(targets))),
        ("device", req.model.compute.device.to_string()),
        ("dtype", p.refiner_dtype.as_str().to_string()),
    ]
    .into_iter()
    // Only when not f32, so that renders interrupted before the flag existed still resume.
    .chain((p.spec.encoder_dtype != DType::F32).then(|| ("encoder_dtype", p.spec.encoder_dtype.as_str().to_string())))
    .map(|(k, v)| (k.to_string(), v))
    .collect()
}

/// The whole run. Outputs go to `req.out` (see the crate docs for the layout).
pub fn run(req: &RenderRequest, progress: &dyn Progress) -> Result<RenderSummary> {
    run_staged(req, progress).map_err(|e| match e {
        PipelineError::Write { path, msg } if output::disk_full(&msg) => PipelineError::Write {
            msg: format!(
                "{msg}: the disk is full. This render was not installed and the previous render in {} is as it was; free some space (or choose another --out) and run it again, with --resume to keep the refined windows it finished",
                req.out.display()
            ),
            path,
        },
        e => e,
    })
}

fn run_staged(req: &RenderRequest, progress: &dyn Progress) -> Result<RenderSummary> {
    let t_all = Instant::now();
    let mut times: Vec<(String, f64)> = Vec::new();
    let t = Instant::now();
    let p = prepare(req, progress)?;
    if p.target_cameras.is_empty() {
        return Err(flag("--targets", "no target cameras to render"));
    }
    let out = &req.out;
    output::check_writable(out, "--out")?;
    output::remove_partials(out);
    let refine_file = match &p.spec.refiner {
        Some((_, w)) => Some(crate::model::refiner_safetensors(w, &|m| progress.note(m))?),
        None => None,
    };
    // Everything goes to the transaction's stage; the run in `out` is replaced only when this one is complete.
    let key = resume_key(req, &p, refine_file.as_deref());
    let txn = crate::txn::Txn::begin(out, &key, req.resume, !req.refine.video_mode, &|m| progress.note(m))?;
    if txn.resumed > 0 {
        progress.note(&format!("--resume: keeping the {} refined window(s) the interrupted render finished", txn.resumed));
    }
    let st = &txn.stage.clone();
    times.push(("prepare".into(), t.elapsed().as_secs_f64()));
    // Cameras first (in the stage, they describe what is being rendered).
    write_cameras(st, &p)?;

    let t = Instant::now();
    let g = encode(&p, progress)?;
    times.push(("encoder".into(), t.elapsed().as_secs_f64()));
    let t = Instant::now();
    let (g, fit_losses) = fit_to_context(&p, g, progress)?;
    if let Some([a, b]) = fit_losses {
        progress.note(&format!("fitting: loss {a:.5} → {b:.5} in {} steps", p.spec.fit.steps));
        times.push(("fit".into(), t.elapsed().as_secs_f64()));
    }
    let n_gauss = g.means.dim(0).map_err(compute("encoder"))?;
    let t = Instant::now();
    export_gaussians(st, &g, req.splat)?;
    times.push(("export".into(), t.elapsed().as_secs_f64()));

    let t = Instant::now();
    let renders = frames_3dgs(&p, &g, progress)?;
    drop(g);
    let (gsplat, stage, feats) = write_3dgs_frames(st, &p, renders)?;
    times.push(("rasterize".into(), t.elapsed().as_secs_f64()));
    let final_frames: Vec<ImageF32> = match &refine_file {
        Some(wf) => {
            let t = Instant::now();
            let mut parts = Vec::new();
            let refined = refine_frames_timed(&p, &feats, wf, &req.refine, progress, &mut parts, txn.windows.as_deref())?;
            times.push(("refine".into(), t.elapsed().as_secs_f64()));
            times.extend(parts);
            let t = Instant::now();
            let finals = write_refined_frames(st, &refined, &stage)?;
            times.push(("histogram".into(), t.elapsed().as_secs_f64()));
            finals
        }
        None => {
            let fd = st.join("frames/final");
            output::create_dir(&fd)?;
            for (i, img) in stage.iter().enumerate() {
                write_png(&fd.join(frame_name(i)), img)?;
            }
            stage
        }
    };
    drop(feats);

    if req.video {
        let t = Instant::now();
        write_videos(st, &p, &final_frames, &gsplat, req.fps, progress)?;
        times.push(("video".into(), t.elapsed().as_secs_f64()));
    }
    if req.metrics && p.target_photos.iter().all(|x| x.is_some()) {
        let t = Instant::now();
        let metrics = score_stage(st, req, refine_file.is_some(), progress)?;
        write_json(&st.join("metrics.json"), &metrics)?;
        times.push(("metrics".into(), t.elapsed().as_secs_f64()));
    }
    times.push(("total".into(), t_all.elapsed().as_secs_f64()));
    let peak = crate::setup::peak_rss_mib();
    let facts = RunFacts { frames: final_frames.len(), gaussians: n_gauss, refiner: refine_file.is_some(), fit_losses, peak };
    let run = run_json(req, &p, &facts, &times, &key, txn.hash_stage()?);
    write_json(&st.join("run.json"), &run)?;
    txn.commit()?;
    Ok(RenderSummary { out: out.clone(), frames: facts.frames, gaussians: n_gauss, refined: facts.refiner, stage_seconds: times, peak_mib: peak })
}

/// `cameras.json`: every context and target camera as the model sees it.
fn write_cameras(st: &Path, p: &Prepared) -> Result<()> {
    let mut cams = Vec::new();
    for (k, c) in p.context_cameras.iter().enumerate() {
        cams.push(camera_json(c, "context", Some(p.choice.context[k]), &p.scene));
    }
    for (k, c) in p.target_cameras.iter().enumerate() {
        cams.push(camera_json(c, "target", p.choice.targets[k].view, &p.scene));
    }
    write_json(
        &st.join("cameras.json"),
        &json!({
            "convention": "OpenCV camera-to-world (x right, y down, z forward), K in pixels",
            "scene_to_model": p.transform.to_json(),
            "cameras": cams,
        }),
    )
}

/// `gaussians.ply`, and `gaussians.splat` with `--splat`.
fn export_gaussians(st: &Path, g: &Gaussians, splat: bool) -> Result<()> {
    let eg = mvsplat360_splat::io::ExportGaussians::from_gaussians(g).map_err(compute("export"))?;
    output::atomic_write(&st.join("gaussians.ply"), |tmp| mvsplat360_splat::io::write_ply(tmp, &eg).map_err(|e| e.to_string()))?;
    if splat {
        output::atomic_write(&st.join("gaussians.splat"), |tmp| mvsplat360_splat::io::write_splat(tmp, &eg).map_err(|e| e.to_string()))?;
    }
    Ok(())
}

/// Writes the 3DGS renders (and the blender's frames, and the target photos) into the stage; returns the renders,
/// the stage's output (the blender's frames when it ran, else the renders) and the feature maps for the refiner.
fn write_3dgs_frames(st: &Path, p: &Prepared, renders: Vec<StageFrame>) -> Result<(Vec<ImageF32>, Vec<ImageF32>, Vec<Tensor>)> {
    let gs_dir = st.join("frames/gsplat");
    output::create_dir(&gs_dir)?;
    let mut gsplat = Vec::with_capacity(renders.len());
    let mut feats = Vec::with_capacity(renders.len());
    let mut stage = Vec::with_capacity(renders.len());
    let bd = st.join("frames/blended");
    if renders.iter().any(|r| r.blended.is_some()) {
        output::create_dir(&bd)?;
    }
    for (i, r) in renders.into_iter().enumerate() {
        let img = output::tensor_image(&r.rgb)?;
        write_png(&gs_dir.join(frame_name(i)), &img)?;
        if let Some(b) = &r.blended {
            let bimg = output::tensor_image(b)?;
            write_png(&bd.join(frame_name(i)), &bimg)?;
            stage.push(bimg);
        } else {
            stage.push(img.clone());
        }
        gsplat.push(img);
        feats.push(r.features);
    }
    if p.target_photos.iter().any(|x| x.is_some()) {
        let gt_dir = st.join("frames/gt");
        output::create_dir(&gt_dir)?;
        for (i, ph) in p.target_photos.iter().enumerate() {
            if let Some(img) = ph {
                write_png(&gt_dir.join(frame_name(i)), img)?;
            }
        }
    }
    Ok((gsplat, stage, feats))
}

/// `frames/refined` and `frames/final` (refined, histogram-matched to the stage's output); returns the finals.
fn write_refined_frames(st: &Path, refined: &[Tensor], stage: &[ImageF32]) -> Result<Vec<ImageF32>> {
    let (rd, fd) = (st.join("frames/refined"), st.join("frames/final"));
    output::create_dir(&rd)?;
    output::create_dir(&fd)?;
    let mut finals = Vec::with_capacity(refined.len());
    for (i, r) in refined.iter().enumerate() {
        let img = output::tensor_image(r)?;
        write_png(&rd.join(frame_name(i)), &img)?;
        let fin = histogram_match(&img, &stage[i])?;
        write_png(&fd.join(frame_name(i)), &fin)?;
        finals.push(fin);
    }
    Ok(finals)
}

/// `video.mp4` of the final frames and `compare.mp4` (3DGS | final | photo where there is one).
fn write_videos(st: &Path, p: &Prepared, final_frames: &[ImageF32], gsplat: &[ImageF32], fps: u32, progress: &dyn Progress) -> Result<()> {
    progress.begin("encoding video", 2);
    let frames: Vec<_> = final_frames.iter().map(output::video_frame).collect();
    output::atomic_write(&st.join("video.mp4"), |tmp| crate::video::write_mp4(tmp, &frames, fps).map_err(|e| e.to_string()))?;
    progress.advance(1);
    let compare: Vec<_> = (0..final_frames.len())
        .map(|i| {
            let a = output::video_frame(&gsplat[i]);
            let b = &frames[i];
            match p.target_photos[i].as_ref().map(output::video_frame) {
                Some(gt) => crate::video::side_by_side(&[&a, b, &gt]),
                None => crate::video::side_by_side(&[&a, b]),
            }
        })
        .collect();
    output::atomic_write(&st.join("compare.mp4"), |tmp| crate::video::write_mp4(tmp, &compare, fps).map_err(|e| e.to_string()))?;
    progress.advance(1);
    progress.end();
    Ok(())
}

/// The frames' scores against the target photos: the paper scores the refined frames; the histogram-matched
/// final frames are a second, labelled row.
fn score_stage(st: &Path, req: &RenderRequest, refined: bool, progress: &dyn Progress) -> Result<serde_json::Value> {
    progress.begin("scoring", 0);
    let opts = mvsplat360_metrics::score::ScoreOptions { weights_dir: req.weights_dir.clone(), fid_variant: req.fid_variant, ..Default::default() };
    let score = |frames: &str| -> Result<serde_json::Value> {
        let report = mvsplat360_metrics::score::score_dirs(&st.join("frames").join(frames), &st.join("frames/gt"), &opts).map_err(compute("metrics"))?;
        for w in &report.warnings {
            progress.note(&format!("metrics ({frames}): {w}"));
        }
        let mut v = serde_json::to_value(&report).map_err(compute("metrics"))?;
        v["frames"] = json!(frames);
        Ok(v)
    };
    let metrics = if refined {
        let mut v = score("refined")?;
        v["final"] = score("final")?;
        v
    } else {
        score("final")?
    };
    progress.end();
    Ok(metrics)
}

/// What a finished render reports beside its settings.
struct RunFacts {
    frames: usize,
    gaussians: usize,
    refiner: bool,
    fit_losses: Option<[f64; 2]>,
    peak: Option<f64>,
}

/// `run.json`: the settings, the stage times and every file of the run with its SHA-256 (`files`).
fn run_json(
    req: &RenderRequest,
    p: &Prepared,
    f: &RunFacts,
    times: &[(String, f64)],
    key: &crate::txn::ResumeKey,
    files: BTreeMap<String, String>,
) -> serde_json::Value {
    json!({
        "version": env!("CARGO_PKG_VERSION"),
        "scene": req.scene.display().to_string(),
        "scene_name": p.scene.name,
        "input_fingerprint": fingerprint(p),
        "model": p.spec.description,
        "experiment": p.spec.data.experiment,
        "settings": {
            "context": p.choice.context,
            "context_names": p.choice.context.iter().map(|&i| p.scene.view_names[i].clone()).collect::<Vec<_>>(),
            "targets": p.choice.targets.iter().map(|t| t.view).collect::<Vec<_>>(),
            "target_mode": format!("{:?}", req.targets),
            "preprocess": p.pre,
            "image_width": p.context_images[0].width,
            "image_height": p.context_images[0].height,
            "scene_scale": p.scene_scale.0,
            "scene_scale_source": p.scene_scale.1,
            "scene_to_model": p.transform.to_json(),
            "near": p.spec.encoder.near,
            "far": p.spec.encoder.far,
            "refiner": f.refiner,
            "refine": req.refine,
            "fit": p.spec.fit,
            "fit_loss": f.fit_losses,
            "blend": p.spec.blend.as_ref().map(|(b, _)| b),
            "device": req.model.compute.device.to_string(),
            "refiner_dtype": p.refiner_dtype.as_str(),
            "encoder_dtype": p.spec.encoder_dtype.as_str(),
            "cpu_bf16": req.model.compute.cpu_bf16_path().map(|b| b.name()),
            "fps": req.fps,
        },
        "frames": f.frames,
        "gaussians": f.gaussians,
        "stage_seconds": times.iter().map(|(k, v)| (k.clone(), json!(v))).collect::<serde_json::Map<_, _>>(),
        "peak_mib": f.peak,
        "resume_key": key,
        // Every file of this run with its SHA-256: a folder holding files of two runs would show it.
        "files": files,
    })
}
