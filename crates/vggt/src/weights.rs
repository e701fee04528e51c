//! Loading VGGT by the official key names. A **VGGT model folder** is `config.json` ([`VggtConfig`]) + the
//! weights (`model.safetensors` or `model.pt`); a bare weights file is VGGT-1B (the official `model.pt` of
//! `facebook/VGGT-1B`, or of `facebook/VGGT-1B-Commercial`: same layout), torch zip pickle or safetensors.
//! Strict: missing, unexpected and mis-shaped keys are listed by name; `track_head.*` is skipped on purpose
//! (the project does not track points) and reported as skipped.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use mvsplat360_dataset::weights::{Checkpoint, StrictLoader, WeightsError};

use crate::config::VggtConfig;
use crate::models::vggt::Vggt;

/// Where the official weights come from and under which licence (said wherever they are missing).
pub const WEIGHTS_HELP: &str = "VGGT-1B: https://huggingface.co/facebook/VGGT-1B/resolve/main/model.pt (CC BY-NC 4.0, non-commercial); \
VGGT-1B-Commercial: https://huggingface.co/facebook/VGGT-1B-Commercial (gated: accept Meta's VGGT licence on that page first). \
Pass the downloaded model.pt (or a folder with config.json + model.pt/model.safetensors) with --vggt-weights";

/// Key prefix of the part not built.
pub const SKIPPED_PREFIX: &str = "track_head.";

#[derive(Debug, thiserror::Error)]
pub enum VggtError {
    #[error("VGGT weights not found at {path}. {WEIGHTS_HELP}")]
    NotFound { path: PathBuf },
    #[error("{path}: no weights file in this folder (looked for model.safetensors, model.pt). {WEIGHTS_HELP}")]
    NoWeightsInFolder { path: PathBuf },
    #[error("{path}: {msg}")]
    Config { path: PathBuf, msg: String },
    #[error("{0}")]
    Weights(#[from] WeightsError),
}

/// A model folder or weights file, resolved.
#[derive(Debug, Clone)]
pub struct VggtSource {
    pub weights: PathBuf,
    pub config: VggtConfig,
    /// `config.json`, when the config came from a folder (None: VGGT-1B by default).
    pub config_path: Option<PathBuf>,
}

/// A model folder's `config.json`, checked.
pub fn read_config(cfg_path: &Path) -> Result<VggtConfig, VggtError> {
    let text = std::fs::read_to_string(cfg_path)
        .map_err(|e| VggtError::Config { path: cfg_path.into(), msg: format!("cannot read the model folder's config ({e})") })?;
    let config: VggtConfig = serde_json::from_str(&text).map_err(|e| VggtError::Config { path: cfg_path.into(), msg: format!("not a VGGT config: {e}") })?;
    config.validate().map_err(|msg| VggtError::Config { path: cfg_path.into(), msg })?;
    Ok(config)
}

impl VggtSource {
    pub fn resolve(path: &Path) -> Result<Self, VggtError> {
        if path.is_dir() {
            let cfg_path = path.join("config.json");
            let config = read_config(&cfg_path)?;
            let weights = ["model.safetensors", "model.pt"]
                .iter()
                .map(|n| path.join(n))
                .find(|p| p.is_file())
                .ok_or_else(|| VggtError::NoWeightsInFolder { path: path.into() })?;
            Ok(Self { weights, config, config_path: Some(cfg_path) })
        } else if path.is_file() {
            Ok(Self { weights: path.into(), config: VggtConfig::default(), config_path: None })
        } else {
            Err(VggtError::NotFound { path: path.into() })
        }
    }
}

/// What loading did besides building the model.
#[derive(Debug, Clone)]
pub struct LoadReport {
    /// Keys in the file deliberately not loaded (`track_head.*`).
    pub skipped: Vec<String>,
}

/// Build the model from a folder or file, strictly (f32 on `device`).
pub fn load(path: &Path, device: &Device) -> Result<(Vggt, LoadReport), VggtError> {
    let src = VggtSource::resolve(path)?;
    load_source(&src, device, DType::F32)
}

/// [`load`] with the aggregator in `trunk` (see [`Vggt::with_trunk_dtype`]).
pub fn load_source(src: &VggtSource, device: &Device, trunk: DType) -> Result<(Vggt, LoadReport), VggtError> {
    let loader = StrictLoader::new(Checkpoint::open(&src.weights)?, "")?;
    let vb = loader.var_builder(DType::F32, device);
    let model = Vggt::with_trunk_dtype(vb, &src.config, trunk);
    // Key problems first: a shape problem usually makes the build itself fail later on.
    let skipped = loader.finish_ignoring(&[SKIPPED_PREFIX])?;
    if !skipped.is_empty() {
        tracing::info!("{}: {} track_head.* tensors skipped (point tracking is not used)", src.weights.display(), skipped.len());
    }
    let model = model.map_err(|source| WeightsError::Build { path: src.weights.clone(), source })?;
    Ok((model, LoadReport { skipped }))
}

/// The model with seeded random weights under the official names, made as the model asks for them (no second
/// copy: benchmarks at the full VGGT-1B shape).
pub fn random_model(cfg: &VggtConfig, seed: u64, device: &Device, trunk: DType) -> candle_core::Result<Vggt> {
    Vggt::with_trunk_dtype(mvsplat360_dataset::weights::random_var_builder(seed, device), cfg, trunk)
}

/// Build from tensors in memory under the official names.
pub fn from_tensors(tensors: HashMap<String, Tensor>, cfg: &VggtConfig, device: &Device, trunk: DType) -> candle_core::Result<Vggt> {
    Vggt::with_trunk_dtype(VarBuilder::from_tensors(tensors, DType::F32, device), cfg, trunk)
}
