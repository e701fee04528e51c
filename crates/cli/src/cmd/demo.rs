//! `mvsplat360 demo`: the bundled scene rendered with the shipped model — a 360° orbit video, its frames,
//! the Gaussians and the views it was made from — with no flag needed.

use std::path::{Path, PathBuf};

use anyhow::Context;
use mvsplat360_pipeline::model::ModelArgs;
use mvsplat360_pipeline::render::{RefineSettings, RenderRequest};
use mvsplat360_pipeline::views::{ContextSpec, TargetSpec};

#[derive(clap::Args)]
pub struct Args {
    /// Output folder (created; a previous demo there is replaced).
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    /// Frames of the 360° orbit.
    #[arg(long, default_value_t = 48)]
    pub frames: usize,
    /// Context views picked from the bundled scene by farthest-point sampling.
    #[arg(long, default_value_t = 5)]
    pub num_context: usize,
    /// Where the model runs: `auto` (GPU 0 when this binary has CUDA and a GPU is present, else the CPU),
    /// `cpu`, `cuda` (GPU 0) or `cuda:N`. CUDA needs a binary built with `--features cuda` (see docs/gpu.md).
    #[arg(long, default_value = "auto")]
    pub device: mvsplat360_pipeline::compute::DeviceSpec,
    /// Precision of the encoder: `f32` (default) or `bf16` (CPU only: weights packed in bf16, bf16 products
    /// with f32 sums where the CPU has AVX512-BF16; recorded in run.json as `encoder_dtype`).
    #[arg(long, default_value = "f32", value_parser = mvsplat360_pipeline::compute::parse_encoder_dtype)]
    pub encoder_dtype: candle_core::DType,
}

/// The bundled scene (`assets/woodbox`): relative to the working directory, then to this binary's source tree.
pub fn bundled_scene() -> Option<PathBuf> {
    let rel = Path::new("assets/woodbox");
    let built = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/woodbox");
    [rel.to_path_buf(), built].into_iter().find(|p| p.join("transforms.json").is_file())
}

pub fn run(a: Args, quiet: bool) -> anyhow::Result<()> {
    let scene = bundled_scene().context("the bundled scene assets/woodbox is missing; run the demo from a clone of the repository")?;
    let model = mvsplat360_pipeline::model::default_model_dir()
        .context("the shipped model assets/models/default is missing; run the demo from a clone of the repository")?;
    let req = RenderRequest {
        scene: scene.clone(),
        scene_key: None,
        context: ContextSpec::Count(a.num_context),
        targets: TargetSpec::Orbit(a.frames),
        model: ModelArgs {
            ckpt: Some(model.clone()),
            compute: mvsplat360_pipeline::compute::Compute { device: a.device, encoder_dtype: a.encoder_dtype, ..Default::default() },
            ..ModelArgs::default()
        },
        size: None,
        // The shipped model's config.json says how scenes are scaled for it.
        scene_scale: None,
        refine: RefineSettings::default(),
        splat: true,
        metrics: false,
        fid_variant: Default::default(),
        weights_dir: None,
        video: true,
        fps: 12,
        out: a.out.clone(),
        resume: false,
    };
    super::progress::clean_partials_on_interrupt(&req.out);
    let bars = super::progress::Bars::new(quiet);
    let t = std::time::Instant::now();
    let s = mvsplat360_pipeline::render::run(&req, &bars).with_context(|| format!("rendering the bundled scene {}", scene.display()))?;
    eprintln!(
        "demo: {} frames{} from {} views of {} with {} in {:.1} s (peak {:.0} MiB) → {}/video.mp4, frames/, gaussians.ply",
        s.frames,
        if s.refined { " (refined)" } else { " (3DGS)" },
        a.num_context,
        scene.display(),
        model.display(),
        t.elapsed().as_secs_f64(),
        s.peak_mib.unwrap_or(f64::NAN),
        s.out.display()
    );
    Ok(())
}
