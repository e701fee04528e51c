//! Where the weights come from and what the model's configuration is: the official Lightning `.ckpt`
//! (DL3DV experiment), a model folder (`config.json` + `model.safetensors`, official key names), or the
//! parts separately (`--encoder FILE`, `--refiner none|FILE`).

use std::path::{Path, PathBuf};

use mvsplat360_encoder::EncoderCostVolumeCfg;
use mvsplat360_refiner::clip::ClipVisionConfig;
use mvsplat360_refiner::unet::VideoUNetConfig;
use mvsplat360_refiner::vae::AutoencoderConfig;
use serde::{Deserialize, Serialize};

use crate::error::{PipelineError, Result};

/// The data conventions of an experiment: input size and depth range the model was trained with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataConfig {
    /// Official experiment name (`dl3dv`, `re10k`, or a project-trained model's own).
    pub experiment: String,
    /// The size photos are scaled to cover and centre-cropped to (`dataset.image_shape`), before the encoder's
    /// crop to a multiple of `shim_patch_size · downscale_factor`.
    pub image_width: u32,
    pub image_height: u32,
    /// Depth range in scene units (after normalisation).
    pub near: f32,
    pub far: f32,
}

impl DataConfig {
    /// `+experiment=dl3dv_mvsplat360`: 480×270 frames (DL3DV 480P), centre-cropped to 448×256; near 1, far 100.
    pub fn dl3dv() -> Self {
        Self { experiment: "dl3dv".into(), image_width: 480, image_height: 270, near: 1.0, far: 100.0 }
    }

    /// `+experiment=re10k_mvsplat360`: 320×180 frames, centre-cropped to 320×176; near 1, far 100.
    pub fn re10k() -> Self {
        Self { experiment: "re10k".into(), image_width: 320, image_height: 180, near: 1.0, far: 100.0 }
    }
}

/// The refiner's three modules (configs with official YAML names).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RefinerModelConfig {
    pub unet: VideoUNetConfig,
    pub vae: AutoencoderConfig,
    pub clip: ClipVisionConfig,
}

impl Default for RefinerModelConfig {
    fn default() -> Self {
        Self { unet: VideoUNetConfig::default(), vae: AutoencoderConfig::default(), clip: ClipVisionConfig::default() }
    }
}

/// A model folder's `config.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    /// Format marker, `mvsplat360-model/1`.
    pub format: String,
    pub data: DataConfig,
    pub encoder: EncoderCostVolumeCfg,
    /// Absent: the model renders 3DGS only.
    #[serde(default)]
    pub refiner: Option<RefinerModelConfig>,
    /// Test-time fitting of the Gaussians to the context photos that `render` runs by default for this model
    /// (see [`crate::fit`]); absent: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fit: Option<crate::fit::FitSettings>,
    /// Learned blending of the 3DGS renders with the context photos (see [`crate::blend`]; weights `blend.*`);
    /// absent: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blend: Option<crate::blend::BlendSettings>,
    /// How scenes are brought to this model's units (`none`, `auto` or a factor; see [`crate::scale`]): the
    /// default of every command that uses the folder, unless `--scene-scale` is given. Absent: `none`, the
    /// official protocol (official checkpoints have no such setting).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_scale: Option<String>,
}

pub const MODEL_FORMAT: &str = "mvsplat360-model/1";
pub const MODEL_CONFIG: &str = "config.json";
pub const MODEL_WEIGHTS: &str = "model.safetensors";
/// A model folder's weights as an official Lightning checkpoint (used when `model.safetensors` is absent).
pub const MODEL_CKPT: &str = "model.ckpt";

/// What the user asked for on the command line.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ModelArgs {
    /// `--ckpt`: an official `.ckpt` or a model folder.
    pub ckpt: Option<PathBuf>,
    /// `--encoder`: encoder weights alone (DL3DV config).
    pub encoder: Option<PathBuf>,
    /// `--refiner`: `none` or a file holding the refiner's weights.
    pub refiner: Option<RefinerArg>,
    /// `--experiment`: overrides the data conventions (`dl3dv`, `re10k`) of a checkpoint without a config.
    pub experiment: Option<String>,
    /// `--device`, `--dtype` and `--encoder-dtype`: where the model runs, the refiner's and the encoder's precision.
    pub compute: crate::compute::Compute,
    /// `--fit-steps`: overrides the model's default test-time fitting step count (0 = off).
    pub fit_steps: Option<usize>,
    /// `--no-blend`: skip the model's learned blending (frames are the plain 3DGS renders).
    pub no_blend: bool,
}

#[derive(Debug, Clone, PartialEq)]
pub enum RefinerArg {
    None,
    File(PathBuf),
}

impl std::str::FromStr for RefinerArg {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Ok(if s == "none" { Self::None } else { Self::File(PathBuf::from(s)) })
    }
}

/// A resolved model: configs and the files each part is read from (nothing loaded yet).
#[derive(Debug, Clone)]
pub struct ModelSpec {
    pub data: DataConfig,
    pub encoder: EncoderCostVolumeCfg,
    pub encoder_file: PathBuf,
    pub refiner: Option<(RefinerModelConfig, RefinerWeights)>,
    /// Human description for logs and run.json.
    pub description: String,
    /// The model's default test-time fitting (steps 0 = none; only model folders set it).
    pub fit: crate::fit::FitSettings,
    /// The model's learned blending and the file holding its weights (only model folders set it).
    pub blend: Option<(crate::blend::BlendSettings, PathBuf)>,
    /// The model's scene scaling (only model folders set it; None = scene units, the official protocol).
    pub scene_scale: Option<crate::scale::SceneScale>,
    /// The encoder's precision for this run (`--encoder-dtype`, set by [`resolve`]; F32 as read).
    pub encoder_dtype: candle_core::DType,
}

/// Where the refiner's weights are.
#[derive(Debug, Clone, PartialEq)]
pub enum RefinerWeights {
    /// One safetensors file holding all three parts (any layout the loaders detect).
    File(PathBuf),
    /// An official `.ckpt` to convert to safetensors on first use (cached).
    Ckpt(PathBuf),
}

/// The default model folder shipped with the repository (relative to the working directory, then the
/// repository this binary was built from).
pub fn default_model_dir() -> Option<PathBuf> {
    let rel = Path::new("assets/models/default");
    let built = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/models/default");
    [rel.to_path_buf(), built].into_iter().find(|p| p.join(MODEL_CONFIG).is_file())
}

fn experiment_data(name: Option<&str>) -> Result<DataConfig> {
    match name.unwrap_or("dl3dv") {
        "dl3dv" => Ok(DataConfig::dl3dv()),
        "re10k" => Ok(DataConfig::re10k()),
        other => Err(PipelineError::Flag { flag: "--experiment", msg: format!("unknown experiment `{other}` (dl3dv or re10k)") }),
    }
}

/// The encoder config of an official experiment.
pub fn experiment_encoder(data: &DataConfig) -> EncoderCostVolumeCfg {
    let mut cfg = EncoderCostVolumeCfg { near: data.near, far: data.far, ..Default::default() };
    if data.experiment == "re10k" {
        // RE10K: cost volume and transformer over all views (null in the YAML), data shim patch 4 (multiple 16).
        cfg.costvolume_nearest_n_views = usize::MAX;
        cfg.multiview_trans_nearest_n_views = usize::MAX;
        cfg.shim_patch_size = 4;
    }
    cfg
}

/// Resolve the command-line model choice. Files are checked to exist; weights are read later.
pub fn resolve(args: &ModelArgs) -> Result<ModelSpec> {
    let mut spec = resolve_weights(args)?;
    if let Some(n) = args.fit_steps {
        spec.fit.steps = n;
    }
    if args.no_blend {
        spec.blend = None;
    }
    spec.encoder_dtype = args.compute.encoder_dtype;
    Ok(spec)
}

fn resolve_weights(args: &ModelArgs) -> Result<ModelSpec> {
    let missing = |flag: &'static str, p: &Path| PipelineError::Flag { flag, msg: format!("{}: no such file or folder", p.display()) };
    if let Some(ck) = &args.ckpt {
        if args.encoder.is_some() {
            return Err(PipelineError::Flag { flag: "--encoder", msg: "give either --ckpt or --encoder, not both".into() });
        }
        if !ck.exists() {
            return Err(missing("--ckpt", ck));
        }
        let mut spec = if ck.is_dir() { read_model_dir(ck)? } else { official_ckpt(ck, args.experiment.as_deref())? };
        match &args.refiner {
            Some(RefinerArg::None) => spec.refiner = None,
            Some(RefinerArg::File(f)) => {
                if !f.is_file() {
                    return Err(missing("--refiner", f));
                }
                let cfg = spec.refiner.as_ref().map(|r| r.0.clone()).unwrap_or_default();
                spec.refiner = Some((cfg, refiner_weights(f)));
            }
            None => {}
        }
        return Ok(spec);
    }
    if let Some(enc) = &args.encoder {
        if !enc.is_file() {
            return Err(missing("--encoder", enc));
        }
        let data = experiment_data(args.experiment.as_deref())?;
        let refiner = match &args.refiner {
            Some(RefinerArg::None) => None,
            Some(RefinerArg::File(f)) => {
                if !f.is_file() {
                    return Err(missing("--refiner", f));
                }
                Some((RefinerModelConfig::default(), refiner_weights(f)))
            }
            None => {
                return Err(PipelineError::Flag {
                    flag: "--refiner",
                    msg: "with --encoder, also pass --refiner none (3DGS only) or --refiner FILE (refiner weights)".into(),
                })
            }
        };
        let desc = format!("encoder {}{}", enc.display(), if refiner.is_some() { " + refiner" } else { " (3DGS only)" });
        return Ok(ModelSpec {
            encoder: experiment_encoder(&data),
            data,
            encoder_file: enc.clone(),
            refiner,
            description: desc,
            fit: Default::default(),
            blend: None,
            scene_scale: None,
            encoder_dtype: candle_core::DType::F32,
        });
    }
    if let Some(RefinerArg::File(_)) = &args.refiner {
        return Err(PipelineError::Flag { flag: "--refiner", msg: "a refiner file needs an encoder: pass --encoder FILE or --ckpt".into() });
    }
    let Some(dir) = default_model_dir() else {
        return Err(PipelineError::NoModel(
            "no model given and assets/models/default/ is absent: pass --ckpt <official .ckpt or model folder>, or --encoder FILE --refiner none|FILE".into(),
        ));
    };
    let mut spec = read_model_dir(&dir)?;
    if let Some(RefinerArg::None) = args.refiner {
        spec.refiner = None;
    }
    Ok(spec)
}

fn refiner_weights(f: &Path) -> RefinerWeights {
    match f.extension().and_then(|e| e.to_str()) {
        Some("ckpt") | Some("pth") | Some("pt") => RefinerWeights::Ckpt(f.to_path_buf()),
        _ => RefinerWeights::File(f.to_path_buf()),
    }
}

/// The official release: encoder and refiner in one Lightning `.ckpt` (or a safetensors copy made by
/// `mvsplat360 convert`), DL3DV config unless `--experiment` says otherwise.
fn official_ckpt(path: &Path, experiment: Option<&str>) -> Result<ModelSpec> {
    let data = experiment_data(experiment)?;
    Ok(ModelSpec {
        encoder: experiment_encoder(&data),
        data,
        encoder_file: path.to_path_buf(),
        refiner: Some((RefinerModelConfig::default(), refiner_weights(path))),
        description: format!("official checkpoint {}", path.display()),
        fit: Default::default(),
        blend: None,
        scene_scale: None,
        encoder_dtype: candle_core::DType::F32,
    })
}

/// A model folder's `config.json` text; a key that was measured and not adopted (and then removed) gets an error
/// naming it, its study and the fix instead of serde's list of the keys there are.
pub fn parse_model_config(text: &str) -> std::result::Result<ModelConfig, String> {
    let removed: [(&str, &[(&str, &str)]); 2] = [("fit", crate::fit::REMOVED_KEYS), ("blend", crate::blend::REMOVED_KEYS)];
    if let Ok(v) = serde_json::from_str::<serde_json::Value>(text) {
        for (section, keys) in removed {
            for (key, study) in keys {
                if v.get(section).and_then(|s| s.get(key)).is_some() {
                    return Err(format!(
                        "`{section}.{key}` is no longer a setting (measured and not adopted: docs/research/{study}); delete the key from config.json — the model then runs as it did with the key at its default"
                    ));
                }
            }
        }
    }
    serde_json::from_str(text).map_err(|e| format!("invalid model config: {e}"))
}

/// Read a model folder (`config.json` + `model.safetensors`, or + an official `model.ckpt`).
pub fn read_model_dir(dir: &Path) -> Result<ModelSpec> {
    let cfg_path = dir.join(MODEL_CONFIG);
    let text =
        std::fs::read_to_string(&cfg_path).map_err(|e| PipelineError::Model { path: cfg_path.clone(), msg: format!("cannot read the model config: {e}") })?;
    let cfg = parse_model_config(&text).map_err(|msg| PipelineError::Model { path: cfg_path.clone(), msg })?;
    if cfg.format != MODEL_FORMAT {
        return Err(PipelineError::Model { path: cfg_path, msg: format!("format is `{}`, expected `{MODEL_FORMAT}`", cfg.format) });
    }
    // An official Lightning checkpoint of another architecture than DL3DV's is a folder with its config.json.
    let ckpt = dir.join(MODEL_CKPT);
    let weights = dir.join(MODEL_WEIGHTS);
    let from_ckpt = !weights.is_file() && ckpt.is_file();
    if !weights.is_file() && !from_ckpt {
        return Err(PipelineError::Model {
            path: weights,
            msg: format!("missing: a model folder holds config.json and {MODEL_WEIGHTS} (or an official Lightning {MODEL_CKPT})"),
        });
    }
    if from_ckpt && cfg.blend.is_some() {
        return Err(PipelineError::Model { path: cfg_path, msg: format!("`blend` needs its weights in {MODEL_WEIGHTS}; {MODEL_CKPT} has none") });
    }
    let weights = if from_ckpt { ckpt } else { weights };
    let fit = cfg.fit.unwrap_or_default();
    fit.validate().map_err(|e| PipelineError::Model { path: cfg_path.clone(), msg: format!("invalid `fit` settings: {e}") })?;
    if let Some(b) = &cfg.blend {
        b.validate().map_err(|e| PipelineError::Model { path: cfg_path.clone(), msg: format!("invalid `blend` settings: {e}") })?;
    }
    let scene_scale = match &cfg.scene_scale {
        None => None,
        Some(s) => Some(s.parse::<crate::scale::SceneScale>().map_err(|e| PipelineError::Model {
            path: cfg_path.clone(),
            msg: format!("invalid `scene_scale`: {e} (`auto` for models trained on auto-scaled scenes; remove the key for the official protocol)"),
        })?),
    };
    let mut encoder = cfg.encoder.clone();
    encoder.near = cfg.data.near;
    encoder.far = cfg.data.far;
    Ok(ModelSpec {
        data: cfg.data,
        encoder,
        encoder_file: weights.clone(),
        refiner: cfg.refiner.map(|r| (r, if from_ckpt { RefinerWeights::Ckpt(weights.clone()) } else { RefinerWeights::File(weights.clone()) })),
        description: format!("model folder {}", dir.display()),
        fit,
        blend: cfg.blend.map(|b| (b, weights.clone())),
        scene_scale,
        encoder_dtype: candle_core::DType::F32,
    })
}

/// Write a model folder from a state dict with official key names (atomically: temp names, then rename).
pub fn write_model_dir(dir: &Path, cfg: &ModelConfig, tensors: &[(String, candle_core::Tensor)]) -> Result<()> {
    let werr = |p: &Path, e: &dyn std::fmt::Display| PipelineError::Write { path: p.to_path_buf(), msg: e.to_string() };
    std::fs::create_dir_all(dir).map_err(|e| werr(dir, &e))?;
    let map: std::collections::HashMap<String, candle_core::Tensor> = tensors.iter().cloned().collect();
    let w = dir.join(MODEL_WEIGHTS);
    crate::output::atomic_write(&w, |p| candle_core::safetensors::save(&map, p).map_err(|e| e.to_string()))?;
    let json = serde_json::to_string_pretty(cfg).map_err(|e| werr(dir, &e))?;
    crate::output::atomic_write(&dir.join(MODEL_CONFIG), |p| std::fs::write(p, &json).map_err(|e| e.to_string()))?;
    Ok(())
}

/// The refiner's weights as one safetensors file: an official `.ckpt` is converted once into the cache
/// (`$MVSPLAT360_CACHE` or `~/.cache/mvsplat360`), keyed by its size and modification time.
pub fn refiner_safetensors(w: &RefinerWeights, note: &dyn Fn(&str)) -> Result<PathBuf> {
    match w {
        RefinerWeights::File(p) => Ok(p.clone()),
        RefinerWeights::Ckpt(p) => {
            let meta = std::fs::metadata(p).map_err(|e| PipelineError::Model { path: p.clone(), msg: e.to_string() })?;
            let mtime = meta.modified().ok().and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map(|d| d.as_secs()).unwrap_or(0);
            let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("ckpt");
            let dir = cache_dir().join("converted");
            let out = dir.join(format!("{stem}-{}-{mtime}.refiner.safetensors", meta.len()));
            if out.is_file() {
                return Ok(out);
            }
            std::fs::create_dir_all(&dir).map_err(|e| PipelineError::Write { path: dir.clone(), msg: e.to_string() })?;
            // One conversion per cache: processes sharing it (ranks on one machine) wait for the first.
            let lock = out.with_extension("safetensors.lock");
            let _held = mvsplat360_dataset::atomic::wait_lock(&lock, || note(&format!("waiting for another process converting {} …", p.display())))
                .map_err(|e| PipelineError::Write { path: lock.clone(), msg: e.to_string() })?;
            if out.is_file() {
                return Ok(out);
            }
            note(&format!("converting the refiner of {} to safetensors (once) → {}", p.display(), out.display()));
            crate::output::atomic_write_ungated(&out, |tmp| {
                mvsplat360_encoder::weights::convert_to_safetensors(p, tmp, "refiner.").map(|_| ()).map_err(|e| e.to_string())
            })?;
            Ok(out)
        }
    }
}

/// Per-user cache folder.
pub fn cache_dir() -> PathBuf {
    if let Some(p) = std::env::var_os("MVSPLAT360_CACHE") {
        return PathBuf::from(p);
    }
    if let Some(p) = std::env::var_os("XDG_CACHE_HOME") {
        return PathBuf::from(p).join("mvsplat360");
    }
    std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache/mvsplat360")).unwrap_or_else(|| PathBuf::from(".mvsplat360-cache"))
}

/// A tiny configuration of the whole model (tests, smoke runs): the tiny encoder, a 3-level 32-channel UNet,
/// a 4-level (factor 8) 32-channel VAE and a 2-layer CLIP tower; input 128×64.
pub fn tiny_config(with_refiner: bool) -> ModelConfig {
    let data = DataConfig { experiment: "tiny".into(), image_width: 128, image_height: 64, near: 1.0, far: 100.0 };
    let encoder = EncoderCostVolumeCfg { near: data.near, far: data.far, ..EncoderCostVolumeCfg::tiny() };
    let refiner = with_refiner.then(|| RefinerModelConfig {
        unet: VideoUNetConfig { channel_mult: vec![1, 2, 2], ..VideoUNetConfig::tiny() },
        vae: AutoencoderConfig { ch: 32, ch_mult: vec![1, 1, 2, 2], num_res_blocks: 1, ..AutoencoderConfig::default() },
        clip: ClipVisionConfig { width: 32, layers: 2, heads: 2, mlp_width: 64, patch_size: 8, image_size: 32, output_dim: 32, ..ClipVisionConfig::default() },
    });
    ModelConfig { format: MODEL_FORMAT.into(), data, encoder, refiner, fit: None, blend: None, scene_scale: None }
}

/// Seeded random weights for `cfg` under the official key names (what a model folder's safetensors holds).
pub fn random_state_dict(cfg: &ModelConfig, seed: u64) -> Result<Vec<(String, candle_core::Tensor)>> {
    let dev = candle_core::Device::Cpu;
    let bad = |msg: String| PipelineError::Model { path: PathBuf::from("<random model>"), msg };
    let enc = mvsplat360_encoder::weights::random_tensors(seed, &dev, |vb| mvsplat360_encoder::encoder_costvolume::EncoderCostVolume::new(vb, &cfg.encoder))
        .map_err(|e| bad(format!("encoder config: {e}")))?;
    let mut out: Vec<(String, candle_core::Tensor)> = enc.into_iter().map(|(k, t)| (format!("encoder.{k}"), t)).collect();
    out.sort_by(|a, b| a.0.cmp(&b.0));
    if let Some(r) = &cfg.refiner {
        out.extend(mvsplat360_refiner::state_dict::random_refiner_state_dict(&r.unet, &r.vae, &r.clip, seed.wrapping_add(17)).map_err(bad)?);
    }
    Ok(out)
}
