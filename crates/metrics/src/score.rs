//! Scoring a folder of predicted images against a folder of ground-truth images, matched by file name, or pairs
//! held in memory ([`score_images`]): the paper's table (PSNR↑ SSIM↑ LPIPS↓ DISTS↓ FID↓).
//!
//! * PSNR ([`crate::psnr`]), SSIM ([`crate::ssim`]), LPIPS-VGG ([`crate::lpips`], the paper's LPIPS) and DISTS
//!   ([`crate::dists`]) are per image pair and averaged over the pairs;
//! * FID is over the whole set: the Fréchet distance ([`crate::frechet`]) between the InceptionV3 pool3
//!   features ([`crate::inception`]) of all predictions and of all ground truths, prepared as pytorch-fid does
//!   unless [`ScoreOptions::fid_variant`] says otherwise.
//!
//! Images are `.png`, `.jpg` or `.jpeg` files (case-insensitive) directly in each folder; other files are
//! ignored. They are decoded to RGB in [0, 1] (grey is expanded, alpha dropped, 16-bit scaled by 65535).
//! A file name present in one folder only, or a pair of different sizes, is an error naming the files;
//! missing network weights are not: the metric is `None` and a warning says what to fetch.

use std::collections::BTreeSet;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use candle_core::{Device, Tensor};
use rayon::prelude::*;
use serde::Serialize;

use crate::dists::Dists;
use crate::inception::{FidInception, FidVariant};
use crate::lpips::{Lpips, Net};
use crate::weights::MetricsWeightsError;
use crate::{psnr, ssim};

/// Name of the report file [`write_report_json`] writes.
pub const REPORT_FILE: &str = "metrics.json";

/// Called after each batch with (pairs done, pairs in all).
pub type ProgressFn = Arc<dyn Fn(usize, usize) + Send + Sync>;

/// How [`score_dirs`] runs.
#[derive(Clone)]
pub struct ScoreOptions {
    /// `--weights-dir`: searched first for the network weights (then `$MVSPLAT360_METRIC_WEIGHTS`, then the
    /// default folder; see [`crate::weights::locate`]).
    pub weights_dir: Option<PathBuf>,
    /// Image pairs decoded and pushed through the networks together (bounds memory).
    pub batch_size: usize,
    /// Compute LPIPS-VGG (when its weights are found).
    pub lpips: bool,
    /// Compute DISTS (when its weights are found).
    pub dists: bool,
    /// Compute FID (when its weights are found).
    pub fid: bool,
    /// Whose input preparation the FID follows (default: pytorch-fid, the paper's).
    pub fid_variant: FidVariant,
    /// Where the networks run.
    pub device: Device,
    /// Progress callback.
    pub progress: Option<ProgressFn>,
}

impl Default for ScoreOptions {
    fn default() -> Self {
        Self { weights_dir: None, batch_size: 4, lpips: true, dists: true, fid: true, fid_variant: FidVariant::default(), device: Device::Cpu, progress: None }
    }
}

impl fmt::Debug for ScoreOptions {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ScoreOptions")
            .field("weights_dir", &self.weights_dir)
            .field("batch_size", &self.batch_size)
            .field("lpips", &self.lpips)
            .field("dists", &self.dists)
            .field("fid", &self.fid)
            .field("fid_variant", &self.fid_variant)
            .field("device", &self.device)
            .field("progress", &self.progress.is_some())
            .finish()
    }
}

/// One image pair's scores.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PerImage {
    /// The file name (same in both folders).
    pub name: String,
    pub psnr: f64,
    pub ssim: f64,
    /// LPIPS-VGG; None without its weights.
    pub lpips: Option<f64>,
}

/// The scores of a folder pair. Serialises to
/// `{"psnr","ssim","lpips","dists","fid","fid_variant","per_image":[{"name","psnr","ssim","lpips"}]}` (missing metrics as
/// `null`; an infinite PSNR — identical images — also becomes `null`, JSON having no infinity).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Mean PSNR over the pairs (dB).
    pub psnr: f64,
    /// Mean SSIM over the pairs.
    pub ssim: f64,
    /// Mean LPIPS-VGG over the pairs.
    pub lpips: Option<f64>,
    /// Mean DISTS over the pairs.
    pub dists: Option<f64>,
    /// FID between the two sets (None without weights or with fewer than 2 images).
    pub fid: Option<f64>,
    /// Whose input preparation the FID followed.
    pub fid_variant: FidVariant,
    /// Per pair, sorted by name.
    pub per_image: Vec<PerImage>,
    /// What was skipped and why (not serialised).
    #[serde(skip)]
    pub warnings: Vec<String>,
}

/// Why a folder pair could not be scored.
#[derive(Debug, thiserror::Error)]
pub enum ScoreError {
    #[error("cannot read folder {}: {source}", path.display())]
    ReadDir { path: PathBuf, source: std::io::Error },
    #[error("no images (.png, .jpg, .jpeg) in {}", .0.display())]
    Empty(PathBuf),
    #[error("{}", mismatch_message(pred, gt, only_pred, only_gt))]
    Mismatch { pred: PathBuf, gt: PathBuf, only_pred: Vec<String>, only_gt: Vec<String> },
    #[error("`{name}` is {}×{} in {} but {}×{} in {} (width×height)", pred_size.0, pred_size.1, pred.display(), gt_size.0, gt_size.1, gt.display())]
    SizeMismatch { name: String, pred: PathBuf, gt: PathBuf, pred_size: (u32, u32), gt_size: (u32, u32) },
    #[error("`{name}`: the prediction is {}×{} but the ground truth {}×{} (width×height)", pred_size.0, pred_size.1, gt_size.0, gt_size.1)]
    PairSize { name: String, pred_size: (usize, usize), gt_size: (usize, usize) },
    #[error("`{name}` is {w}×{h}: SSIM needs at least {min}×{min} pixels", min = ssim::WIN_SIZE)]
    TooSmall { name: String, w: u32, h: u32 },
    #[error("cannot read image {}: {msg}", path.display())]
    Image { path: PathBuf, msg: String },
    #[error(transparent)]
    Weights(MetricsWeightsError),
    #[error("computing {metric}: {source}")]
    Compute { metric: &'static str, source: candle_core::Error },
}

fn list_names(names: &[String], max: usize) -> String {
    let mut s = names.iter().take(max).map(|n| format!("`{n}`")).collect::<Vec<_>>().join(", ");
    if names.len() > max {
        s.push_str(&format!(" and {} more", names.len() - max));
    }
    s
}

fn mismatch_message(pred: &Path, gt: &Path, only_pred: &[String], only_gt: &[String]) -> String {
    let mut parts = Vec::new();
    if !only_pred.is_empty() {
        parts.push(format!("{} file(s) only in {} (predictions): {}", only_pred.len(), pred.display(), list_names(only_pred, 10)));
    }
    if !only_gt.is_empty() {
        parts.push(format!("{} file(s) only in {} (ground truth): {}", only_gt.len(), gt.display(), list_names(only_gt, 10)));
    }
    format!("the folders' image names do not match: {}", parts.join("; "))
}

/// Whether a file name has an image extension the scorer reads.
pub fn is_image_name(name: &str) -> bool {
    let lower = name.to_ascii_lowercase();
    [".png", ".jpg", ".jpeg"].iter().any(|e| lower.ends_with(e) && lower.len() > e.len())
}

/// The image file names directly in `dir`, sorted.
fn image_names(dir: &Path) -> Result<BTreeSet<String>, ScoreError> {
    let err = |source| ScoreError::ReadDir { path: dir.to_path_buf(), source };
    let mut out = BTreeSet::new();
    for entry in std::fs::read_dir(dir).map_err(err)? {
        let entry = entry.map_err(err)?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if is_image_name(&name) && entry.path().is_file() {
            out.insert(name);
        }
    }
    Ok(out)
}

/// The matched file names of the two folders (sorted), or the error naming the unmatched ones.
pub fn match_names(pred: &Path, gt: &Path) -> Result<Vec<String>, ScoreError> {
    let p = image_names(pred)?;
    let g = image_names(gt)?;
    let only_pred: Vec<String> = p.difference(&g).cloned().collect();
    let only_gt: Vec<String> = g.difference(&p).cloned().collect();
    if !only_pred.is_empty() || !only_gt.is_empty() {
        return Err(ScoreError::Mismatch { pred: pred.to_path_buf(), gt: gt.to_path_buf(), only_pred, only_gt });
    }
    if p.is_empty() {
        return Err(ScoreError::Empty(pred.to_path_buf()));
    }
    Ok(p.into_iter().collect())
}

/// An RGB image as (3, H, W) f32 in [0, 1].
#[derive(Debug, Clone)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    /// Channel-first, row-major.
    pub data: Vec<f32>,
}

/// Decode an image file (format from its content) to (3, H, W) in [0, 1].
pub fn load_rgb(path: &Path) -> Result<RgbImage, ScoreError> {
    let err = |msg: String| ScoreError::Image { path: path.to_path_buf(), msg };
    let img = image::ImageReader::open(path)
        .map_err(|e| err(e.to_string()))?
        .with_guessed_format()
        .map_err(|e| err(e.to_string()))?
        .decode()
        .map_err(|e| err(e.to_string()))?;
    let rgb = img.to_rgb32f();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    let plane = w * h;
    let mut data = vec![0.0f32; 3 * plane];
    for (i, px) in rgb.as_raw().chunks_exact(3).enumerate() {
        data[i] = px[0];
        data[plane + i] = px[1];
        data[2 * plane + i] = px[2];
    }
    Ok(RgbImage { width: w, height: h, data })
}

fn dims(path: &Path) -> Result<(u32, u32), ScoreError> {
    image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| ScoreError::Image { path: path.to_path_buf(), msg: e.to_string() })?
        .into_dimensions()
        .map_err(|e| ScoreError::Image { path: path.to_path_buf(), msg: e.to_string() })
}

/// A network that is loaded, or the warning why not (missing weights); other load failures are errors.
fn load_net<T>(what: &str, r: Result<T, MetricsWeightsError>, warnings: &mut Vec<String>) -> Result<Option<T>, ScoreError> {
    match r {
        Ok(n) => Ok(Some(n)),
        Err(e @ MetricsWeightsError::Missing { .. }) => {
            warnings.push(format!("{what} skipped (null): {e}"));
            Ok(None)
        }
        Err(e) => Err(ScoreError::Weights(e)),
    }
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n as f64
}

/// Score the predictions in `pred` against the ground truths in `gt` (see the module docs).
pub fn score_dirs(pred: &Path, gt: &Path, opts: &ScoreOptions) -> Result<Report, ScoreError> {
    let names = match_names(pred, gt)?;
    // Sizes first (headers only): a mismatch fails before any heavy work.
    names
        .par_iter()
        .map(|n| {
            let (pp, gp) = (pred.join(n), gt.join(n));
            let (ps, gs) = (dims(&pp)?, dims(&gp)?);
            if ps != gs {
                return Err(ScoreError::SizeMismatch { name: n.clone(), pred: pp, gt: gp, pred_size: ps, gt_size: gs });
            }
            check_size(n, ps.0 as usize, ps.1 as usize)
        })
        .collect::<Result<Vec<()>, _>>()?;
    let mut scorer = Scorer::new(opts)?;
    let total = names.len();
    for chunk in names.chunks(opts.batch_size.max(1)) {
        let pairs = chunk.par_iter().map(|n| Ok((n.clone(), load_rgb(&pred.join(n))?, load_rgb(&gt.join(n))?))).collect::<Result<Vec<_>, ScoreError>>()?;
        scorer.add(&pairs)?;
        if let Some(cb) = &opts.progress {
            cb(scorer.per_image.len(), total);
        }
    }
    Ok(scorer.finish())
}

/// Score image pairs held in memory, `(name, prediction, ground truth)`, as [`score_dirs`] scores files (no
/// 8-bit rounding: what a caller renders is scored as it is).
pub fn score_images(pairs: &[(String, RgbImage, RgbImage)], opts: &ScoreOptions) -> Result<Report, ScoreError> {
    for (n, p, g) in pairs {
        if (p.width, p.height) != (g.width, g.height) || p.data.len() != 3 * p.width * p.height || g.data.len() != 3 * g.width * g.height {
            return Err(ScoreError::PairSize { name: n.clone(), pred_size: (p.width, p.height), gt_size: (g.width, g.height) });
        }
        check_size(n, p.width, p.height)?;
    }
    let mut scorer = Scorer::new(opts)?;
    for chunk in pairs.chunks(opts.batch_size.max(1)) {
        scorer.add(chunk)?;
        if let Some(cb) = &opts.progress {
            cb(scorer.per_image.len(), pairs.len());
        }
    }
    Ok(scorer.finish())
}

fn check_size(name: &str, w: usize, h: usize) -> Result<(), ScoreError> {
    if w < ssim::WIN_SIZE || h < ssim::WIN_SIZE {
        return Err(ScoreError::TooSmall { name: name.to_string(), w: w as u32, h: h as u32 });
    }
    Ok(())
}

/// The metric networks of one scoring run and the scores gathered so far.
struct Scorer {
    lpips: Option<Lpips>,
    dists: Option<Dists>,
    inception: Option<FidInception>,
    fid_variant: FidVariant,
    device: Device,
    per_image: Vec<PerImage>,
    dists_vals: Vec<f64>,
    feats_pred: Vec<f64>,
    feats_gt: Vec<f64>,
    warnings: Vec<String>,
}

impl Scorer {
    fn new(opts: &ScoreOptions) -> Result<Self, ScoreError> {
        let mut warnings = Vec::new();
        let wd = opts.weights_dir.as_deref();
        let dev = &opts.device;
        let lpips = if opts.lpips { load_net("LPIPS", Lpips::load(wd, Net::Vgg, dev), &mut warnings)? } else { None };
        let dists = if opts.dists { load_net("DISTS", Dists::load(wd, dev), &mut warnings)? } else { None };
        let inception = if opts.fid { load_net("FID", FidInception::load(wd, dev).map(|n| n.with_variant(opts.fid_variant)), &mut warnings)? } else { None };
        Ok(Self {
            lpips,
            dists,
            inception,
            fid_variant: opts.fid_variant,
            device: dev.clone(),
            per_image: Vec::new(),
            dists_vals: Vec::new(),
            feats_pred: Vec::new(),
            feats_gt: Vec::new(),
            warnings,
        })
    }

    /// Score a batch of pairs whose sizes are checked.
    fn add(&mut self, pairs: &[(String, RgbImage, RgbImage)]) -> Result<(), ScoreError> {
        let dev = &self.device;
        let closed: Vec<(f64, f64)> = pairs
            .par_iter()
            .map(|(_, p, g)| {
                let s = ssim::ssim(&p.data, &g.data, 3, p.height, p.width).expect("sizes checked above");
                (psnr::psnr(&p.data, &g.data), s)
            })
            .collect();
        let mut lp: Vec<Option<f64>> = vec![None; pairs.len()];
        // Runs of equal-sized pairs go through the networks as one (m, 3, H, W) batch.
        let mut start = 0;
        while start < pairs.len() {
            let (w, h) = (pairs[start].1.width, pairs[start].1.height);
            let mut end = start + 1;
            while end < pairs.len() && pairs[end].1.width == w && pairs[end].1.height == h {
                end += 1;
            }
            let run = &pairs[start..end];
            if self.lpips.is_some() || self.dists.is_some() || self.inception.is_some() {
                let stack = |which: usize| -> candle_core::Result<Tensor> {
                    let mut v = Vec::with_capacity(run.len() * 3 * w * h);
                    for (_, p, g) in run {
                        v.extend_from_slice(if which == 0 { &p.data } else { &g.data });
                    }
                    Tensor::from_vec(v, (run.len(), 3, h, w), dev)
                };
                let compute = |metric: &'static str| move |source: candle_core::Error| ScoreError::Compute { metric, source };
                let tp = stack(0).map_err(compute("image batch"))?;
                let tg = stack(1).map_err(compute("image batch"))?;
                if let Some(net) = &self.lpips {
                    let d = net.distance(&tp, &tg).map_err(compute("LPIPS"))?;
                    for (k, v) in d.into_iter().enumerate() {
                        lp[start + k] = Some(v as f64);
                    }
                }
                if let Some(net) = &self.dists {
                    let d = net.distance(&tp, &tg).map_err(compute("DISTS"))?;
                    self.dists_vals.extend(d.into_iter().map(f64::from));
                }
                if let Some(net) = &self.inception {
                    let fp = net.features(&tp).and_then(|f| f.flatten_all()?.to_vec1::<f32>()).map_err(compute("FID features"))?;
                    let fg = net.features(&tg).and_then(|f| f.flatten_all()?.to_vec1::<f32>()).map_err(compute("FID features"))?;
                    self.feats_pred.extend(fp.into_iter().map(f64::from));
                    self.feats_gt.extend(fg.into_iter().map(f64::from));
                }
            }
            start = end;
        }
        for (((n, _, _), (p, s)), l) in pairs.iter().zip(closed).zip(lp) {
            self.per_image.push(PerImage { name: n.clone(), psnr: p, ssim: s, lpips: l });
        }
        Ok(())
    }

    fn finish(mut self) -> Report {
        let per_image = self.per_image;
        let total = per_image.len();
        let infinite = per_image.iter().filter(|p| p.psnr.is_infinite()).count();
        if infinite > 0 {
            self.warnings.push(format!("{infinite} pair(s) are identical: their PSNR is +inf (null in JSON), and so is the mean PSNR"));
        }
        let fid = match &self.inception {
            Some(_) if total < 2 => {
                self.warnings.push(format!("FID skipped (null): it needs at least 2 images per folder, got {total}"));
                None
            }
            Some(_) => {
                let d = crate::inception::DIM;
                crate::frechet::frechet_from_features(&self.feats_pred, total, &self.feats_gt, total, d)
            }
            None => None,
        };
        Report {
            psnr: mean(per_image.iter().map(|p| p.psnr)),
            ssim: mean(per_image.iter().map(|p| p.ssim)),
            lpips: self.lpips.as_ref().map(|_| mean(per_image.iter().map(|p| p.lpips.unwrap_or(f64::NAN)))),
            dists: self.dists.as_ref().map(|_| mean(self.dists_vals.iter().copied())),
            fid,
            fid_variant: self.fid_variant,
            per_image,
            warnings: self.warnings,
        }
    }
}

/// Write `report` as `dir/metrics.json` (pretty JSON), atomically: a temporary file in `dir`, then a rename.
/// Creates `dir`. Returns the file's path.
pub fn write_report_json(dir: &Path, report: &Report) -> std::io::Result<PathBuf> {
    std::fs::create_dir_all(dir)?;
    let path = dir.join(REPORT_FILE);
    let mut text = serde_json::to_string_pretty(report).map_err(std::io::Error::other)?;
    text.push('\n');
    mvsplat360_dataset::atomic::write_bytes_synced(&path, text.as_bytes()).map(|()| path)
}
