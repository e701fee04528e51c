//! `mvsplat360 bench train`: wall time of real optimizer steps (data, forward, losses, backward, clipping, Adam)
//! of a training config, through the same loop as `train`, in a throw-away output folder.

use std::path::Path;
use std::sync::Mutex;

use serde_json::json;

use crate::{Monitor, Result, RunOptions, StepRecord, TrainConfig, TrainError};

struct Times(Mutex<Vec<f64>>);

impl Monitor for Times {
    fn step(&self, rec: &StepRecord, _total: u64) {
        self.0.lock().map(|mut v| v.push(rec.seconds)).ok();
    }
}

/// Median and minimum seconds per optimizer step over `runs` steps after `warmup` untimed ones, on `threads`
/// worker threads (0 = all cores), and the process's peak RSS. The config's own output folder, checkpoint
/// cadence and step count are replaced; everything else (data, model size, losses, `init`) is used as is.
pub fn run_train_bench(
    config: &Path,
    runs: usize,
    warmup: usize,
    threads: usize,
    device: mvsplat360_pipeline::compute::DeviceSpec,
) -> Result<serde_json::Value> {
    if runs == 0 {
        return Err(TrainError::Config { path: config.into(), msg: "bench train: --runs must be at least 1".into() });
    }
    let mut cfg = TrainConfig::from_file(config)?;
    let dir = std::env::temp_dir().join(format!("mvsplat360-bench-train-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    cfg.train.out = dir.clone();
    cfg.train.steps = (runs + warmup) as u64;
    cfg.train.checkpoint_every = cfg.train.steps + 1;
    let times = Times(Mutex::new(Vec::new()));
    let opts = RunOptions { device, ..Default::default() };
    let run = || crate::run(&cfg, &opts, &times);
    let res = if threads > 0 {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| TrainError::Config { path: config.into(), msg: format!("bench train: cannot build a {threads}-thread pool: {e}") })?;
        pool.install(run)
    } else {
        run()
    };
    let _ = std::fs::remove_dir_all(&dir);
    res?;
    let all = times.0.into_inner().unwrap_or_default();
    let mut timed: Vec<f64> = all.iter().skip(warmup).copied().collect();
    timed.sort_by(f64::total_cmp);
    let median = match timed.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => timed[n / 2],
        n => 0.5 * (timed[n / 2 - 1] + timed[n / 2]),
    };
    Ok(json!({
        "bench": "train",
        "config": config.display().to_string(),
        "device": format!("{device}"),
        "threads": if threads > 0 { threads } else { rayon::current_num_threads() },
        "warmup": warmup,
        "runs": timed.len(),
        "step_s": median,
        "step_s_min": timed.first().copied().unwrap_or(f64::NAN),
        "peak_rss_mib": mvsplat360_pipeline::setup::peak_rss_mib(),
    }))
}
