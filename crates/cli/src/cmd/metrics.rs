//! `mvsplat360 metrics`: score a folder of predicted images against a folder of ground truths (matched by
//! file name) with the paper's metrics: PSNR↑ SSIM↑ LPIPS↓ DISTS↓ FID↓. Missing network weights leave their
//! column empty ('-' / null) with a warning on stderr; they are not an error.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use mvsplat360_metrics::inception::FidVariant;
use mvsplat360_metrics::score::{score_dirs, write_report_json, Report, ScoreOptions};

#[derive(clap::Args)]
pub struct Args {
    /// Folder of predicted images (.png / .jpg / .jpeg).
    pub pred_dir: PathBuf,
    /// Folder of ground-truth images with the same file names and sizes.
    pub gt_dir: PathBuf,
    /// Print the report as JSON on stdout instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Also write the JSON report to DIR/metrics.json (DIR is created).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Folder with the converted metric weights (searched before $MVSPLAT360_METRIC_WEIGHTS and the default
    /// cache folder; fetch them with scripts/metric-weights/fetch).
    #[arg(long, value_name = "DIR")]
    pub weights_dir: Option<PathBuf>,
    /// Image pairs decoded and run through the networks at once (bounds memory).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..))]
    pub batch_size: u64,
    /// Whose FID: `pytorch-fid` (the paper's: `python -m pytorch_fid`, bilinear resize of the float image, range
    /// [−1, 1]) or `fid-helper` (fid-helper-pytorch's defaults: NVIDIA's resize of the 8-bit image, TF range).
    #[arg(long, default_value = "pytorch-fid")]
    pub fid_variant: FidVariant,
}

/// A cell of the table: the value with `digits` decimals, or '-' when missing.
fn cell(v: Option<f64>, digits: usize) -> String {
    match v {
        Some(x) if x.is_nan() => "-".to_string(),
        Some(x) if x.is_infinite() => if x > 0.0 { "inf" } else { "-inf" }.to_string(),
        Some(x) => format!("{x:.digits$}"),
        None => "-".to_string(),
    }
}

/// The table in the paper's column order.
pub fn table(r: &Report) -> String {
    let head = ["PSNR↑", "SSIM↑", "LPIPS↓", "DISTS↓", "FID↓"];
    let vals = [cell(Some(r.psnr), 2), cell(Some(r.ssim), 4), cell(r.lpips, 4), cell(r.dists, 4), cell(r.fid, 2)];
    let width = |i: usize| head[i].chars().count().max(vals[i].chars().count());
    let line = |cells: &[String]| cells.iter().enumerate().map(|(i, c)| format!("{c:>w$}", w = width(i))).collect::<Vec<_>>().join("  ");
    let head: Vec<String> = head.iter().map(|s| s.to_string()).collect();
    format!("{}\n{}\nimages: {}\n", line(&head), line(&vals), r.per_image.len())
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<()> {
    let bar = if quiet {
        None
    } else {
        let pb = ProgressBar::new(0);
        pb.set_style(
            ProgressStyle::with_template("{msg:>8} [{bar:30}] {pos}/{len} {elapsed_precise} ETA {eta}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        pb.set_message("metrics");
        Some(pb)
    };
    let progress = bar.clone().map(|pb| {
        Arc::new(move |done: usize, total: usize| {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        }) as mvsplat360_metrics::score::ProgressFn
    });
    let opts = ScoreOptions {
        weights_dir: args.weights_dir.clone(),
        batch_size: args.batch_size as usize,
        fid_variant: args.fid_variant,
        progress,
        ..ScoreOptions::default()
    };
    let result = score_dirs(&args.pred_dir, &args.gt_dir, &opts);
    if let Some(pb) = &bar {
        pb.finish_and_clear();
    }
    let report = result.with_context(|| format!("cannot score {} against {}", args.pred_dir.display(), args.gt_dir.display()))?;
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    if let Some(dir) = &args.out {
        let path = write_report_json(dir, &report).with_context(|| format!("cannot write the report into {}", dir.display()))?;
        if !args.json && !quiet {
            eprintln!("wrote {}", path.display());
        }
    }
    let mut stdout = std::io::stdout().lock();
    if args.json {
        serde_json::to_writer_pretty(&mut stdout, &report)?;
        writeln!(stdout)?;
    } else {
        write!(stdout, "{}", table(&report))?;
    }
    Ok(())
}
