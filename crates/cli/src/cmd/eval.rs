//! `mvsplat360 eval`: the official evaluation protocol over a `.torch` dataset and an evaluation index (images in
//! the official folders, per-scene and overall PSNR/SSIM/LPIPS/DISTS/FID, resumable), and
//! `mvsplat360 eval-index`: the official DL3DV index generator.

use std::path::PathBuf;

use anyhow::Context;
use mvsplat360_pipeline::eval::{EvalRequest, IndexOptions};

use super::views::{ModelFlags, RefineFlags};

#[derive(clap::Args)]
pub struct Args {
    /// Folder of `.torch` chunks (with the dataset's `index.json` mapping scenes to chunks), e.g.
    /// `datasets/dl3dv/test`.
    #[arg(long)]
    pub data: PathBuf,
    /// Evaluation index: `{scene: {"context": [...], "target": [...], "target_quantify"?: [...]} | null}`
    /// (e.g. the official `dl3dv_ctx_5v_tgt_56v.json`, its `_n150` variant, or `re10k_inter_14_target_views_match.json`).
    #[arg(long)]
    pub index: PathBuf,
    /// Output folder: ImagesGT/, ImagesGSplat/, ImagesRefined0/, ImagesPostprocessed0V2/, scenes/, metrics.json,
    /// metrics.md. A re-run with the same settings resumes: complete scenes are skipped.
    #[arg(long, default_value = "out/eval")]
    pub out: PathBuf,
    /// Only these scenes of the index (comma-separated keys).
    #[arg(long, value_delimiter = ',')]
    pub scenes: Option<Vec<String>>,
    /// At most this many scenes (index order; scenes missing from the data count).
    #[arg(long)]
    pub limit: Option<usize>,
    #[command(flatten)]
    pub model: ModelFlags,
    #[command(flatten)]
    pub refine: RefineFlags,
    /// Folder with the metric networks' weights (default: `$MVSPLAT360_METRIC_WEIGHTS`, then
    /// `~/.cache/mvsplat360/metric-weights`). Missing weights make that metric null, with a warning.
    #[arg(long)]
    pub weights_dir: Option<PathBuf>,
    /// Skip LPIPS.
    #[arg(long)]
    pub no_lpips: bool,
    /// Skip DISTS.
    #[arg(long)]
    pub no_dists: bool,
    /// Skip FID.
    #[arg(long)]
    pub no_fid: bool,
}

pub fn request(a: &Args) -> EvalRequest {
    EvalRequest {
        data: a.data.clone(),
        index: a.index.clone(),
        model: a.model.model_args(),
        size: a.model.size,
        scene_scale: a.model.scene_scale,
        refine: a.refine.settings(),
        weights_dir: a.weights_dir.clone(),
        lpips: !a.no_lpips,
        dists: !a.no_dists,
        fid: !a.no_fid,
        scenes: a.scenes.clone(),
        limit: a.limit,
        out: a.out.clone(),
    }
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<()> {
    let req = request(&args);
    super::progress::clean_partials_on_interrupt(&req.out);
    let bars = super::progress::Bars::new(quiet);
    let s = mvsplat360_pipeline::eval::run(&req, &bars).with_context(|| format!("evaluating {} on {}", args.index.display(), args.data.display()))?;
    if !quiet {
        let fmt = |v: Option<f64>, d: usize| v.map(|x| format!("{x:.d$}")).unwrap_or_else(|| "–".into());
        for (m, sc) in &s.methods {
            eprintln!(
                "{:<24} PSNR {} SSIM {} LPIPS {} DISTS {} FID {}",
                m.dir(),
                fmt(sc.psnr, 2),
                fmt(sc.ssim, 3),
                fmt(sc.lpips, 3),
                fmt(sc.dists, 3),
                fmt(sc.fid, 2)
            );
        }
        eprintln!(
            "{} scenes: rendered {}, resumed {}, re-scored {}, missing from the data {}, skipped {}; {} images per method; {:.1}s → {}",
            s.selected,
            s.rendered.len(),
            s.resumed.len(),
            s.rescored.len(),
            s.missing.len(),
            s.skipped_fov.len(),
            s.images,
            s.seconds,
            s.out.join(mvsplat360_pipeline::eval::METRICS_MD).display()
        );
    }
    Ok(())
}

#[derive(clap::Args)]
pub struct IndexArgs {
    /// Folder of `.torch` chunks (all `*.torch` files are read, in name order).
    #[arg(long)]
    pub data: PathBuf,
    /// Index file to write (the official name for the defaults is `dl3dv_ctx_5v_tgt_56v.json`).
    #[arg(long)]
    pub out: PathBuf,
    /// Context views per scene (farthest-point sampling of the camera centres).
    #[arg(long, default_value_t = 5)]
    pub num_context: usize,
    /// Target views per scene (equally spaced through the remaining views).
    #[arg(long, default_value_t = 56)]
    pub num_target: usize,
    /// Use only the first int(N · RATIO) views of each scene (official `--view_selection_ratio`).
    #[arg(long, default_value_t = 1.0, conflicts_with = "n")]
    pub view_selection_ratio: f64,
    /// The official `_nN` variant, e.g. `--n 150` = ratio 150/300 = 0.5 (the official name assumes 300 views).
    #[arg(long)]
    pub n: Option<u32>,
}

pub fn run_index(args: IndexArgs, quiet: bool) -> anyhow::Result<()> {
    let ratio = match args.n {
        Some(n) => n as f64 / 300.0,
        None => args.view_selection_ratio,
    };
    let opts = IndexOptions { num_context: args.num_context, num_target: args.num_target, view_selection_ratio: ratio };
    let bars = super::progress::Bars::new(quiet);
    let g = mvsplat360_pipeline::eval::generate_index(&args.data, &opts, &bars).with_context(|| format!("generating an index from {}", args.data.display()))?;
    for w in &g.warnings {
        eprintln!("warning: {w}");
    }
    mvsplat360_pipeline::eval::write_index(&args.out, &g)?;
    if !quiet {
        let nulls = g.entries.iter().filter(|(_, e)| e.is_none()).count();
        eprintln!(
            "wrote {} scenes ({} null) from {} chunks to {} (official name: {})",
            g.entries.len(),
            nulls,
            g.chunks,
            args.out.display(),
            opts.official_file_name()
        );
    }
    Ok(())
}
