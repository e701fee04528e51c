//! `mvsplat360 train-blend`: trains the learned blender (`mvsplat360_pipeline::blend`) of a model folder and
//! writes the folder with it, as the shipped model's blender was made.
//!
//! 1. **Inputs.** Every scene runs the held-out protocol (5 context views by farthest-point sampling, every other
//!    view a target) through the product path — `render::prepare` (scene scale `auto`), the encoder, the model's
//!    test-time fitting, then `render::blend_input` per target — and its inputs and target photos are stored in
//!    `OUT/cache/{train,val}/NAME.safetensors` (written atomically; a re-run skips cached scenes). Procedural
//!    seeds are first written as scene folders (`OUT/procedural/proc-SEED`, 8-bit PNGs + `transforms.json`).
//!    `OUT/cache/settings.json` records the model and layout; another model or layout in the same `--out` is
//!    refused, since the cached inputs would no longer be the blender's.
//! 2. **Training.** MSE, Adam (PyTorch defaults) at `lr` with a cosine decay to 0 over `steps`, batches of `batch`
//!    targets drawn with replacement, a horizontal flip of the whole batch with probability ½. The draws of step k
//!    depend only on (seed, k), so a run resumed from its checkpoint continues exactly where it stopped.
//!    Every `every` steps (and at the last): the validation scenes' mean PSNR, `OUT/checkpoint.safetensors`
//!    (weights, Adam's moments and the step in one file, written atomically) and a line in `OUT/log.jsonl`.
//!    `OUT/train-settings.json` holds the training flags; `resume` requires the same.
//! 3. **`OUT/model`**: a copy of the model folder with the blender's weights (`blend.*`) and its `blend` settings,
//!    read back and loaded as `render` does before it is reported.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, IndexOp, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use mvsplat360_pipeline::blend::{BlendNet, BlendSettings, PREFIX};
use mvsplat360_pipeline::model::{self, ModelArgs, RefinerArg};
use mvsplat360_pipeline::render::{self, Progress};
use rand::Rng;

use crate::error::{Result, TrainError};
use crate::optim::{Adam, Param};

/// Where training or validation scenes come from.
#[derive(Debug, Clone, PartialEq)]
pub enum SceneSource {
    /// A scene folder, or a folder of scene folders.
    Folder(PathBuf),
    /// Procedural scenes (`data::procedural`) with these seeds, inclusive.
    Procedural { first: u64, last: u64 },
}

impl std::str::FromStr for SceneSource {
    type Err = String;
    /// `procedural:SEED` or `procedural:FIRST-LAST`, else a path.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let Some(r) = s.strip_prefix("procedural:") else { return Ok(Self::Folder(PathBuf::from(s))) };
        let num = |x: &str| x.trim().parse::<u64>().map_err(|e| format!("`{s}`: `{x}` is not a seed ({e}); use procedural:SEED or procedural:FIRST-LAST"));
        let (first, last) = match r.split_once('-') {
            Some((a, b)) => (num(a)?, num(b)?),
            None => (num(r)?, num(r)?),
        };
        if last < first {
            return Err(format!("`{s}`: the last seed is below the first"));
        }
        Ok(Self::Procedural { first, last })
    }
}

/// Everything `train-blend` needs.
#[derive(Debug, Clone)]
pub struct BlendRequest {
    /// The model folder whose encoder and fitting make the blender's inputs (its own blender, if any, is
    /// ignored and replaced in `OUT/model`).
    pub model: PathBuf,
    /// Overrides the model's test-time fitting step count (as `render --fit-steps`).
    pub fit_steps: Option<usize>,
    pub compute: mvsplat360_pipeline::compute::Compute,
    pub train: Vec<SceneSource>,
    pub val: Vec<SceneSource>,
    /// The blender's layout and width.
    pub layout: BlendSettings,
    pub steps: u64,
    pub lr: f64,
    pub batch: usize,
    pub seed: u64,
    pub every: u64,
    /// Continue from `OUT/checkpoint.safetensors` (the same settings are required).
    pub resume: bool,
    /// Stop after this step (a checkpoint is written there); for tests of `resume`. None = `steps`.
    pub stop_after: Option<u64>,
    pub out: PathBuf,
}

/// What a run reports.
#[derive(Debug, Clone)]
pub struct BlendSummary {
    pub train_scenes: usize,
    pub train_images: usize,
    pub val_scenes: usize,
    /// Validation PSNR of the renders as they are (the blender at step 0 is close to them) and after training.
    pub val_psnr_renders: Option<f64>,
    pub val_psnr: Option<f64>,
    pub step: u64,
    /// The model folder written (None when stopped early by `stop_after`).
    pub model: Option<PathBuf>,
}

/// One line of `log.jsonl`.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct BlendLogRecord {
    pub step: u64,
    /// Mean training MSE over the steps since the previous record.
    pub mse: f64,
    pub val_psnr: Option<f64>,
    pub lr: f64,
}

fn data_err(msg: impl Into<String>) -> TrainError {
    TrainError::Data(msg.into())
}

fn write_err(p: &Path, e: impl std::fmt::Display) -> TrainError {
    TrainError::Write { path: p.to_path_buf(), msg: e.to_string() }
}

/// The protocol's scenes of `sources` as (name, folder); procedural seeds are written under `proc_dir` first.
fn scene_folders(sources: &[SceneSource], proc_dir: &Path, width: u32, height: u32) -> Result<Vec<(String, PathBuf)>> {
    let is_scene = |p: &Path| p.join("transforms.json").is_file() || p.join("sparse").is_dir();
    let mut out: Vec<(String, PathBuf)> = Vec::new();
    for s in sources {
        match s {
            SceneSource::Folder(p) => {
                if is_scene(p) {
                    out.push((name_of(p), p.clone()));
                    continue;
                }
                let rd = std::fs::read_dir(p)
                    .map_err(|e| data_err(format!("{}: {e} (give a scene folder, a folder of scenes, or procedural:SEEDS)", p.display())))?;
                let mut v: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).filter(|q| q.is_dir() && is_scene(q)).collect();
                if v.is_empty() {
                    return Err(data_err(format!("{}: no scene folders (with transforms.json or sparse/) inside", p.display())));
                }
                v.sort();
                out.extend(v.into_iter().map(|q| (name_of(&q), q)));
            }
            SceneSource::Procedural { first, last } => {
                for seed in *first..=*last {
                    let dir = proc_dir.join(format!("proc-{seed}"));
                    if !dir.join("transforms.json").is_file() {
                        write_procedural(seed, &dir, width, height)?;
                    }
                    out.push((format!("proc-{seed}"), dir));
                }
            }
        }
    }
    let mut seen = std::collections::BTreeMap::new();
    for (n, p) in &out {
        if let Some(q) = seen.insert(n.clone(), p.clone()) {
            return Err(data_err(format!("two scenes are named `{n}` ({} and {}); each scene name must be unique", q.display(), p.display())));
        }
    }
    Ok(out)
}

fn name_of(p: &Path) -> String {
    p.file_name().map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().to_string())
}

/// Procedural scene `seed` (32 views on a loop) as a scene folder: `images/NNN.png` and `transforms.json`.
pub fn write_procedural(seed: u64, dir: &Path, width: u32, height: u32) -> Result<()> {
    let g = crate::data::procedural::generate(seed, &crate::data::procedural::GenOptions { views: 32, width, height, samples: 2 });
    let tmp = dir.with_extension("partial");
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(tmp.join("images")).map_err(|e| write_err(&tmp, e))?;
    let mut frames = Vec::new();
    let c0 = &g.views[0].camera;
    for (i, v) in g.views.iter().enumerate() {
        let f = format!("images/{i:03}.png");
        let img = mvsplat360_dataset::ImageF32 { width, height, data: v.image.clone() };
        img.to_rgb8().save(tmp.join(&f)).map_err(|e| write_err(&tmp.join(&f), e))?;
        let cv = nalgebra::Matrix4::from_fn(|r, c| v.camera.c2w[r][c]);
        let gl = mvsplat360_camera::convert::opencv_to_opengl(&cv);
        frames.push(serde_json::json!({ "file_path": f, "transform_matrix": mvsplat360_camera::convert::to_array(&gl) }));
    }
    let t = serde_json::json!({
        "camera_model": "PINHOLE", "fl_x": c0.fx, "fl_y": c0.fy, "cx": c0.cx, "cy": c0.cy, "w": width, "h": height,
        "frames": frames,
    });
    let p = tmp.join("transforms.json");
    std::fs::write(&p, serde_json::to_string_pretty(&t).unwrap_or_default()).map_err(|e| write_err(&p, e))?;
    let _ = std::fs::remove_dir_all(dir);
    std::fs::rename(&tmp, dir).map_err(|e| write_err(dir, e))
}

/// The product path on one scene: (inputs (N,C,H,W), target photos (N,3,H,W)) of the protocol's targets.
pub fn scene_inputs(req: &BlendRequest, scene: &Path, progress: &dyn Progress) -> Result<(Tensor, Tensor)> {
    let model = ModelArgs {
        ckpt: Some(req.model.clone()),
        refiner: Some(RefinerArg::None),
        fit_steps: req.fit_steps,
        no_blend: true,
        compute: req.compute.clone(),
        ..Default::default()
    };
    let p = mvsplat360_pipeline::eval_scenes::protocol_prepared(scene, model, 5, None)?;
    let g = render::encode(&p, progress)?;
    let (g, _) = render::fit_to_context(&p, g, progress)?;
    let (mut xs, mut ts) = (Vec::new(), Vec::new());
    for (c, photo) in p.target_cameras.iter().zip(&p.target_photos) {
        let (_, x) = render::blend_input(&p, &g, &req.layout, c)?;
        let (h, w) = (c.height as usize, c.width as usize);
        xs.push(Tensor::from_vec(x, (req.layout.channels(), h, w), &Device::Cpu)?);
        let photo = photo.as_ref().ok_or_else(|| data_err(format!("{}: a target without a photo", scene.display())))?;
        ts.push(Tensor::from_slice(&photo.data, (3, h, w), &Device::Cpu)?);
    }
    Ok((Tensor::stack(&xs, 0)?, Tensor::stack(&ts, 0)?))
}

/// What makes cached inputs valid: the model's config and weights, the fitting override and the layout.
fn cache_settings(req: &BlendRequest) -> Result<serde_json::Value> {
    let cfg_path = req.model.join(model::MODEL_CONFIG);
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cfg_path).map_err(|e| data_err(format!("{}: {e} (--model needs a model folder)", cfg_path.display())))?)
            .map_err(|e| data_err(format!("{}: {e}", cfg_path.display())))?;
    let weights = req.model.join(model::MODEL_WEIGHTS);
    let bytes = std::fs::read(&weights).map_err(|e| data_err(format!("{}: {e}", weights.display())))?;
    // FNV-1a: identifies the weights without another dependency; not a security measure.
    let hash = bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3));
    let mut cfg = cfg;
    if let Some(o) = cfg.as_object_mut() {
        o.remove("blend");
    }
    let layout = serde_json::json!({ "planes": req.layout.planes, "views": req.layout.views, "span": req.layout.span });
    Ok(serde_json::json!({
        "model_config": cfg,
        "model_weights_fnv1a": format!("{hash:016x}"),
        "fit_steps": req.fit_steps,
        "layout": layout,
    }))
}

fn check_or_write_settings(path: &Path, want: &serde_json::Value, what: &str) -> Result<()> {
    if let Ok(text) = std::fs::read_to_string(path) {
        let have: serde_json::Value = serde_json::from_str(&text).map_err(|e| data_err(format!("{}: {e}", path.display())))?;
        if &have != want {
            return Err(data_err(format!("{}: this --out was made with other {what}; use another --out (or delete it)", path.display())));
        }
        return Ok(());
    }
    if let Some(d) = path.parent() {
        std::fs::create_dir_all(d).map_err(|e| write_err(d, e))?;
    }
    write_atomic(path, &serde_json::to_vec_pretty(want).unwrap_or_default())
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(mvsplat360_pipeline::output::write_bytes(path, bytes)?)
}

/// Named tensors as one safetensors file, written atomically (an interruption leaves the previous file).
fn save_tensors(path: &Path, tensors: HashMap<String, Tensor>) -> Result<()> {
    Ok(mvsplat360_pipeline::output::atomic_write(path, |p| candle_core::safetensors::save(&tensors, p).map_err(|e| e.to_string()))?)
}

/// Caches every scene (name, folder) in `dir`; returns the cache files in scene order.
fn cache(req: &BlendRequest, scenes: &[(String, PathBuf)], dir: &Path, progress: &dyn Progress) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).map_err(|e| write_err(dir, e))?;
    let mut files = Vec::new();
    let todo = scenes.iter().filter(|(n, _)| !dir.join(format!("{n}.safetensors")).is_file()).count();
    if todo > 0 {
        progress.note(&format!("computing the blender's inputs of {todo} scene(s) into {}", dir.display()));
        progress.begin("blender inputs", todo as u64);
    }
    for (name, scene) in scenes {
        let file = dir.join(format!("{name}.safetensors"));
        if !file.is_file() {
            let t0 = std::time::Instant::now();
            let (x, t) = scene_inputs(req, scene, &render::Silent)?;
            let n = x.dim(0)?;
            save_tensors(&file, [("x".to_string(), x), ("target".to_string(), t)].into())?;
            progress.note(&format!("{name}: {n} targets, {:.0} s", t0.elapsed().as_secs_f64()));
            progress.advance(1);
        }
        files.push(file);
    }
    if todo > 0 {
        progress.end();
    }
    Ok(files)
}

/// The cached (inputs, targets) of `files`, concatenated.
fn load(files: &[PathBuf], channels: usize) -> Result<(Tensor, Tensor)> {
    let (mut x, mut t) = (Vec::new(), Vec::new());
    for f in files {
        let m = candle_core::safetensors::load(f, &Device::Cpu).map_err(|e| data_err(format!("{}: {e} (delete it to recompute)", f.display())))?;
        let (Some(a), Some(b)) = (m.get("x"), m.get("target")) else {
            return Err(data_err(format!("{}: not a blender cache (no `x`/`target`); delete it to recompute", f.display())));
        };
        if a.dim(1)? != channels {
            return Err(data_err(format!("{}: {} input channels, the layout takes {channels}; delete it to recompute", f.display(), a.dim(1)?)));
        }
        x.push(a.clone());
        t.push(b.clone());
    }
    Ok((Tensor::cat(&x, 0)?, Tensor::cat(&t, 0)?))
}

/// Mean PSNR (predictions clamped to [0, 1]) over the images of (N,3,H,W) tensors.
pub fn mean_psnr(pred: &Tensor, target: &Tensor) -> Result<f64> {
    let n = pred.dim(0)?;
    let mut s = 0.0;
    for i in 0..n {
        let a: Vec<f32> = pred.i(i)?.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
        let b: Vec<f32> = target.i(i)?.flatten_all()?.to_vec1()?;
        s += mvsplat360_metrics::psnr::psnr(&a, &b);
    }
    Ok(s / n.max(1) as f64)
}

fn evaluate(net: &BlendNet, x: &Tensor, t: &Tensor) -> Result<f64> {
    let n = x.dim(0)?;
    let mut outs = Vec::new();
    for s in (0..n).step_by(32) {
        outs.push(net.forward(&x.narrow(0, s, 32.min(n - s))?)?.detach().to_device(&Device::Cpu)?);
    }
    mean_psnr(&Tensor::cat(&outs, 0)?, &t.to_device(&Device::Cpu)?)
}

/// The learning rate of step `step` (1-based): cosine from `lr` to 0 over `steps`.
pub fn cosine_lr(lr: f64, step: u64, steps: u64) -> f64 {
    0.5 * lr * (1.0 + (std::f64::consts::PI * step as f64 / steps.max(1) as f64).cos())
}

const CHECKPOINT: &str = "checkpoint.safetensors";
const TRAIN_SETTINGS: &str = "train-settings.json";
const LOG: &str = "log.jsonl";

fn train_settings(req: &BlendRequest) -> serde_json::Value {
    serde_json::json!({ "steps": req.steps, "lr": req.lr, "batch": req.batch, "seed": req.seed, "every": req.every, "width": req.layout.width })
}

/// Candle's conv2d initialisation (weights Kaiming-normal over the fan-in, biases uniform in ±1/√in_channels), drawn
/// from `seed` so that a run is reproducible; the output conv starts at zero, so step 0 returns the render (the
/// softmax's bias favours it).
fn seeded_init(vars: &[(String, Var)], seed: u64) -> Result<()> {
    use rand::SeedableRng;
    use rand_distr::Distribution;
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0xB1E2_D000);
    let mut in_channels: HashMap<String, usize> = HashMap::new();
    for (k, v) in vars {
        if let Some(layer) = k.strip_suffix(".weight") {
            in_channels.insert(layer.to_string(), v.dims().get(1).copied().unwrap_or(1));
        }
    }
    for (k, v) in vars {
        let n = v.elem_count();
        let vals: Vec<f32> = if k.starts_with(&format!("{PREFIX}.out.")) {
            vec![0.0; n]
        } else if k.ends_with(".weight") {
            let fan_in: usize = v.dims()[1..].iter().product();
            let d = rand_distr::Normal::new(0.0, (2.0 / fan_in.max(1) as f64).sqrt()).map_err(|e| data_err(e.to_string()))?;
            (0..n).map(|_| d.sample(&mut rng) as f32).collect()
        } else {
            let c = in_channels.get(k.strip_suffix(".bias").unwrap_or(k)).copied().unwrap_or(1);
            let b = 1.0 / (c as f64).sqrt();
            (0..n).map(|_| rng.gen_range(-b..b) as f32).collect()
        };
        v.set(&Tensor::from_vec(vals, v.dims(), v.device())?)?;
    }
    Ok(())
}

/// The whole run (see the module docs).
pub fn run(req: &BlendRequest, progress: &dyn Progress) -> Result<BlendSummary> {
    req.layout.validate().map_err(|e| data_err(format!("--layout/--width: {e}")))?;
    if req.steps == 0 || req.batch == 0 || req.every == 0 {
        return Err(data_err("--steps, --batch and --every must be at least 1"));
    }
    if !(req.lr > 0.0 && req.lr.is_finite()) {
        return Err(data_err(format!("--lr must be a positive number, got {}", req.lr)));
    }
    if req.train.is_empty() {
        return Err(data_err("no training scenes (--train)"));
    }
    let (w, h) = {
        let spec = model::read_model_dir(&req.model)?;
        (spec.data.image_width, spec.data.image_height)
    };
    std::fs::create_dir_all(&req.out).map_err(|e| write_err(&req.out, e))?;
    // Scenes are resolved (and procedural ones written) before any work, and validation must stay unseen.
    let proc_dir = req.out.join("procedural");
    let train_scenes = scene_folders(&req.train, &proc_dir, w, h)?;
    let val_scenes = scene_folders(&req.val, &proc_dir, w, h)?;
    if let Some((n, _)) = val_scenes.iter().find(|(n, _)| train_scenes.iter().any(|(t, _)| t == n)) {
        return Err(data_err(format!("scene `{n}` is both a training and a validation scene; validation scenes must not be trained on")));
    }
    check_or_write_settings(&req.out.join("cache/settings.json"), &cache_settings(req)?, "model weights, fitting or layout")?;
    let train_files = cache(req, &train_scenes, &req.out.join("cache/train"), progress)?;
    let val_files = if val_scenes.is_empty() { vec![] } else { cache(req, &val_scenes, &req.out.join("cache/val"), progress)? };

    let dev = req.compute.open()?;
    let ch = req.layout.channels();
    let (tx, tt) = load(&train_files, ch)?;
    let (tx, tt) = (tx.to_device(&dev)?, tt.to_device(&dev)?);
    let val = if val_files.is_empty() { None } else { Some(load(&val_files, ch)?) };
    let n = tx.dim(0)?;
    progress.note(&format!(
        "training on {n} targets of {} scenes{}",
        train_files.len(),
        val.as_ref().map(|(x, _)| format!(", validating on {} targets of {} scenes", x.dim(0).unwrap_or(0), val_files.len())).unwrap_or_default()
    ));

    let vm = VarMap::new();
    let net = BlendNet::new(VarBuilder::from_varmap(&vm, DType::F32, &dev).pp(PREFIX), &req.layout)?;
    let mut vars: Vec<(String, Var)> = vm.data().lock().map_err(|_| data_err("varmap poisoned"))?.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    seeded_init(&vars, req.seed)?;
    let mut opt = Adam::new(vars.iter().map(|(k, v)| Param { name: k.clone(), var: v.clone(), lr_scale: 1.0 }).collect())?;
    let settings = train_settings(req);
    let ck = req.out.join(CHECKPOINT);
    let sj = req.out.join(TRAIN_SETTINGS);
    let mut start = 0u64;
    if req.resume {
        let text =
            std::fs::read_to_string(&sj).map_err(|e| TrainError::Checkpoint(format!("{}: {e} (nothing to resume; run without --resume)", sj.display())))?;
        let have: serde_json::Value = serde_json::from_str(&text).map_err(|e| TrainError::Checkpoint(format!("{}: {e}", sj.display())))?;
        if have != settings {
            return Err(TrainError::Checkpoint(format!(
                "{}: the run was started with {have} but this one has {settings}; resume with the same flags",
                sj.display()
            )));
        }
        if !ck.is_file() {
            return Err(TrainError::Checkpoint(format!("{}: no checkpoint yet (the run stopped before its first one); run without --resume", ck.display())));
        }
        let m = candle_core::safetensors::load(&ck, &dev).map_err(|e| TrainError::Checkpoint(format!("{}: {e}", ck.display())))?;
        let st = m.get("step").ok_or_else(|| TrainError::Checkpoint(format!("{}: no `step`", ck.display())))?.to_vec1::<u32>()?;
        start = st[0] as u64 | ((st.get(1).copied().unwrap_or(0) as u64) << 32);
        for (k, v) in &vars {
            let t = m.get(k).ok_or_else(|| TrainError::Checkpoint(format!("{}: no `{k}`", ck.display())))?;
            v.set(t)?;
        }
        let optim: HashMap<String, Tensor> = m.iter().filter_map(|(k, t)| k.strip_prefix("adam.").map(|s| (s.to_string(), t.clone()))).collect();
        opt.load_state(&optim)?;
        progress.note(&format!("resuming at step {start} of {}", req.steps));
    } else if ck.exists() {
        return Err(TrainError::Checkpoint(format!("{} exists: add --resume to continue that run, or use another --out", ck.display())));
    } else {
        write_atomic(&sj, &serde_json::to_vec_pretty(&settings).unwrap_or_default())?;
    }
    let renders_psnr = match &val {
        Some((x, t)) => Some(mean_psnr(&x.narrow(1, 0, 3)?, t)?),
        None => None,
    };
    if start > 0 {
        // Records after the checkpoint (written before an interruption) are written again.
        let log = req.out.join(LOG);
        let kept: Vec<String> = std::fs::read_to_string(&log)
            .unwrap_or_default()
            .lines()
            .filter(|l| serde_json::from_str::<BlendLogRecord>(l).is_ok_and(|r| r.step <= start))
            .map(|l| format!("{l}\n"))
            .collect();
        write_atomic(&log, kept.concat().as_bytes())?;
    }
    if start == 0 {
        let _ = std::fs::remove_file(req.out.join(LOG));
        if let (Some((x, t)), Some(r)) = (&val, renders_psnr) {
            progress.note(&format!("step 0: validation PSNR {:.3} (the renders as they are: {r:.3})", evaluate(&net, &x.to_device(&dev)?, t)?));
        }
    }
    let stop = req.stop_after.unwrap_or(req.steps).min(req.steps);
    let mut last_psnr = None;
    let mut run_mse = (0.0, 0u64);
    progress.begin("training the blender", req.steps);
    progress.advance(start);
    for step in start + 1..=stop {
        let lr = cosine_lr(req.lr, step, req.steps);
        let mut rng = crate::trainer::step_rng(req.seed, step, 0);
        let idx: Vec<u32> = (0..req.batch).map(|_| rng.gen_range(0..n as u32)).collect();
        let idx = Tensor::from_vec(idx, req.batch, &dev)?;
        let (mut x, mut t) = (tx.index_select(&idx, 0)?, tt.index_select(&idx, 0)?);
        // A mirrored input is the input of the mirrored target: every channel comes from the same pixel.
        if rng.gen_bool(0.5) {
            (x, t) = (x.flip(&[3])?, t.flip(&[3])?);
        }
        let loss = (net.forward(&x)? - &t)?.sqr()?.mean_all()?;
        let l = loss.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        if !l.is_finite() {
            return Err(TrainError::NonFinite { step, what: "blender MSE".into() });
        }
        let grads = loss.backward()?;
        let gs: Vec<Option<Tensor>> = opt.params.iter().map(|p| grads.get(p.var.as_tensor()).cloned()).collect();
        opt.step(&gs, lr)?;
        run_mse = (run_mse.0 + l, run_mse.1 + 1);
        progress.advance(1);
        if step % req.every == 0 || step == stop {
            let psnr = match &val {
                Some((x, t)) => Some(evaluate(&net, &x.to_device(&dev)?, t)?),
                None => None,
            };
            last_psnr = psnr;
            let rec = BlendLogRecord { step, mse: run_mse.0 / run_mse.1.max(1) as f64, val_psnr: psnr, lr };
            run_mse = (0.0, 0);
            progress.note(&format!("step {step}: train MSE {:.5}{}", rec.mse, psnr.map(|p| format!(", validation PSNR {p:.3}")).unwrap_or_default()));
            let mut tensors: Vec<(String, Tensor)> =
                vars.iter().map(|(k, v)| Ok((k.clone(), v.as_tensor().to_device(&Device::Cpu)?))).collect::<Result<_>>()?;
            tensors.extend(opt.state_tensors()?.into_iter().map(|(k, t)| (format!("adam.{k}"), t)));
            tensors.push(("step".into(), Tensor::new(&[(step & 0xffff_ffff) as u32, (step >> 32) as u32], &Device::Cpu)?));
            save_tensors(&ck, tensors.into_iter().collect())?;
            append_line(&req.out.join(LOG), &rec)?;
        }
    }
    progress.end();
    let val_scenes = val_files.len();
    let summary = |model: Option<PathBuf>, step: u64| BlendSummary {
        train_scenes: train_files.len(),
        train_images: n,
        val_scenes,
        val_psnr_renders: renders_psnr,
        val_psnr: last_psnr,
        step,
        model,
    };
    if stop < req.steps {
        return Ok(summary(None, stop));
    }
    let dir = req.out.join("model");
    write_model(&req.model, &vars, &req.layout, &dir)?;
    Ok(summary(Some(dir), stop))
}

fn append_line(path: &Path, rec: &BlendLogRecord) -> Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new().create(true).append(true).open(path).map_err(|e| write_err(path, e))?;
    writeln!(f, "{}", serde_json::to_string(rec).unwrap_or_default()).map_err(|e| write_err(path, e))
}

/// A copy of the model folder `src` with the blender's weights and settings; loaded back as `render` does.
fn write_model(src: &Path, vars: &[(String, Var)], layout: &BlendSettings, out: &Path) -> Result<()> {
    let cfg_path = src.join(model::MODEL_CONFIG);
    let mut cfg = model::parse_model_config(&std::fs::read_to_string(&cfg_path).map_err(|e| data_err(format!("{}: {e}", cfg_path.display())))?)
        .map_err(|e| data_err(format!("{}: {e}", cfg_path.display())))?;
    cfg.blend = Some(*layout);
    let mut tensors: Vec<(String, Tensor)> = candle_core::safetensors::load(src.join(model::MODEL_WEIGHTS), &Device::Cpu)?
        .into_iter()
        .filter(|(k, _)| !k.starts_with(&format!("{PREFIX}.")))
        .collect();
    for (k, v) in vars {
        tensors.push((k.clone(), v.as_tensor().to_device(&Device::Cpu)?));
    }
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    model::write_model_dir(out, &cfg, &tensors)?;
    let spec = model::read_model_dir(out)?;
    let (s, f) = spec.blend.ok_or_else(|| data_err(format!("{}: written without `blend`", out.display())))?;
    BlendNet::load(&f, &s, &Device::Cpu)?;
    Ok(())
}
