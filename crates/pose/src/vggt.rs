//! A folder of a few photos → a posed scene folder by the VGGT model (`mvsplat360-vggt`; no model code here):
//! one forward pass gives every photo's camera and a depth map with its confidence, where COLMAP needs overlap
//! that five photos far apart do not have.
//!
//! The scene folder has the layout COLMAP's path writes, so every scene reader takes it as it is:
//! - `images/`: each photo as decoded (no EXIF rotation, as upstream's loader; an RGBA PNG composited on white,
//!   as the model saw it), its long side scaled down to `max_size` (never up), written as PNG;
//! - `sparse/0`: one PINHOLE camera per image, the images with their poses, and `points3D` unprojected from the
//!   confident depth (as upstream's `demo_colmap.py` without tracks: each point observed by the image it came
//!   from);
//! - `pose.json` ([`VggtPoseReport`]): what ran, on what, with which weights, and the raw predictions.
//!
//! Cameras are upstream's: `pose_encoding_to_extri_intri` of the last camera-head iteration, world → camera in
//! OpenCV axes, inverted to camera → world. The first camera is kept as predicted (VGGT's reference frame, near
//! the identity), not forced to it. The world is VGGT's normalised one (mean point distance ≈ 1); `render`'s
//! scene scale `auto` makes it the model's. The intrinsics are mapped from the model's frame back to each
//! photo's pixel grid (`ViewGeometry::intrinsics_to_original`: crop offset, resize factors) and then scaled to
//! the kept image, in corner-origin pixels (the principal point of a centred camera at `(W/2, H/2)`, COLMAP's
//! convention).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device};
use mvsplat360_vggt::utils::load_fn::{self, LoadError, PreprocessMode, Preprocessed, ViewGeometry};
use mvsplat360_vggt::utils::pose_enc::{pose_encoding_to_extri_intri, VggtCamera};
use mvsplat360_vggt::weights::{self as vggt_weights, VggtError, VggtSource};
use mvsplat360_vggt::VggtConfig;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::colmap_writer::{self, PinholeCamera, Point2D, Point3D, PosedImage, TrackElement};
use crate::error::PoseError;
use crate::{photos, InputKind, Progress};

pub use mvsplat360_vggt::weights::WEIGHTS_HELP;

/// VGGT needs at least two views to relate cameras (MVSplat360 itself takes five context views).
pub const MIN_PHOTOS: usize = 2;
/// `--engine auto` sends a photo folder with fewer photos than this to VGGT (when weights are given): few
/// photos are where COLMAP fails, and VGGT's global attention grows with the square of the photos.
pub const AUTO_MAX_PHOTOS: usize = 20;
/// Depth confidence a pixel needs to become a 3D point (upstream `demo_colmap.py`'s `conf_thres_value`).
pub const CONFIDENCE_THRESHOLD: f32 = 5.0;
/// When fewer than this share of the pixels reach [`CONFIDENCE_THRESHOLD`] (an untrained or unsure model),
/// the most confident [`FALLBACK_SHARE`] are kept instead, so the model still has points.
pub const MIN_PASSING_SHARE: f64 = 0.01;
pub const FALLBACK_SHARE: f64 = 0.10;
/// At most this many points (upstream's demo: 100 000), subsampled evenly in pixel order (deterministic).
pub const MAX_POINTS: usize = 100_000;

/// Notes written into every VGGT `pose.json`.
pub const NOTES: [&str; 4] = [
    "first camera as predicted (VGGT's reference frame, not forced to the identity)",
    "world in VGGT's normalised units (scene scale `auto` applies in render)",
    "photos decoded as stored: no EXIF rotation (as upstream's load_and_preprocess_images)",
    "views in file-name order; the first is VGGT's reference view",
];

#[derive(Debug, Clone, PartialEq)]
pub struct VggtPoseOptions {
    /// A VGGT model folder (`config.json` + `model.safetensors`/`model.pt`) or a bare weights file (VGGT-1B).
    pub weights: PathBuf,
    /// Long side, in pixels, of the images the scene keeps (never scaled up); the model always sees 518 wide.
    pub max_size: u32,
    /// Upstream's preprocessing mode (`crop`, upstream's default, is what `pose` uses).
    pub mode: PreprocessMode,
    /// VGGT's precision (`--encoder-dtype`): F32, or BF16 (the aggregator's linears and the DPT heads'
    /// products on weights packed in bf16 where the CPU has AVX512-BF16; `Vggt::with_trunk_dtype`). The camera
    /// head stays f32.
    pub dtype: DType,
}

impl VggtPoseOptions {
    pub fn new(weights: impl Into<PathBuf>, max_size: u32) -> Self {
        Self { weights: weights.into(), max_size, mode: PreprocessMode::Crop, dtype: DType::F32 }
    }
}

/// `pose.json` of a scene posed by VGGT.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VggtPoseReport {
    /// `"vggt"` (a COLMAP `pose.json` has no `engine` key).
    pub engine: String,
    pub input: String,
    pub input_kind: InputKind,
    /// SHA-256 of the photos' names and bytes, the weights' SHA-256, the model config and the settings: the
    /// scene is reused only while it matches.
    pub fingerprint: String,
    pub settings: VggtSettings,
    pub weights: WeightsRecord,
    /// The size the model saw (every view, after upstream's preprocessing).
    pub model_input: ModelInput,
    pub images_total: usize,
    pub views: Vec<ViewRecord>,
    pub points: PointsRecord,
    /// The scene's COLMAP model, relative to the scene folder.
    pub model_folder: String,
    pub seconds: VggtSeconds,
    pub notes: Vec<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VggtSettings {
    pub max_size: u32,
    /// Upstream's `load_and_preprocess_images` mode.
    pub preprocessing: String,
    pub device: String,
    pub dtype: String,
    pub confidence_threshold: f32,
    pub max_points: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WeightsRecord {
    pub path: String,
    pub sha256: String,
    /// The model folder's `config.json` (None: a bare file, read as VGGT-1B).
    pub config_path: Option<String>,
    /// The model's shape.
    pub config: VggtConfig,
    /// Keys in the file not loaded (`track_head.*`: point tracking is not used).
    pub skipped_keys: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ModelInput {
    pub width: usize,
    pub height: usize,
    pub frames: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewRecord {
    /// The file in `images/`.
    pub file: String,
    /// The photo it came from (a name in the input folder).
    pub source: String,
    /// The decoded photo's (width, height).
    pub original_size: (u32, u32),
    /// The kept image's (width, height).
    pub kept_size: (u32, u32),
    /// Where the photo went in the model's frame: its resized size and the resized image's corner (negative:
    /// cropped).
    pub model_resized: (u32, u32),
    pub model_offset: (i64, i64),
    /// Mean depth confidence over the view's own pixels (padding excluded).
    pub mean_depth_confidence: f64,
    /// The last camera-head iteration, as predicted: `(tx, ty, tz, qx, qy, qz, qw, fov_h, fov_w)`.
    pub pose_encoding: [f32; 9],
    /// PINHOLE intrinsics of the kept image, pixels: `[fx, fy, cx, cy]`.
    pub intrinsics: [f64; 4],
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointsRecord {
    pub count: usize,
    /// The views' own pixels with a finite positive depth (the candidates).
    pub candidates: usize,
    /// Candidates with confidence ≥ the threshold.
    pub confident: usize,
    /// How points were chosen: `"confidence >= 5"` or `"most confident 10 %"` (when fewer than 1 % pass).
    pub selection: String,
    /// The lowest confidence among the kept points.
    pub min_confidence: Option<f32>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct VggtSeconds {
    /// Per stage, in the order run.
    pub stages: Vec<(String, f64)>,
    pub total: f64,
}

/// The engine that posed a scene folder (`"colmap"` or `"vggt"`) and its fingerprint, from its `pose.json`
/// (a COLMAP report has no `engine` key).
pub fn read_engine(scene: &Path) -> Option<(String, String)> {
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(scene.join("pose.json")).ok()?).ok()?;
    let engine = v.get("engine").and_then(|e| e.as_str()).unwrap_or("colmap").to_string();
    Some((engine, v.get("fingerprint")?.as_str()?.to_string()))
}

/// The `pose.json` of a scene posed by VGGT, if `scene` has one.
pub fn read_report(scene: &Path) -> Option<VggtPoseReport> {
    let r: VggtPoseReport = serde_json::from_str(&std::fs::read_to_string(scene.join("pose.json")).ok()?).ok()?;
    (r.engine == "vggt").then_some(r)
}

/// A `VggtError` as a `PoseError`; the strict loader's lists are cut to their first keys (a config of another
/// width mismatches nearly every key).
fn weights_error(e: VggtError) -> PoseError {
    const SHOWN: usize = 8;
    let msg = match e {
        VggtError::Weights(mvsplat360_dataset::weights::WeightsError::Strict { path, missing, unexpected, mismatched }) => {
            let list = |title: &str, keys: &[String]| -> String {
                if keys.is_empty() {
                    return String::new();
                }
                let more = if keys.len() > SHOWN { format!(" … ({} more)", keys.len() - SHOWN) } else { String::new() };
                format!("\n  {title} ({}): {}{more}", keys.len(), keys[..keys.len().min(SHOWN)].join(", "))
            };
            let shapes: String =
                mismatched.iter().take(SHOWN).map(|(k, want, got)| format!("\n  shape mismatch `{k}`: model expects {want:?}, file has {got:?}")).collect();
            let more = if mismatched.len() > SHOWN { format!("\n  … and {} more mis-shaped keys", mismatched.len() - SHOWN) } else { String::new() };
            format!(
                "{}: VGGT weights do not match the model its config describes (is config.json the one these weights were saved with?):{}{}{shapes}{more}",
                path.display(),
                list("missing", &missing),
                list("unexpected", &unexpected)
            )
        }
        other => other.to_string(),
    };
    PoseError::Vggt(msg)
}

fn load_error(e: LoadError) -> PoseError {
    match e {
        LoadError::Decode { path, msg } => {
            PoseError::Input { path, msg: format!("cannot decode this photo ({msg}); remove it or replace it with a readable JPEG/PNG") }
        }
        LoadError::Read { path, source } => PoseError::Io { path, source },
        // Names the photo and what to do.
        other => PoseError::Vggt(other.to_string()),
    }
}

/// The photos of `dir` and the model source, checked (the errors every run gives before any work).
fn check_inputs(dir: &Path, opts: &VggtPoseOptions, progress: &dyn Progress) -> Result<(Vec<PathBuf>, VggtSource), PoseError> {
    if !dir.is_dir() {
        return Err(if dir.is_file() {
            PoseError::input(dir, "VGGT poses a folder of photos, not a video; give the folder (a video goes to COLMAP: --engine colmap or auto)")
        } else {
            PoseError::input(dir, "no such folder")
        });
    }
    let (photos, others) = photos::list(dir)?;
    if photos.len() < MIN_PHOTOS {
        let also = photos::others_suffix(&others);
        return Err(PoseError::input(
            dir,
            format!(
                "holds {} photo(s) (.jpg, .jpeg, .png){also}; VGGT needs at least {MIN_PHOTOS} views of the scene, and MVSplat360 takes 5 context views: give 5 or more photos",
                photos.len()
            ),
        ));
    }
    photos::note_ignored(dir, &others, progress);
    let src = VggtSource::resolve(&opts.weights).map_err(weights_error)?;
    Ok((photos, src))
}

fn hash_file(h: &mut Sha256, p: &Path) -> Result<(), PoseError> {
    let mut f = std::fs::File::open(p).map_err(|e| PoseError::io(p, e))?;
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(|e| PoseError::io(p, e))?;
        if n == 0 {
            return Ok(());
        }
        h.update(&buf[..n]);
    }
}

fn fingerprint_of(photos: &[PathBuf], src: &VggtSource, weights_sha: &str, opts: &VggtPoseOptions) -> Result<String, PoseError> {
    let mut h = Sha256::new();
    h.update(format!("pose vggt 1|max {}|mode {}|cpu {}|conf {CONFIDENCE_THRESHOLD}|points {MAX_POINTS}\n", opts.max_size, opts.mode, opts.dtype.as_str()));
    h.update(weights_sha);
    h.update(serde_json::to_string(&src.config).unwrap_or_default());
    h.update([0u8]);
    for p in photos {
        h.update(p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default());
        h.update([0u8]);
        hash_file(&mut h, p)?;
    }
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

/// The fingerprint `pose_vggt` gives this folder with these options (hashes the weights file: seconds for
/// VGGT-1B).
pub fn fingerprint(dir: &Path, opts: &VggtPoseOptions) -> Result<String, PoseError> {
    let (photos, src) = check_inputs(dir, opts, &crate::NoProgress)?;
    let sha = mvsplat360_dataset::atomic::sha256_file(&src.weights).map_err(|e| PoseError::io(&src.weights, e))?;
    fingerprint_of(&photos, &src, &sha, opts)
}

/// The size a `w × h` photo is kept at: long side at most `max_size`, never scaled up.
pub fn kept_size(w: u32, h: u32, max_size: u32) -> (u32, u32) {
    if w.max(h) > max_size {
        let s = max_size as f64 / w.max(h) as f64;
        (((w as f64 * s).round() as u32).max(1), ((h as f64 * s).round() as u32).max(1))
    } else {
        (w, h)
    }
}

/// One view's camera in every frame it is needed in.
struct ViewCamera {
    vggt: VggtCamera,
    c2w: [[f64; 4]; 4],
    kept: (u32, u32),
    /// `[fx, fy, cx, cy]` of the kept image.
    kept_k: [f64; 4],
}

fn view_camera(enc: &[f32; 9], g: &ViewGeometry, h: usize, w: usize, max_size: u32, file: &Path) -> Result<ViewCamera, PoseError> {
    let vggt = pose_encoding_to_extri_intri(enc, h, w);
    let k = g.intrinsics_to_original(&vggt.intrinsic);
    let kept = kept_size(g.original.0, g.original.1, max_size);
    let (sx, sy) = (kept.0 as f64 / g.original.0 as f64, kept.1 as f64 / g.original.1 as f64);
    let kept_k = [k[0][0] * sx, k[1][1] * sy, k[0][2] * sx, k[1][2] * sy];
    let fov_ok = enc[7..].iter().all(|f| *f > 0.0 && (*f as f64) < std::f64::consts::PI);
    if !fov_ok || kept_k.iter().any(|v| !v.is_finite()) || kept_k[0] <= 0.0 || kept_k[1] <= 0.0 || enc.iter().any(|v| !v.is_finite()) {
        return Err(PoseError::Vggt(format!(
            "{}: VGGT predicted no usable camera for this photo (pose encoding {enc:?}: fields of view {} and {} rad, a pinhole camera's lie strictly between 0 and π); are these the right weights?",
            file.display(),
            enc[7],
            enc[8]
        )));
    }
    Ok(ViewCamera { vggt, c2w: vggt.cam_to_world(), kept, kept_k })
}

/// The pixels of view `s` that show its photo (not the white padding of a batch of mixed shapes), as model-frame
/// row and column ranges.
fn own_region(g: &ViewGeometry, h: usize, w: usize) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
    let clamp = |lo: i64, len: u32, max: usize| -> std::ops::Range<usize> {
        let a = lo.clamp(0, max as i64) as usize;
        let b = (lo + len as i64).clamp(0, max as i64) as usize;
        a..b
    };
    (clamp(g.offset.1, g.resized.1, h), clamp(g.offset.0, g.resized.0, w))
}

/// A chosen pixel: view, row, column (model frame).
#[derive(Clone, Copy)]
struct Pixel {
    s: usize,
    y: usize,
    x: usize,
}

struct Selection {
    pixels: Vec<Pixel>,
    candidates: usize,
    confident: usize,
    fallback: bool,
    min_confidence: Option<f32>,
}

/// Upstream's demo rule: depth confidence ≥ 5; when fewer than 1 % of the candidates pass, the most confident
/// 10 % (ties broken by pixel order); then at most [`MAX_POINTS`], evenly spaced in pixel order.
fn select_points(pre: &Preprocessed, depth: &[f32], conf: &[f32]) -> Selection {
    let (h, w) = (pre.height, pre.width);
    let mut cand: Vec<(u32, f32)> = vec![];
    for (s, g) in pre.views.iter().enumerate() {
        let (rows, cols) = own_region(g, h, w);
        for y in rows {
            for x in cols.clone() {
                let i = (s * h + y) * w + x;
                if depth[i].is_finite() && depth[i] > 0.0 && conf[i].is_finite() {
                    cand.push((i as u32, conf[i]));
                }
            }
        }
    }
    let candidates = cand.len();
    let confident = cand.iter().filter(|c| c.1 >= CONFIDENCE_THRESHOLD).count();
    let fallback = (confident as f64) < MIN_PASSING_SHARE * candidates as f64;
    let mut kept: Vec<(u32, f32)> = if fallback {
        let k = ((FALLBACK_SHARE * candidates as f64).ceil() as usize).min(candidates);
        let mut c = cand;
        c.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        c.truncate(k);
        c.sort_by_key(|c| c.0);
        c
    } else {
        cand.into_iter().filter(|c| c.1 >= CONFIDENCE_THRESHOLD).collect()
    };
    if kept.len() > MAX_POINTS {
        let m = kept.len();
        kept = (0..MAX_POINTS).map(|k| kept[k * m / MAX_POINTS]).collect();
    }
    let min_confidence = kept.iter().map(|c| c.1).min_by(|a, b| a.total_cmp(b));
    let pixels = kept
        .iter()
        .map(|&(i, _)| {
            let i = i as usize;
            Pixel { s: i / (h * w), y: (i / w) % h, x: i % w }
        })
        .collect();
    Selection { pixels, candidates, confident, fallback, min_confidence }
}

/// Poses the photos of `dir` with VGGT into the new scene folder `out`. Every input is checked before anything
/// is written (photos, weights, their shape); the work happens in a hidden folder beside `out`, renamed into
/// place whole. An `out` that exists is reused when its `pose.json` has this fingerprint, and refused otherwise.
pub fn pose_vggt(dir: &Path, out: &Path, opts: &VggtPoseOptions, progress: &dyn Progress) -> Result<VggtPoseReport, PoseError> {
    let t0 = Instant::now();
    let mut stages: Vec<(String, f64)> = vec![];
    let (photos, src) = check_inputs(dir, opts, progress)?;

    let t = Instant::now();
    progress.begin("fingerprint", 0);
    let weights_sha = mvsplat360_dataset::atomic::sha256_file(&src.weights).map_err(|e| PoseError::io(&src.weights, e));
    progress.end();
    let weights_sha = weights_sha?;
    let fp = fingerprint_of(&photos, &src, &weights_sha, opts)?;
    stages.push(("fingerprint".into(), t.elapsed().as_secs_f64()));
    let _lock = crate::lock_out(out)?;
    if out.exists() {
        return match read_report(out) {
            Some(r) if r.fingerprint == fp => {
                progress.note(&format!("{} is already posed by VGGT from this input ({} images); reusing it", out.display(), r.images_total));
                Ok(r)
            }
            _ => Err(PoseError::input(
                out,
                "already exists and was not posed by VGGT from this input with these weights and settings; choose another --out or delete it",
            )),
        };
    }

    // Preprocessing first: a photo that does not decode is found before the weights are read.
    let t = Instant::now();
    progress.begin("preprocess", 0);
    let pre = load_fn::load_and_preprocess_images(&photos, opts.mode).map_err(load_error);
    progress.end();
    let pre = pre?;
    stages.push(("preprocess".into(), t.elapsed().as_secs_f64()));

    let t = Instant::now();
    progress.begin("load", 0);
    if !matches!(opts.dtype, DType::F32 | DType::BF16) {
        return Err(PoseError::Vggt(format!("VGGT runs on the CPU in f32 or bf16, not {:?}", opts.dtype)));
    }
    let loaded = vggt_weights::load_source(&src, &Device::Cpu, opts.dtype).map_err(weights_error);
    progress.end();
    let (model, load_report) = loaded?;
    if !src.config.enable_camera || !src.config.enable_depth {
        return Err(PoseError::Vggt(format!(
            "{}: this VGGT config has enable_camera = {}, enable_depth = {}; posing needs the camera and the depth heads",
            src.config_path.as_deref().unwrap_or(&src.weights).display(),
            src.config.enable_camera,
            src.config.enable_depth
        )));
    }
    stages.push(("load".into(), t.elapsed().as_secs_f64()));

    let t = Instant::now();
    progress.begin("forward", 0);
    let fwd = forward(&model, &pre);
    progress.end();
    let (encs, depth, conf) = fwd?;
    drop(model);
    stages.push(("forward".into(), t.elapsed().as_secs_f64()));

    let (h, w) = (pre.height, pre.width);
    let cams = pre.views.iter().zip(&encs).zip(&photos).map(|((g, e), p)| view_camera(e, g, h, w, opts.max_size, p)).collect::<Result<Vec<_>, _>>()?;

    let t = Instant::now();
    let work = crate::work_dir(out, &fp);
    // Nothing of an interrupted VGGT run is worth keeping: start clean.
    crate::remove_if_exists(&work)?;
    std::fs::create_dir_all(&work).map_err(|e| PoseError::io(&work, e))?;
    let res = write_scene(&work, &photos, &pre, &cams, &encs, &depth, &conf, progress);
    let report = match res {
        Ok(parts) => {
            stages.push(("write".into(), t.elapsed().as_secs_f64()));
            let (views, points) = parts;
            let report = VggtPoseReport {
                engine: "vggt".into(),
                input: dir.display().to_string(),
                input_kind: InputKind::Photos,
                fingerprint: fp,
                settings: VggtSettings {
                    max_size: opts.max_size,
                    preprocessing: opts.mode.to_string(),
                    device: "cpu".into(),
                    dtype: opts.dtype.as_str().into(),
                    confidence_threshold: CONFIDENCE_THRESHOLD,
                    max_points: MAX_POINTS,
                },
                weights: WeightsRecord {
                    path: std::fs::canonicalize(&src.weights).unwrap_or_else(|_| src.weights.clone()).display().to_string(),
                    sha256: weights_sha,
                    config_path: src.config_path.as_ref().map(|p| std::fs::canonicalize(p).unwrap_or_else(|_| p.clone()).display().to_string()),
                    config: src.config.clone(),
                    skipped_keys: load_report.skipped.len(),
                },
                model_input: ModelInput { width: w, height: h, frames: pre.frames },
                images_total: photos.len(),
                views,
                points,
                model_folder: "sparse/0".into(),
                seconds: VggtSeconds { stages, total: t0.elapsed().as_secs_f64() },
                notes: NOTES.iter().map(|s| s.to_string()).collect(),
            };
            let scene = work.join("scene");
            crate::write_json(&scene.join("pose.json"), &report).and_then(|()| std::fs::rename(&scene, out).map_err(|e| PoseError::io(out, e))).map(|()| report)
        }
        Err(e) => Err(e),
    };
    let _ = std::fs::remove_dir_all(&work);
    report
}

type Forward = (Vec<[f32; 9]>, Vec<f32>, Vec<f32>);

fn forward(model: &mvsplat360_vggt::Vggt, pre: &Preprocessed) -> Result<Forward, PoseError> {
    let err = |e: candle_core::Error| PoseError::Vggt(format!("VGGT forward pass failed: {e}"));
    let images = pre.to_tensor(&Device::Cpu).map_err(err)?;
    let p = model.forward(&images, &[]).map_err(err)?;
    // f32 whatever the trunk ran in (the heads' outputs are f32 upstream; the cast is a no-op then).
    let enc = p
        .pose_enc()
        .ok_or_else(|| PoseError::Vggt("the model has no camera head".into()))?
        .to_dtype(DType::F32)
        .and_then(|t| t.to_vec2::<f32>())
        .map_err(err)?;
    let encs = enc
        .iter()
        .map(|r| <[f32; 9]>::try_from(r.as_slice()).map_err(|_| PoseError::Vggt(format!("pose encoding of {} numbers, expected 9", r.len()))))
        .collect::<Result<Vec<_>, _>>()?;
    let (depth, conf) = p.depth.ok_or_else(|| PoseError::Vggt("the model has no depth head".into()))?;
    let depth = depth.flatten_all().and_then(|t| t.to_dtype(DType::F32)).and_then(|t| t.to_vec1::<f32>()).map_err(err)?;
    let conf = conf.flatten_all().and_then(|t| t.to_dtype(DType::F32)).and_then(|t| t.to_vec1::<f32>()).map_err(err)?;
    let n = pre.frames * pre.height * pre.width;
    if depth.len() != n || conf.len() != n || encs.len() != pre.frames {
        return Err(PoseError::Vggt(format!(
            "VGGT returned {} cameras and {} depth values for {} frames of {}x{}",
            encs.len(),
            depth.len(),
            pre.frames,
            pre.width,
            pre.height
        )));
    }
    Ok((encs, depth, conf))
}

/// The photo as decoded for the model (RGBA composited on white as upstream does), scaled to `kept`.
fn kept_image(path: &Path, kept: (u32, u32)) -> Result<image::RgbImage, PoseError> {
    let rgba = load_fn::load_image_like_pil(path).map_err(load_error)?;
    let rgb = image::RgbImage::from_fn(rgba.width(), rgba.height(), |x, y| {
        let p = rgba.get_pixel(x, y);
        let a = p[3];
        image::Rgb([0, 1, 2].map(|c| if a == 255 { p[c] } else { load_fn::composite_over_white(p[c], a) }))
    });
    Ok(if (rgb.width(), rgb.height()) == kept { rgb } else { image::imageops::resize(&rgb, kept.0, kept.1, image::imageops::FilterType::Lanczos3) })
}

#[allow(clippy::too_many_arguments)]
fn write_scene(
    work: &Path,
    photos: &[PathBuf],
    pre: &Preprocessed,
    cams: &[ViewCamera],
    encs: &[[f32; 9]],
    depth: &[f32],
    conf: &[f32],
    progress: &dyn Progress,
) -> Result<(Vec<ViewRecord>, PointsRecord), PoseError> {
    let scene = work.join("scene");
    let images_dir = scene.join("images");
    std::fs::create_dir_all(&images_dir).map_err(|e| PoseError::io(&images_dir, e))?;
    let (h, w) = (pre.height, pre.width);
    let width = photos.len().to_string().len().max(4);
    progress.begin("write", photos.len() as u64 + 1);

    let mut views = vec![];
    let mut cameras = vec![];
    let mut images = vec![];
    for (k, (p, cam)) in photos.iter().zip(cams).enumerate() {
        let stem = p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let file = format!("{k:0width$}_{stem}.png");
        let img = kept_image(p, cam.kept)?;
        let target = images_dir.join(&file);
        let f = std::fs::File::create(&target).map_err(|e| PoseError::io(&target, e))?;
        let mut bw = std::io::BufWriter::new(f);
        img.write_to(&mut bw, image::ImageFormat::Png).map_err(|e| PoseError::io(&target, std::io::Error::other(e)))?;
        drop(bw);

        let g = &pre.views[k];
        let (rows, cols) = own_region(g, h, w);
        let (mut sum, mut n) = (0.0f64, 0usize);
        for y in rows {
            for x in cols.clone() {
                let c = conf[(k * h + y) * w + x];
                if c.is_finite() {
                    sum += c as f64;
                    n += 1;
                }
            }
        }
        let id = k as u32 + 1;
        let [fx, fy, cx, cy] = cam.kept_k;
        cameras.push(PinholeCamera { id, width: cam.kept.0, height: cam.kept.1, fx, fy, cx, cy });
        images.push(PosedImage::from_c2w(id, id, file.clone(), &cam.c2w)?);
        views.push(ViewRecord {
            file,
            source: p.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default(),
            original_size: g.original,
            kept_size: cam.kept,
            model_resized: g.resized,
            model_offset: g.offset,
            mean_depth_confidence: if n > 0 { sum / n as f64 } else { f64::NAN },
            pose_encoding: encs[k],
            intrinsics: cam.kept_k,
        });
        progress.set(k as u64 + 1);
    }

    // Points: each confident pixel's centre unprojected along its ray to its depth with the predicted camera
    // (model frame), coloured by the preprocessed image, observed by its own image at the same spot on the kept
    // grid. Pixel centres sit at `x + ½` in the corner-origin convention the intrinsics are in (upstream's
    // `unproject_depth_map_to_point_map` uses the integer index: half a pixel apart).
    let sel = select_points(pre, depth, conf);
    let mut points = Vec::with_capacity(sel.pixels.len());
    for (n, px) in sel.pixels.iter().enumerate() {
        let cam = &cams[px.s];
        let kk = &cam.vggt.intrinsic;
        let (u, v) = (px.x as f64 + 0.5, px.y as f64 + 0.5);
        let d = depth[(px.s * h + px.y) * w + px.x] as f64;
        let pc = [(u - kk[0][2]) / kk[0][0] * d, (v - kk[1][2]) / kk[1][1] * d, d];
        let m = &cam.c2w;
        let xyz = [0, 1, 2].map(|i| m[i][0] * pc[0] + m[i][1] * pc[1] + m[i][2] * pc[2] + m[i][3]);
        let frame = pre.frame(px.s);
        let rgb = [0, 1, 2].map(|c| (frame[(c * h + px.y) * w + px.x] * 255.0).round().clamp(0.0, 255.0) as u8);
        let g = &pre.views[px.s];
        let (ox, oy) = g.point_to_original(u, v);
        let (sx, sy) = (cam.kept.0 as f64 / g.original.0 as f64, cam.kept.1 as f64 / g.original.1 as f64);
        let im = &mut images[px.s];
        let id = n as u64 + 1;
        let idx = im.points2d.len() as u32;
        im.points2d.push(Point2D { x: ox * sx, y: oy * sy, point3d_id: Some(id) });
        points.push(Point3D { id, xyz, rgb, error: colmap_writer::UNKNOWN_ERROR, track: vec![TrackElement { image_id: im.id, point2d_idx: idx }] });
    }
    colmap_writer::write_binary(&scene.join("sparse/0"), &cameras, &images, &points)?;
    progress.set(photos.len() as u64 + 1);
    progress.end();
    let record = PointsRecord {
        count: points.len(),
        candidates: sel.candidates,
        confident: sel.confident,
        selection: if sel.fallback {
            format!(
                "most confident {:.0} % (fewer than {:.0} % of the pixels reach confidence {CONFIDENCE_THRESHOLD})",
                FALLBACK_SHARE * 100.0,
                MIN_PASSING_SHARE * 100.0
            )
        } else {
            format!("confidence >= {CONFIDENCE_THRESHOLD}")
        },
        min_confidence: sel.min_confidence,
    };
    Ok((views, record))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kept_size_never_scales_up() {
        assert_eq!(kept_size(4000, 3000, 1000), (1000, 750));
        assert_eq!(kept_size(640, 480, 1000), (640, 480));
        assert_eq!(kept_size(10, 4000, 1000), (3, 1000));
    }

    fn batch(frames: usize, h: usize, w: usize) -> Preprocessed {
        let g = ViewGeometry { original: (w as u32, h as u32), resized: (w as u32, h as u32), offset: (0, 0) };
        Preprocessed { images: vec![0.5; frames * 3 * h * w], frames, height: h, width: w, views: vec![g; frames] }
    }

    #[test]
    fn confident_pixels_or_the_most_confident_tenth() {
        let pre = batch(2, 10, 10);
        let depth = vec![1.0; 200];
        // 3 of 200 pass: 1.5 % ≥ 1 %.
        let mut conf = vec![1.0; 200];
        for i in [5, 50, 150] {
            conf[i] = 6.0;
        }
        let s = select_points(&pre, &depth, &conf);
        assert!(!s.fallback && s.pixels.len() == 3 && s.confident == 3 && s.candidates == 200);
        assert_eq!((s.pixels[2].s, s.pixels[2].y, s.pixels[2].x), (1, 5, 0));
        // 1 of 200 pass: the 20 most confident.
        let mut conf: Vec<f32> = (0..200).map(|i| 1.0 + i as f32 / 100.0).collect();
        conf[7] = 9.0;
        let s = select_points(&pre, &depth, &conf);
        assert!(s.fallback && s.pixels.len() == 20);
        assert_eq!(s.min_confidence, Some(1.0 + 181.0 / 100.0));
        // Padding (outside the view's own region) and bad depth are never points.
        let mut pre = batch(1, 10, 10);
        pre.views[0] = ViewGeometry { original: (20, 10), resized: (10, 5), offset: (0, 3) };
        let mut depth = vec![1.0; 100];
        depth[35] = f32::NAN;
        let s = select_points(&pre, &depth, &[6.0; 100]);
        assert_eq!(s.candidates, 49);
        assert!(s.pixels.iter().all(|p| (3..8).contains(&p.y)));
    }
}
