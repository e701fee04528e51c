//! The training loop: sample views, encode, rasterize the targets, MSE + LPIPS, accumulate, clip, Adam with the
//! one-cycle schedule; checkpoints and a JSONL log that a resumed run continues exactly.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device, IndexOp, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use mvsplat360_camera::Camera;
use mvsplat360_encoder::encoder_costvolume::camera_tensors;
use mvsplat360_encoder::EncoderCostVolume;
use mvsplat360_metrics::lpips::Lpips;
use mvsplat360_pipeline::compute::DeviceSpec;
use mvsplat360_pipeline::model::{DataConfig, ModelConfig, MODEL_FORMAT};
use mvsplat360_pipeline::render::raster_camera;
use mvsplat360_pipeline::scale::{scene_transform, SceneScale};
use mvsplat360_splat::{Gaussians, RenderOptions};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use crate::checkpoint::{self, State};
use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use crate::optim::{clip_grad_norm, Adam, OneCycle, Param};
use crate::refiner::TrainRefiner;
use crate::sampler::{self, SamplerSettings};
use crate::scenes::{SceneSource, TrainScene};

/// Progress and interruption, supplied by the caller (the CLI shows a bar; tests stay silent).
pub trait Monitor {
    fn note(&self, _msg: &str) {}
    fn step(&self, _rec: &StepRecord, _total: u64) {}
    /// Checked after every step; true = write a checkpoint and stop.
    fn should_stop(&self) -> bool {
        false
    }
}

pub struct Quiet;
impl Monitor for Quiet {}

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

#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Continue from the newest checkpoint in `train.out` (a fresh start when there is none).
    pub resume: bool,
    /// Folder of the metric weights (LPIPS); None = the default search.
    pub weights_dir: Option<PathBuf>,
    /// Where the encoder, rasterizer and losses run (`--device`); data, sampling and checkpoints stay on the host.
    /// In a data-parallel run rank r uses `cuda:(N + r)` for `cuda:N`.
    pub device: DeviceSpec,
    /// This process's rank in a data-parallel run ([`crate::dist::launch`]); None = a single process.
    pub dist: Option<crate::dist::Rank>,
}

#[derive(Debug, Clone)]
pub struct Summary {
    pub steps: u64,
    pub last: Option<StepRecord>,
    pub model_dir: PathBuf,
    pub train_seconds: f64,
    pub lpips: bool,
}

/// Everything trainable, built from a config.
pub struct Model {
    pub varmap: VarMap,
    pub encoder: EncoderCostVolume,
    /// Present with `[model.refiner]` (stage `model`).
    pub refiner: Option<TrainRefiner>,
    /// Stage `vae`: the autoencoder being trained (the encoder is then not trained).
    pub vae: Option<crate::vae_stage::TrainVae>,
    pub cfg: TrainConfig,
}

impl Model {
    /// The encoder with seeded initial weights, or `train.init`'s; the refiner (if configured) from
    /// `train.refiner_init` or seeded random weights written to `train.out`.
    pub fn new(cfg: &TrainConfig) -> Result<Self> {
        Self::new_on(cfg, &Device::Cpu)
    }

    /// The encoder of a training config with trained weights (a model folder or safetensors file) and no
    /// refiner, on the CPU: what the analysis examples evaluate.
    pub fn encoder_with_weights(config: &std::path::Path, weights: &std::path::Path) -> Result<Self> {
        Self::encoder_with_weights_on(config, weights, &Device::Cpu)
    }

    /// As [`Model::encoder_with_weights`], on `dev`.
    pub fn encoder_with_weights_on(config: &std::path::Path, weights: &std::path::Path, dev: &Device) -> Result<Self> {
        let mut cfg = TrainConfig::from_file(config)?;
        cfg.train.init = Some(weights.to_path_buf());
        cfg.model.refiner = None;
        Self::new_on(&cfg, dev)
    }

    /// As [`Model::new`], with the encoder's weights on `dev`. The initial weights are drawn on the host, so a
    /// seed gives the same model on every device.
    pub fn new_on(cfg: &TrainConfig, dev: &Device) -> Result<Self> {
        let ecfg = cfg.encoder();
        let varmap = VarMap::new();
        let encoder = EncoderCostVolume::new(VarBuilder::from_varmap(&varmap, DType::F32, dev).pp("encoder"), &ecfg)?;
        let init = mvsplat360_encoder::weights::random_tensors(cfg.train.seed, &Device::Cpu, |vb| EncoderCostVolume::new(vb.pp("encoder"), &ecfg))?;
        {
            let data = varmap.data().lock().map_err(|_| TrainError::Data("varmap poisoned".into()))?;
            for (name, var) in data.iter() {
                var.set(&init[name].to_device(dev)?)?;
            }
        }
        let vae_stage = cfg.train.stage == crate::config::Stage::Vae;
        let vae = match &cfg.model.refiner {
            Some(r) if vae_stage => Some(crate::vae_stage::TrainVae::new(&r.vae, cfg.train.refiner_init.as_deref(), cfg.train.seed, dev)?),
            _ => None,
        };
        let refiner = match &cfg.model.refiner {
            Some(_) if vae_stage => None,
            Some(r) => {
                std::fs::create_dir_all(&cfg.train.out).map_err(|e| TrainError::Write { path: cfg.train.out.clone(), msg: e.to_string() })?;
                Some(TrainRefiner::new(r, cfg.train.refiner_init.as_deref(), cfg.train.seed, &cfg.train.out, dev)?)
            }
            None => None,
        };
        let m = Self { varmap, encoder, refiner, vae, cfg: cfg.clone() };
        if let Some(p) = &cfg.train.init {
            crate::init::load_into(&m.varmap, p)?;
        }
        Ok(m)
    }

    /// (name, var) of what this run trains, sorted by name.
    pub fn vars(&self) -> Vec<(String, Var)> {
        if let Some(v) = &self.vae {
            let mut v = v.vars.clone();
            v.sort_by(|a, b| a.0.cmp(&b.0));
            return v;
        }
        let data = self.varmap.data().lock().expect("varmap lock");
        let mut v: Vec<(String, Var)> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        if let Some(r) = &self.refiner {
            v.extend(r.unet_vars.iter().cloned());
        }
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }

    /// The trainable weights, on the host.
    pub fn state_dict(&self) -> Result<Vec<(String, Tensor)>> {
        self.vars().into_iter().map(|(k, v)| Ok((k, v.as_tensor().detach().to_device(&Device::Cpu)?))).collect()
    }

    pub fn load_state_dict(&self, sd: &std::collections::HashMap<String, Tensor>) -> Result<()> {
        for (name, var) in self.vars() {
            let t = sd.get(&name).ok_or_else(|| TrainError::Checkpoint(format!("model weights lack `{name}`")))?;
            if t.dims() != var.dims() {
                return Err(TrainError::Checkpoint(format!("`{name}` has shape {:?}, the model {:?}", t.dims(), var.dims())));
            }
            var.set(&t.to_dtype(DType::F32)?.to_device(var.device())?)?;
        }
        Ok(())
    }

    /// Everything a model folder holds: the trained weights and the refiner's frozen VAE and CLIP. Stage `vae`:
    /// the encoder as initialised, the trained autoencoder, a seeded random UNet and CLIP (a `refiner_init`).
    pub fn model_tensors(&self) -> Result<Vec<(String, Tensor)>> {
        if let (Some(v), Some(r)) = (&self.vae, &self.cfg.model.refiner) {
            let data = self.varmap.data().lock().map_err(|_| TrainError::Data("varmap poisoned".into()))?;
            let mut t: Vec<(String, Tensor)> =
                data.iter().map(|(k, var)| Ok((k.clone(), var.as_tensor().detach().to_device(&Device::Cpu)?))).collect::<Result<_>>()?;
            let trained: std::collections::HashMap<&str, &Var> = v.vars.iter().map(|(k, var)| (k.as_str(), var)).collect();
            let rest = mvsplat360_refiner::state_dict::random_refiner_state_dict(&r.unet, &r.vae, &r.clip, self.cfg.train.seed.wrapping_add(17))
                .map_err(|msg| TrainError::Config { path: PathBuf::from("model.refiner"), msg })?;
            for (k, x) in rest {
                match trained.get(k.as_str()) {
                    Some(var) => t.push((k, var.as_tensor().detach().to_device(&Device::Cpu)?)),
                    None => t.push((k, x)),
                }
            }
            return Ok(t);
        }
        let mut t = self.state_dict()?;
        if let Some(r) = &self.refiner {
            t.extend(r.frozen().iter().cloned());
        }
        Ok(t)
    }

    /// The model-folder config of this model.
    pub fn model_config(&self) -> ModelConfig {
        let m = &self.cfg.model;
        ModelConfig {
            format: MODEL_FORMAT.into(),
            data: DataConfig { experiment: m.experiment.clone(), image_width: m.width, image_height: m.height, near: m.near, far: m.far },
            encoder: self.cfg.encoder(),
            refiner: self.cfg.model.refiner.clone(),
            fit: self.cfg.model.fit,
            // The blender is trained apart from the encoder (the `blend` example) and added to a folder by hand.
            blend: None,
            // Training brings every scene to model units by `auto` (`example_from_views`).
            scene_scale: Some("auto".into()),
        }
    }
}

/// One training example at model scale: context and targets with their photos.
#[derive(Clone)]
pub struct Example {
    pub context_images: Tensor,
    pub context_cameras: Vec<Camera>,
    pub target_images: Tensor,
    pub target_cameras: Vec<Camera>,
    /// (V,H,W) ground-truth ray distances of the context views in model units (infinite = sky), when the
    /// source knows them.
    pub context_depths: Option<Tensor>,
}

impl Example {
    /// The photos and depths on `dev` (cameras stay on the host; the encoder builds its camera tensors there).
    pub fn to_device(self, dev: &Device) -> Result<Self> {
        if dev.same_device(self.context_images.device()) {
            return Ok(self);
        }
        Ok(Self {
            context_images: self.context_images.to_device(dev)?,
            target_images: self.target_images.to_device(dev)?,
            context_depths: self.context_depths.map(|d| d.to_device(dev)).transpose()?,
            ..self
        })
    }

    /// Mean |ln d − ln d_true| of pixel-aligned, view-major Gaussians `g` of the context views, d = each
    /// Gaussian's distance from its view's camera, over the pixels whose true distance is below 0.9 `far`
    /// (sky and the far background left out); None when the source knows no depths.
    pub fn context_distance_error(&self, g: &Gaussians, far: f32) -> Result<Option<f64>> {
        let Some(depths) = self.context_depths.as_ref() else { return Ok(None) };
        let truth: Vec<f32> = depths.flatten_all()?.to_vec1()?;
        let m: Vec<f32> = g.means.flatten_all()?.to_vec1()?;
        let per = truth.len() / self.context_cameras.len();
        let (mut s, mut n) = (0.0, 0);
        for (i, &t) in truth.iter().enumerate() {
            if t as f64 >= 0.9 * far as f64 {
                continue;
            }
            let o = self.context_cameras[i / per].center();
            let d = ((m[3 * i] as f64 - o.x).powi(2) + (m[3 * i + 1] as f64 - o.y).powi(2) + (m[3 * i + 2] as f64 - o.z).powi(2)).sqrt();
            s += (d / t as f64).ln().abs();
            n += 1;
        }
        Ok(Some(s / n.max(1) as f64))
    }
}

/// What the encoder and rasterizer make of an example.
pub struct Rendered {
    /// (T,3,H,W) target renders.
    pub rgb: Tensor,
    /// (T,C,H,W) rendered latent features.
    pub features: Tensor,
    pub gaussians: Gaussians,
    /// (V,H,W) the encoder's per-pixel ray distances of the context views.
    pub depths: Tensor,
}

/// Randomness of optimizer step `step`, micro-batch `micro`: a pure function of the seed, so that a resumed
/// run draws exactly what the uninterrupted one drew.
pub fn step_rng(seed: u64, step: u64, micro: u32) -> rand::rngs::StdRng {
    let mut x = seed ^ 0x9E37_79B9_7F4A_7C15u64.wrapping_mul(step.wrapping_add(1)) ^ ((micro as u64) << 48);
    // splitmix64 finaliser
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    rand::rngs::StdRng::seed_from_u64(x ^ (x >> 31))
}

/// Build an example from a scene: sample views, scale like `render --scene-scale auto`, flip.
pub fn make_example(scene: &TrainScene, s: &SamplerSettings, near: f32, far: f32, rng: &mut impl Rng) -> Result<Option<Example>> {
    let Some(v) = sampler::sample(&scene.cameras, s, rng) else { return Ok(None) };
    example_from_views(scene, &v, near, far).map(Some)
}

/// The example of chosen views: scaled like `render --scene-scale auto` (from the context cameras), flipped
/// when `v.flip`.
pub fn example_from_views(scene: &TrainScene, v: &sampler::ViewSample, near: f32, far: f32) -> Result<Example> {
    let ctx: Vec<Camera> = v.context.iter().map(|&i| scene.cameras[i].clone()).collect();
    let (tf, _) = scene_transform(SceneScale::Auto, &ctx, near, far);
    let prep = |idx: &[usize]| -> Result<(Tensor, Vec<Camera>)> {
        let (w, h) = (scene.images[idx[0]].width as usize, scene.images[idx[0]].height as usize);
        let mut data = Vec::with_capacity(idx.len() * 3 * w * h);
        let mut cams = Vec::with_capacity(idx.len());
        for &i in idx {
            let mut img = scene.images[i].data.clone();
            let mut cam = tf.apply(&scene.cameras[i]);
            if v.flip {
                sampler::flip_image(&mut img, w);
                cam = sampler::flip_camera(&cam);
            }
            data.extend_from_slice(&img);
            cams.push(cam);
        }
        Ok((Tensor::from_vec(data, (idx.len(), 3, h, w), &Device::Cpu)?, cams))
    };
    let (ci, cc) = prep(&v.context)?;
    let (ti, tc) = prep(&v.target)?;
    let context_depths = match &scene.depths {
        Some(depths) => {
            let (w, h) = (scene.images[v.context[0]].width as usize, scene.images[v.context[0]].height as usize);
            let mut data = Vec::with_capacity(v.context.len() * w * h);
            for &i in &v.context {
                // Scaling the scene scales every distance; a flip mirrors the map with its image.
                let mut d: Vec<f32> = depths[i].iter().map(|&x| (x as f64 * tf.scale) as f32).collect();
                if v.flip {
                    sampler::flip_image(&mut d, w);
                }
                data.extend_from_slice(&d);
            }
            Some(Tensor::from_vec(data, (v.context.len(), h, w), &Device::Cpu)?)
        }
        None => None,
    };
    Ok(Example { context_images: ci, context_cameras: cc, target_images: ti, target_cameras: tc, context_depths })
}

/// Encoder forward and target renders: (renders (T,3,H,W), Gaussians).
pub fn render_example(model: &Model, ex: &Example) -> Result<(Tensor, Gaussians)> {
    let r = render_example_full(model, ex)?;
    Ok((r.rgb, r.gaussians))
}

/// As [`render_example`], also returning the rendered features and the encoder's depths.
pub fn render_example_full(model: &Model, ex: &Example) -> Result<Rendered> {
    let dev = ex.context_images.device().clone();
    let v = ex.context_cameras.len();
    let k: Vec<[f64; 4]> = ex.context_cameras.iter().map(|c| c.normalized_intrinsics()).collect();
    let c2w: Vec<[[f64; 4]; 4]> = ex.context_cameras.iter().map(|c| c.c2w).collect();
    let (intr, extr) = camera_tensors(&k, &c2w, &dev)?;
    let (near, far) = (model.cfg.model.near, model.cfg.model.far);
    let nt = Tensor::full(near, (1, v), &dev)?;
    let ft = Tensor::full(far, (1, v), &dev)?;
    let g = model.encoder.forward(&ex.context_images.unsqueeze(0)?, &intr, &extr, &nt, &ft)?;
    let gs = Gaussians {
        means: g.means.i(0)?,
        covariances: g.covariances.i(0)?,
        opacities: g.opacities.i(0)?,
        harmonics: g.harmonics.i(0)?,
        feature_harmonics: g.feature_harmonics.i(0)?,
    };
    let mut renders = Vec::with_capacity(ex.target_cameras.len());
    let mut features = Vec::with_capacity(ex.target_cameras.len());
    for c in &ex.target_cameras {
        let grad_mode = match model.cfg.train.raster_grad {
            crate::config::RasterGrad::Official => mvsplat360_splat::GradMode::Official,
            crate::config::RasterGrad::Exact => mvsplat360_splat::GradMode::Exact,
        };
        let r = mvsplat360_splat::render(&gs, &raster_camera(c, near, far), &RenderOptions { grad_mode, ..RenderOptions::default() })?;
        renders.push(r.rgb);
        features.push(r.features);
    }
    let depths = g.depths.i(0)?.reshape((v, ex.context_images.dim(2)?, ex.context_images.dim(3)?))?;
    Ok(Rendered { rgb: Tensor::stack(&renders, 0)?, features: Tensor::stack(&features, 0)?, gaussians: gs, depths })
}

/// The 3DGS losses of one example: (total, mse, lpips).
pub fn losses(cfg: &TrainConfig, lpips: Option<&Lpips>, step: u64, pred: &Tensor, gt: &Tensor) -> Result<(Tensor, Tensor, Option<Tensor>)> {
    let mse = crate::loss::mse(pred, gt)?;
    let mut total = (&mse * cfg.train.mse_weight)?;
    let lp = lpips_term(cfg, lpips, step, pred, gt)?;
    if let Some(v) = &lp {
        total = (total + (v * cfg.train.lpips_weight)?)?;
    }
    Ok((total, mse, lp))
}

/// LPIPS of `pred` against `gt` (unweighted) when the term is on at this step.
fn lpips_term(cfg: &TrainConfig, lpips: Option<&Lpips>, step: u64, pred: &Tensor, gt: &Tensor) -> Result<Option<Tensor>> {
    match lpips.filter(|_| step >= cfg.train.lpips_after_step && cfg.train.lpips_weight > 0.0) {
        Some(l) => Ok(Some(crate::loss::lpips(l, pred, gt)?)),
        None => Ok(None),
    }
}

/// Whether a checkpoint was written with `cfg`, compared as parsed configs, so that a field added later with its
/// default value does not block a resume or an export.
fn written_with(ck: &checkpoint::Loaded, cfg: &TrainConfig) -> bool {
    ck.state.config == cfg.to_toml() || TrainConfig::from_toml(&ck.state.config, &ck.path).is_ok_and(|c| c == *cfg)
}

/// Write the checkpoint of `step` (the newest when `None`) in `cfg`'s `train.out` as a model folder: `to`, or
/// `<out>/model-<step>`. The checkpoint must have been written with `cfg` (as for `--resume`). Returns the step
/// and the folder.
pub fn export_checkpoint(cfg: &TrainConfig, step: Option<u64>, to: Option<&std::path::Path>) -> Result<(u64, PathBuf)> {
    let out = &cfg.train.out;
    let ck = checkpoint::load_step(out, step)?;
    if !written_with(&ck, cfg) {
        return Err(TrainError::Checkpoint(format!(
            "{} was written with a different config; export with the config the run was started with",
            ck.path.display()
        )));
    }
    let model = Model::new(cfg)?;
    model.load_state_dict(&ck.model)?;
    let dir = to.map(PathBuf::from).unwrap_or_else(|| out.join(format!("model-{}", ck.state.step)));
    mvsplat360_pipeline::model::write_model_dir(&dir, &model.model_config(), &model.model_tensors()?)?;
    Ok((ck.state.step, dir))
}

/// Train as configured; returns when `train.steps` are done or the monitor asks to stop.
pub fn run(cfg: &TrainConfig, opts: &RunOptions, mon: &dyn Monitor) -> Result<Summary> {
    let out = cfg.train.out.clone();
    std::fs::create_dir_all(&out).map_err(|e| TrainError::Write { path: out.clone(), msg: e.to_string() })?;
    let (rank, world) = opts.dist.as_ref().map_or((0, 1), |r| (r.rank, r.world));
    // Rank 0 owns the output folder: lock, log, plots, checkpoints, model folders.
    let main = rank == 0;
    let _lock = if main { Some(checkpoint::RunLock::acquire(&out)?) } else { None };
    let dev = match opts.device {
        DeviceSpec::Cuda(n) => DeviceSpec::Cuda(n + rank),
        d => d,
    }
    .open()?;
    let mut coll = opts.dist.as_ref().map(|r| crate::dist::connect(r, &dev)).transpose()?;
    let model = Model::new_on(cfg, &dev)?;
    let multiple = cfg.model.encoder.image_multiple() as u32;
    let mut sources = cfg.data.sources.iter().map(|s| SceneSource::open(s, cfg.model.width, cfg.model.height, multiple)).collect::<Result<Vec<_>>>()?;
    let lpips = if cfg.train.lpips_weight > 0.0 {
        match Lpips::load(opts.weights_dir.as_deref(), mvsplat360_metrics::lpips::Net::Vgg, &dev) {
            Ok(l) => Some(l),
            Err(e) => {
                mon.note(&format!("training without LPIPS (its VGG weights are missing: {e}); run scripts/metric-weights/fetch"));
                None
            }
        }
    } else {
        None
    };
    let frozen = |n: &str| cfg.train.freeze.iter().any(|p| n.starts_with(p.as_str()));
    let params: Vec<Param> = model
        .vars()
        .into_iter()
        .filter(|(n, _)| !frozen(n))
        .map(|(name, var)| {
            let lr_scale = cfg.train.lr_groups.iter().find(|g| name.contains(&g.contains)).map(|g| g.scale).unwrap_or(1.0);
            Param { name, var, lr_scale }
        })
        .collect();
    if params.is_empty() {
        return Err(TrainError::Config { path: PathBuf::from("train.freeze"), msg: "every parameter is frozen; nothing to train".into() });
    }
    let mut adam = Adam::new(params)?;
    let sched = OneCycle::new(cfg.train.lr, cfg.train.steps, cfg.train.pct_start);
    let config_text = cfg.to_toml();

    let mut start = 0u64;
    let mut train_seconds = 0.0;
    if opts.resume {
        if let Some(ck) = checkpoint::load_latest(&out)? {
            if !written_with(&ck, cfg) {
                return Err(TrainError::Checkpoint(format!(
                    "{} was written with a different config; resume with the same config or choose another `train.out`",
                    ck.path.display()
                )));
            }
            model.load_state_dict(&ck.model)?;
            adam.load_state(&ck.optim)?;
            start = ck.state.step;
            train_seconds = ck.state.train_seconds;
            mon.note(&format!("resuming from {} (step {start})", ck.path.display()));
        } else {
            mon.note("no checkpoint to resume from; starting at step 0");
        }
    } else if !checkpoint::list(&out)?.is_empty() {
        return Err(TrainError::Checkpoint(format!(
            "{} already holds checkpoints; pass --resume to continue them or choose another output folder",
            out.display()
        )));
    }
    if start == 0 && main {
        // The step-0 model, for before/after comparisons.
        mvsplat360_pipeline::model::write_model_dir(&out.join("model-step0"), &model.model_config(), &model.model_tensors()?)?;
    }
    let log_path = out.join("log.jsonl");
    let mut records = Vec::new();
    let mut log = None;
    if main {
        records = crate::log::read(&log_path)?.into_iter().filter(|r| r.step <= start).collect::<Vec<_>>();
        crate::log::rewrite(&log_path, &records)?;
        log = Some(
            std::fs::OpenOptions::new()
                .append(true)
                .create(true)
                .open(&log_path)
                .map_err(|e| TrainError::Write { path: log_path.clone(), msg: e.to_string() })?,
        );
    }

    let mut settings = SamplerSettings {
        num_context: cfg.data.num_context,
        num_target: cfg.data.num_target,
        gap: cfg.data.gap,
        gap_initial: cfg.data.gap_initial,
        warm_up: 0.0,
        closed_loop: cfg.data.closed_loop,
        flip: cfg.data.flip,
    };
    let weights: Vec<f64> = if cfg.data.weights.is_empty() { vec![1.0; sources.len()] } else { cfg.data.weights.clone() };
    let wsum: f64 = weights.iter().sum();
    let accum = cfg.train.accumulate;
    // Every loss is divided by all micro-batches of the step, over all ranks (Lightning's 1/k times DDP's mean).
    let denom = (accum as usize * world) as f64;
    let save = |adam: &Adam, step: u64, secs: f64| -> Result<()> {
        let state = State { step, seed: cfg.train.seed, config: config_text.clone(), train_seconds: secs };
        checkpoint::save(&out, &state, &model.state_dict()?, &adam.state_tensors()?, cfg.train.keep_checkpoints)?;
        Ok(())
    };
    let mut step = start;
    while step < cfg.train.steps {
        let t0 = Instant::now();
        settings.warm_up = if cfg.data.gap_warm_up_steps == 0 { 1.0 } else { step as f64 / cfg.data.gap_warm_up_steps as f64 };
        let mut grads: Vec<Option<Tensor>> = vec![None; adam.params.len()];
        let (mut sum_loss, mut sum_mse, mut sum_lp, mut sum_ref) = (0f64, 0f64, None::<f64>, None::<(f64, f64)>);
        let (mut n_lp, mut n_ref) = (0usize, 0usize);
        let mut sum_vae: Option<(f64, f64)> = None;
        // Mean over the micro-batches whose scene has ground-truth depth.
        let mut depth_terms = Vec::new();
        // Examples are drawn in micro-batch order (sources cache scenes); forward and backward may then run in
        // parallel, and gradients are summed in micro-batch order either way.
        let mut examples = Vec::with_capacity(accum as usize);
        // Rank r's micro-batch m is the step's micro-batch r·k + m, as in one process accumulating world·k.
        let global = |micro: u32| rank as u32 * accum + micro;
        for micro in 0..accum {
            let mut rng = step_rng(cfg.train.seed, step, global(micro));
            examples.push(draw_example(&mut sources, &weights, wsum, &settings, cfg, &mut rng)?.to_device(&dev)?);
        }
        let train_encoder = adam.params.iter().any(|p| p.name.starts_with("encoder."));
        let micro_step = |micro: u32, ex: &Example| -> Result<MicroResult> {
            if let Some(v) = model.vae.as_ref() {
                let mut rng = step_rng(cfg.train.seed ^ 0x7AE0_0000_0000_0000, step, global(micro));
                let l = v.losses(&ex.target_images, &mut rng)?;
                let mse = crate::loss::mse(&l.recon.detach(), &ex.target_images)?;
                let mut total = (&l.l1 + (&l.kl * cfg.train.kl_weight)?)?;
                let lp = lpips_term(cfg, lpips.as_ref(), step, &l.recon, &ex.target_images)?;
                if let Some(x) = &lp {
                    total = (total + (x * cfg.train.lpips_weight)?)?;
                }
                let tv = total.to_scalar::<f32>()? as f64;
                if !tv.is_finite() {
                    return Err(TrainError::NonFinite { step: step + 1, what: format!("loss {tv}") });
                }
                let g = (total / denom)?.backward()?;
                return Ok(MicroResult {
                    loss: tv,
                    mse: mse.to_scalar::<f32>()? as f64,
                    lpips: lp.map(|l| l.to_scalar::<f32>()).transpose()?.map(|l| l as f64),
                    depth: None,
                    refiner: None,
                    vae: Some((l.l1.to_scalar::<f32>()? as f64, l.kl.to_scalar::<f32>()? as f64)),
                    grads: adam.params.iter().map(|p| g.get(p.var.as_tensor()).cloned()).collect(),
                });
            }
            let mut rendered = render_example_full(&model, ex)?;
            if !train_encoder {
                // A frozen encoder (e.g. a refiner-only run): no backward through the rasterizer and encoder.
                rendered.rgb = rendered.rgb.detach();
                rendered.features = rendered.features.detach();
                rendered.depths = rendered.depths.detach();
            }
            let (pred, feats) = (&rendered.rgb, &rendered.features);
            let (mut total, mse, lp) = losses(cfg, lpips.as_ref(), step, pred, &ex.target_images)?;
            let mut depth_term = None;
            if let Some(gt) = ex.context_depths.as_ref().filter(|_| cfg.train.depth_weight > 0.0) {
                let d = crate::loss::depth_log_l1(&rendered.depths, gt, cfg.model.near, cfg.model.far)?;
                total = (total + (&d * cfg.train.depth_weight)?)?;
                depth_term = Some(d.to_scalar::<f32>()? as f64);
            }
            let mut refiner_terms = None;
            if let Some(r) = model.refiner.as_ref().filter(|_| cfg.train.refiner_weight > 0.0) {
                // A stream of its own, so adding the refiner leaves the examples' draws unchanged.
                let mut rng = step_rng(cfg.train.seed ^ 0x5EF1_4E70_0000_0000, step, global(micro));
                let rl = r.losses(feats, &ex.target_images, &ex.context_images, &mut rng)?;
                total = (total + ((&rl.diffusion + &rl.alignment)? * cfg.train.refiner_weight)?)?;
                refiner_terms = Some((rl.diffusion.to_scalar::<f32>()? as f64, rl.alignment.to_scalar::<f32>()? as f64));
            }
            let tv = total.to_scalar::<f32>()? as f64;
            if !tv.is_finite() {
                return Err(TrainError::NonFinite { step: step + 1, what: format!("loss {tv}") });
            }
            // Lightning divides each micro-batch's loss by the accumulation count.
            let g = (total / denom)?.backward()?;
            let grads = adam.params.iter().map(|p| g.get(p.var.as_tensor()).cloned()).collect();
            Ok(MicroResult {
                loss: tv,
                mse: mse.to_scalar::<f32>()? as f64,
                lpips: lp.map(|l| l.to_scalar::<f32>()).transpose()?.map(|l| l as f64),
                depth: depth_term,
                refiner: refiner_terms,
                vae: None,
                grads,
            })
        };
        let results: Vec<Result<MicroResult>> = if cfg.train.parallel_micro_batches && accum > 1 {
            std::thread::scope(|sc| {
                let handles: Vec<_> = examples.iter().zip(0u32..).map(|(ex, m)| sc.spawn(move || micro_step(m, ex))).collect();
                handles.into_iter().map(|h| h.join().unwrap_or_else(|_| Err(TrainError::Data("a micro-batch thread panicked".into())))).collect()
            })
        } else {
            examples.iter().zip(0u32..).map(|(ex, m)| micro_step(m, ex)).collect()
        };
        for r in results {
            let r = r?;
            sum_loss += r.loss / denom;
            sum_mse += r.mse / denom;
            if let Some(l) = r.lpips {
                *sum_lp.get_or_insert(0.0) += l / denom;
                n_lp += 1;
            }
            depth_terms.extend(r.depth);
            if let Some((d, a)) = r.refiner {
                let s = sum_ref.get_or_insert((0.0, 0.0));
                s.0 += d / denom;
                s.1 += a / denom;
                n_ref += 1;
            }
            if let Some((l1, kl)) = r.vae {
                let s = sum_vae.get_or_insert((0.0, 0.0));
                s.0 += l1 / denom;
                s.1 += kl / denom;
            }
            for (i, gi) in r.grads.into_iter().enumerate() {
                if let Some(gi) = gi {
                    grads[i] = Some(match grads[i].take() {
                        None => gi,
                        Some(a) => (a + gi)?,
                    });
                }
            }
        }
        let mut depth_mean = (!depth_terms.is_empty()).then(|| depth_terms.iter().sum::<f64>() / depth_terms.len() as f64);
        let mut stop_all = None;
        if let Some(c) = coll.as_mut() {
            // Sampled before the sums, so that every rank stops after the same step.
            let stop_here = mon.should_stop();
            let sums = StepSums {
                loss: sum_loss,
                mse: sum_mse,
                lpips: sum_lp,
                n_lpips: n_lp,
                refiner: sum_ref,
                n_refiner: n_ref,
                vae: sum_vae,
                depth: &depth_terms,
                stop: stop_here,
            };
            let r = reduce_step(c.as_mut(), sums, &mut grads, &adam.params, &dev)?;
            (sum_loss, sum_mse, sum_lp, sum_ref, sum_vae, depth_mean, stop_all) = (r.loss, r.mse, r.lpips, r.refiner, r.vae, r.depth, Some(r.stop));
        }
        let norm = if cfg.train.clip_grad_norm > 0.0 { clip_grad_norm(&mut grads, cfg.train.clip_grad_norm)? } else { crate::optim::grad_norm(&grads)? };
        if !norm.is_finite() {
            return Err(TrainError::NonFinite { step: step + 1, what: format!("gradient norm {norm}") });
        }
        let lr = sched.lr(step);
        adam.step(&grads, lr)?;
        step += 1;
        let secs = t0.elapsed().as_secs_f64();
        train_seconds += secs;
        let rec = StepRecord {
            step,
            loss: sum_loss,
            mse: sum_mse,
            lpips: sum_lp,
            depth: depth_mean,
            diffusion: sum_ref.map(|r| r.0),
            alignment: sum_ref.map(|r| r.1),
            l1: sum_vae.map(|v| v.0),
            kl: sum_vae.map(|v| v.1),
            lr,
            grad_norm: norm,
            seconds: secs,
        };
        if let Some(log) = log.as_mut() {
            let line = serde_json::to_string(&rec).map_err(|e| TrainError::Write { path: log_path.clone(), msg: e.to_string() })?;
            writeln!(log, "{line}").and_then(|_| log.flush()).map_err(|e| TrainError::Write { path: log_path.clone(), msg: e.to_string() })?;
            records.push(rec.clone());
        }
        mon.step(&rec, cfg.train.steps);
        let stop = stop_all.unwrap_or_else(|| mon.should_stop());
        if main && (step % cfg.train.checkpoint_every == 0 || step == cfg.train.steps || stop) {
            save(&adam, step, train_seconds)?;
            let _ = crate::log::plot(&records, &out.join("loss.png"));
        }
        if stop {
            return Err(TrainError::Interrupted);
        }
    }
    let model_dir = out.join("model");
    if main {
        mvsplat360_pipeline::model::write_model_dir(&model_dir, &model.model_config(), &model.model_tensors()?)?;
        let _ = crate::log::plot(&records, &out.join("loss.png"));
    }
    Ok(Summary { steps: step, last: records.last().cloned(), model_dir, train_seconds, lpips: lpips.is_some() })
}

/// One rank's sums of a step, before the all-reduce (losses already divided by the step's micro-batch count).
struct StepSums<'a> {
    loss: f64,
    mse: f64,
    lpips: Option<f64>,
    n_lpips: usize,
    refiner: Option<(f64, f64)>,
    n_refiner: usize,
    vae: Option<(f64, f64)>,
    /// This rank's depth terms (their mean over all ranks is logged).
    depth: &'a [f64],
    stop: bool,
}

struct Reduced {
    loss: f64,
    mse: f64,
    lpips: Option<f64>,
    refiner: Option<(f64, f64)>,
    vae: Option<(f64, f64)>,
    depth: Option<f64>,
    stop: bool,
}

/// Sums the step's losses and gradients over the ranks. A parameter without a gradient on some rank adds
/// zeros there; it keeps none only when no rank has one (as in one process).
fn reduce_step(c: &mut dyn crate::dist::Collective, s: StepSums, grads: &mut [Option<Tensor>], params: &[Param], dev: &Device) -> Result<Reduced> {
    let (lp, rf) = (s.lpips.unwrap_or(0.0), s.refiner.unwrap_or((0.0, 0.0)));
    let mut v = vec![
        s.loss,
        s.mse,
        lp,
        s.n_lpips as f64,
        rf.0,
        rf.1,
        s.n_refiner as f64,
        s.depth.iter().sum::<f64>(),
        s.depth.len() as f64,
        s.stop as u8 as f64,
        s.vae.unwrap_or((0.0, 0.0)).0,
        s.vae.unwrap_or((0.0, 0.0)).1,
        s.vae.is_some() as u8 as f64,
    ];
    const HEAD: usize = 13;
    v.extend(grads.iter().map(|g| g.is_some() as u8 as f64));
    c.all_reduce_f64(&mut v)?;
    let present: Vec<usize> = (0..grads.len()).filter(|&i| v[HEAD + i] > 0.0).collect();
    if !present.is_empty() {
        let parts = present
            .iter()
            .map(|&i| match &grads[i] {
                Some(g) => g.flatten_all(),
                None => Tensor::zeros(params[i].var.elem_count(), DType::F32, dev),
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        let sum = c.all_reduce_tensor(&Tensor::cat(&parts, 0)?)?;
        let mut off = 0;
        for &i in &present {
            let n = params[i].var.elem_count();
            grads[i] = Some(sum.narrow(0, off, n)?.reshape(params[i].var.dims())?);
            off += n;
        }
    }
    Ok(Reduced {
        loss: v[0],
        mse: v[1],
        lpips: (v[3] > 0.0).then_some(v[2]),
        refiner: (v[6] > 0.0).then_some((v[4], v[5])),
        depth: (v[8] > 0.0).then(|| v[7] / v[8]),
        stop: v[9] > 0.0,
        vae: (v[12] > 0.0).then_some((v[10], v[11])),
    })
}

struct MicroResult {
    loss: f64,
    mse: f64,
    lpips: Option<f64>,
    depth: Option<f64>,
    refiner: Option<(f64, f64)>,
    /// Stage `vae`: (l1, kl).
    vae: Option<(f64, f64)>,
    grads: Vec<Option<Tensor>>,
}

fn draw_example(sources: &mut [SceneSource], weights: &[f64], wsum: f64, s: &SamplerSettings, cfg: &TrainConfig, rng: &mut impl Rng) -> Result<Example> {
    for _ in 0..20 {
        let mut u = rng.gen_range(0.0..wsum);
        let mut k = 0;
        while k + 1 < weights.len() && u >= weights[k] {
            u -= weights[k];
            k += 1;
        }
        let scene = sources[k].draw(rng)?;
        if let Some(ex) = make_example(&scene, s, cfg.model.near, cfg.model.far, rng)? {
            return Ok(ex);
        }
    }
    Err(TrainError::Data(format!("no scene has enough views for {} context + targets; add longer sequences or lower data.num_context", s.num_context)))
}

pub fn out_dir(cfg: &TrainConfig) -> &Path {
    &cfg.train.out
}
