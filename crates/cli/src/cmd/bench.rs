//! `mvsplat360 bench <what>`: each benchmark lives in the crate it measures; this only dispatches and prints
//! the JSON line on stdout.

use clap::Subcommand;

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

/// `--threads`, one setting for every bench: 0 = all cores, N = N worker threads.
#[derive(clap::Args, Clone, Copy)]
struct Threads {
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
}

impl Threads {
    /// The worker count this setting means: all cores (the machine's available parallelism) for 0.
    fn count(self) -> usize {
        resolve_threads(self.threads)
    }
}

/// 0 → the number of cores (`std::thread::available_parallelism`), otherwise `threads` itself.
pub fn resolve_threads(threads: usize) -> usize {
    if threads > 0 {
        threads
    } else {
        std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
    }
}

#[derive(clap::Args, Clone, Copy)]
struct Common {
    #[command(flatten)]
    threads: Threads,
    /// Timed runs after one warm-up; the median is reported.
    #[arg(long, default_value_t = 5)]
    runs: usize,
}

#[derive(Subcommand)]
enum What {
    /// Rasterizer forward and forward+backward on a synthetic depth-layered scene (pixel-aligned Gaussians of
    /// several 256×448 views) rendered into one view with latent features.
    Raster {
        /// Number of Gaussians (default: 5 views × 256 × 448).
        #[arg(long, default_value_t = 573_440)]
        gaussians: usize,
        /// Rendered image width.
        #[arg(long, default_value_t = 448)]
        width: usize,
        /// Rendered image height.
        #[arg(long, default_value_t = 256)]
        height: usize,
        /// Latent feature channels rendered beside RGB.
        #[arg(long, default_value_t = 4)]
        features: usize,
        #[command(flatten)]
        common: Common,
    },
    /// Encoder forward (DL3DV configuration, random weights): time and peak memory.
    Encoder {
        /// Context views.
        #[arg(long, default_value_t = 5)]
        views: usize,
        /// Image height (a multiple of 64).
        #[arg(long, default_value_t = 256)]
        height: usize,
        /// Image width (a multiple of 64).
        #[arg(long, default_value_t = 448)]
        width: usize,
        /// Time only the backbone (CNN + multi-view transformer) instead of the whole encoder.
        #[arg(long)]
        backbone_only: bool,
        /// Precision: `f32` or `bf16` (weights packed once in bf16, f32 activations; the JSON's `cpu_bf16`
        /// names the path the products take on this CPU).
        #[arg(long, default_value = "f32", value_parser = mvsplat360_pipeline::compute::parse_encoder_dtype)]
        dtype: candle_core::DType,
        #[command(flatten)]
        common: Common,
    },
    /// Refiner (real SVD img2vid configuration, random weights): one guided UNet step and the VAE's decode of
    /// --vae-frames latent frames, one per call (as MVSplat360 and scripts/bench-reference/bench_refiner.py).
    Refiner {
        /// Where it runs: `cpu`, `cuda` or `cuda:N` (CUDA needs a `--features cuda` build).
        #[arg(long, default_value = "cpu")]
        device: mvsplat360_pipeline::compute::DeviceSpec,
        /// Precision: `f32`, `f16` or `bf16` (on the CPU: bf16 weights and products, f32 activations; the
        /// JSON's `cpu_bf16` names the path).
        #[arg(long, default_value = "f32", value_parser = mvsplat360_pipeline::compute::parse_dtype)]
        dtype: candle_core::DType,
        /// Latent frames the VAE decodes (one per call).
        #[arg(long, default_value_t = 1)]
        vae_frames: usize,
        /// Frames denoised together in one UNet call (a temporal window).
        #[arg(long, default_value_t = 14)]
        frames: usize,
        /// Latent height (image height / 4: images are upscaled 2× before the VAE's 8× downsampling).
        #[arg(long, default_value_t = 64)]
        latent_h: usize,
        /// Latent width.
        #[arg(long, default_value_t = 112)]
        latent_w: usize,
        #[command(flatten)]
        common: Common,
    },
    /// The whole `render` pipeline (encoder → rasterizer → refiner → histogram matching) on a synthetic scene
    /// with random weights: per-stage times (median over --runs, after --warmup untimed runs) and peak memory
    /// (warm-up runs included). Defaults are the
    /// paper's setting (official DL3DV configs) — hours on a CPU; `--tiny` uses the tests' tiny model. With
    /// MVSPLAT360_PROFILE=1 the line also has `profile`: encoder-stage and refiner-module totals (ms, calls) over the timed runs,
    /// nested scopes counted in each; on a GPU every scope waits for the device, so runs get slower.
    Scene {
        /// Where the pipeline runs: `cpu`, `cuda` or `cuda:N` (CUDA needs a `--features cuda` build).
        #[arg(long, default_value = "cpu")]
        device: mvsplat360_pipeline::compute::DeviceSpec,
        /// Precision of the refiner: `f32`, `f16` or `bf16` (on the CPU: bf16 weights and products, f32
        /// activations).
        #[arg(long, default_value = "f32", value_parser = mvsplat360_pipeline::compute::parse_dtype)]
        dtype: candle_core::DType,
        /// Precision of the encoder: `f32` or `bf16` (CPU only: weights packed in bf16, f32 activations).
        #[arg(long, default_value = "f32", value_parser = mvsplat360_pipeline::compute::parse_encoder_dtype)]
        encoder_dtype: candle_core::DType,
        /// Context views.
        #[arg(long, default_value_t = 5)]
        views: usize,
        /// Input height (a multiple of 64).
        #[arg(long, default_value_t = 256)]
        height: u32,
        /// Input width (a multiple of 64).
        #[arg(long, default_value_t = 448)]
        width: u32,
        /// Target frames (a 360° orbit), refined in windows of 14.
        #[arg(long, default_value_t = 56)]
        frames: usize,
        /// Guided sampling steps of the refiner.
        #[arg(long, default_value_t = 25)]
        steps: usize,
        /// Timed runs; the median of each stage is reported.
        #[arg(long, default_value_t = 1)]
        runs: usize,
        /// Untimed runs before the timed ones (on a GPU the first run also loads kernels and creates handles).
        #[arg(long, default_value_t = 0)]
        warmup: usize,
        /// The tests' tiny model (narrow encoder, tiny UNet/VAE/CLIP) instead of the official configs.
        #[arg(long)]
        tiny: bool,
        /// 3DGS only: skip the refiner.
        #[arg(long)]
        no_refiner: bool,
        #[command(flatten)]
        threads: Threads,
    },
    /// Optimizer steps of a training config (data, forward, losses, backward, clipping, Adam) through the
    /// `train` loop in a throw-away output folder: median and fastest seconds per step after --warmup untimed
    /// steps, and peak memory. The config's data, model, losses and `init` are used as they are.
    Train {
        /// Training config (TOML), e.g. configs/train/recipe/05-povray-depth.toml (its `init`, stage 4's model folder, must exist).
        #[arg(long)]
        config: std::path::PathBuf,
        /// Timed steps.
        #[arg(long, default_value_t = 5)]
        runs: usize,
        /// Untimed steps before the timed ones.
        #[arg(long, default_value_t = 1)]
        warmup: usize,
        /// Where the steps run: `cpu`, `cuda` or `cuda:N` (CUDA needs a `--features cuda` build).
        #[arg(long, default_value = "cpu")]
        device: mvsplat360_pipeline::compute::DeviceSpec,
        #[command(flatten)]
        threads: Threads,
    },
    /// Test-time fitting (a model folder's `fit`, see `render --fit-steps`) of the encoder's Gaussians on a
    /// scene's context views: seconds per fit and per step (median after --warmup untimed fits) and peak memory.
    /// The encoder runs once, untimed. Defaults: the shipped model on the bundled scene, as `demo` runs it.
    Fit {
        /// Model folder (default: the shipped model, assets/models/default), a path or a name (`default`,
        /// `hf:OWNER/REPO[@REV]`; an existing path wins).
        #[arg(long, value_name = "DIR|NAME")]
        model: Option<std::path::PathBuf>,
        /// Scene folder (default: the bundled scene, assets/woodbox).
        #[arg(long)]
        scene: Option<std::path::PathBuf>,
        /// Context views, picked by farthest-point sampling.
        #[arg(long, default_value_t = 5)]
        views: usize,
        /// Fitting steps (default: the model's `fit.steps`).
        #[arg(long)]
        steps: Option<usize>,
        /// Timed fits.
        #[arg(long, default_value_t = 3)]
        runs: usize,
        /// Untimed fits before the timed ones.
        #[arg(long, default_value_t = 1)]
        warmup: usize,
        /// Where the fit runs: `cpu`, `cuda` or `cuda:N` (CUDA needs a `--features cuda` build).
        #[arg(long, default_value = "cpu")]
        device: mvsplat360_pipeline::compute::DeviceSpec,
        #[command(flatten)]
        threads: Threads,
    },
    /// VGGT forward (aggregator, camera, depth and point heads) with seeded random weights at the VGGT-1B shape
    /// (or a model folder's config) on synthetic frames: median time, peak memory, TFLOP counted from the
    /// shapes and the achieved GFLOP/s.
    Vggt {
        /// Where it runs: `cpu`, `cuda` or `cuda:N` (CUDA needs a `--features cuda` build).
        #[arg(long, default_value = "cpu")]
        device: mvsplat360_pipeline::compute::DeviceSpec,
        /// Precision of VGGT: `f32` or `bf16`; `f16` on a GPU only. bf16 on a CPU with AVX512-BF16 runs the
        /// aggregator's linears and attention products and the DPT heads' convolutions and projections in bf16
        /// (weights packed once, f32 sums), the rest in f32 (norms, softmax, the camera head); on a GPU bf16 is
        /// the aggregator's only (the heads stay f32, as upstream).
        #[arg(long, default_value = "f32", value_parser = mvsplat360_pipeline::compute::parse_dtype)]
        dtype: candle_core::DType,
        /// Frames (photos) in the forward.
        #[arg(long, default_value_t = 5)]
        frames: usize,
        /// Frame size WIDTHxHEIGHT, both multiples of 14 (518x294: a 16:9 photo as VGGT's loader prepares it).
        #[arg(long, default_value = "518x294")]
        size: String,
        /// Take the shape from this VGGT model folder's config.json instead of VGGT-1B (weights stay random).
        #[arg(long)]
        config: Option<std::path::PathBuf>,
        /// Timed runs; the median is reported.
        #[arg(long, default_value_t = 3)]
        runs: usize,
        /// Untimed runs before the timed ones.
        #[arg(long, default_value_t = 1)]
        warmup: usize,
        #[command(flatten)]
        threads: Threads,
    },
    /// bf16 on the CPU: `vdpbf16ps` against `vfmadd231ps` peak GFLOP/s (1 thread and --threads), then the
    /// bf16 gemm (AVX512-BF16, f32 accumulation) against the f32 gemm on the model's shapes.
    Bf16 {
        /// Gemm shapes MxKxN, comma-separated (default: VGGT block linears and an SVD UNet 3×3 conv as a gemm).
        #[arg(long)]
        shapes: Option<String>,
        /// Inner iterations of one microbenchmark run (each issues 12 instructions per thread).
        #[arg(long, default_value_t = 40_000_000)]
        micro_iters: u64,
        #[command(flatten)]
        common: Common,
    },
    /// Image metrics at 256×448: images (pairs) per second of PSNR, SSIM, LPIPS, DISTS and FID features
    /// (the networks only when their weights are installed, see scripts/metric-weights/fetch).
    Metrics {
        /// Image width.
        #[arg(long, default_value_t = 448)]
        width: usize,
        /// Image height.
        #[arg(long, default_value_t = 256)]
        height: usize,
        /// Timed runs after one warm-up; the median is reported.
        #[arg(long, default_value_t = 3)]
        runs: usize,
        #[command(flatten)]
        threads: Threads,
    },
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let line = match args.what {
        What::Raster { gaussians, width, height, features, common } => {
            if gaussians == 0 || width == 0 || height == 0 {
                anyhow::bail!("bench raster: --gaussians, --width and --height must be positive");
            }
            let opts = mvsplat360_splat::bench::RasterBenchOpts { gaussians, width, height, features, threads: common.threads.count(), runs: common.runs };
            mvsplat360_splat::bench::run_raster_bench(&opts)?
        }
        What::Encoder { views, height, width, backbone_only, dtype, common } => {
            if height % 64 != 0 || width % 64 != 0 || views < 2 {
                anyhow::bail!("bench encoder: need --views ≥ 2 and --height/--width multiples of 64 (got {views}, {height}x{width})");
            }
            if backbone_only {
                mvsplat360_encoder::bench::run_backbone_bench(views, height, width, common.threads.count(), common.runs, dtype)?
            } else {
                mvsplat360_encoder::bench::run_encoder_bench(views, height, width, common.threads.count(), common.runs, dtype)?
            }
        }
        What::Refiner { device, dtype, vae_frames, frames, latent_h, latent_w, common } => {
            if frames == 0 || latent_h == 0 || latent_w == 0 || latent_h % 8 != 0 || latent_w % 8 != 0 {
                anyhow::bail!("bench refiner: need --frames ≥ 1 and latent sizes that are positive multiples of 8 (three 2× downsamplings) (got {frames}, {latent_h}x{latent_w})");
            }
            let compute = mvsplat360_pipeline::compute::Compute { device, refiner_dtype: dtype, ..Default::default() };
            let mut v = mvsplat360_refiner::bench::run_refiner_bench(&mvsplat360_refiner::bench::RefinerBench {
                device: compute.open()?,
                dtype,
                vae_frames,
                ..mvsplat360_refiner::bench::RefinerBench::new(frames, latent_h, latent_w, common.threads.count(), common.runs)
            })?;
            if let Some(path) = compute.cpu_bf16_path() {
                v["cpu_bf16"] = serde_json::json!(path.name());
            }
            v
        }
        What::Scene { device, dtype, encoder_dtype, views, height, width, frames, steps, runs, warmup, tiny, no_refiner, threads } => {
            mvsplat360_pipeline::bench::run_scene_bench(&mvsplat360_pipeline::bench::SceneBenchOpts {
                device,
                dtype,
                encoder_dtype,
                views,
                height,
                width,
                frames,
                steps,
                warmup,
                runs,
                threads: threads.count(),
                tiny,
                no_refiner,
            })?
        }
        What::Train { config, runs, warmup, device, threads } => mvsplat360_train::bench::run_train_bench(&config, runs, warmup, threads.count(), device)?,
        What::Fit { model, scene, views, steps, runs, warmup, device, threads } => {
            let model = match model {
                Some(m) => super::names::resolve(&m, "--model", super::names::Default::ModelFolder, super::names::Freshness::Ask, false)?,
                None => mvsplat360_pipeline::model::default_model_dir()
                    .ok_or_else(|| anyhow::anyhow!("bench fit: the shipped model assets/models/default is missing; pass --model DIR"))?,
            };
            let scene = match scene {
                Some(s) => s,
                None => {
                    super::demo::bundled_scene().ok_or_else(|| anyhow::anyhow!("bench fit: the bundled scene assets/woodbox is missing; pass --scene DIR"))?
                }
            };
            mvsplat360_pipeline::bench::run_fit_bench(&mvsplat360_pipeline::bench::FitBenchOpts {
                model,
                scene,
                views,
                steps,
                warmup,
                runs,
                threads: threads.count(),
                device,
            })?
        }
        What::Vggt { device, dtype, frames, size, config, runs, warmup, threads } => {
            // bf16 on the CPU: the trunk's linears in the packed bf16 product with AVX512-BF16, candle's bf16 ops without.
            if device == mvsplat360_pipeline::compute::DeviceSpec::Cpu && !matches!(dtype, candle_core::DType::F32 | candle_core::DType::BF16) {
                anyhow::bail!("bench vggt: --dtype {dtype:?} needs --device cuda (the CPU runs f32 or bf16)");
            }
            let (width, height) = size
                .split_once('x')
                .and_then(|(w, h)| Some((w.parse::<usize>().ok()?, h.parse::<usize>().ok()?)))
                .ok_or_else(|| anyhow::anyhow!("bench vggt: --size `{size}` is not WIDTHxHEIGHT (e.g. 518x294)"))?;
            let cfg = match config {
                Some(dir) => mvsplat360_vggt::weights::read_config(&dir.join("config.json"))?,
                None => mvsplat360_vggt::VggtConfig::default(),
            };
            let device = device.open()?;
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads.count()).build()?;
            let b = mvsplat360_vggt::bench::VggtBench { frames, height, width, runs, warmup, seed: 0, trunk: dtype };
            pool.install(|| mvsplat360_vggt::bench::run(&cfg, &b, &device))?
        }
        What::Bf16 { shapes, micro_iters, common } => {
            let shapes = match shapes {
                None => mvsplat360_nn::bf16::bench::default_shapes(),
                Some(s) => s
                    .split(',')
                    .filter(|t| !t.trim().is_empty())
                    .map(|t| {
                        let v: Vec<usize> = t.trim().split('x').filter_map(|x| x.parse().ok()).collect();
                        match v[..] {
                            [m, k, n] => Ok((m, k, n)),
                            _ => Err(anyhow::anyhow!("bench bf16: shape `{t}` is not MxKxN")),
                        }
                    })
                    .collect::<anyhow::Result<Vec<_>>>()?,
            };
            let opts = mvsplat360_nn::bf16::bench::Bf16BenchOpts { threads: common.threads.count(), runs: common.runs, shapes, micro_iters };
            let line = mvsplat360_nn::bf16::bench::run(&opts).map_err(|e| anyhow::anyhow!("bench bf16: {e}"))?;
            serde_json::from_str::<serde_json::Value>(&line)?
        }
        What::Metrics { width, height, runs, threads } => {
            if width < 11 || height < 11 {
                anyhow::bail!("bench metrics: --width and --height must be at least 11 (the SSIM window)");
            }
            mvsplat360_metrics::bench::run_metrics_bench_with(&mvsplat360_metrics::bench::MetricsBenchOpts {
                width,
                height,
                runs,
                threads: threads.count(),
                weights_dir: None,
            })
        }
    };
    println!("{line}");
    Ok(())
}
