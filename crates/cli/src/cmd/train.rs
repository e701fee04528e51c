//! `mvsplat360 train --config <toml>`: train the encoder (MSE + LPIPS on 3DGS renders), with checkpoints,
//! `log.jsonl`, `loss.png`, and the final model folder `<out>/model`.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use mvsplat360_train::{Monitor, RunOptions, StepRecord, TrainConfig, TrainError};

use super::names::{self, Freshness};

#[derive(clap::Args)]
pub struct Args {
    /// Training config (TOML): `[model]` size and encoder, `[data]` sources and views, `[train]` steps, lr,
    /// checkpoints; see `configs/train/README.md` (the shipped model's stages in `configs/train/recipe/`).
    #[arg(long, required_unless_present = "plot")]
    pub config: Option<PathBuf>,
    /// Instead of training, draw the loss curve of a `log.jsonl` (e.g. one brought back from another machine) as
    /// `loss.png` beside it (or `--plot-to FILE`), then exit.
    #[arg(long, value_name = "LOG.jsonl", conflicts_with_all = ["config", "export"])]
    pub plot: Option<PathBuf>,
    /// Where `--plot` writes the PNG.
    #[arg(long, value_name = "FILE", requires = "plot")]
    pub plot_to: Option<PathBuf>,
    /// Continue from the newest checkpoint in the config's `train.out` (the same config is required).
    #[arg(long)]
    pub resume: bool,
    /// With --resume: continue a checkpoint written with another --world-size; the global batch (world size ×
    /// `train.accumulate` examples per step) changes from then on. Without it such a resume is refused.
    #[arg(long, requires = "resume")]
    pub allow_world_change: bool,
    /// Override `train.out`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Folder with the metric networks' weights (LPIPS VGG; default: `$MVSPLAT360_METRIC_WEIGHTS`, then
    /// `~/.cache/mvsplat360/metric-weights`). Without them training runs without the LPIPS term and says so.
    #[arg(long)]
    pub weights_dir: Option<PathBuf>,
    /// Where the encoder, the refiner (`[model.refiner]`), the rasterizer and the losses run: cpu, cuda (GPU 0)
    /// or cuda:N. CUDA needs a build with `--features cuda` (docs/gpu.md); scene loading, view sampling, noise
    /// draws and checkpoints stay on the host.
    #[arg(long, default_value = "cpu")]
    pub device: mvsplat360_pipeline::compute::DeviceSpec,
    /// Data-parallel training over N processes (ranks), started by this command: one per GPU with `--device
    /// cuda` (GPUs N..N+world-1 for `cuda:N`), or sharing the cores on the CPU. Each rank draws its own
    /// micro-batches and gradients are summed every step, so a step equals one process with `accumulate` ×
    /// N micro-batches. Rank 0 writes the log, checkpoints and model folder. Under srun, torchrun or mpirun
    /// each started process is a rank already: leave this out (docs/cluster.md, "Training on a cluster").
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub world_size: u64,
    /// How the ranks sum gradients: `nccl` (GPUs; a build with `--features nccl`), `host` (a TCP ring through
    /// host memory, any device), or `auto` = nccl on GPUs, host on the CPU. Every rank must be given the same.
    #[arg(long, default_value = "auto")]
    pub dist_backend: mvsplat360_train::dist::Backend,
    /// Instead of training, write the checkpoint of this step (or `latest`) in `train.out` as a model folder
    /// (`config.json` + `model.safetensors`, for `render --ckpt`, `eval`, `view`), then exit. The config must
    /// be the one the run was started with.
    #[arg(long, value_name = "STEP|latest", value_parser = parse_step)]
    pub export: Option<Step>,
    /// Where `--export` writes the model folder (default: `<train.out>/model-<STEP>`).
    #[arg(long, value_name = "DIR", requires = "export")]
    pub export_to: Option<PathBuf>,
}

/// A checkpoint step for `--export`: `None` = the newest.
#[derive(Clone, Copy, Debug)]
pub struct Step(Option<u64>);

fn parse_step(s: &str) -> Result<Step, String> {
    mvsplat360_train::checkpoint::parse_step(s).map(Step)
}

struct Bar {
    pb: Option<ProgressBar>,
    stop: Arc<AtomicBool>,
    rank: usize,
}

impl Monitor for Bar {
    fn note(&self, msg: &str) {
        match &self.pb {
            Some(pb) => pb.println(msg),
            None if self.rank > 0 => eprintln!("rank {}: {msg}", self.rank),
            None => eprintln!("{msg}"),
        }
    }
    fn step(&self, rec: &StepRecord, total: u64) {
        if let Some(pb) = &self.pb {
            pb.set_length(total);
            pb.set_position(rec.step);
            let lp = rec.lpips.map(|l| format!(" lpips {l:.4}")).unwrap_or_default();
            let rf = rec.diffusion.zip(rec.alignment).map(|(d, a)| format!(" diffusion {d:.4} align {a:.5}")).unwrap_or_default();
            pb.set_message(format!("loss {:.5} mse {:.5}{lp}{rf} lr {:.2e} {:.2} steps/s", rec.loss, rec.mse, rec.lr, 1.0 / rec.seconds.max(1e-9)));
        }
    }
    fn should_stop(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }
}

pub fn run(a: Args, quiet: bool) -> anyhow::Result<()> {
    if let Some(log) = &a.plot {
        let records = mvsplat360_train::log::read(log)?;
        anyhow::ensure!(!records.is_empty(), "{}: no log records (a `log.jsonl` that `train` writes)", log.display());
        let to = a.plot_to.clone().unwrap_or_else(|| log.with_file_name("loss.png"));
        mvsplat360_train::log::plot(&records, &to)?;
        eprintln!("{} steps plotted → {}", records.len(), to.display());
        return Ok(());
    }
    let config = a.config.as_deref().context("--config is required (or --plot LOG)")?;
    let mut cfg = TrainConfig::from_file(config)?;
    if let Some(o) = a.out {
        cfg.train.out = o;
    }
    let rank = mvsplat360_train::dist::Rank::from_env()?;
    // A resume, an export and the ranks this command starts take the file the run started with (the cache's,
    // no request): the checkpoint records the config with the resolved paths.
    let fresh = if a.resume || a.export.is_some() || rank.is_some() { Freshness::CachedFirst } else { Freshness::Ask };
    resolve_inits(&mut cfg, fresh, quiet || rank.as_ref().is_some_and(|r| r.rank > 0))?;
    if let Some(Step(step)) = a.export {
        let (step, dir) = mvsplat360_train::export_checkpoint(&cfg, step, a.export_to.as_deref())
            .with_context(|| format!("exporting a checkpoint of {}", cfg.train.out.display()))?;
        eprintln!("checkpoint of step {step} written as the model folder {} (render it with --ckpt {})", dir.display(), dir.display());
        blender_note(&cfg, &dir);
        return Ok(());
    }
    if let Some(r) = rank.as_ref().filter(|r| r.place.launcher != mvsplat360_pipeline::launch::Launcher::Project && a.world_size > 1) {
        anyhow::bail!(
            "--world-size {} under {} with {} ranks: each rank would start its own; give the ranks to one of them (drop --world-size, or start one task)",
            a.world_size,
            r.place.launcher.name(),
            r.world
        );
    }
    let stop = Arc::new(AtomicBool::new(false));
    let s2 = stop.clone();
    if rank.is_some() {
        // A rank: its launcher forwards one SIGTERM per interrupt; finish the step, checkpoint, exit 130.
        let _ = ctrlc::set_handler(move || s2.store(true, Ordering::SeqCst));
    } else {
        let _ = ctrlc::set_handler(move || {
            if s2.swap(true, Ordering::SeqCst) {
                eprintln!("interrupted again: exiting without a checkpoint");
                std::process::exit(130);
            }
            eprintln!("interrupt: finishing this step and writing a checkpoint (Ctrl-C again to exit now)");
        });
    }
    let cuda = a.device != mvsplat360_pipeline::compute::DeviceSpec::Cpu;
    if rank.is_none() && a.world_size > 1 {
        return match mvsplat360_train::dist::launch_self(a.world_size as usize, a.dist_backend, cuda, &stop) {
            Ok(()) => Ok(()),
            Err(TrainError::Interrupted) => {
                eprintln!("stopped; continue with --resume");
                std::process::exit(130);
            }
            Err(e) => Err(e).with_context(|| format!("training with {} on {} ranks", config.display(), a.world_size)),
        };
    }
    let rank_no = rank.as_ref().map_or(0, |r| r.rank);
    let pb = (!quiet && rank_no == 0).then(|| {
        let pb = ProgressBar::new(cfg.train.steps);
        pb.set_style(
            ProgressStyle::with_template("train [{bar:30}] {pos}/{len} {elapsed_precise} ETA {eta} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        pb
    });
    let mon = Bar { pb, stop, rank: rank_no };
    let opts = RunOptions {
        resume: a.resume,
        weights_dir: a.weights_dir,
        device: a.device,
        dist: rank,
        allow_world_change: a.allow_world_change,
        dist_backend: a.dist_backend,
    };
    match mvsplat360_train::run(&cfg, &opts, &mon) {
        Ok(_) if rank_no > 0 => Ok(()),
        Ok(s) => {
            if let Some(pb) = &mon.pb {
                pb.finish();
            }
            eprintln!(
                "trained {} steps in {:.0} s{}; model folder {} (render it with --ckpt {})",
                s.steps,
                s.train_seconds,
                if s.lpips { "" } else { " (without LPIPS)" },
                s.model_dir.display(),
                s.model_dir.display()
            );
            blender_note(&cfg, &s.model_dir);
            Ok(())
        }
        Err(TrainError::Interrupted) => {
            if rank_no == 0 {
                eprintln!("stopped; continue with --resume");
            }
            std::process::exit(130);
        }
        Err(e) if rank_no > 0 => Err(e).with_context(|| format!("rank {rank_no}: training with {}", config.display())),
        Err(e) => Err(e).with_context(|| format!("training with {}", config.display())),
    }
}

/// Names in `train.init` and `train.refiner_init` → local paths (see [`super::names`]); `default` is the shipped
/// model folder for `init`.
pub fn resolve_inits(cfg: &mut TrainConfig, fresh: Freshness, quiet: bool) -> anyhow::Result<()> {
    names::resolve_opt(&mut cfg.train.init, "train.init", names::Default::ModelFolder, fresh, quiet)?;
    let refiner_default = names::Default::Refuse("refiner weights (the shipped model has no refiner)");
    names::resolve_opt(&mut cfg.train.refiner_init, "train.refiner_init", refiner_default, fresh, quiet)
}

/// A trained encoder changes what a learned blender sees, so the written folder has none; say so when the
/// run started from a folder that had one.
fn blender_note(cfg: &TrainConfig, dir: &std::path::Path) {
    let had = cfg.train.init.as_ref().and_then(|i| mvsplat360_pipeline::model::read_model_dir(i).ok()).is_some_and(|m| m.blend.is_some());
    if had {
        eprintln!(
            "note: {} has no learned blender (its init had one, trained on the old encoder's renders); train one with `mvsplat360 train-blend --model {} --train … --out …`",
            dir.display(),
            dir.display()
        );
    }
}
