//! Stand-alone trainer (`mvsplat360-train --config C [--resume]`): the same loop as `mvsplat360 train`, in a
//! small binary for background jobs and the crate's kill-and-resume test. Prints one JSON line per step.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

fn main() {
    let mut config = None;
    let mut opts = mvsplat360_train::RunOptions::default();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--config" => config = args.next(),
            "--resume" => opts.resume = true,
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
            "-h" | "--help" => {
                println!("usage: mvsplat360-train --config <toml> [--resume] [--weights-dir DIR] [--device cpu|cuda|cuda:N]");
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
    mvsplat360_pipeline::setup::init_process();
    let lines = Lines { stop: Arc::new(AtomicBool::new(false)) };
    let stop = lines.stop.clone();
    // Background jobs are stopped with SIGTERM (and a shell's `&` ignores SIGINT): finish the step, checkpoint.
    if let Err(e) = ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst)) {
        eprintln!("warning: no stop handler ({e}); a stop signal will lose the steps since the last checkpoint");
    }
    let result = mvsplat360_train::TrainConfig::from_file(config.as_ref()).and_then(|cfg| mvsplat360_train::run(&cfg, &opts, &lines));
    match result {
        Ok(s) => eprintln!("done: {} steps, model in {}", s.steps, s.model_dir.display()),
        Err(mvsplat360_train::TrainError::Interrupted) => {
            eprintln!("stopped: checkpoint written; continue with --resume");
            std::process::exit(130);
        }
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
}

struct Lines {
    stop: Arc<AtomicBool>,
}

impl mvsplat360_train::Monitor for Lines {
    fn should_stop(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }
    fn note(&self, msg: &str) {
        eprintln!("{msg}");
    }
    fn step(&self, rec: &mvsplat360_train::StepRecord, _total: u64) {
        println!("{}", serde_json::to_string(rec).unwrap_or_default());
    }
}
