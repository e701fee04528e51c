//! `mvsplat360 bench refiner`: one guided sampling step of the real-size VideoUNet with random weights.

use std::time::Instant;

use candle_core::Device;

use crate::refiner::{seeded_noise, LatentDecoder};
use crate::sampling::{guided_unet_input, v_scaling_edm};
use crate::unet::util::timestep_embedding;
use crate::unet::{UNetError, UNetInputs, VideoUNet, VideoUNetConfig};
use crate::vae::{AutoencoderConfig, AutoencoderKL};
use mvsplat360_nn::bench::median;

/// Peak resident set size of this process in MiB (Linux `VmHWM`), None elsewhere.
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// Time `runs` guided UNet steps (batch 2·frames: [uncond; cond]) of the MVSplat360 config with random
/// weights on `threads` threads (0 = all cores; the JSON's `threads` is the pool size that ran); `vae_decode_ms` is measured only when a decoder is given.
pub fn run_refiner_bench_with(
    cfg: &VideoUNetConfig,
    frames: usize,
    latent_h: usize,
    latent_w: usize,
    threads: usize,
    runs: usize,
    decoder: Option<&dyn LatentDecoder>,
) -> Result<serde_json::Value, UNetError> {
    // 0 = all cores (rayon's default), as `--threads` documents; `threads.max(1)` used to turn it into one.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|e| UNetError::Config { path: "<bench>".into(), msg: e.to_string() })?;
    pool.install(|| {
        let dev = Device::Cpu;
        let t0 = Instant::now();
        let unet = VideoUNet::random(cfg, 0, &dev)?;
        let load_ms = t0.elapsed().as_secs_f64() * 1e3;
        let n = frames;
        let x = seeded_noise(1, &[n, 4, latent_h, latent_w], &dev)?;
        let concat = seeded_noise(2, &[n, cfg.in_channels.saturating_sub(4), latent_h, latent_w], &dev)?;
        let ctx = seeded_noise(3, &[2 * n, 1, cfg.context_dim], &dev)?;
        let sigma = 700f32;
        let (_, _, c_in, c_noise) = v_scaling_edm(sigma);
        let y = match cfg.adm_in_channels {
            Some(adm) => Some(timestep_embedding(&vec![0.02; 2 * n], adm, 10000.0, &dev)?),
            None => None,
        };
        let mut times = Vec::new();
        for _ in 0..runs.max(1) {
            let t = Instant::now();
            let inp = guided_unet_input(&x, &concat, c_in)?;
            let v = unet.forward(&UNetInputs {
                x: &inp,
                timesteps: &vec![c_noise; 2 * n],
                context: &ctx,
                y: y.as_ref(),
                num_video_frames: frames,
                num_splits: None,
            })?;
            let _ = v.sum_all()?.to_scalar::<f32>()?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let unet_peak = peak_rss_mib();
        drop(unet);
        // One latent frame per decoder call (MVSplat360's `en_and_decode_n_samples_a_time: 1`), as the
        // PyTorch reference (scripts/bench-reference/bench_refiner.py) times it.
        let vae_ms = match decoder {
            Some(d) => {
                let z = (x.narrow(0, 0, 1)? / 0.18215)?;
                let t = Instant::now();
                let out = d.decode(&z, 1)?;
                let _ = out.sum_all()?.to_scalar::<f32>()?;
                Some(t.elapsed().as_secs_f64() * 1e3)
            }
            None => None,
        };
        Ok(serde_json::json!({
            "bench": "refiner",
            "frames": frames,
            "latent_h": latent_h,
            "latent_w": latent_w,
            "threads": rayon::current_num_threads(),
            "unet_step_ms": median(times.clone()),
            "unet_step_runs_ms": times,
            "vae_decode_ms": vae_ms,
            "vae_frames": 1,
            "weights_init_ms": load_ms,
            "unet_peak_mib": unet_peak,
            "peak_mib": peak_rss_mib(),
        }))
    })
}

/// The real MVSplat360 UNet and VAE configs (`svd_wo_mb_fps`), random weights; `vae_decode_ms` times one
/// latent frame through the temporal decoder. See [`run_refiner_bench_with`].
pub fn run_refiner_bench(frames: usize, latent_h: usize, latent_w: usize, threads: usize, runs: usize) -> Result<serde_json::Value, UNetError> {
    let vae = AutoencoderKL::random(&AutoencoderConfig::default(), 1, &Device::Cpu)
        .map_err(|e| UNetError::Config { path: "<bench VAE>".into(), msg: e.to_string() })?;
    run_refiner_bench_with(&VideoUNetConfig::default(), frames, latent_h, latent_w, threads, runs, Some(&vae))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> VideoUNetConfig {
        VideoUNetConfig::tiny()
    }

    /// `threads` 0 means all cores (it used to run on one), any other value that many; the JSON says which.
    #[test]
    fn threads_zero_means_all_cores() {
        let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
        for (asked, want) in [(0, cores), (1, 1), (3, 3)] {
            let v = run_refiner_bench_with(&tiny(), 2, 8, 8, asked, 1, None).unwrap();
            assert_eq!(v["threads"], want, "--threads {asked}: {v}");
            assert_eq!(v["bench"], "refiner");
            assert!(v["unet_step_ms"].as_f64().is_some_and(|t| t >= 0.0), "{v}");
            assert!(v["vae_decode_ms"].is_null(), "{v}");
        }
    }
}
