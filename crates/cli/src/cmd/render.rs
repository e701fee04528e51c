//! `mvsplat360 render`: posed photos in → Gaussians, 3DGS and refined frames, videos, cameras and a run record.

use std::path::PathBuf;

use anyhow::Context;
use mvsplat360_pipeline::model::{ModelArgs, RefinerArg};
use mvsplat360_pipeline::preprocess::InputSize;
use mvsplat360_pipeline::render::{RefineSettings, RenderRequest};
use mvsplat360_pipeline::views::TargetSpec;

use super::views::{view_list, ContextArgs, ViewList};

#[derive(clap::Args)]
pub struct Args {
    /// Scene: a folder with transforms.json, a transforms*.json file, a COLMAP folder (sparse/0 + images/),
    /// or a `.torch` chunk.
    pub scene: PathBuf,
    /// Output folder (created; a previous render there is replaced).
    #[arg(long, default_value = "out/render")]
    pub out: PathBuf,
    #[command(flatten)]
    pub views: ContextArgs,
    /// Render at these views' cameras and sizes (sorted), e.g. `--targets 1,2,5`; their photos go to
    /// `frames/gt/` preprocessed the same way, for pixel-wise comparison.
    #[arg(long, value_parser = view_list, conflicts_with_all = ["orbit", "path"])]
    pub targets: Option<ViewList>,
    /// A closed 360° orbit of this many frames around the context cameras (the default target, 56 frames).
    #[arg(long, conflicts_with = "path")]
    pub orbit: Option<usize>,
    /// A smoothed video along the scene's own camera path, this many frames.
    #[arg(long)]
    pub path: Option<usize>,
    /// Model: an official MVSplat360 Lightning `.ckpt` (encoder + refiner, DL3DV config) or a model folder
    /// (`config.json` + `model.safetensors`). Default: `assets/models/default/`.
    #[arg(long)]
    pub ckpt: Option<PathBuf>,
    /// Encoder weights alone (safetensors / `.ckpt` with `encoder.*` keys, DL3DV config); needs `--refiner`.
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// `none` for the 3DGS-only result, or a file with the refiner's weights (an official `.ckpt`, its
    /// safetensors copy, or Stability's `svd.safetensors`).
    #[arg(long)]
    pub refiner: Option<RefinerArg>,
    /// Data conventions for weights without a config (`dl3dv`: 448×256, `re10k`: 256×256, all-view cost volume).
    #[arg(long)]
    pub experiment: Option<String>,
    /// Model input size WIDTHxHEIGHT (photos are scaled to cover it and centre-cropped) or `native`.
    /// Default: the model's training size.
    #[arg(long)]
    pub size: Option<InputSize>,
    /// Scene units → model units: `none` (the official behaviour: the model expects content 1–100 units away),
    /// `auto` (median camera distance to the looked-at point becomes 10) or a factor. See docs/cameras.md.
    #[arg(long, default_value = "none")]
    pub scene_scale: mvsplat360_pipeline::scale::SceneScale,
    /// Diffusion sampling steps (EDM Euler).
    #[arg(long, default_value_t = 25)]
    pub steps: usize,
    /// Classifier-free guidance scale of a window's first frame (linear ramp to --guidance-max).
    #[arg(long, default_value_t = 1.0)]
    pub guidance_min: f32,
    /// Guidance scale of a window's last frame.
    #[arg(long, default_value_t = 2.5)]
    pub guidance_max: f32,
    /// Seed of the initial noise (drawn once, reused for every window).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Frames per refiner window (a short last window is padded by repeating its last frame).
    #[arg(long, default_value_t = 14)]
    pub window: usize,
    /// Refine all frames in one UNet call with temporal attention split into --window-sized groups (the
    /// official video mode; more memory).
    #[arg(long)]
    pub video_mode: bool,
    /// Frames per VAE decode call. 1 = the official setting; larger is faster but the temporal decoder then
    /// mixes neighbouring frames, which changes the output slightly.
    #[arg(long, default_value_t = 1)]
    pub vae_chunk: usize,
    /// Also write `gaussians.splat` (antimatter15 format).
    #[arg(long)]
    pub splat: bool,
    /// Skip `metrics.json` (written when every target is a scene view with a photo: PSNR, SSIM, and LPIPS,
    /// DISTS, FID when their weights are installed by `scripts/metric-weights/fetch`).
    #[arg(long)]
    pub no_metrics: bool,
    /// Folder with the metric networks' weights (default: `$MVSPLAT360_METRIC_WEIGHTS`, then
    /// `~/.cache/mvsplat360/metric-weights`).
    #[arg(long)]
    pub weights_dir: Option<PathBuf>,
    /// Skip `video.mp4` and `compare.mp4`.
    #[arg(long)]
    pub no_video: bool,
    /// Video frame rate.
    #[arg(long, default_value_t = 8)]
    pub fps: u32,
}

pub fn request(a: &Args) -> RenderRequest {
    let targets = if let Some(t) = &a.targets {
        TargetSpec::Views(t.0.clone())
    } else if let Some(m) = a.orbit {
        TargetSpec::Orbit(m)
    } else if let Some(m) = a.path {
        TargetSpec::Path(m)
    } else if a.views.index.is_some() {
        TargetSpec::Index
    } else {
        TargetSpec::Orbit(56)
    };
    RenderRequest {
        scene: a.scene.clone(),
        scene_key: a.views.scene_key.clone(),
        context: a.views.spec(),
        targets,
        model: ModelArgs { ckpt: a.ckpt.clone(), encoder: a.encoder.clone(), refiner: a.refiner.clone(), experiment: a.experiment.clone() },
        size: a.size,
        scene_scale: a.scene_scale,
        refine: RefineSettings {
            steps: a.steps,
            guidance_min: a.guidance_min,
            guidance_max: a.guidance_max,
            seed: a.seed,
            window: a.window,
            video_mode: a.video_mode,
            vae_chunk: a.vae_chunk,
        },
        splat: a.splat,
        metrics: !a.no_metrics,
        weights_dir: a.weights_dir.clone(),
        video: !a.no_video,
        fps: a.fps,
        out: a.out.clone(),
    }
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<()> {
    let req = request(&args);
    super::progress::clean_partials_on_interrupt(&req.out);
    let bars = super::progress::Bars::new(quiet);
    let s = mvsplat360_pipeline::render::run(&req, &bars).with_context(|| format!("rendering {}", args.scene.display()))?;
    if !quiet {
        let times: Vec<String> = s.stage_seconds.iter().map(|(k, v)| format!("{k} {v:.1}s")).collect();
        eprintln!(
            "wrote {} frames{} and {} Gaussians to {} ({}; peak {:.0} MiB)",
            s.frames,
            if s.refined { " (refined)" } else { " (3DGS only)" },
            s.gaussians,
            s.out.display(),
            times.join(", "),
            s.peak_mib.unwrap_or(f64::NAN)
        );
    }
    Ok(())
}
