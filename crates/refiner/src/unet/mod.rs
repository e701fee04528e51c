//! Stable Video Diffusion spatio-temporal UNet (sgm `VideoUNet`), as configured by MVSplat360
//! (`svd_wo_mb_fps`: 8 input channels, `label_emb` fed by the 256-d cond_aug embedding only).
//!
//! The model code uses sgm key names only. Official checkpoints (`refiner.model.diffusion_model.*`,
//! Stability's `model.diffusion_model.*`) load directly; diffusers folders load through the single
//! name table in [`keymap`].

pub mod keymap;
pub mod util;
pub mod video_attention;
pub mod video_model;
pub mod weights;

use std::path::{Path, PathBuf};

use candle_core::{DType, Device};
use serde::{Deserialize, Serialize};

pub use video_model::{UNetInputs, VideoResBlock, VideoUNet};
pub use weights::{UNetLayout, Weights};

#[derive(Debug, thiserror::Error)]
pub enum UNetError {
    #[error("cannot open UNet weights {path}: {msg}")]
    Open { path: PathBuf, msg: String },
    #[error("{path}: no UNet keys recognised (expected sgm `model.diffusion_model.*`, `refiner.model.diffusion_model.*`, `input_blocks.*` or diffusers `conv_in.weight`, `down_blocks.*`)")]
    UnknownLayout { path: PathBuf },
    #[error("{path}: UNet weights do not match the config ({} missing, {} unexpected, {} wrong shape) — check the config (model_channels, channel_mult, in_channels, adm_in_channels) against the checkpoint\n  missing: {missing:?}\n  unexpected: {unexpected:?}\n  wrong shape: {mismatched:?}", missing.len(), unexpected.len(), mismatched.len())]
    KeyMismatch { path: PathBuf, missing: Vec<String>, unexpected: Vec<String>, mismatched: Vec<String> },
    #[error("UNet config {path}: {msg}")]
    Config { path: PathBuf, msg: String },
    #[error("UNet: {0}")]
    Tensor(#[from] candle_core::Error),
}

/// sgm `VideoUNet` parameters (names as in the official YAML); defaults = MVSplat360 `svd_wo_mb_fps`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct VideoUNetConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    pub model_channels: usize,
    pub num_res_blocks: usize,
    /// Downsampling factors (1, 2, 4, …) whose levels carry a SpatialVideoTransformer.
    pub attention_resolutions: Vec<usize>,
    pub channel_mult: Vec<usize>,
    pub num_head_channels: usize,
    pub transformer_depth: usize,
    pub context_dim: usize,
    /// `label_emb` input width (`num_classes: sequential`); None = no vector condition.
    pub adm_in_channels: Option<usize>,
    /// Only `softmax`/`softmax-xformers` exist; both are plain softmax attention here.
    pub spatial_transformer_attn_type: String,
    /// Only `learned_with_images` is supported (all AlphaBlenders: sigmoid(mix_factor)).
    pub merge_strategy: String,
    pub video_kernel_size: [usize; 3],
    pub use_linear_in_transformer: bool,
    pub extra_ff_mix_layer: bool,
    pub use_spatial_context: bool,
    pub max_ddpm_temb_period: f32,
    /// GroupNorm eps of every ResBlock (sgm `normalization`: 1e-5).
    pub resnet_eps: f64,
    /// GroupNorm eps of the ResBlocks of down levels with attention: 1e-5 in sgm; diffusers'
    /// `CrossAttnDownBlockSpatioTemporal` hard-codes 1e-6, so diffusers configs set that.
    pub down_attn_resnet_eps: f64,
    /// GroupNorm eps of the output (up) ResBlocks: 1e-5 in sgm; diffusers' up blocks never receive
    /// `resnet_eps` and keep their 1e-6 default.
    pub up_resnet_eps: f64,
    /// Attention score buffer budget in floats (query/batch chunking), 64 Mi floats = 256 MiB.
    pub attn_max_score_elems: usize,
}

impl Default for VideoUNetConfig {
    fn default() -> Self {
        Self {
            in_channels: 8,
            out_channels: 4,
            model_channels: 320,
            num_res_blocks: 2,
            attention_resolutions: vec![4, 2, 1],
            channel_mult: vec![1, 2, 4, 4],
            num_head_channels: 64,
            transformer_depth: 1,
            context_dim: 1024,
            adm_in_channels: Some(256),
            spatial_transformer_attn_type: "softmax-xformers".into(),
            merge_strategy: "learned_with_images".into(),
            video_kernel_size: [3, 1, 1],
            use_linear_in_transformer: true,
            extra_ff_mix_layer: true,
            use_spatial_context: true,
            max_ddpm_temb_period: 10000.0,
            resnet_eps: 1e-5,
            down_attn_resnet_eps: 1e-5,
            up_resnet_eps: 1e-5,
            attn_max_score_elems: 64 << 20,
        }
    }
}

fn usize_list(v: &serde_json::Value, key: &str, n: usize, path: &Path) -> Result<Vec<usize>, UNetError> {
    let err = |msg: String| UNetError::Config { path: path.to_path_buf(), msg };
    match v.get(key) {
        Some(serde_json::Value::Array(a)) => {
            a.iter().map(|x| x.as_u64().map(|u| u as usize).ok_or_else(|| err(format!("`{key}` must hold integers")))).collect()
        }
        Some(x) => x.as_u64().map(|u| vec![u as usize; n]).ok_or_else(|| err(format!("`{key}` must be an integer or list"))),
        None => Err(err(format!("missing `{key}`"))),
    }
}

impl VideoUNetConfig {
    /// A 2-level, 32-channel UNet with every block kind (tests, smoke benches); 8 input channels, 32-wide
    /// context and vector condition.
    pub fn tiny() -> Self {
        Self {
            model_channels: 32,
            channel_mult: vec![1, 2],
            attention_resolutions: vec![1, 2],
            num_res_blocks: 1,
            num_head_channels: 16,
            context_dim: 32,
            adm_in_channels: Some(32),
            ..Self::default()
        }
    }

    /// From a diffusers `UNetSpatioTemporalConditionModel` `config.json`.
    pub fn from_diffusers_json(path: &Path) -> Result<Self, UNetError> {
        let text = std::fs::read_to_string(path).map_err(|e| UNetError::Config { path: path.to_path_buf(), msg: e.to_string() })?;
        let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| UNetError::Config { path: path.to_path_buf(), msg: e.to_string() })?;
        Self::from_diffusers_value(&v, path)
    }

    pub fn from_diffusers_value(v: &serde_json::Value, path: &Path) -> Result<Self, UNetError> {
        let err = |msg: String| UNetError::Config { path: path.to_path_buf(), msg };
        let get = |k: &str| v.get(k).and_then(|x| x.as_u64()).map(|u| u as usize).ok_or_else(|| err(format!("missing integer `{k}`")));
        let boc = usize_list(v, "block_out_channels", 0, path)?;
        let levels = boc.len();
        if levels == 0 {
            return Err(err("`block_out_channels` is empty".into()));
        }
        let heads = usize_list(v, "num_attention_heads", levels, path)?;
        let layers = usize_list(v, "layers_per_block", levels, path)?;
        let depth = usize_list(v, "transformer_layers_per_block", levels, path)?;
        let types: Vec<String> = v
            .get("down_block_types")
            .and_then(|x| x.as_array())
            .map(|a| a.iter().filter_map(|s| s.as_str().map(String::from)).collect())
            .ok_or_else(|| err("missing `down_block_types`".into()))?;
        let mc = boc[0];
        if boc.iter().any(|c| c % mc != 0) || layers.iter().any(|&l| l != layers[0]) || depth.iter().any(|&d| d != depth[0]) {
            return Err(err("block_out_channels must be multiples of the first; layers_per_block / transformer_layers_per_block uniform".into()));
        }
        let head_ch: Vec<usize> = boc.iter().zip(&heads).map(|(c, h)| c / h.max(&1)).collect();
        if head_ch.iter().any(|&d| d != head_ch[0]) {
            return Err(err(format!("channels per head differ between levels: {head_ch:?}")));
        }
        let attention_resolutions = types.iter().enumerate().filter(|(_, t)| t.starts_with("CrossAttn")).map(|(i, _)| 1usize << i).collect();
        let ctx = v
            .get("cross_attention_dim")
            .and_then(|x| x.as_u64().or_else(|| x.as_array().and_then(|a| a.first()).and_then(|y| y.as_u64())))
            .ok_or_else(|| err("missing `cross_attention_dim`".into()))? as usize;
        Ok(Self {
            in_channels: get("in_channels")?,
            out_channels: get("out_channels")?,
            model_channels: mc,
            num_res_blocks: layers[0],
            attention_resolutions,
            channel_mult: boc.iter().map(|c| c / mc).collect(),
            num_head_channels: head_ch[0],
            transformer_depth: depth[0],
            context_dim: ctx,
            adm_in_channels: Some(get("projection_class_embeddings_input_dim")?),
            down_attn_resnet_eps: 1e-6,
            up_resnet_eps: 1e-6,
            ..Self::default()
        })
    }

    fn validate(&self) -> Result<(), UNetError> {
        let bad = |msg: &str| Err(UNetError::Config { path: PathBuf::from("<VideoUNetConfig>"), msg: msg.into() });
        if self.merge_strategy != "learned_with_images" {
            return bad("only merge_strategy `learned_with_images` is supported");
        }
        if !self.use_linear_in_transformer || !self.extra_ff_mix_layer || !self.use_spatial_context {
            return bad("use_linear_in_transformer, extra_ff_mix_layer and use_spatial_context must be true (SVD)");
        }
        if self.video_kernel_size[1] != 1 || self.video_kernel_size[2] != 1 || self.video_kernel_size[0] % 2 == 0 {
            return bad("video_kernel_size must be [odd, 1, 1]");
        }
        if self.model_channels % 32 != 0 || self.num_head_channels == 0 {
            return bad("model_channels must be a multiple of 32 (GroupNorm 32) and num_head_channels > 0");
        }
        Ok(())
    }
}

impl VideoUNet {
    /// Load from a safetensors file (layout auto-detected unless given), strict: any missing, unexpected or
    /// wrongly shaped key is an error that lists them. f16/bf16 are upcast to f32; one copy of the weights.
    pub fn load(path: &Path, layout: Option<UNetLayout>, cfg: &VideoUNetConfig, device: &Device) -> Result<Self, UNetError> {
        Self::load_as(path, layout, cfg, device, DType::F32)
    }

    /// [`Self::load`] computing in `dtype` (f16/bf16: half the weight memory; inputs are cast, the output
    /// comes back as f32).
    pub fn load_as(path: &Path, layout: Option<UNetLayout>, cfg: &VideoUNetConfig, device: &Device, dtype: DType) -> Result<Self, UNetError> {
        cfg.validate()?;
        let w = Weights::from_file(path, layout, cfg, device)?.with_dtype(dtype);
        let model = VideoUNet::new(cfg, &w)?;
        w.finish()?;
        Ok(model)
    }

    /// Load a diffusers folder (`config.json` + `diffusion_pytorch_model[.fp16].safetensors`).
    pub fn load_diffusers_dir(dir: &Path, device: &Device) -> Result<Self, UNetError> {
        let cfg = VideoUNetConfig::from_diffusers_json(&dir.join("config.json"))?;
        let file = crate::diffusers_weights_file(dir)
            .ok_or_else(|| UNetError::Open { path: dir.to_path_buf(), msg: "no diffusion_pytorch_model[.fp16].safetensors in folder".into() })?;
        Self::load(&file, Some(UNetLayout::Diffusers), &cfg, device)
    }

    /// Seeded random weights with the given config (benchmarks).
    pub fn random(cfg: &VideoUNetConfig, seed: u64, device: &Device) -> Result<Self, UNetError> {
        Self::random_as(cfg, seed, device, DType::F32)
    }

    /// [`Self::random`] computing in `dtype` (the same values, rounded).
    pub fn random_as(cfg: &VideoUNetConfig, seed: u64, device: &Device, dtype: DType) -> Result<Self, UNetError> {
        cfg.validate()?;
        let w = Weights::random(seed, device).with_dtype(dtype);
        Ok(VideoUNet::new(cfg, &w)?)
    }

    /// Seeded random weights handed out as `Var`s (gradient tests), with the `Var`s by sgm name; the same
    /// values as [`Self::random`] with that seed. For a file: `Weights::from_file(..)?.trainable()`,
    /// [`VideoUNet::new`], [`Weights::take_vars`], [`Weights::finish`].
    pub fn random_trainable(cfg: &VideoUNetConfig, seed: u64, device: &Device) -> Result<(Self, Vec<(String, candle_core::Var)>), UNetError> {
        cfg.validate()?;
        let w = Weights::random(seed, device).trainable();
        let model = VideoUNet::new(cfg, &w)?;
        Ok((model, w.take_vars()))
    }
}
