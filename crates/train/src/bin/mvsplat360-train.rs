//! Stand-alone trainer (`mvsplat360-train --config C [--resume]`): the same loop as `mvsplat360 train`, in a
//! small binary for background jobs and the crate's kill-and-resume test. Prints one JSON line per step.
//! `--world-size N` trains data-parallel: this binary starts N copies of itself (ranks), rank 0 prints the lines.
//! `--export STEP|latest [--export-to DIR]` writes a checkpoint as a model folder instead of training.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

fn main() {
    let mut config = None;
    let mut opts = mvsplat360_train::RunOptions::default();
    let (mut world, mut backend) = (1usize, mvsplat360_train::dist::Backend::Auto);
    let (mut export, mut export_to): (Option<Option<u64>>, Option<std::path::PathBuf>) = (None, None);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--config" => config = args.next(),
            "--resume" => opts.resume = true,
            "--allow-world-change" => opts.allow_world_change = true,
            "--export" => match args.next().as_deref().map(mvsplat360_train::checkpoint::parse_step) {
                Some(Ok(s)) => export = Some(s),
                Some(Err(e)) => {
                    eprintln!("error: --export: {e}");
                    std::process::exit(2);
                }
                None => {
                    eprintln!("error: --export needs a checkpoint step or `latest`");
                    std::process::exit(2);
                }
            },
            "--export-to" => export_to = args.next().map(Into::into),
            "--weights-dir" => opts.weights_dir = args.next().map(Into::into),
            "--device" => match args.next().map(|d| d.parse()) {
                Some(Ok(d)) => opts.device = d,
                Some(Err(e)) => {
                    eprintln!("error: --device: {e}");
                    std::process::exit(2);
                }
                None => {
                    eprintln!("error: --device needs a value (cpu, cuda or cuda:N)");
                    std::process::exit(2);
                }
            },
            "--world-size" => match args.next().map(|n| n.parse::<usize>()) {
                Some(Ok(n)) if n > 0 => world = n,
                _ => {
                    eprintln!("error: --world-size needs a number of processes ≥ 1");
                    std::process::exit(2);
                }
            },
            "--dist-backend" => match args.next().map(|b| b.parse()) {
                Some(Ok(b)) => backend = b,
                Some(Err(e)) => {
                    eprintln!("error: --dist-backend: {e}");
                    std::process::exit(2);
                }
                None => {
                    eprintln!("error: --dist-backend needs a value (auto, host or nccl)");
                    std::process::exit(2);
                }
            },
            "-h" | "--help" => {
                println!(
                    "usage: mvsplat360-train --config <toml> [--resume [--allow-world-change]] [--weights-dir DIR] [--device cpu|cuda|cuda:N] \
                     [--world-size N] [--dist-backend auto|host|nccl]\n       mvsplat360-train --config <toml> --export STEP|latest \
                     [--export-to DIR]   (a checkpoint as a model folder, default <train.out>/model-STEP)"
                );
                return;
            }
            other => {
                eprintln!("error: unknown argument `{other}` (see --help)");
                std::process::exit(2);
            }
        }
    }
    let Some(config) = config else {
        eprintln!("error: --config <toml> is required");
        std::process::exit(2);
    };
    if let Some(step) = export {
        let result =
            mvsplat360_train::TrainConfig::from_file(config.as_ref()).and_then(|cfg| mvsplat360_train::export_checkpoint(&cfg, step, export_to.as_deref()));
        match result {
            Ok((step, dir)) => eprintln!("checkpoint of step {step} written as the model folder {}", dir.display()),
            Err(e) => {
                eprintln!("error: {e}");
                std::process::exit(1);
            }
        }
        return;
    } else if export_to.is_some() {
        eprintln!("error: --export-to goes with --export STEP|latest");
        std::process::exit(2);
    }
    mvsplat360_pipeline::setup::init_process();
    let rank = match mvsplat360_train::dist::Rank::from_env() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(2);
        }
    };
    if let Some(r) = rank.as_ref().filter(|r| r.place.launcher != mvsplat360_pipeline::launch::Launcher::Project && world > 1) {
        eprintln!(
            "error: --world-size {world} under {} with {} ranks: each rank would start its own; drop --world-size, or start one task",
            r.place.launcher.name(),
            r.world
        );
        std::process::exit(2);
    }
    let lines = Lines { stop: Arc::new(AtomicBool::new(false)), rank: rank.as_ref().map_or(0, |r| r.rank) };
    let stop = lines.stop.clone();
    // Background jobs are stopped with SIGTERM (and a shell's `&` ignores SIGINT): finish the step, checkpoint.
    if let Err(e) = ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst)) {
        eprintln!("warning: no stop handler ({e}); a stop signal will lose the steps since the last checkpoint");
    }
    let cuda = opts.device != mvsplat360_pipeline::compute::DeviceSpec::Cpu;
    if rank.is_none() && world > 1 {
        let result =
            mvsplat360_train::TrainConfig::from_file(config.as_ref()).and_then(|_| mvsplat360_train::dist::launch_self(world, backend, cuda, &lines.stop));
        match result {
            Ok(()) => {}
            Err(mvsplat360_train::TrainError::Interrupted) => std::process::exit(130),
            Err(e) => {
                eprintln!("error: {e}");
                std::process::exit(1);
            }
        }
        return;
    }
    opts.dist = rank;
    opts.dist_backend = backend;
    let result = mvsplat360_train::TrainConfig::from_file(config.as_ref()).and_then(|cfg| mvsplat360_train::run(&cfg, &opts, &lines));
    match result {
        Ok(s) if lines.rank > 0 => drop(s),
        Ok(s) => eprintln!("done: {} steps, model in {}", s.steps, s.model_dir.display()),
        Err(mvsplat360_train::TrainError::Interrupted) => {
            if lines.rank == 0 {
                eprintln!("stopped: checkpoint written; continue with --resume");
            }
            std::process::exit(130);
        }
        Err(e) => {
            lines.note(&format!("error: {e}"));
            std::process::exit(1);
        }
    }
}

struct Lines {
    stop: Arc<AtomicBool>,
    rank: usize,
}

use mvsplat360_train::Monitor as _;

impl mvsplat360_train::Monitor for Lines {
    fn should_stop(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }
    fn note(&self, msg: &str) {
        match self.rank {
            0 => eprintln!("{msg}"),
            r => eprintln!("rank {r}: {msg}"),
        }
    }
    fn step(&self, rec: &mvsplat360_train::StepRecord, _total: u64) {
        if self.rank == 0 {
            println!("{}", serde_json::to_string(rec).unwrap_or_default());
        }
    }
}
