//! `eval`: the official evaluation protocol over a `.torch` dataset and an evaluation index, and
//! `eval-index`: the official generator of DL3DV evaluation indices.
//!
//! **Evaluation** (`donydchen/mvsplat360`, `src/model/model_wrapper.py::test_step`, `src/scripts/post_process.py`,
//! `src/scripts/compute_dl3dv_metrics.py`). For every non-null scene of the index: context and targets from the
//! entry (both sorted, as the official `sort_context_index` / `sort_target_index` do), the encoder, the 3DGS
//! renders of all targets, the refiner over all targets (windows of 14 frames, one noise), and the images of the
//! scored views — the entry's `target_quantify` when it has one (RE10K), else every target — saved as
//!
//! ```text
//! OUT/ImagesGT/{scene}_{view:06}.png                 preprocessed target photo
//! OUT/ImagesGSplat/{scene}_{view:06}.png             3DGS render (after the learned blending, when the model has it)
//! OUT/ImagesRefined0/{scene}_{view:06}.png           refiner output (version 0: one refiner loop)
//! OUT/ImagesPostprocessed0V2/{scene}_{view:06}.png   refined, histogram-matched to the 3DGS render (post_process.py)
//! ```
//!
//! where `view` is the target's view index in the scene (`batch["target"]["index"]`), not its position. The
//! scores are computed from the saved 8-bit PNGs as the official scorer does: PSNR, SSIM, LPIPS-VGG and DISTS per
//! image, averaged over all images of the run (and per scene); FID over the whole image set per method (null
//! below 2 images). The paper's numbers are those of `ImagesRefined0` (the scorer's default; `--use_pp` scores
//! the post-processed folder), both are reported, plus the 3DGS renders.
//!
//! Further outputs: `scenes/{scene}.json` (written atomically after all of the scene's images, so a scene with
//! a record is complete), `scenes/{scene}.fid.safetensors` (its Inception features, so FID needs no re-run),
//! `eval.json` (the settings; a re-run with other settings into the same folder is refused), `metrics.json` and
//! `metrics.md` (the paper's column order PSNR↑ SSIM↑ LPIPS↓ DISTS↓ FID↓). A re-run skips complete scenes; when
//! metric weights have been installed since, it only re-scores the saved images.
//!
//! Like the official loaders, a scene with a view wider than 100° (`max_fov`) is skipped. Deviations: scenes are
//! processed one at a time (weights are re-read per scene); a scene of the index absent from the data is listed
//! as missing instead of silently ignored; duplicate target indices are rendered once.
//!
//! **Index generation** (`src/scripts/generate_evaluation_index_dl3dv.py`): per scene of every chunk (chunks
//! sorted by name, scenes in chunk order), keep the first `int(N · ratio)` views, take `num_context` views by the
//! official farthest-point sampling of the camera centres (start: the centre farthest from the barycentre; then
//! repeatedly the view whose squared distance to the chosen set is largest; first index on ties) sorted, and
//! `num_target` targets `rest[i · (len(rest) // num_target)]` of the remaining views `rest`
//! (`partition_list(...)[:num_target]`). The `_n150` index is `ratio = 0.5` (`int(ratio · 300)` in its name).
//! Deviations: centres are computed in f64 (the official inverts the float32 w2c in float32); a scene with too
//! few views (where the official script stops with an error) is written as `null` with a warning.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor};
use mvsplat360_camera::Camera;
use mvsplat360_dataset::index::{index_from_chunks, index_json, GeneratedIndex, IndexOptions};
use mvsplat360_dataset::torch_chunk::{self, ChunkScene};
use mvsplat360_dataset::{EvaluationEntry, ImageF32, Scene};
use mvsplat360_metrics::dists::Dists;
use mvsplat360_metrics::inception::{FidInception, FidVariant};
use mvsplat360_metrics::lpips::{Lpips, Net};
use mvsplat360_metrics::score::{load_rgb, RgbImage};
use mvsplat360_metrics::weights::MetricsWeightsError;
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::error::{compute, flag, PipelineError, Result};
use crate::model::ModelArgs;
use crate::output::{self, write_json, write_png};
use crate::preprocess::{InputSize, Preprocess};
use crate::render::{self, Prepared, Progress, RefineSettings};
use crate::scale::SceneScale;
use crate::views::{Target, ViewChoice};

pub mod lease;
mod report;
mod run;
mod score;

pub use report::markdown;
use score::*;

/// Ground-truth folder (official name).
pub const GT_DIR: &str = "ImagesGT";
/// Per-scene records and Inception features.
pub const SCENES_DIR: &str = "scenes";
pub const METRICS_JSON: &str = "metrics.json";
pub const METRICS_MD: &str = "metrics.md";
/// The run's settings (checked on resume).
pub const SETTINGS_JSON: &str = "eval.json";
/// Official `dataset.max_fov`: scenes with a wider view are skipped by the loaders.
pub const MAX_FOV_DEG: f64 = 100.0;
const SETTINGS_FORMAT: &str = "mvsplat360-eval/1";
const SCENE_FORMAT: &str = "mvsplat360-eval-scene/1";

/// The official output file name of a target view: `{scene}_{view:06}.png`, `view` its index in the scene.
pub fn image_name(scene: &str, view: usize) -> String {
    format!("{scene}_{view:06}.png")
}

/// A scored image set, in the order of the tables.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Method {
    /// The refiner's output (`ImagesRefined0`): the paper's numbers.
    Refined,
    /// Refined, histogram-matched to the 3DGS render (`ImagesPostprocessed0V2`).
    Postprocessed,
    /// The 3DGS render alone (`ImagesGSplat`).
    GSplat,
}

impl Method {
    pub const ALL: [Method; 3] = [Method::Refined, Method::Postprocessed, Method::GSplat];

    /// Key in the JSON files.
    pub fn key(self) -> &'static str {
        match self {
            Method::Refined => "refined",
            Method::Postprocessed => "postprocessed",
            Method::GSplat => "gsplat",
        }
    }

    /// The official folder.
    pub fn dir(self) -> &'static str {
        match self {
            Method::Refined => "ImagesRefined0",
            Method::Postprocessed => "ImagesPostprocessed0V2",
            Method::GSplat => "ImagesGSplat",
        }
    }

    /// Row label of the tables; `blended`: the model has a learned blender, whose frames `ImagesGSplat` holds.
    pub fn label(self, blended: bool) -> &'static str {
        match self {
            Method::Refined => "MVSplat360 (refined)",
            Method::Postprocessed => "refined + histogram matching",
            Method::GSplat if blended => "3DGS render + learned blending",
            Method::GSplat => "3DGS render",
        }
    }
}

/// Everything `eval` needs.
#[derive(Debug, Clone)]
pub struct EvalRequest {
    /// Folder of `.torch` chunks (with the pixelSplat `index.json` scene → chunk map, else every chunk is read).
    pub data: PathBuf,
    /// Evaluation index (`{scene: {"context", "target", "target_quantify"?} | null}`).
    pub index: PathBuf,
    pub model: ModelArgs,
    /// Model input size; None = the model's own.
    pub size: Option<InputSize>,
    /// `--scene-scale`; None = the model's own setting ([`crate::scale::resolve`]).
    pub scene_scale: Option<SceneScale>,
    pub refine: RefineSettings,
    /// Where the metric networks' weights are (`--weights-dir`; then the env var, then the default folder).
    pub weights_dir: Option<PathBuf>,
    /// Compute these metrics when their weights are found (PSNR and SSIM always).
    pub lpips: bool,
    pub dists: bool,
    pub fid: bool,
    /// Whose FID (default pytorch-fid, the paper's).
    pub fid_variant: FidVariant,
    /// Only these scenes of the index (index order kept).
    pub scenes: Option<Vec<String>>,
    /// At most this many (non-null) scenes, in index order.
    pub limit: Option<usize>,
    pub out: PathBuf,
    /// `--noise`: a safetensors file with the refiner's initial noise per scene (key = scene, shape = one
    /// window's latents: window × 4 × H/8 × W/8), e.g. the noise the official `test_step` drew; None = `--seed`.
    pub noise: Option<PathBuf>,
    /// One rank of `eval --world-size N` ([`crate::launch`]): render and score only the selected scenes whose
    /// position in index order is `rank` modulo `world`, and write no `metrics.json`/`metrics.md` (the launcher
    /// writes them from every scene's record once the ranks are done, as a resumed run does). None = all.
    pub shard: Option<crate::launch::Place>,
    /// `eval --merge`, and a cluster rank once its scenes are done: write `metrics.json`/`metrics.md` from the scene
    /// records already on disk, rendering nothing and never opening the compute device (so a bf16 GPU run merges
    /// on any machine); while some scene is incomplete nothing is written and [`EvalSummary::incomplete`] names it.
    pub merge_only: bool,
    /// `--exclude`: scenes of the index left out (listed in `metrics.json`).
    pub exclude: Vec<String>,
    /// When another process's scene is taken over (`--lease-stale`, `--lease-stall`; see [`lease`]).
    pub lease: lease::Timing,
}

/// Averages of one method over a set of images.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MethodScores {
    pub folder: String,
    pub images: usize,
    /// `+inf` (JSON null) when an image is identical to its ground truth.
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    pub lpips: Option<f64>,
    pub dists: Option<f64>,
    /// Set-level; None for per-scene scores, without weights, or below 2 images.
    pub fid: Option<f64>,
}

/// What a finished run reports.
#[derive(Debug, Clone)]
pub struct EvalSummary {
    pub out: PathBuf,
    /// Non-null scenes of the index in this run's selection.
    pub selected: usize,
    /// Null entries of the index (skipped by the protocol).
    pub null_entries: usize,
    /// Scenes rendered (and scored) in this run.
    pub rendered: Vec<String>,
    /// Complete scenes re-scored from their saved images (metric weights installed since).
    pub rescored: Vec<String>,
    /// Complete scenes skipped without any work.
    pub resumed: Vec<String>,
    /// Index scenes absent from the data.
    pub missing: Vec<String>,
    /// Scenes skipped for a field of view above [`MAX_FOV_DEG`].
    pub skipped_fov: Vec<String>,
    /// Scored images per method.
    pub images: usize,
    pub methods: Vec<(Method, MethodScores)>,
    pub warnings: Vec<String>,
    pub seconds: f64,
    /// With [`EvalRequest::merge_only`]: scenes without a complete record (no tables were written).
    pub incomplete: Vec<String>,
    /// Scenes whose data could not be evaluated (scene, error), recorded in `scenes/{scene}.error.json`; the
    /// others are scored, `metrics.json` lists these, and a rerun tries them again (or `--exclude` them).
    pub failed: Vec<(String, String)>,
}

/// One image's scores.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageScores {
    pub name: String,
    pub view: usize,
    /// dB; `+inf` is stored as null.
    #[serde(with = "inf_as_null")]
    pub psnr: f64,
    pub ssim: f64,
    pub lpips: Option<f64>,
    pub dists: Option<f64>,
}

mod inf_as_null {
    use serde::{Deserialize, Deserializer, Serializer};
    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_f64(*v)
        } else {
            s.serialize_none()
        }
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
    }
}

/// Which networks a scene was scored with.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Networks {
    pub lpips: bool,
    pub dists: bool,
    pub fid: bool,
    /// The FID features' input preparation (absent in records of runs that predate the choice: fid-helper).
    #[serde(default)]
    pub fid_variant: Option<FidVariant>,
}

/// `scenes/{scene}.json`: written last, so its presence means the scene's images and scores are complete.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneRecord {
    pub format: String,
    pub scene: String,
    pub chunk: String,
    /// Sorted context views.
    pub context: Vec<usize>,
    /// Sorted rendered targets.
    pub targets: Vec<usize>,
    /// The scored (saved) targets.
    pub scored: Vec<usize>,
    /// Why the scene was skipped (no images then).
    #[serde(default)]
    pub skipped: Option<String>,
    pub networks: Networks,
    /// Method key → per-image scores (in `scored` order).
    pub methods: BTreeMap<String, Vec<ImageScores>>,
    pub gaussians: usize,
    pub seconds: f64,
    /// Who rendered it (absent in records of earlier versions).
    #[serde(default)]
    pub rendered_by: Option<RenderedBy>,
}

/// The process that rendered a scene, and in what precision.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderedBy {
    pub host: String,
    pub pid: u32,
    pub device: String,
    /// The refiner's `--dtype` (`f32` also without a refiner).
    pub refiner_dtype: String,
    /// The encoder's `--encoder-dtype` (`f32` in records written before the flag).
    #[serde(default = "f32_name")]
    pub encoder_dtype: String,
}

fn f32_name() -> String {
    "f32".into()
}

/// One scene's work, from its index entry.
#[derive(Debug, Clone)]
struct ScenePlan {
    key: String,
    chunk: String,
    context: Vec<usize>,
    targets: Vec<usize>,
    scored: Vec<usize>,
}

impl ScenePlan {
    fn new(key: &str, chunk: &str, e: &EvaluationEntry) -> Self {
        let mut context = e.context.clone();
        context.sort_unstable();
        let mut targets = e.target.clone();
        targets.sort_unstable();
        targets.dedup();
        let scored = match &e.target_quantify {
            Some(q) => {
                let q: BTreeSet<usize> = q.iter().copied().collect();
                targets.iter().copied().filter(|t| q.contains(t)).collect()
            }
            None => targets.clone(),
        };
        Self { key: key.to_string(), chunk: chunk.to_string(), context, targets, scored }
    }
}

fn werr(path: &Path, e: impl std::fmt::Display) -> PipelineError {
    PipelineError::Write { path: path.to_path_buf(), msg: e.to_string() }
}

/// The chunk folder and its scene → chunk file map (`index.json`; `test/index.json` below a dataset root;
/// else every chunk is read for its keys).
fn chunk_map(data: &Path, progress: &dyn Progress) -> Result<(PathBuf, HashMap<String, String>)> {
    if !data.is_dir() {
        return Err(flag("--data", format!("{}: not a folder of .torch chunks", data.display())));
    }
    if data.join("index.json").is_file() {
        return Ok((data.to_path_buf(), torch_chunk::read_chunk_index(&data.join("index.json"))?));
    }
    if data.join("test/index.json").is_file() {
        progress.note(&format!("using {} (the test split)", data.join("test").display()));
        return chunk_map(&data.join("test"), progress);
    }
    let chunks = list_chunks(data)?;
    progress.note(&format!("{} has no index.json: reading {} chunks for their scene keys", data.display(), chunks.len()));
    let mut map = HashMap::new();
    for c in chunks {
        for s in torch_chunk::read_chunk(&data.join(&c))? {
            map.entry(s.key).or_insert_with(|| c.clone());
        }
    }
    Ok((data.to_path_buf(), map))
}

/// The `.torch` file names of a folder, sorted (the official `sorted(glob("*.torch"))`).
fn list_chunks(data: &Path) -> Result<Vec<String>> {
    let rd = std::fs::read_dir(data).map_err(|e| flag("--data", format!("{}: {e}", data.display())))?;
    let mut v: Vec<String> =
        rd.flatten().filter(|e| e.path().is_file()).map(|e| e.file_name().to_string_lossy().into_owned()).filter(|n| n.ends_with(".torch")).collect();
    v.sort();
    if v.is_empty() {
        return Err(flag("--data", format!("{}: no .torch chunks", data.display())));
    }
    Ok(v)
}

/// Field of view (x, y) in degrees as the official `get_fov`: the angle between the rays through the middles
/// of the left and right (top and bottom) image borders.
pub fn official_fov_deg(c: &Camera) -> (f64, f64) {
    let [fx, fy, cx, cy] = c.normalized_intrinsics();
    let ray = |u: f64, v: f64| {
        let r = [(u - cx) / fx, (v - cy) / fy, 1.0];
        let n = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
        [r[0] / n, r[1] / n, r[2] / n]
    };
    let angle = |a: [f64; 3], b: [f64; 3]| (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0).acos().to_degrees();
    (angle(ray(0.0, 0.5), ray(1.0, 0.5)), angle(ray(0.5, 0.0), ray(0.5, 1.0)))
}

/// The settings that must match for a resumed run to reuse scenes.
fn settings_json(req: &EvalRequest, spec: &crate::model::ModelSpec, size: InputSize) -> serde_json::Value {
    let file = |p: &Path| {
        json!({
            "name": p.file_name().map(|n| n.to_string_lossy().into_owned()),
            "bytes": std::fs::metadata(p).map(|m| m.len()).ok(),
        })
    };
    let refiner_file = spec.refiner.as_ref().map(|(_, w)| match w {
        crate::model::RefinerWeights::File(p) | crate::model::RefinerWeights::Ckpt(p) => file(p),
    });
    let mut v = json!({
        "format": SETTINGS_FORMAT,
        "experiment": spec.data.experiment,
        "encoder": file(&spec.encoder_file),
        "refiner": refiner_file,
        "size": size,
        // What applies, not how it was asked for: a folder resumes whichever way the same scaling was chosen.
        "scene_scale": crate::scale::resolve(req.scene_scale, None, spec.scene_scale).0,
        "refine": spec.refiner.as_ref().map(|_| &req.refine),
    });
    // Given noise changes every refined frame; none adds nothing, so folders of earlier runs still resume.
    if let Some(n) = &req.noise {
        v["noise"] = file(n);
    }
    // Fitting changes every frame; none adds nothing, so folders of earlier runs still resume.
    if spec.fit.steps > 0 {
        v["fit"] = json!(spec.fit);
    }
    // Blending changes every frame, as fitting does.
    if let Some((b, _)) = &spec.blend {
        v["blend"] = json!(b);
    }
    // Half precision changes the refined frames; f32 adds nothing, so folders of earlier runs still resume.
    let dtype = req.model.compute.refiner_dtype;
    if spec.refiner.is_some() && dtype != candle_core::DType::F32 {
        v["refiner_dtype"] = json!(dtype.as_str());
    }
    // A bf16 encoder moves every Gaussian, so it is part of the settings too (f32 adds nothing, as above).
    let enc = req.model.compute.encoder_dtype;
    if enc != candle_core::DType::F32 {
        v["encoder_dtype"] = json!(enc.as_str());
    }
    // As read back from eval.json (f32 settings print shortest-f32 and parse back as a different f64).
    serde_json::to_string(&v).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or(v)
}

/// Check the folder's `eval.json` against this run's settings (write it when absent).
fn check_settings(out: &Path, settings: &serde_json::Value) -> Result<()> {
    let path = out.join(SETTINGS_JSON);
    if let Ok(text) = std::fs::read_to_string(&path) {
        let old: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| flag("--out", format!("{}: unreadable ({e}); remove it or use another --out", path.display())))?;
        if &old != settings {
            let mut diffs = Vec::new();
            if let (Some(a), Some(b)) = (old.as_object(), settings.as_object()) {
                let keys: BTreeSet<&String> = a.keys().chain(b.keys()).collect();
                for k in keys {
                    if a.get(k) != b.get(k) {
                        diffs.push(format!("{k}: {} → {}", a.get(k).unwrap_or(&json!(null)), b.get(k).unwrap_or(&json!(null))));
                    }
                }
            }
            return Err(flag(
                "--out",
                format!(
                    "{} holds an evaluation with other settings ({}); use another --out, or remove the folder to start over",
                    out.display(),
                    diffs.join("; ")
                ),
            ));
        }
        return Ok(());
    }
    write_json(&path, settings)
}

enum Resume {
    /// Complete: nothing to do.
    Done(Box<SceneRecord>),
    /// Images complete, scores incomplete (e.g. metric weights installed since).
    Rescore,
    Render,
}

fn scene_json(out: &Path, key: &str) -> PathBuf {
    out.join(SCENES_DIR).join(format!("{key}.json"))
}

fn features_file(out: &Path, key: &str) -> PathBuf {
    out.join(SCENES_DIR).join(format!("{key}.fid.safetensors"))
}

fn images_present(out: &Path, plan: &ScenePlan, methods: &[Method]) -> bool {
    let dirs = std::iter::once(GT_DIR).chain(methods.iter().map(|m| m.dir()));
    dirs.into_iter().all(|d| plan.scored.iter().all(|&v| out.join(d).join(image_name(&plan.key, v)).is_file()))
}

fn resume_state(out: &Path, plan: &ScenePlan, methods: &[Method], nets: Networks) -> Resume {
    let Ok(text) = std::fs::read_to_string(scene_json(out, &plan.key)) else { return Resume::Render };
    let Ok(rec) = serde_json::from_str::<SceneRecord>(&text) else { return Resume::Render };
    if rec.format != SCENE_FORMAT || rec.scene != plan.key || rec.context != plan.context || rec.targets != plan.targets || rec.scored != plan.scored {
        return Resume::Render;
    }
    if rec.skipped.is_some() {
        return Resume::Done(Box::new(rec));
    }
    if !images_present(out, plan, methods) {
        return Resume::Render;
    }
    let scores_ok = methods.iter().all(|m| rec.methods.get(m.key()).is_some_and(|v| v.len() == plan.scored.len()));
    let nets_ok = (!nets.lpips || rec.networks.lpips)
        && (!nets.dists || rec.networks.dists)
        && (!nets.fid || (rec.networks.fid && rec.networks.fid_variant == nets.fid_variant && features_file(out, &plan.key).is_file()));
    if scores_ok && nets_ok {
        Resume::Done(Box::new(rec))
    } else {
        Resume::Rescore
    }
}

/// Shared state of a run.
struct Ctx<'a> {
    req: &'a EvalRequest,
    spec: crate::model::ModelSpec,
    pre: Preprocess,
    refine_file: Option<PathBuf>,
    /// Opened once for every scene.
    device: candle_core::Device,
    methods: Vec<Method>,
    nets: Nets,
    /// The scene scaling that applies and why ([`crate::scale::resolve`]).
    scene_scale: (SceneScale, &'static str),
    /// `--noise`, read once.
    noise: Option<HashMap<String, Tensor>>,
    progress: &'a dyn Progress,
}

/// Render one scene, save its scored views in the official layout, score them, write its record; nothing is
/// written once `mine()` says another process took the scene over.
fn render_scene(cx: &Ctx, scene: Scene, plan: &ScenePlan, mine: &dyn Fn() -> bool, warnings: &mut Vec<String>) -> Result<Rendered> {
    let t = Instant::now();
    let out = &cx.req.out;
    let idx_err = |what: &str, v: usize| {
        flag("--index", format!("{}: scene {} {what} view {v} is out of range (the scene has {} views)", cx.req.index.display(), plan.key, scene.len()))
    };
    for &v in &plan.context {
        if v >= scene.len() {
            return Err(idx_err("context", v));
        }
    }
    for &v in &plan.targets {
        if v >= scene.len() {
            return Err(idx_err("target", v));
        }
    }
    let mut record = SceneRecord {
        format: SCENE_FORMAT.into(),
        scene: plan.key.clone(),
        chunk: plan.chunk.clone(),
        context: plan.context.clone(),
        targets: plan.targets.clone(),
        scored: plan.scored.clone(),
        skipped: None,
        networks: cx.nets.used(),
        methods: BTreeMap::new(),
        gaussians: 0,
        seconds: 0.0,
        rendered_by: Some(RenderedBy {
            host: mvsplat360_dataset::atomic::host_name(),
            pid: std::process::id(),
            device: cx.req.model.compute.device.to_string(),
            refiner_dtype: if cx.refine_file.is_some() { cx.req.model.compute.refiner_dtype.as_str().to_string() } else { "f32".into() },
            encoder_dtype: cx.req.model.compute.encoder_dtype.as_str().to_string(),
        }),
    };
    // The official loaders skip scenes with a view wider than max_fov (all views of the scene are checked).
    if let Some((i, (fx, fy))) = scene.cameras.iter().map(official_fov_deg).enumerate().find(|(_, (x, y))| *x > MAX_FOV_DEG || *y > MAX_FOV_DEG) {
        let why = format!("view {i} has a {fx:.1}°×{fy:.1}° field of view, above the official max_fov {MAX_FOV_DEG}°");
        if !mine() {
            return Ok(Rendered::Lost);
        }
        warnings.push(format!("scene {} skipped: {why}", plan.key));
        record.skipped = Some(why);
        return write_record(out, &record).map(Rendered::Record);
    }
    if plan.context.len() < 2 {
        return Err(flag("--index", format!("scene {}: need at least 2 context views, got {}", plan.key, plan.context.len())));
    }
    let spec = &cx.spec;
    cx.pre.check_sizes(&scene, &[&plan.context[..], &plan.targets[..]].concat())?;
    let mut context_images = Vec::new();
    let mut raw_cams = Vec::new();
    for &i in &plan.context {
        let (img, cam) = cx.pre.view(&scene.image(i)?, &scene.cameras[i])?;
        context_images.push(img);
        raw_cams.push(cam);
    }
    let (transform, warning) = crate::scale::scene_transform(cx.scene_scale.0, &raw_cams, spec.data.near, spec.data.far);
    if let Some(w) = warning {
        cx.progress.note(&format!("warning: scene {}: {w}", plan.key));
    }
    let context_cameras: Vec<Camera> = raw_cams.iter().map(|c| transform.apply(c)).collect();
    let mut target_cameras = Vec::new();
    let mut target_photos = Vec::new();
    for &i in &plan.targets {
        let (img, cam) = cx.pre.view(&scene.image(i)?, &scene.cameras[i])?;
        target_cameras.push(transform.apply(&cam));
        target_photos.push(Some(img));
    }
    let choice = ViewChoice {
        context: plan.context.clone(),
        targets: plan.targets.iter().map(|&i| Target { camera: scene.cameras[i].clone(), view: Some(i) }).collect(),
        quantify: Some(plan.scored.clone()),
    };
    let p = Prepared {
        scene,
        spec: spec.clone(),
        choice,
        pre: cx.pre,
        transform,
        scene_scale: cx.scene_scale,
        context_images,
        context_cameras,
        target_cameras,
        target_photos,
        device: cx.device.clone(),
        refiner_dtype: cx.req.model.compute.refiner_dtype,
        // Every scene's key was checked when the file was read.
        noise: cx.noise.as_ref().and_then(|m| m.get(&plan.key).cloned()),
    };

    let g = render::encode(&p, cx.progress)?;
    let (g, _) = render::fit_to_context(&p, g, cx.progress)?;
    record.gaussians = g.means.dim(0).map_err(compute("encoder"))?;
    let renders = render::frames_3dgs(&p, &g, cx.progress)?;
    drop(g);
    let mut gsplat = Vec::with_capacity(renders.len());
    let mut feats = Vec::with_capacity(renders.len());
    // The 3DGS stage's output (the blender's frames when the model has one; the settings record it).
    for r in renders {
        gsplat.push(output::tensor_image(r.output())?);
        feats.push(r.features);
    }
    let refined: Option<Vec<ImageF32>> = match &cx.refine_file {
        Some(wf) => {
            let r = render::refine_frames(&p, &feats, wf, &cx.req.refine, cx.progress)?;
            Some(r.iter().map(output::tensor_image).collect::<Result<Vec<_>>>()?)
        }
        None => None,
    };
    drop(feats);
    if !mine() {
        return Ok(Rendered::Lost);
    }
    let scored: BTreeSet<usize> = plan.scored.iter().copied().collect();
    for (k, &v) in plan.targets.iter().enumerate() {
        if !scored.contains(&v) {
            continue;
        }
        let name = image_name(&plan.key, v);
        if let Some(gt) = &p.target_photos[k] {
            write_png(&out.join(GT_DIR).join(&name), gt)?;
        }
        write_png(&out.join(Method::GSplat.dir()).join(&name), &gsplat[k])?;
        if let Some(r) = &refined {
            write_png(&out.join(Method::Refined.dir()).join(&name), &r[k])?;
            write_png(&out.join(Method::Postprocessed.dir()).join(&name), &render::histogram_match(&r[k], &gsplat[k])?)?;
        }
    }
    cx.progress.begin("scoring", 0);
    record.methods = score_scene(out, plan, &cx.methods, &cx.nets)?;
    cx.progress.end();
    record.seconds = t.elapsed().as_secs_f64();
    if !mine() {
        return Ok(Rendered::Lost);
    }
    write_record(out, &record).map(Rendered::Record)
}

/// Scene positions in the order this process takes them: a `--world-size` rank its own share only (its launcher
/// supervises the others), a cluster rank its share first and then the rest (helping with what others have
/// not claimed), a lone process all in index order; scenes of one chunk stay together within each part.
fn scene_order(plans: &[ScenePlan], shard: Option<crate::launch::Place>) -> Vec<usize> {
    let by_chunk = |mut v: Vec<usize>| {
        let first: HashMap<&str, usize> = v.iter().rev().map(|&i| (plans[i].chunk.as_str(), i)).collect();
        v.sort_by_key(|&i| (first[plans[i].chunk.as_str()], i));
        v
    };
    let all: Vec<usize> = (0..plans.len()).collect();
    match shard {
        None => by_chunk(all),
        Some(p) => {
            let (own, rest): (Vec<usize>, Vec<usize>) = all.into_iter().partition(|i| i % p.world == p.rank);
            let mut v = by_chunk(own);
            if p.launcher != crate::launch::Launcher::Project {
                v.extend(by_chunk(rest));
            }
            v
        }
    }
}

fn failure_json(out: &Path, key: &str) -> PathBuf {
    out.join(SCENES_DIR).join(format!("{key}.error.json"))
}

fn read_failure(out: &Path, key: &str) -> Option<String> {
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(failure_json(out, key)).ok()?).ok()?;
    Some(v["error"].as_str().unwrap_or("failed").to_string())
}

/// A failure recorded by another process during this run (an older one is tried again).
fn read_failure_since(out: &Path, key: &str, since: std::time::SystemTime) -> Option<String> {
    let t = std::fs::metadata(failure_json(out, key)).and_then(|m| m.modified()).ok()?;
    (t >= since).then(|| read_failure(out, key)).flatten()
}

/// Errors of one scene's data (an undecodable image, a view out of range, non-finite output), which are recorded
/// while the evaluation goes on; anything else (the device, the disk) ends it.
fn is_data_error(e: &PipelineError) -> bool {
    matches!(e, PipelineError::Dataset(_) | PipelineError::Camera(_) | PipelineError::NonFinite { .. } | PipelineError::Flag { flag: "--index", .. })
}

/// What became of a claimed scene.
enum Rendered {
    Record(SceneRecord),
    /// The chunk the data's index names does not hold it.
    NotInChunk,
    /// Another process took its lease over: nothing was written.
    Lost,
}

/// Reads the scene from its chunk (the last chunk read is kept) and renders it while `mine()` says this process
/// still holds it.
fn render_claimed(
    cx: &Ctx,
    data_dir: &Path,
    plan: &ScenePlan,
    cache: &mut Option<(String, HashMap<String, ChunkScene>)>,
    mine: &dyn Fn() -> bool,
    warnings: &mut Vec<String>,
) -> Result<Rendered> {
    let path = data_dir.join(&plan.chunk);
    if cache.as_ref().is_none_or(|(c, _)| *c != plan.chunk) {
        *cache = None;
        let scenes = torch_chunk::read_chunk(&path)?.into_iter().map(|s| (s.key.clone(), s)).collect();
        *cache = Some((plan.chunk.clone(), scenes));
    }
    let Some(cs) = cache.as_mut().and_then(|(_, m)| m.remove(&plan.key)) else { return Ok(Rendered::NotInChunk) };
    let scene = cs.into_scene(&path)?;
    scene.validate()?;
    render_scene(cx, scene, plan, mine, warnings)
}

/// Write `scenes/{scene}.json` atomically and return the record as read back from it, so a first run and a
/// resumed one aggregate bit-identical numbers.
fn write_record(out: &Path, rec: &SceneRecord) -> Result<SceneRecord> {
    let path = scene_json(out, &rec.scene);
    let text = serde_json::to_string_pretty(rec).map_err(|e| werr(&path, e))?;
    output::write_bytes(&path, text.as_bytes())?;
    serde_json::from_str(&text).map_err(|e| werr(&path, e))
}

/// What the ranks of a multi-process evaluation share, done once before they start: the model resolved, the
/// output folder's settings checked (`eval.json` written), an official checkpoint's refiner converted.
pub fn prepare(req: &EvalRequest, progress: &dyn Progress) -> Result<()> {
    let spec = crate::model::resolve(&req.model)?;
    output::check_writable(&req.out, "--out")?;
    let size = req.size.unwrap_or(InputSize::Fixed { width: spec.data.image_width, height: spec.data.image_height });
    check_settings(&req.out, &settings_json(req, &spec, size))?;
    if let Some((_, w)) = &spec.refiner {
        crate::model::refiner_safetensors(w, &|m| progress.note(m))?;
    }
    Ok(())
}

/// The whole evaluation (see the module docs).
pub fn run(req: &EvalRequest, progress: &dyn Progress) -> Result<EvalSummary> {
    run::run_scenes(req, progress).map_err(|e| match e {
        PipelineError::Write { path, msg } if crate::output::disk_full(&msg) => PipelineError::Write {
            msg: format!("{msg}: the disk is full. The scenes finished so far are kept in {} (every file there is whole); free some space and run the same command again to go on", req.out.display()),
            path,
        },
        e => e,
    })
}

// ------------------------------------------------------------------------------------------------------------
// Evaluation index generation (generate_evaluation_index_dl3dv.py)
// ------------------------------------------------------------------------------------------------------------

/// Run the official generator over every `.torch` chunk of `data`.
pub fn generate_index(data: &Path, opts: &IndexOptions, progress: &dyn Progress) -> Result<GeneratedIndex> {
    if opts.num_context == 0 {
        return Err(flag("--num-context", "must be at least 1"));
    }
    if opts.num_target == 0 {
        return Err(flag("--num-target", "must be at least 1"));
    }
    if !(opts.view_selection_ratio > 0.0 && opts.view_selection_ratio <= 1.0) {
        return Err(flag("--view-selection-ratio", format!("must be in (0, 1], got {}", opts.view_selection_ratio)));
    }
    if !data.is_dir() {
        return Err(flag("--data", format!("{}: not a folder of .torch chunks", data.display())));
    }
    let chunks = list_chunks(data)?;
    progress.begin("reading chunks", chunks.len() as u64);
    let g = index_from_chunks(data, &chunks, opts, &mut || progress.advance(1));
    progress.end();
    Ok(g?)
}

/// Write a generated index atomically.
pub fn write_index(path: &Path, g: &GeneratedIndex) -> Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        output::create_dir(parent)?;
    }
    output::write_bytes(path, index_json(&g.entries).as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fov_of_a_square_90_degree_camera() {
        let c = Camera {
            fx: 50.0,
            fy: 50.0,
            cx: 50.0,
            cy: 50.0,
            width: 100,
            height: 100,
            c2w: [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        };
        let (x, y) = official_fov_deg(&c);
        assert!((x - 90.0).abs() < 1e-9 && (y - 90.0).abs() < 1e-9);
    }
}
