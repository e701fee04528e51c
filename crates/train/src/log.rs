//! `log.jsonl` (one [`StepRecord`] per optimizer step) and the loss-curve plot `loss.png`.

use std::io::BufRead;
use std::path::Path;

use crate::error::{Result, TrainError};
use serde::{Deserialize, Serialize};

/// Records of a log file (missing file: none). A torn last line from a kill is skipped.
pub fn read(path: &Path) -> Result<Vec<StepRecord>> {
    let Ok(f) = std::fs::File::open(path) else { return Ok(vec![]) };
    Ok(std::io::BufReader::new(f).lines().map_while(|l| l.ok()).filter_map(|l| serde_json::from_str(&l).ok()).collect())
}

/// Replace the log with `records` (atomically).
pub fn rewrite(path: &Path, records: &[StepRecord]) -> Result<()> {
    let mut text = String::new();
    for r in records {
        text.push_str(&serde_json::to_string(r).unwrap_or_default());
        text.push('\n');
    }
    mvsplat360_dataset::atomic::write_bytes_synced(path, text.as_bytes()).map_err(|e| TrainError::Write { path: path.to_path_buf(), msg: e.to_string() })
}

const FONT_PATHS: &[&str] = &["/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", "/usr/share/fonts/TTF/DejaVuSans.ttf", "/Library/Fonts/Arial.ttf"];

fn register_font() -> bool {
    static DONE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *DONE.get_or_init(|| {
        for p in FONT_PATHS {
            if let Ok(bytes) = std::fs::read(p) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        false
    })
}

/// Loss (and its MSE part) against the step, log-scale y, with a moving average; axis labels when a system
/// font is found.
pub fn plot(records: &[StepRecord], path: &Path) -> Result<()> {
    use plotters::prelude::*;
    if records.is_empty() {
        return Ok(());
    }
    let perr = |e: &dyn std::fmt::Display| TrainError::Write { path: path.to_path_buf(), msg: e.to_string() };
    let labels = register_font();
    let (w, h) = (900u32, 500u32);
    let mut pixels = vec![0u8; 3 * (w * h) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| perr(&e))?;
        let max_step = records.iter().map(|r| r.step).max().unwrap_or(1).max(2) as f64;
        let vals: Vec<f64> = records.iter().flat_map(|r| [r.loss, r.mse]).filter(|v| *v > 0.0 && v.is_finite()).collect();
        let (lo, hi) = vals.iter().fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        let (lo, hi) = if lo < hi { (lo * 0.9, hi * 1.1) } else { (1e-4, 1.0) };
        let mut b = ChartBuilder::on(&root);
        b.margin(15);
        if labels {
            b.caption("training loss", ("sans-serif", 22)).x_label_area_size(40).y_label_area_size(70);
        }
        let mut chart = b.build_cartesian_2d(0f64..max_step, (lo..hi).log_scale()).map_err(|e| perr(&e))?;
        let mut mesh = chart.configure_mesh();
        mesh.x_desc("optimizer step").y_desc("loss").y_label_formatter(&|v| format!("{v:.3}")).x_label_formatter(&|v| format!("{v:.0}"));
        if !labels {
            mesh.disable_x_mesh().disable_y_mesh();
        }
        if labels {
            mesh.draw().map_err(|e| perr(&e))?;
        }
        let smooth = |f: &dyn Fn(&StepRecord) -> f64| -> Vec<(f64, f64)> {
            let k = (records.len() / 20).clamp(1, 100);
            records
                .iter()
                .enumerate()
                .map(|(i, r)| {
                    let w = &records[i.saturating_sub(k)..=i];
                    (r.step as f64, w.iter().map(f).sum::<f64>() / w.len() as f64)
                })
                .collect()
        };
        let raw = records.iter().map(|r| (r.step as f64, r.loss)).filter(|p| p.1 > 0.0);
        chart.draw_series(LineSeries::new(raw, RGBColor(200, 200, 230))).map_err(|e| perr(&e))?;
        let s = chart.draw_series(LineSeries::new(smooth(&|r| r.loss), BLUE.stroke_width(2))).map_err(|e| perr(&e))?;
        if labels {
            s.label("loss (moving mean)").legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE));
        }
        let s = chart.draw_series(LineSeries::new(smooth(&|r| r.mse), RED.stroke_width(2))).map_err(|e| perr(&e))?;
        if labels {
            s.label("MSE (moving mean)").legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED));
            chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(|e| perr(&e))?;
        }
        root.present().map_err(|e| perr(&e))?;
    }
    let img = image::RgbImage::from_raw(w, h, pixels).ok_or_else(|| perr(&"plot buffer size"))?;
    mvsplat360_dataset::atomic::write_atomic(path, |tmp| img.save_with_format(tmp, image::ImageFormat::Png).map_err(std::io::Error::other))
        .map_err(|e| perr(&e))
}

/// One line of `log.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepRecord {
    /// Optimizer steps done (1-based).
    pub step: u64,
    pub loss: f64,
    pub mse: f64,
    #[serde(default)]
    pub lpips: Option<f64>,
    /// Depth-supervision loss (unweighted), on steps whose examples have ground-truth depth.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth: Option<f64>,
    /// Refiner losses (unweighted): v-prediction diffusion loss and 0.01·latent alignment.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diffusion: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alignment: Option<f64>,
    /// Stage `vae`: reconstruction L1 (in [−1, 1]) and KL terms (unweighted); `mse` is then the
    /// reconstruction's MSE in [0, 1].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub l1: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kl: Option<f64>,
    pub lr: f64,
    pub grad_norm: f64,
    /// Wall seconds of this step.
    pub seconds: f64,
}
