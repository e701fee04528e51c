//! `mvsplat360 train --config <toml>`: train the encoder (MSE + LPIPS on 3DGS renders), with checkpoints,
//! `log.jsonl`, `loss.png`, and the final model folder `<out>/model`.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use mvsplat360_train::{Monitor, RunOptions, StepRecord, TrainConfig, TrainError};

#[derive(clap::Args)]
pub struct Args {
    /// Training config (TOML): `[model]` size and encoder, `[data]` sources and views, `[train]` steps, lr,
    /// checkpoints; see `configs/train/*.toml`.
    #[arg(long)]
    pub config: PathBuf,
    /// Continue from the newest checkpoint in the config's `train.out` (the same config is required).
    #[arg(long)]
    pub resume: bool,
    /// Override `train.out`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Folder with the metric networks' weights (LPIPS VGG; default: `$MVSPLAT360_METRIC_WEIGHTS`, then
    /// `~/.cache/mvsplat360/metric-weights`). Without them training runs without the LPIPS term and says so.
    #[arg(long)]
    pub weights_dir: Option<PathBuf>,
    /// Where the encoder, rasterizer and losses run: cpu, cuda (GPU 0) or cuda:N. CUDA needs a build with
    /// `--features cuda` (README, GPU); scene loading, view sampling and checkpoints stay on the host. The
    /// refiner (`[model.refiner]`) trains on the CPU only.
    #[arg(long, default_value = "cpu")]
    pub device: mvsplat360_pipeline::compute::DeviceSpec,
}

struct Bar {
    pb: Option<ProgressBar>,
    stop: Arc<AtomicBool>,
}

impl Monitor for Bar {
    fn note(&self, msg: &str) {
        match &self.pb {
            Some(pb) => pb.println(msg),
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
    let mut cfg = TrainConfig::from_file(&a.config)?;
    if let Some(o) = a.out {
        cfg.train.out = o;
    }
    let stop = Arc::new(AtomicBool::new(false));
    let s2 = stop.clone();
    let _ = ctrlc::set_handler(move || {
        if s2.swap(true, Ordering::SeqCst) {
            eprintln!("interrupted again: exiting without a checkpoint");
            std::process::exit(130);
        }
        eprintln!("interrupt: finishing this step and writing a checkpoint (Ctrl-C again to exit now)");
    });
    let pb = (!quiet).then(|| {
        let pb = ProgressBar::new(cfg.train.steps);
        pb.set_style(
            ProgressStyle::with_template("train [{bar:30}] {pos}/{len} {elapsed_precise} ETA {eta} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        pb
    });
    let mon = Bar { pb, stop };
    let opts = RunOptions { resume: a.resume, weights_dir: a.weights_dir, device: a.device };
    match mvsplat360_train::run(&cfg, &opts, &mon) {
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
            Ok(())
        }
        Err(TrainError::Interrupted) => {
            eprintln!("stopped; continue with --resume");
            std::process::exit(130);
        }
        Err(e) => Err(e).with_context(|| format!("training with {}", a.config.display())),
    }
}
