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

pub use engine::{stop_children, ColmapGpu, ColmapInfo, CommandRecord};
pub use error::PoseError;
use mvsplat360_dataset::atomic::DirLock;
pub use sfm::Matcher;

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
    /// `--matcher`; `None`: sequential for a video or more than [`EXHAUSTIVE_MAX`] photos, else exhaustive.
    pub matcher: Option<Matcher>,
    /// `--colmap-gpu`.
    pub colmap_gpu: ColmapGpu,
}

impl Default for PoseOptions {
    fn default() -> Self {
        PoseOptions {
            colmap: None,
            ffmpeg: None,
            frames: 150,
            max_size: 1000,
            camera_model: "SIMPLE_RADIAL".into(),
            min_views: 5,
            matcher: None,
            colmap_gpu: ColmapGpu::Auto,
        }
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
    // Only a chosen matcher changes the hash, so scenes posed before `--matcher` existed are still reused.
    if let Some(m) = opts.matcher {
        h.update(format!("matcher {}\n", m.command()));
    }
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

/// Holds `out` for this run: a [`DirLock`] on `.NAME.pose.lock` beside it, where the work folders are. A
/// second run into the same `--out` (`pose`, or `render` of a video or photos) is refused at once, naming the
/// process that holds it: two runs would share the work folder and COLMAP's `database.db`.
pub fn lock_out(out: &Path) -> Result<DirLock, PoseError> {
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into());
    let lock = out.with_file_name(format!(".{name}.pose.lock"));
    if let Some(parent) = lock.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| PoseError::io(parent, e))?;
    }
    DirLock::acquire(&lock, "pose run", "choose another --out").map_err(|m| PoseError::Busy(format!("{}: {m}", out.display())))
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

/// What was checked of the input before anything is written: its photos, or its video.
struct Source {
    photos: Vec<PathBuf>,
    video: Option<video::VideoInfo>,
}

/// Poses `input` into the new folder `out`. An `out` that exists is reused when its `pose.json` has this
/// input's fingerprint, and refused otherwise; another run into `out` is refused ([`lock_out`]).
pub fn pose(input: &Path, out: &Path, opts: &PoseOptions, progress: &dyn Progress) -> Result<PoseReport, PoseError> {
    let t0 = Instant::now();
    if !sfm::CAMERA_MODELS.contains(&opts.camera_model.as_str()) {
        return Err(PoseError::input(Path::new("--camera-model"), format!("`{}` is not one of {}", opts.camera_model, sfm::CAMERA_MODELS.join(", "))));
    }
    let kind = input_kind(input)?;
    let engines = find_engines(kind, opts)?;
    let source = check_source(input, kind, &engines, opts, progress)?;
    let fp = fingerprint(input, opts)?;
    let _lock = lock_out(out)?;
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
    let run = Run { input, kind, engines: &engines, opts, progress, images: work.join("images"), logs: work.join("logs"), work: work.clone() };
    let res = pose_in(&run, &source, fp, out, t0);
    // What the input cannot give is final: nothing is kept. An engine or disk failure (or Ctrl-C) keeps the
    // finished stages for the rerun.
    if matches!(res, Err(PoseError::NotPosed(_)) | Err(PoseError::Input { .. })) {
        let _ = std::fs::remove_dir_all(&work);
    }
    res
}

/// The photos of a folder (enough of them), or what ffprobe says of a video.
fn check_source(input: &Path, kind: InputKind, engines: &Engines, opts: &PoseOptions, progress: &dyn Progress) -> Result<Source, PoseError> {
    match kind {
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
            Ok(Source { photos: p, video: None })
        }
        InputKind::Video => {
            let (_, ffprobe, _) = engines.ffmpeg.as_ref().ok_or_else(|| PoseError::input(input, "no ffmpeg"))?;
            let info = video::probe(ffprobe, input)?;
            progress.note(&format!("{}: {}", input.display(), video::describe(&info)));
            Ok(Source { photos: vec![], video: Some(info) })
        }
    }
}

/// One run's settings and folders, shared by its stages.
struct Run<'a> {
    input: &'a Path,
    kind: InputKind,
    engines: &'a Engines,
    opts: &'a PoseOptions,
    progress: &'a dyn Progress,
    work: PathBuf,
    images: PathBuf,
    logs: PathBuf,
}

/// What the stages ran and how long they took, for the report.
#[derive(Default)]
struct Tally {
    seconds: Seconds,
    commands: Vec<CommandRecord>,
}

impl Tally {
    fn stage(&mut self, name: &str, t: Instant) {
        self.seconds.stages.push((name.to_string(), t.elapsed().as_secs_f64()));
    }
}

/// The images COLMAP poses (`images/`, as `frames.json` lists them).
struct Frames {
    files: Vec<String>,
    detail: serde_json::Value,
    input_frames: u64,
    /// One camera per subfolder of `images/` (several devices), else one camera for all.
    per_folder: bool,
}

/// The mapper's kept model and what it left out.
struct Mapped {
    models: Vec<(usize, PathBuf, Vec<String>)>,
    kept_idx: usize,
    kept_path: PathBuf,
    registered: usize,
    unregistered: Vec<String>,
    matched_pairs: Option<u64>,
}

fn pose_in(run: &Run, source: &Source, fp: String, out: &Path, t0: Instant) -> Result<PoseReport, PoseError> {
    std::fs::create_dir_all(&run.logs).map_err(|e| PoseError::io(&run.logs, e))?;
    let mut tally = Tally::default();
    let frames = frames(run, source, &mut tally)?;
    check_frames(run, &frames.files)?;
    let n = frames.files.len();
    let matcher = choose_matcher(run.opts.matcher, run.kind, n);
    let w = sfm::Work {
        colmap: &run.engines.colmap,
        root: &run.work,
        images: run.images.clone(),
        database: run.work.join("database.db"),
        logs: run.logs.clone(),
        gpu: run.opts.colmap_gpu,
    };
    features_and_matches(run, &w, &frames, matcher, &mut tally)?;
    let mapped = map(run, &w, &frames.files, matcher, &mut tally)?;
    // Reprojection error of the kept model, then undistortion to PINHOLE.
    let (rec, reproj) = w.analyze(&mapped.kept_path, run.progress)?;
    tally.commands.push(rec);
    let t = Instant::now();
    let undist = run.work.join("undistorted");
    remove_if_exists(&undist)?;
    tally.commands.push(w.undistort(&mapped.kept_path, &undist, mapped.registered as u64, run.progress)?);
    tally.stage("undistort", t);
    let scene = assemble_scene(run, &undist, &mapped)?;
    let report = report(run, fp, frames, matcher, mapped, reproj, tally, t0);
    write_json(&scene.join("pose.json"), &report)?;
    std::fs::rename(&run.logs, scene.join("logs")).map_err(|e| PoseError::io(&run.logs, e))?;
    std::fs::rename(&scene, out).map_err(|e| PoseError::io(out, e))?;
    remove_if_exists(&run.work)?;
    Ok(report)
}

/// `--matcher`, else sequential for a video or many photos (capture order), exhaustive for fewer.
fn choose_matcher(chosen: Option<Matcher>, kind: InputKind, n: usize) -> Matcher {
    chosen.unwrap_or(if kind == InputKind::Video || n > EXHAUSTIVE_MAX { Matcher::Sequential } else { Matcher::Exhaustive })
}

/// Stage 1: the frames of the video or the photos, reused when a run before finished them.
fn frames(run: &Run, source: &Source, tally: &mut Tally) -> Result<Frames, PoseError> {
    let frames_json = run.work.join("frames.json");
    if let Some(f) = read_frames(&frames_json) {
        tally.seconds.reused.push("frames".into());
        return Ok(f);
    }
    let t = Instant::now();
    remove_if_exists(&run.images)?;
    std::fs::create_dir_all(&run.images).map_err(|e| PoseError::io(&run.images, e))?;
    let f = match (&source.video, &run.engines.ffmpeg) {
        (Some(info), Some((ffmpeg, _, _))) => {
            let ex = video::extract(ffmpeg, run.input, info, run.opts.frames, run.opts.max_size, &run.images, run.progress)?;
            let files = ex.frames.iter().map(|f| f.file.clone()).collect();
            Frames { files, detail: serde_json::json!({ "video": info, "extraction": ex }), input_frames: info.frames, per_folder: false }
        }
        _ => photo_frames(run, &source.photos)?,
    };
    let record = serde_json::json!({ "files": f.files, "detail": f.detail, "input_frames": f.input_frames, "per_folder": f.per_folder });
    write_json(&frames_json, &record)?;
    // New frames: the features and matches of older ones are stale.
    for s in ["features", "matches"] {
        remove_if_exists(&done(&run.work, s))?;
    }
    tally.stage("frames", t);
    Ok(f)
}

/// The photos, upright and scaled, each device's in its own subfolder when there are several: COLMAP shares a
/// camera per folder (`single_camera_per_folder`).
fn photo_frames(run: &Run, files: &[PathBuf]) -> Result<Frames, PoseError> {
    let mut ph = photos::prepare(files, run.opts.max_size, &run.images, run.progress)?;
    let (cameras, group_of) = photos::camera_groups(&ph);
    let per_folder = cameras.len() > 1;
    if per_folder {
        for (p, &g) in ph.iter_mut().zip(&group_of) {
            let sub = &cameras[g].folder;
            let d = run.images.join(sub);
            std::fs::create_dir_all(&d).map_err(|e| PoseError::io(&d, e))?;
            std::fs::rename(run.images.join(&p.file), d.join(&p.file)).map_err(|e| PoseError::io(&d, e))?;
            p.file = format!("{sub}/{}", p.file);
        }
        let list: Vec<String> = cameras.iter().map(describe_camera).collect();
        run.progress.note(&format!("{} cameras (by image size and EXIF make, model, focal length): {}", cameras.len(), list.join("; ")));
    }
    let rotated = ph.iter().filter(|p| p.orientation > 1).count();
    if rotated > 0 {
        run.progress.note(&format!("{rotated} photo(s) carried an EXIF orientation; their pixels were turned upright for COLMAP"));
    }
    let sizes: std::collections::BTreeSet<(u32, u32)> = ph.iter().map(|p| p.size).collect();
    let files = ph.iter().map(|p| p.file.clone()).collect();
    let n = ph.len() as u64;
    Ok(Frames { files, detail: serde_json::json!({ "photos": ph, "sizes": sizes, "cameras": cameras }), input_frames: n, per_folder })
}

/// `images/640x480-2: 12 photos, Acme Phone 2, 4.2 mm`.
fn describe_camera(c: &photos::CameraGroup) -> String {
    let device: Vec<String> = [c.make.clone(), c.model.clone(), c.focal_mm.map(|f| format!("{f} mm"))].into_iter().flatten().collect();
    let device = if device.is_empty() { "no EXIF".to_string() } else { device.join(" ") };
    format!("images/{}: {} photo(s), {device}", c.folder, c.photos)
}

/// Refuses images that cannot be posed: all alike (nothing to triangulate), or too few.
fn check_frames(run: &Run, files: &[String]) -> Result<(), PoseError> {
    let n = files.len();
    if all_identical(&run.images, files)? {
        return Err(PoseError::NotPosed(format!(
            "{}: all {n} sampled images are identical, so nothing can be triangulated; record the scene while moving around it",
            run.input.display()
        )));
    }
    let need = run.opts.min_views.max(2);
    if n < need {
        return Err(PoseError::NotPosed(format!("{}: only {n} images were sampled; at least {need} are needed (raise --frames)", run.input.display())));
    }
    Ok(())
}

/// Stages 2 and 3, features and matches (with the loop closure of a sequence), each reused when finished.
fn features_and_matches(run: &Run, w: &sfm::Work, frames: &Frames, matcher: Matcher, tally: &mut Tally) -> Result<(), PoseError> {
    let n = frames.files.len() as u64;
    for stage in ["features", "matches"] {
        if done(&run.work, stage).is_file() {
            tally.seconds.reused.push(stage.into());
            continue;
        }
        let t = Instant::now();
        if stage == "features" {
            remove_if_exists(&w.database)?;
            remove_if_exists(&done(&run.work, "matches"))?;
            tally.commands.push(w.extract(&run.opts.camera_model, frames.per_folder, n, run.progress)?);
        } else {
            tally.commands.push(w.matches(matcher, n, run.progress)?);
            if matcher == Matcher::Sequential {
                tally.commands.extend(w.close_loop(&frames.files, run.progress)?);
            }
        }
        std::fs::write(done(&run.work, stage), b"").map_err(|e| PoseError::io(&run.work, e))?;
        tally.stage(stage, t);
    }
    Ok(())
}

/// Stage 4, the mapper; the largest sub-model is kept, and too few registered images is a failure that says why.
fn map(run: &Run, w: &sfm::Work, files: &[String], matcher: Matcher, tally: &mut Tally) -> Result<Mapped, PoseError> {
    let t = Instant::now();
    let (rec, mlog, sparse) = w.map(files.len() as u64, run.progress)?;
    tally.commands.push(rec);
    tally.stage("mapper", t);
    let models = sfm::sub_models(&sparse)?;
    let kept = models.first();
    let registered = kept.map_or(0, |m| m.2.len());
    let kept_names: std::collections::HashSet<&String> = kept.map(|m| m.2.iter().collect()).unwrap_or_default();
    let unregistered: Vec<String> = files.iter().filter(|f| !kept_names.contains(f)).cloned().collect();
    let n = files.len();
    let need = run.opts.min_views.max(2);
    if registered < need {
        let pairs = match (mlog.matched_pairs, matcher) {
            (Some(m), Matcher::Exhaustive) => format!("{m} of {} image pairs matched", n * (n - 1) / 2),
            (Some(m), Matcher::Sequential) => format!("{m} image pairs matched (sequential matcher, first and last frames paired for loop closure)"),
            (None, _) => "the matcher's pair count is not in the mapper's log".into(),
        };
        let what = if registered == 0 { "no images were registered".to_string() } else { format!("only {registered} of {n} images were registered") };
        let sample: Vec<&str> = unregistered.iter().take(12).map(String::as_str).collect();
        let more = if unregistered.len() > 12 { format!(" and {} more", unregistered.len() - 12) } else { String::new() };
        return Err(PoseError::NotPosed(format!(
            "{}: COLMAP could not pose the scene: {what} ({pairs}; at least {need} are needed). Not registered: {}{more}. \
             Classical SfM needs overlap: record a video while walking around the scene, or take many more photos, each sharing most of its view with the next \
             (five photos far apart cannot be posed).",
            run.input.display(),
            sample.join(", "),
        )));
    }
    let (kept_idx, kept_path) = kept.map(|m| (m.0, m.1.clone())).ok_or_else(|| PoseError::NotPosed("no model".into()))?;
    let share = registered as f64 / n as f64;
    if share < 0.4 {
        run.progress.note(&format!(
            "WARNING: only {registered} of {n} images ({:.0} %) are in the kept model; the scene is badly covered. Record a slower, steadier video around the scene, or more overlapping photos. Not registered: {}",
            share * 100.0,
            unregistered.join(", ")
        ));
    } else if share < 0.8 {
        run.progress.note(&format!("warning: {registered} of {n} images ({:.0} %) registered; {} were left out", share * 100.0, unregistered.len()));
    }
    Ok(Mapped { models, kept_idx, kept_path, registered, unregistered, matched_pairs: mlog.matched_pairs })
}

/// The scene folder in the work folder (`images/`, `sparse/0` from the undistorter), to be renamed into place.
fn assemble_scene(run: &Run, undist: &Path, mapped: &Mapped) -> Result<PathBuf, PoseError> {
    let scene = run.work.join("scene");
    remove_if_exists(&scene)?;
    std::fs::create_dir_all(scene.join("sparse")).map_err(|e| PoseError::io(&scene, e))?;
    std::fs::rename(undist.join("images"), scene.join("images")).map_err(|e| PoseError::io(undist, e))?;
    std::fs::rename(undist.join("sparse"), scene.join("sparse/0")).map_err(|e| PoseError::io(undist, e))?;
    if mapped.models.len() > 1 {
        let others: Vec<String> = mapped.models[1..].iter().map(|m| format!("{} images", m.2.len())).collect();
        run.progress.note(&format!(
            "COLMAP split the scene into {} models; kept the largest ({} images), left out: {}",
            mapped.models.len(),
            mapped.registered,
            others.join(", ")
        ));
    }
    Ok(scene)
}

#[allow(clippy::too_many_arguments)]
fn report(run: &Run, fp: String, frames: Frames, matcher: Matcher, mapped: Mapped, reproj: Option<f64>, tally: Tally, t0: Instant) -> PoseReport {
    let Tally { mut seconds, commands } = tally;
    let colmap_s: f64 = commands.iter().map(|c| c.seconds).sum();
    let total = t0.elapsed().as_secs_f64();
    seconds.colmap = colmap_s;
    seconds.total = total;
    seconds.overhead_share = if colmap_s > 0.0 { (total - colmap_s) / colmap_s } else { 0.0 };
    let colmap = &run.engines.colmap;
    let mut engines =
        vec![("colmap".to_string(), Engine { path: colmap.path.display().to_string(), version: colmap.version.clone(), cuda: Some(colmap.cuda) })];
    if let Some((ffmpeg, _, version)) = &run.engines.ffmpeg {
        engines.push(("ffmpeg".into(), Engine { path: ffmpeg.display().to_string(), version: version.clone(), cuda: None }));
    }
    let n = frames.files.len();
    let sub_models =
        mapped.models.iter().map(|m| SubModel { index: m.0, images: m.2.len(), names: if m.0 == mapped.kept_idx { vec![] } else { m.2.clone() } }).collect();
    let opts = run.opts;
    PoseReport {
        input: run.input.display().to_string(),
        input_kind: run.kind,
        fingerprint: fp,
        settings: Settings { frames: opts.frames, max_size: opts.max_size, camera_model: opts.camera_model.clone(), matcher },
        input_frames: frames.input_frames,
        images_total: n,
        registered: mapped.registered,
        registered_share: mapped.registered as f64 / n as f64,
        unregistered: mapped.unregistered,
        sub_models,
        matched_pairs: mapped.matched_pairs,
        mean_reprojection_error_px: reproj,
        model_folder: "sparse/0".into(),
        frames: frames.detail,
        seconds,
        commands,
        engines,
    }
}

fn read_frames(path: &Path) -> Option<Frames> {
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()?;
    let files = v.get("files")?.as_array()?.iter().map(|f| f.as_str().map(String::from)).collect::<Option<Vec<_>>>()?;
    let dir = path.parent()?.join("images");
    if !files.iter().all(|f| dir.join(f).is_file()) {
        return None;
    }
    Some(Frames { files, detail: v.get("detail")?.clone(), input_frames: v.get("input_frames")?.as_u64()?, per_folder: v.get("per_folder")?.as_bool()? })
}
