//! `mvsplat360 export`: predict Gaussians for a scene with the encoder and write them as `.ply` (and `.splat`).

use std::path::PathBuf;

use anyhow::Context;
use mvsplat360_pipeline::model::{ModelArgs, RefinerArg};
use mvsplat360_pipeline::preprocess::InputSize;
use mvsplat360_pipeline::render::{RefineSettings, RenderRequest};
use mvsplat360_pipeline::views::TargetSpec;

use super::views::ContextArgs;

#[derive(clap::Args)]
pub struct Args {
    /// Weights: the official Lightning `.ckpt`, a model folder, or a safetensors/`.pth` file with `encoder.*`
    /// keys (DL3DV config); a path or a name (`dl3dv`, `default`, `hf:OWNER/REPO[/FILE][@REV]`, a Hub URL; see
    /// `mvsplat360 weights list`; an existing path wins). Default: `assets/models/default/`.
    #[arg(long, value_name = "PATH|NAME")]
    ckpt: Option<PathBuf>,
    /// Scene: a transforms.json (or its folder), a COLMAP folder, or a `.torch` chunk.
    scene: PathBuf,
    /// Output `.ply` (standard 3DGS layout).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    views: ContextArgs,
    /// Also write an antimatter15 `.splat` file.
    #[arg(long)]
    splat: Option<PathBuf>,
    /// Model input size WIDTHxHEIGHT (photos are scaled to cover it and centre-cropped) or `native`.
    /// Default: the model's training size (448x256 for DL3DV).
    #[arg(long)]
    size: Option<InputSize>,
    /// Scene units → model units: `none` (the official protocol), `auto` (median camera distance to the
    /// looked-at point becomes 10) or a factor. Default: `auto` for scenes posed by VGGT (its normalised units),
    /// else the model folder's `scene_scale` (the shipped model: `auto`), else `none`. See docs/cameras.md.
    #[arg(long)]
    scene_scale: Option<mvsplat360_pipeline::scale::SceneScale>,
    /// Data conventions for weights without a config (`dl3dv` or `re10k`).
    #[arg(long)]
    experiment: Option<String>,
    /// Steps of test-time fitting of the Gaussians to the context photos, as `render --fit-steps` (default: the
    /// model's own setting, so the file holds the Gaussians `render` rasterizes; 0 = the encoder's as they are).
    #[arg(long)]
    fit_steps: Option<usize>,
}

pub fn run(mut args: Args, quiet: bool) -> anyhow::Result<()> {
    super::names::resolve_opt(&mut args.ckpt, "--ckpt", super::names::Default::ModelFolder, super::names::Freshness::Ask, quiet)?;
    let mut model = ModelArgs { refiner: Some(RefinerArg::None), experiment: args.experiment.clone(), fit_steps: args.fit_steps, ..Default::default() };
    // A file is encoder weights alone; a folder (or none: the shipped model) is a whole model.
    match &args.ckpt {
        Some(p) if p.is_file() => model.encoder = Some(p.clone()),
        other => model.ckpt = other.clone(),
    }
    let req = RenderRequest {
        scene: args.scene.clone(),
        scene_key: args.views.scene_key.clone(),
        context: args.views.spec(),
        targets: TargetSpec::Views(vec![]),
        model,
        size: args.size,
        scene_scale: args.scene_scale,
        refine: RefineSettings::default(),
        splat: args.splat.is_some(),
        metrics: false,
        fid_variant: Default::default(),
        weights_dir: None,
        video: false,
        fps: 1,
        out: PathBuf::new(),
        resume: false,
    };
    let bars = super::progress::Bars::new(quiet);
    let p = mvsplat360_pipeline::render::prepare(&req, &bars).with_context(|| format!("reading scene {}", args.scene.display()))?;
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        mvsplat360_pipeline::output::check_writable(dir, "--out")?;
    }
    if !quiet {
        let names: Vec<&str> = p.choice.context.iter().map(|&i| p.scene.view_names[i].as_str()).collect();
        let im = &p.context_images[0];
        eprintln!("encoding {} context views at {}x{}: {}", names.len(), im.width, im.height, names.join(", "));
    }
    let t0 = std::time::Instant::now();
    let gaussians = mvsplat360_pipeline::render::encode(&p, &bars)?;
    let (gaussians, _) = mvsplat360_pipeline::render::fit_to_context(&p, gaussians, &bars)?;
    if !quiet {
        eprintln!("predicted {} Gaussians in {:.1} s", gaussians.means.dim(0)?, t0.elapsed().as_secs_f64());
    }
    use mvsplat360_splat::io::{write_ply, write_splat, ExportGaussians};
    let eg = ExportGaussians::from_gaussians(&gaussians).context("converting Gaussians to the file parameterisation")?;
    mvsplat360_pipeline::output::atomic_write(&args.out, |p| write_ply(p, &eg).map_err(|e| e.to_string()))?;
    if let Some(s) = &args.splat {
        mvsplat360_pipeline::output::atomic_write(s, |p| write_splat(p, &eg).map_err(|e| e.to_string()))?;
    }
    Ok(())
}
