//! `mvsplat360 bench refiner`: one guided sampling step of the real-size VideoUNet and the VAE's decode, random
//! weights, on the CPU or a GPU.

use std::time::Instant;

use candle_core::{DType, Device};

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

/// What `bench refiner` measures and where.
#[derive(Debug, Clone)]
pub struct RefinerBench {
    /// Frames denoised together (the UNet batch is 2·frames: [uncond; cond]).
    pub frames: usize,
    pub latent_h: usize,
    pub latent_w: usize,
    /// CPU threads (0 = all cores; the JSON's `threads` is the pool size that ran).
    pub threads: usize,
    pub runs: usize,
    /// Untimed runs first (kernel loading, caches, cuDNN plans).
    pub warmup: usize,
    pub device: Device,
    /// The refiner's precision (f16/bf16 on a GPU).
    pub dtype: DType,
    /// Latent frames the VAE decodes, one per call as MVSplat360 does (`en_and_decode_n_samples_a_time: 1`).
    pub vae_frames: usize,
}

impl RefinerBench {
    /// The paper's window on the CPU in f32.
    pub fn new(frames: usize, latent_h: usize, latent_w: usize, threads: usize, runs: usize) -> Self {
        Self { frames, latent_h, latent_w, threads, runs, warmup: 1, device: Device::Cpu, dtype: DType::F32, vae_frames: 1 }
    }
}

/// Time `runs` guided UNet steps of `cfg` with random weights and, when a decoder is given, the decode of
/// `vae_frames` latent frames one per call (as the PyTorch reference, scripts/bench-reference/bench_refiner.py,
/// times diffusers).
pub fn run_refiner_bench_with(cfg: &VideoUNetConfig, o: &RefinerBench, decoder: Option<&dyn LatentDecoder>) -> Result<serde_json::Value, UNetError> {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(o.threads).build().map_err(|e| UNetError::Config { path: "<bench>".into(), msg: e.to_string() })?;
    pool.install(|| {
        let dev = &o.device;
        let t0 = Instant::now();
        let unet = VideoUNet::random_as(cfg, 0, dev, o.dtype)?;
        let load_ms = t0.elapsed().as_secs_f64() * 1e3;
        let n = o.frames;
        let x = seeded_noise(1, &[n, 4, o.latent_h, o.latent_w], dev)?;
        let concat = seeded_noise(2, &[n, cfg.in_channels.saturating_sub(4), o.latent_h, o.latent_w], dev)?;
        let ctx = seeded_noise(3, &[2 * n, 1, cfg.context_dim], dev)?;
        let sigma = 700f32;
        let (_, _, c_in, c_noise) = v_scaling_edm(sigma);
        let y = match cfg.adm_in_channels {
            Some(adm) => Some(timestep_embedding(&vec![0.02; 2 * n], adm, 10000.0, dev)?),
            None => None,
        };
        let mut times = Vec::new();
        for r in 0..o.warmup + o.runs.max(1) {
            let t = Instant::now();
            let inp = guided_unet_input(&x, &concat, c_in)?;
            let v =
                unet.forward(&UNetInputs { x: &inp, timesteps: &vec![c_noise; 2 * n], context: &ctx, y: y.as_ref(), num_video_frames: n, num_splits: None })?;
            // Reading one value waits for the device's queued kernels.
            let _ = v.sum_all()?.to_scalar::<f32>()?;
            if r >= o.warmup {
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        let unet_peak = peak_rss_mib();
        drop(unet);
        let vae_ms = match decoder {
            Some(d) => {
                let frames = o.vae_frames.max(1);
                let z = (seeded_noise(4, &[frames, 4, o.latent_h, o.latent_w], dev)? / 0.18215)?;
                let decode = || -> Result<f64, UNetError> {
                    let t = Instant::now();
                    for f in 0..frames {
                        let out = d.decode(&z.narrow(0, f, 1)?, 1)?;
                        let _ = out.sum_all()?.to_scalar::<f32>()?;
                    }
                    Ok(t.elapsed().as_secs_f64() * 1e3)
                };
                for _ in 0..o.warmup {
                    decode()?;
                }
                Some(median((0..o.runs.max(1)).map(|_| decode()).collect::<Result<Vec<_>, _>>()?))
            }
            None => None,
        };
        Ok(serde_json::json!({
            "bench": "refiner",
            "device": format!("{:?}", o.device.location()),
            "dtype": format!("{:?}", o.dtype).to_lowercase(),
            "frames": n,
            "latent_h": o.latent_h,
            "latent_w": o.latent_w,
            "threads": rayon::current_num_threads(),
            "warmup": o.warmup,
            "unet_step_ms": median(times.clone()),
            "unet_step_runs_ms": times,
            "vae_decode_ms": vae_ms,
            "vae_frames": o.vae_frames.max(1),
            "weights_init_ms": load_ms,
            "unet_peak_mib": unet_peak,
            "peak_mib": peak_rss_mib(),
            "gpu_ops": mvsplat360_nn::gpu_ops::from_env().map(|s| s.names()).unwrap_or_default(),
        }))
    })
}

/// The real MVSplat360 UNet and VAE configs (`svd_wo_mb_fps`), random weights. See [`run_refiner_bench_with`].
pub fn run_refiner_bench(o: &RefinerBench) -> Result<serde_json::Value, UNetError> {
    let vae = AutoencoderKL::random_as(&AutoencoderConfig::default(), 1, &o.device, o.dtype)
        .map_err(|e| UNetError::Config { path: "<bench VAE>".into(), msg: e.to_string() })?;
    run_refiner_bench_with(&VideoUNetConfig::default(), o, Some(&vae))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> VideoUNetConfig {
        VideoUNetConfig::tiny()
    }

    /// `threads` 0 means all cores, any other value that many; the JSON says which.
    #[test]
    fn threads_zero_means_all_cores() {
        let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
        for (asked, want) in [(0, cores), (1, 1), (3, 3)] {
            let v = run_refiner_bench_with(&tiny(), &RefinerBench::new(2, 8, 8, asked, 1), None).unwrap();
            assert_eq!(v["threads"], want, "--threads {asked}: {v}");
            assert_eq!(v["bench"], "refiner");
            assert!(v["unet_step_ms"].as_f64().is_some_and(|t| t >= 0.0), "{v}");
            assert!(v["vae_decode_ms"].is_null(), "{v}");
        }
    }
}
