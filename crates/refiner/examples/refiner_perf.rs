//! Times one guided UNet step, a temporal-VAE decode and a CLIP embed with random weights at the real
//! model configs and a chosen size, and prints per-module totals with `--profile`.
//!
//! cargo run --release -p mvsplat360-refiner --example refiner_perf -- --frames 2 --h 32 --w 56 --profile

use std::time::Instant;

use candle_core::{Device, Tensor};
use mvsplat360_nn::prof;
use mvsplat360_refiner::bench::{peak_rss_mib, run_refiner_bench_with};
use mvsplat360_refiner::clip::{ClipImageEmbedder, ClipVisionConfig};
use mvsplat360_refiner::refiner::seeded_noise;
use mvsplat360_refiner::unet::VideoUNetConfig;
use mvsplat360_refiner::vae::{AutoencoderConfig, AutoencoderKL};

fn main() -> anyhow::Result<()> {
    let mut frames = 2usize;
    let (mut h, mut w) = (32usize, 56usize);
    let mut threads = rayon::current_num_threads();
    let mut runs = 1usize;
    let (mut unet, mut vae, mut clip, mut profile) = (true, true, true, false);
    let (mut vae_h, mut vae_w, mut vae_frames) = (0usize, 0usize, 1usize);
    let mut clip_views = 1usize;
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < args.len() {
        let val = |i: usize| -> anyhow::Result<usize> {
            args.get(i + 1).ok_or_else(|| anyhow::anyhow!("{} needs a value", args[i]))?.parse().map_err(|e| anyhow::anyhow!("{}: {e}", args[i]))
        };
        match args[i].as_str() {
            "--frames" => {
                frames = val(i)?;
                i += 1
            }
            "--h" => {
                h = val(i)?;
                i += 1
            }
            "--w" => {
                w = val(i)?;
                i += 1
            }
            "--threads" => {
                threads = val(i)?;
                i += 1
            }
            "--runs" => {
                runs = val(i)?;
                i += 1
            }
            "--vae-h" => {
                vae_h = val(i)?;
                i += 1
            }
            "--vae-w" => {
                vae_w = val(i)?;
                i += 1
            }
            "--vae-frames" => {
                vae_frames = val(i)?;
                i += 1
            }
            "--clip-views" => {
                clip_views = val(i)?;
                i += 1
            }
            "--no-unet" => unet = false,
            "--no-vae" => vae = false,
            "--no-clip" => clip = false,
            "--profile" => profile = true,
            other => anyhow::bail!("unknown argument {other}"),
        }
        i += 1;
    }
    if vae_h == 0 {
        vae_h = h;
    }
    if vae_w == 0 {
        vae_w = w;
    }
    prof::set_enabled(profile);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    let print_prof = |what: &str| {
        if profile {
            for (name, ms, n) in prof::take_report() {
                eprintln!("  [{what}] {name:<28} {ms:>10.1} ms  {n:>6} calls");
            }
        }
    };
    if unet {
        let r = if vae {
            mvsplat360_refiner::bench::run_refiner_bench(&mvsplat360_refiner::bench::RefinerBench::new(frames, h, w, threads, runs))?
        } else {
            run_refiner_bench_with(&VideoUNetConfig::default(), &mvsplat360_refiner::bench::RefinerBench::new(frames, h, w, threads, runs), None)?
        };
        println!("{r}");
        print_prof("unet");
    }
    let dev = Device::Cpu;
    if vae {
        let m = AutoencoderKL::random(&AutoencoderConfig::default(), 0, &dev)?;
        let z = seeded_noise(5, &[vae_frames, 4, vae_h, vae_w], &dev)?;
        let mut times = Vec::new();
        pool.install(|| -> anyhow::Result<()> {
            for _ in 0..runs {
                let t = Instant::now();
                let out = m.decode_chunked(&z, Some(1))?;
                let _ = out.sum_all()?.to_scalar::<f32>()?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
            Ok(())
        })?;
        println!(
            "{}",
            serde_json::json!({"bench": "vae_decode", "frames": vae_frames, "latent_h": vae_h, "latent_w": vae_w, "runs_ms": times, "peak_mib": peak_rss_mib()})
        );
        print_prof("vae");
    }
    if clip {
        let m = ClipImageEmbedder::random(&ClipVisionConfig::default(), 0, &dev)?;
        let views = (seeded_noise(6, &[clip_views, 3, 256, 448], &dev)?.abs()? * 0.3)?;
        let mut times = Vec::new();
        pool.install(|| -> anyhow::Result<()> {
            for _ in 0..runs {
                let t = Instant::now();
                let e: Tensor = m.embed(&views)?;
                let _ = e.sum_all()?.to_scalar::<f32>()?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
            Ok(())
        })?;
        println!("{}", serde_json::json!({"bench": "clip_embed", "views": clip_views, "runs_ms": times, "peak_mib": peak_rss_mib()}));
        print_prof("clip");
    }
    Ok(())
}
