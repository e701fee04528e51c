//! `mvsplat360 bench metrics`: throughput (image pairs per second) of each metric at one resolution
//! (default 256×448, the DL3DV evaluation size), median of timed runs after one warm-up.
//!
//! Each run scores one batch of [`BATCH`] pseudo-random image pairs the way [`crate::score::score_dirs`]
//! does (PSNR and SSIM in parallel over the pairs; the networks on the stacked batch). The networks are timed
//! only when their weights are found (`weights_dir`, `$MVSPLAT360_METRIC_WEIGHTS`, the default folder); else
//! their entries are `null` and `notes` says why. `fid` times the Inception features of both images of each
//! pair; `frechet_ms` the Fréchet distance of two 2048-d sets of [`FRECHET_SET`] features.

use std::path::PathBuf;
use std::time::Instant;

use candle_core::{Device, Tensor};
use rayon::prelude::*;
use serde_json::{json, Value};

use crate::dists::Dists;
use crate::inception::FidInception;
use crate::lpips::{Lpips, Net};
use mvsplat360_nn::bench::median;

/// Image pairs per timed run.
pub const BATCH: usize = 4;
/// Feature rows per set in the Fréchet timing.
pub const FRECHET_SET: usize = 256;

/// What [`run_metrics_bench_with`] measures.
#[derive(Debug, Clone)]
pub struct MetricsBenchOpts {
    pub width: usize,
    pub height: usize,
    /// Timed runs after one warm-up.
    pub runs: usize,
    /// Worker threads (0 = rayon's default: all cores).
    pub threads: usize,
    /// `--weights-dir` for the networks.
    pub weights_dir: Option<PathBuf>,
}

/// Deterministic values in [0, 1) (xorshift), so runs are comparable without a random-number crate.
fn pseudo_random(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect()
}

/// Median seconds of `f` over `runs` runs after one warm-up; the error (as text) of the first failing call.
fn time<F: FnMut() -> Result<(), String>>(runs: usize, mut f: F) -> Result<f64, String> {
    f()?;
    let mut t = Vec::with_capacity(runs.max(1));
    for _ in 0..runs.max(1) {
        let s = Instant::now();
        f()?;
        t.push(s.elapsed().as_secs_f64());
    }
    Ok(median(t))
}

/// Throughput of PSNR, SSIM, LPIPS-VGG, DISTS and FID features at `width`×`height` on all cores, with the
/// weights found through the environment / default folder. See [`run_metrics_bench_with`].
pub fn run_metrics_bench(width: usize, height: usize, runs: usize) -> Value {
    run_metrics_bench_with(&MetricsBenchOpts { width, height, runs, threads: 0, weights_dir: None })
}

/// One JSON object: `{"bench":"metrics","width","height","batch","runs","threads",
/// "images_per_s":{"psnr","ssim","lpips","dists","fid"},"frechet_ms","notes":[…]}` (a network's entry is
/// `null` when its weights are missing or it failed; `notes` says which and why).
pub fn run_metrics_bench_with(opts: &MetricsBenchOpts) -> Value {
    let pool = match rayon::ThreadPoolBuilder::new().num_threads(opts.threads).build() {
        Ok(p) => p,
        Err(e) => return json!({ "bench": "metrics", "error": e.to_string() }),
    };
    pool.install(|| bench_inner(opts))
}

fn bench_inner(opts: &MetricsBenchOpts) -> Value {
    let (w, h, runs) = (opts.width.max(crate::ssim::WIN_SIZE), opts.height.max(crate::ssim::WIN_SIZE), opts.runs);
    let per = 3 * w * h;
    let pred: Vec<Vec<f32>> = (0..BATCH).map(|i| pseudo_random(per, 2 * i as u64 + 1)).collect();
    // Ground truth = prediction + structured noise, so SSIM / PSNR are in a realistic range.
    let gt: Vec<Vec<f32>> = pred
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let noise = pseudo_random(per, 2 * i as u64 + 2);
            p.iter().zip(noise).map(|(&a, n)| (0.8 * a + 0.2 * n).clamp(0.0, 1.0)).collect()
        })
        .collect();
    let mut notes: Vec<String> = Vec::new();
    let ips = |secs: Result<f64, String>, what: &str, notes: &mut Vec<String>| -> Value {
        match secs {
            Ok(s) => json!(BATCH as f64 / s),
            Err(e) => {
                notes.push(format!("{what}: {e}"));
                Value::Null
            }
        }
    };

    let psnr = time(runs, || {
        let v: f64 = pred.par_iter().zip(&gt).map(|(a, b)| crate::psnr::psnr(a, b)).sum();
        std::hint::black_box(v);
        Ok(())
    });
    let psnr = ips(psnr, "psnr", &mut notes);
    let ssim = time(runs, || {
        let v = pred.par_iter().zip(&gt).map(|(a, b)| crate::ssim::ssim(a, b, 3, h, w)).collect::<Result<Vec<_>, _>>().map_err(|e| e.to_string())?;
        std::hint::black_box(v);
        Ok(())
    });
    let ssim = ips(ssim, "ssim", &mut notes);

    let dev = Device::Cpu;
    let stack = |imgs: &[Vec<f32>]| Tensor::from_vec(imgs.concat(), (imgs.len(), 3, h, w), &dev);
    let (tp, tg) = match (stack(&pred), stack(&gt)) {
        (Ok(a), Ok(b)) => (a, b),
        (Err(e), _) | (_, Err(e)) => return json!({ "bench": "metrics", "error": e.to_string() }),
    };
    let wd = opts.weights_dir.as_deref();
    let lpips = match Lpips::load(wd, Net::Vgg, &dev) {
        Ok(net) => ips(time(runs, || net.distance(&tp, &tg).map(|_| ()).map_err(|e| e.to_string())), "lpips", &mut notes),
        Err(e) => ips(Err(e.to_string()), "lpips", &mut notes),
    };
    let dists = match Dists::load(wd, &dev) {
        Ok(net) => ips(time(runs, || net.distance(&tp, &tg).map(|_| ()).map_err(|e| e.to_string())), "dists", &mut notes),
        Err(e) => ips(Err(e.to_string()), "dists", &mut notes),
    };
    let fid = match FidInception::load(wd, &dev) {
        Ok(net) => ips(time(runs, || net.features(&tp).and_then(|_| net.features(&tg)).map(|_| ()).map_err(|e| e.to_string())), "fid", &mut notes),
        Err(e) => ips(Err(e.to_string()), "fid", &mut notes),
    };

    let d = crate::inception::DIM;
    let fa: Vec<f64> = pseudo_random(FRECHET_SET * d, 101).into_iter().map(f64::from).collect();
    let fb: Vec<f64> = pseudo_random(FRECHET_SET * d, 102).into_iter().map(f64::from).collect();
    let frechet_ms = time(runs, || {
        std::hint::black_box(crate::frechet::frechet_from_features(&fa, FRECHET_SET, &fb, FRECHET_SET, d));
        Ok(())
    })
    .map(|s| s * 1e3)
    .ok();

    json!({
        "bench": "metrics",
        "width": w,
        "height": h,
        "batch": BATCH,
        "runs": runs.max(1),
        "threads": rayon::current_num_threads(),
        "images_per_s": { "psnr": psnr, "ssim": ssim, "lpips": lpips, "dists": dists, "fid": fid },
        "frechet_ms": frechet_ms,
        "frechet_set": [FRECHET_SET, d],
        "notes": notes,
    })
}
