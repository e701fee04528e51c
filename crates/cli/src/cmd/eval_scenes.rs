//! `mvsplat360 eval-scenes`: a model on posed scene folders by the held-out protocol of the shipped model's card
//! (context views by farthest-point sampling, every other view a target), against the nearest-context-photo
//! baseline; prints one table and optionally writes the per-scene rows as JSON.

use std::path::PathBuf;

use anyhow::Context;
use mvsplat360_pipeline::eval_scenes::{self, ScenesRequest};

use super::views::ModelFlags;

#[derive(clap::Args)]
pub struct Args {
    /// Scene folders (transforms.json, COLMAP or a `.torch` chunk with one scene), e.g. `data/heldout/*`
    /// (scripts/render-povray-sets --sets heldout).
    #[arg(required = true)]
    pub scenes: Vec<PathBuf>,
    /// Context views per scene, by farthest-point sampling from the first view; every other view is a target.
    #[arg(long, default_value_t = 5)]
    pub num_context: usize,
    #[command(flatten)]
    pub model: ModelFlags,
    /// Folder with the metric networks' weights (default: `$MVSPLAT360_METRIC_WEIGHTS`, then
    /// `~/.cache/mvsplat360/metric-weights`); without them LPIPS is left out with a warning.
    #[arg(long)]
    pub weights_dir: Option<PathBuf>,
    /// Also write the per-scene rows (scene, method, psnr, ssim, lpips, targets) to this JSON file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

pub fn run(mut a: Args, quiet: bool) -> anyhow::Result<()> {
    a.model.resolve_names(super::names::Freshness::Ask, quiet)?;
    let req = ScenesRequest {
        scenes: a.scenes.clone(),
        model: a.model.model_args(),
        num_context: a.num_context,
        scene_scale: a.model.scene_scale,
        weights_dir: a.weights_dir.clone(),
    };
    let bars = super::progress::Bars::new(quiet);
    let rows = eval_scenes::run(&req, &bars, &|w| eprintln!("warning: {w}")).context("evaluating the scenes")?;
    print!("{}", eval_scenes::markdown(&rows));
    if let Some(j) = &a.json {
        let text = serde_json::to_string_pretty(&rows)?;
        mvsplat360_dataset::atomic::write_bytes_synced(j, text.as_bytes()).with_context(|| format!("writing {}", j.display()))?;
    }
    Ok(())
}
