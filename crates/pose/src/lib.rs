//! `mvsplat360 pose`: a video or a folder of overlapping photos → a posed scene folder (`images/` undistorted,
//! `sparse/0` a PINHOLE COLMAP model, `pose.json` the report) that every scene reader takes as it is.
//!
//! The engines are the `colmap`, `ffmpeg` and `ffprobe` programs, run as children in their own process groups
//! ([`engine`]). Work happens in a hidden folder beside the output, named by a hash of the input and settings,
//! and renamed into place at the end: an interrupted run leaves no half scene, and a rerun on the same input
//! reuses the stages it finished (frames, features, matches). Classical SfM needs overlap: five photos far
//! apart do not match (measured: 0 of 10 pairs); a video, or many overlapping photos, posed together does.
//! For a few photos, [`vggt::pose_vggt`] runs the VGGT model instead (cameras and depth in one forward pass)
//! and writes the same layout.

pub mod colmap_log;
pub mod colmap_writer;
pub mod engine;
pub mod error;
pub mod photos;
pub mod sfm;
pub mod vggt;
pub mod video;

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

pub use engine::{stop_children, ColmapInfo, CommandRecord};
pub use error::PoseError;
use sfm::Matcher;

/// Progress of the stages (a bar each in the CLI).
pub trait Progress: Sync {
    fn begin(&self, stage: &str, total: u64);
    fn set(&self, pos: u64);
    fn set_total(&self, _total: u64) {}
    fn end(&self);
    fn note(&self, msg: &str);
}

pub struct NoProgress;

impl Progress for NoProgress {
    fn begin(&self, _: &str, _: u64) {}
    fn set(&self, _: u64) {}
    fn end(&self) {}
    fn note(&self, _: &str) {}
}

/// Photos up to this many are matched exhaustively (every pair; ≈ n²/2 pairs, about 10 minutes for 100 photos
/// on 2 CPU cores); above it, in sequence of capture time (and name).
pub const EXHAUSTIVE_MAX: usize = 100;

#[derive(Debug, Clone)]
pub struct PoseOptions {
    pub colmap: Option<PathBuf>,
    pub ffmpeg: Option<PathBuf>,
    /// Frames sampled from a video (the sharpest of each of this many equal intervals).
    pub frames: u64,
    /// Long side of the frames and photos COLMAP sees (and the scene keeps), in pixels.
    pub max_size: u32,
    pub camera_model: String,
    /// Fewer registered images than this is a failure (the context views `render` will pick).
    pub min_views: usize,
}

impl Default for PoseOptions {
    fn default() -> Self {
        PoseOptions { colmap: None, ffmpeg: None, frames: 150, max_size: 1000, camera_model: "SIMPLE_RADIAL".into(), min_views: 5 }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InputKind {
    Video,
    Photos,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Engine {
    pub path: String,
    pub version: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cuda: Option<bool>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SubModel {
    pub index: usize,
    pub images: usize,
    /// Its image names (only for the models not kept: what the others held).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub names: Vec<String>,
}

/// `pose.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseReport {
    pub input: String,
    pub input_kind: InputKind,
    /// SHA-256 of the input's bytes and of the settings below: the scene is reused only while it matches.
    pub fingerprint: String,
    pub settings: Settings,
    /// Frames in the video (or photos in the folder).
    pub input_frames: u64,
    pub images_total: usize,
    pub registered: usize,
    pub registered_share: f64,
    /// Files not in the kept model (as named in `images/` before undistortion).
    pub unregistered: Vec<String>,
    pub sub_models: Vec<SubModel>,
    /// Image pairs with verified matches (the mapper's count).
    pub matched_pairs: Option<u64>,
    pub mean_reprojection_error_px: Option<f64>,
    /// The scene's COLMAP model, relative to the scene folder (PINHOLE, from `image_undistorter`).
    pub model_folder: String,
    pub frames: serde_json::Value,
    pub seconds: Seconds,
    pub commands: Vec<CommandRecord>,
    pub engines: Vec<(String, Engine)>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Settings {
    pub frames: u64,
    pub max_size: u32,
    pub camera_model: String,
    pub matcher: Matcher,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct Seconds {
    /// Per stage, in the order run; a stage reused from an interrupted run counts 0 here.
    pub stages: Vec<(String, f64)>,
    pub reused: Vec<String>,
    /// Time inside COLMAP's processes.
    pub colmap: f64,
    pub total: f64,
    /// `total − colmap` over `colmap`: what `pose` itself (frame sampling included) adds.
    pub overhead_share: f64,
}

/// Video file or photo folder.
pub fn input_kind(input: &Path) -> Result<InputKind, PoseError> {
    if input.is_dir() {
        Ok(InputKind::Photos)
    } else if input.is_file() {
        Ok(InputKind::Video)
    } else {
        Err(PoseError::input(input, "no such file or folder"))
    }
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

/// SHA-256 over the input's bytes (every photo's name and bytes) and the settings that change the result.
pub fn fingerprint(input: &Path, opts: &PoseOptions) -> Result<String, PoseError> {
    let mut h = Sha256::new();
    h.update(format!("pose 1|frames {}|max {}|model {}\n", opts.frames, opts.max_size, opts.camera_model));
    match input_kind(input)? {
        InputKind::Video => hash_file(&mut h, input)?,
        InputKind::Photos => {
            for p in photos::list(input)?.0 {
                h.update(p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default());
                h.update([0u8]);
                hash_file(&mut h, &p)?;
            }
        }
    }
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

/// The report of an existing scene folder, if it has one.
pub fn read_report(scene: &Path) -> Option<PoseReport> {
    serde_json::from_str(&std::fs::read_to_string(scene.join("pose.json")).ok()?).ok()
}

pub(crate) fn write_json<T: Serialize>(path: &Path, v: &T) -> Result<(), PoseError> {
    let text = serde_json::to_string_pretty(v).map_err(|e| PoseError::io(path, std::io::Error::other(e)))?;
    mvsplat360_dataset::atomic::write_atomic(path, |tmp| std::fs::write(tmp, text + "\n")).map_err(|e| PoseError::io(path, e))
}

pub(crate) fn remove_if_exists(p: &Path) -> Result<(), PoseError> {
    if p.is_dir() {
        std::fs::remove_dir_all(p).map_err(|e| PoseError::io(p, e))
    } else if p.exists() {
        std::fs::remove_file(p).map_err(|e| PoseError::io(p, e))
    } else {
        Ok(())
    }
}

/// The hidden work folder for `out` and this fingerprint (beside `out`, so the final rename stays on one
/// file system).
pub fn work_dir(out: &Path, fingerprint: &str) -> PathBuf {
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into());
    out.with_file_name(format!(".{name}.pose-{}", &fingerprint[..16]))
}

struct Engines {
    colmap: ColmapInfo,
    ffmpeg: Option<(PathBuf, PathBuf, String)>,
}

fn find_engines(kind: InputKind, opts: &PoseOptions) -> Result<Engines, PoseError> {
    let colmap = ColmapInfo::probe(&engine::find_program("colmap", opts.colmap.as_deref())?)?;
    let ffmpeg = if kind == InputKind::Video {
        let ffmpeg = engine::find_program("ffmpeg", opts.ffmpeg.as_deref())?;
        // ffprobe ships with ffmpeg: beside an explicit --ffmpeg, else on PATH.
        let beside = opts.ffmpeg.as_ref().map(|p| p.with_file_name("ffprobe"));
        let ffprobe = engine::find_program("ffprobe", beside.as_deref())?;
        let version = engine::ffmpeg_version(&ffmpeg)?;
        Some((ffmpeg, ffprobe, version))
    } else {
        None
    };
    Ok(Engines { colmap, ffmpeg })
}

/// Whether every image shows the same picture (a video of a still scene from a still camera: nothing to
/// triangulate). Compared on small grey thumbnails, so video compression noise does not make frames differ.
fn all_identical(dir: &Path, files: &[String]) -> Result<bool, PoseError> {
    let thumb = |f: &String| -> Result<Vec<f32>, PoseError> {
        let p = dir.join(f);
        let img = image::open(&p).map_err(|e| PoseError::input(&p, format!("cannot decode it: {e}")))?;
        Ok(img.resize_exact(32, 32, image::imageops::FilterType::Triangle).to_luma8().pixels().map(|p| p.0[0] as f32).collect())
    };
    let Some(first) = files.first() else { return Ok(true) };
    let t0 = thumb(first)?;
    for f in &files[1..] {
        let t = thumb(f)?;
        let mad = t.iter().zip(&t0).map(|(a, b)| (a - b).abs()).sum::<f32>() / t.len() as f32;
        if mad > 2.0 {
            return Ok(false);
        }
    }
    Ok(true)
}

/// A stage's marker: written when it finishes, so a rerun skips it.
fn done(work: &Path, stage: &str) -> PathBuf {
    work.join(format!("{stage}.done"))
}

/// Poses `input` into the new folder `out`. An `out` that exists is reused when its `pose.json` has this
/// input's fingerprint, and refused otherwise.
pub fn pose(input: &Path, out: &Path, opts: &PoseOptions, progress: &dyn Progress) -> Result<PoseReport, PoseError> {
    let t0 = Instant::now();
    if !sfm::CAMERA_MODELS.contains(&opts.camera_model.as_str()) {
        return Err(PoseError::input(Path::new("--camera-model"), format!("`{}` is not one of {}", opts.camera_model, sfm::CAMERA_MODELS.join(", "))));
    }
    let kind = input_kind(input)?;
    let engines = find_engines(kind, opts)?;
    // Inputs are checked before anything is written.
    let (photo_files, video_info) = match kind {
        InputKind::Photos => {
            let (p, others) = photos::list(input)?;
            if p.is_empty() {
                let also = photos::others_suffix(&others);
                return Err(PoseError::input(input, format!("holds no photos (.jpg, .jpeg, .png){also}; give a folder of overlapping photos or a video")));
            }
            if p.len() < 2 || p.len() < opts.min_views {
                return Err(PoseError::input(
                    input,
                    format!(
                        "holds {} photo(s); posing needs many overlapping photos (20 or more, each sharing most of its view with the next) or a video",
                        p.len()
                    ),
                ));
            }
            photos::note_ignored(input, &others, progress);
            (p, None)
        }
        InputKind::Video => {
            let (_, ffprobe, _) = engines.ffmpeg.as_ref().ok_or_else(|| PoseError::input(input, "no ffmpeg"))?;
            let info = video::probe(ffprobe, input)?;
            progress.note(&format!("{}: {}", input.display(), video::describe(&info)));
            (vec![], Some(info))
        }
    };
    let fp = fingerprint(input, opts)?;
    if out.exists() {
        return match read_report(out) {
            Some(r) if r.fingerprint == fp => {
                progress.note(&format!("{} is already posed from this input ({} of {} images); reusing it", out.display(), r.registered, r.images_total));
                Ok(r)
            }
            _ => Err(PoseError::input(out, "already exists and was not posed from this input with these settings; choose another --out or delete it")),
        };
    }
    let work = work_dir(out, &fp);
    std::fs::create_dir_all(&work).map_err(|e| PoseError::io(&work, e))?;
    let res = pose_in(&work, t0, kind, &engines, &photo_files, video_info.as_ref(), fp, input, out, opts, progress);
    // What the input cannot give is final: nothing is kept. An engine or disk failure (or Ctrl-C) keeps the
    // finished stages for the rerun.
    if matches!(res, Err(PoseError::NotPosed(_)) | Err(PoseError::Input { .. })) {
        let _ = std::fs::remove_dir_all(&work);
    }
    res
}

#[allow(clippy::too_many_arguments)]
fn pose_in(
    work: &Path,
    t0: Instant,
    kind: InputKind,
    engines: &Engines,
    photo_files: &[PathBuf],
    video_info: Option<&video::VideoInfo>,
    fp: String,
    input: &Path,
    out: &Path,
    opts: &PoseOptions,
    progress: &dyn Progress,
) -> Result<PoseReport, PoseError> {
    let work = work.to_path_buf();
    let images = work.join("images");
    let logs = work.join("logs");
    std::fs::create_dir_all(&logs).map_err(|e| PoseError::io(&logs, e))?;
    let mut seconds = Seconds::default();
    let mut commands: Vec<CommandRecord> = vec![];
    let stage_time = |seconds: &mut Seconds, name: &str, t: Instant| seconds.stages.push((name.to_string(), t.elapsed().as_secs_f64()));

    // 1. Frames (video) or photos.
    let frames_json = work.join("frames.json");
    let (files, frames_value, input_frames, per_folder): (Vec<String>, serde_json::Value, u64, bool) = match read_frames(&frames_json) {
        Some(v) => {
            seconds.reused.push("frames".into());
            v
        }
        None => {
            let t = Instant::now();
            remove_if_exists(&images)?;
            std::fs::create_dir_all(&images).map_err(|e| PoseError::io(&images, e))?;
            let v = match (video_info, &engines.ffmpeg) {
                (Some(info), Some((ffmpeg, _, _))) => {
                    let ex = video::extract(ffmpeg, input, info, opts.frames, opts.max_size, &images, progress)?;
                    let files = ex.frames.iter().map(|f| f.file.clone()).collect();
                    let value = serde_json::json!({ "video": info, "extraction": ex });
                    (files, value, info.frames, false)
                }
                _ => {
                    let mut ph = photos::prepare(photo_files, opts.max_size, &images, progress)?;
                    let sizes: std::collections::BTreeSet<(u32, u32)> = ph.iter().map(|p| p.size).collect();
                    // One camera per image size: COLMAP shares a camera per folder, so each size gets one.
                    let per_folder = sizes.len() > 1;
                    if per_folder {
                        for p in &mut ph {
                            let sub = format!("{}x{}", p.size.0, p.size.1);
                            let d = images.join(&sub);
                            std::fs::create_dir_all(&d).map_err(|e| PoseError::io(&d, e))?;
                            std::fs::rename(images.join(&p.file), d.join(&p.file)).map_err(|e| PoseError::io(&d, e))?;
                            p.file = format!("{sub}/{}", p.file);
                        }
                    }
                    let rotated = ph.iter().filter(|p| p.orientation > 1).count();
                    if rotated > 0 {
                        progress.note(&format!("{rotated} photo(s) carried an EXIF orientation; their pixels were turned upright for COLMAP"));
                    }
                    let files = ph.iter().map(|p| p.file.clone()).collect();
                    let n = ph.len() as u64;
                    (files, serde_json::json!({ "photos": ph, "sizes": sizes }), n, per_folder)
                }
            };
            write_json(&frames_json, &serde_json::json!({ "files": v.0, "detail": v.1, "input_frames": v.2, "per_folder": v.3 }))?;
            for s in ["features", "matches"] {
                remove_if_exists(&done(&work, s))?;
            }
            stage_time(&mut seconds, "frames", t);
            v
        }
    };
    let n = files.len();
    if all_identical(&images, &files)? {
        return Err(PoseError::NotPosed(format!(
            "{}: all {n} sampled images are identical, so nothing can be triangulated; record the scene while moving around it",
            input.display()
        )));
    }
    if n < opts.min_views.max(2) {
        return Err(PoseError::NotPosed(format!(
            "{}: only {n} images were sampled; at least {} are needed (raise --frames)",
            input.display(),
            opts.min_views.max(2)
        )));
    }
    let matcher = if kind == InputKind::Video || n > EXHAUSTIVE_MAX { Matcher::Sequential } else { Matcher::Exhaustive };
    let w = sfm::Work { colmap: &engines.colmap, root: &work, images: images.clone(), database: work.join("database.db"), logs: logs.clone() };

    // 2. Features, 3. matches: reused when finished.
    for (stage, run) in [("features", 0), ("matches", 1)] {
        if done(&work, stage).is_file() {
            seconds.reused.push(stage.into());
            continue;
        }
        let t = Instant::now();
        let rec = if run == 0 {
            remove_if_exists(&w.database)?;
            remove_if_exists(&done(&work, "matches"))?;
            w.extract(&opts.camera_model, per_folder, n as u64, progress)?
        } else {
            let rec = w.matches(matcher, n as u64, progress)?;
            let closing = if matcher == Matcher::Sequential { w.close_loop(&files, progress)? } else { None };
            match closing {
                Some(r) => {
                    commands.push(rec);
                    r
                }
                None => rec,
            }
        };
        commands.push(rec);
        std::fs::write(done(&work, stage), b"").map_err(|e| PoseError::io(&work, e))?;
        stage_time(&mut seconds, stage, t);
    }

    // 4. Mapper; the largest sub-model is kept.
    let t = Instant::now();
    let (rec, mlog, sparse) = w.map(n as u64, progress)?;
    commands.push(rec);
    stage_time(&mut seconds, "mapper", t);
    let models = sfm::sub_models(&sparse)?;
    let kept = models.first();
    let registered = kept.map_or(0, |m| m.2.len());
    let kept_names: std::collections::HashSet<&String> = kept.map(|m| m.2.iter().collect()).unwrap_or_default();
    let unregistered: Vec<String> = files.iter().filter(|f| !kept_names.contains(f)).cloned().collect();
    let pairs = match (mlog.matched_pairs, matcher) {
        (Some(m), Matcher::Exhaustive) => format!("{m} of {} image pairs matched", n * (n - 1) / 2),
        (Some(m), Matcher::Sequential) => format!("{m} image pairs matched (sequential matcher, first and last frames paired for loop closure)"),
        (None, _) => "the matcher's pair count is not in the mapper's log".into(),
    };
    let need = opts.min_views.max(2);
    if registered < need {
        let what = if registered == 0 { "no images were registered".to_string() } else { format!("only {registered} of {n} images were registered") };
        let sample: Vec<&str> = unregistered.iter().take(12).map(String::as_str).collect();
        let more = if unregistered.len() > 12 { format!(" and {} more", unregistered.len() - 12) } else { String::new() };
        return Err(PoseError::NotPosed(format!(
            "{}: COLMAP could not pose the scene: {what} ({pairs}; at least {need} are needed). Not registered: {}{more}. \
             Classical SfM needs overlap: record a video while walking around the scene, or take many more photos, each sharing most of its view with the next \
             (five photos far apart cannot be posed).",
            input.display(),
            sample.join(", "),
        )));
    }
    let (kept_idx, kept_path) = kept.map(|m| (m.0, m.1.clone())).ok_or_else(|| PoseError::NotPosed("no model".into()))?;
    let share = registered as f64 / n as f64;
    if share < 0.4 {
        progress.note(&format!(
            "WARNING: only {registered} of {n} images ({:.0} %) are in the kept model; the scene is badly covered. Record a slower, steadier video around the scene, or more overlapping photos. Not registered: {}",
            share * 100.0,
            unregistered.join(", ")
        ));
    } else if share < 0.8 {
        progress.note(&format!("warning: {registered} of {n} images ({:.0} %) registered; {} were left out", share * 100.0, unregistered.len()));
    }

    // 5. Reprojection error of the kept model, then 6. undistortion to PINHOLE.
    let (rec, reproj) = w.analyze(&kept_path, progress)?;
    commands.push(rec);
    let t = Instant::now();
    let undist = work.join("undistorted");
    remove_if_exists(&undist)?;
    commands.push(w.undistort(&kept_path, &undist, registered as u64, progress)?);
    stage_time(&mut seconds, "undistort", t);

    // 7. The scene folder, renamed into place whole.
    let scene = work.join("scene");
    remove_if_exists(&scene)?;
    std::fs::create_dir_all(scene.join("sparse")).map_err(|e| PoseError::io(&scene, e))?;
    std::fs::rename(undist.join("images"), scene.join("images")).map_err(|e| PoseError::io(&undist, e))?;
    std::fs::rename(undist.join("sparse"), scene.join("sparse/0")).map_err(|e| PoseError::io(&undist, e))?;
    let sub_models = models.iter().map(|m| SubModel { index: m.0, images: m.2.len(), names: if m.0 == kept_idx { vec![] } else { m.2.clone() } }).collect();
    if models.len() > 1 {
        let others: Vec<String> = models[1..].iter().map(|m| format!("{} images", m.2.len())).collect();
        progress.note(&format!("COLMAP split the scene into {} models; kept the largest ({registered} images), left out: {}", models.len(), others.join(", ")));
    }
    let colmap_s: f64 = commands.iter().map(|c| c.seconds).sum();
    let total = t0.elapsed().as_secs_f64();
    seconds.colmap = colmap_s;
    seconds.total = total;
    seconds.overhead_share = if colmap_s > 0.0 { (total - colmap_s) / colmap_s } else { 0.0 };
    let mut engines_rec = vec![(
        "colmap".to_string(),
        Engine { path: engines.colmap.path.display().to_string(), version: engines.colmap.version.clone(), cuda: Some(engines.colmap.cuda) },
    )];
    if let Some((ffmpeg, _, version)) = &engines.ffmpeg {
        engines_rec.push(("ffmpeg".into(), Engine { path: ffmpeg.display().to_string(), version: version.clone(), cuda: None }));
    }
    let report = PoseReport {
        input: input.display().to_string(),
        input_kind: kind,
        fingerprint: fp,
        settings: Settings { frames: opts.frames, max_size: opts.max_size, camera_model: opts.camera_model.clone(), matcher },
        input_frames,
        images_total: n,
        registered,
        registered_share: share,
        unregistered,
        sub_models,
        matched_pairs: mlog.matched_pairs,
        mean_reprojection_error_px: reproj,
        model_folder: "sparse/0".into(),
        frames: frames_value,
        seconds,
        commands,
        engines: engines_rec,
    };
    write_json(&scene.join("pose.json"), &report)?;
    std::fs::rename(&logs, scene.join("logs")).map_err(|e| PoseError::io(&logs, e))?;
    std::fs::rename(&scene, out).map_err(|e| PoseError::io(out, e))?;
    remove_if_exists(&work)?;
    Ok(report)
}

type Frames = (Vec<String>, serde_json::Value, u64, bool);

fn read_frames(path: &Path) -> Option<Frames> {
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()?;
    let files = v.get("files")?.as_array()?.iter().map(|f| f.as_str().map(String::from)).collect::<Option<Vec<_>>>()?;
    let dir = path.parent()?.join("images");
    if !files.iter().all(|f| dir.join(f).is_file()) {
        return None;
    }
    Some((files, v.get("detail")?.clone(), v.get("input_frames")?.as_u64()?, v.get("per_folder")?.as_bool()?))
}
