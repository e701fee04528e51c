//! OpenCLIP ViT-H/14 image embedder as sgm `FrozenOpenCLIPImageEmbedder` uses it (vision tower only,
//! projected pooled embedding, not normalised), with its preprocessing.
//!
//! The model code uses open_clip key names (`conv1.weight`, `transformer.resblocks.N.attn.in_proj_weight`, …).
//! Official checkpoints (`refiner.conditioner.embedders.0.open_clip.model.visual.*`) load directly;
//! transformers `CLIPVisionModelWithProjection` files load through [`crate::keymap::clip`].

pub mod preprocess;
pub mod transformer;

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};

pub use preprocess::{clip_preprocess, resize_with_antialiasing, CLIP_MEAN, CLIP_STD};
pub use transformer::VisionTransformer;

use crate::weights::{self, StrictWeights, WeightsError};

#[derive(Debug, thiserror::Error)]
pub enum ClipError {
    #[error(transparent)]
    Weights(#[from] WeightsError),
    #[error("CLIP config {path}: {msg}")]
    Config { path: PathBuf, msg: String },
    #[error("CLIP input: {0}")]
    Input(String),
    #[error("CLIP: {0}")]
    Tensor(#[from] candle_core::Error),
}

/// MLP activation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ClipAct {
    /// Exact (erf) GELU: open_clip ViT-H/14, transformers `gelu`.
    Gelu,
    /// x·sigmoid(1.702x): OpenAI CLIP, transformers `quick_gelu`.
    QuickGelu,
}

/// open_clip vision-tower parameters; defaults = ViT-H-14 (SVD's image embedder).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ClipVisionConfig {
    pub width: usize,
    pub layers: usize,
    pub heads: usize,
    /// `mlp_ratio · width` (4 × 1280).
    pub mlp_width: usize,
    pub patch_size: usize,
    pub image_size: usize,
    /// `embed_dim` of the CLIP model = width of `proj`'s output.
    pub output_dim: usize,
    pub layer_norm_eps: f64,
    pub act: ClipAct,
    /// Attention score buffer budget in floats.
    pub attn_max_score_elems: usize,
}

impl Default for ClipVisionConfig {
    fn default() -> Self {
        Self {
            width: 1280,
            layers: 32,
            heads: 16,
            mlp_width: 5120,
            patch_size: 14,
            image_size: 224,
            output_dim: 1024,
            layer_norm_eps: 1e-5,
            act: ClipAct::Gelu,
            attn_max_score_elems: 32 << 20,
        }
    }
}

impl ClipVisionConfig {
    /// From a transformers `CLIPVisionConfig` json (`to_dict()` / `config.json`, vision part).
    pub fn from_transformers_json(path: &Path) -> Result<Self, ClipError> {
        let err = |msg: String| ClipError::Config { path: path.to_path_buf(), msg };
        let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
        let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| err(e.to_string()))?;
        // A full CLIPConfig nests the vision part.
        let v = v.get("vision_config").cloned().unwrap_or(v);
        Self::from_transformers_value(&v, path)
    }

    pub fn from_transformers_value(v: &serde_json::Value, path: &Path) -> Result<Self, ClipError> {
        let err = |msg: String| ClipError::Config { path: path.to_path_buf(), msg };
        let int = |k: &str| v.get(k).and_then(|x| x.as_u64()).map(|u| u as usize).ok_or_else(|| err(format!("missing integer `{k}`")));
        let act = match v.get("hidden_act").and_then(|x| x.as_str()).unwrap_or("quick_gelu") {
            "gelu" => ClipAct::Gelu,
            "quick_gelu" => ClipAct::QuickGelu,
            other => return Err(err(format!("unsupported hidden_act `{other}` (gelu or quick_gelu)"))),
        };
        let cfg = Self {
            width: int("hidden_size")?,
            layers: int("num_hidden_layers")?,
            heads: int("num_attention_heads")?,
            mlp_width: int("intermediate_size")?,
            patch_size: int("patch_size")?,
            image_size: int("image_size")?,
            output_dim: int("projection_dim")?,
            layer_norm_eps: v.get("layer_norm_eps").and_then(|x| x.as_f64()).unwrap_or(1e-5),
            act,
            ..Self::default()
        };
        cfg.validate().map_err(err)?;
        Ok(cfg)
    }

    fn validate(&self) -> Result<(), String> {
        if self.heads == 0 || self.width % self.heads != 0 {
            return Err(format!("width {} not divisible by heads {}", self.width, self.heads));
        }
        if self.patch_size == 0 || self.image_size % self.patch_size != 0 {
            return Err(format!("image_size {} not a multiple of patch_size {}", self.image_size, self.patch_size));
        }
        Ok(())
    }
}

/// How the vision-tower keys are spelled in a file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ClipLayout {
    /// open_clip `VisionTransformer` names under a prefix, e.g.
    /// `refiner.conditioner.embedders.0.open_clip.model.visual.` (MVSplat360 checkpoint),
    /// `conditioner.embedders.0.open_clip.model.visual.` (svd.safetensors), `visual.` (open_clip model) or ``.
    OpenClip { prefix: String },
    /// transformers `CLIPVisionModelWithProjection` names (`vision_model.*`, `visual_projection.weight`).
    Transformers,
}

impl ClipLayout {
    pub fn detect(keys: &[String]) -> Option<Self> {
        let set: std::collections::HashSet<&str> = keys.iter().map(|s| s.as_str()).collect();
        let mut prefixes: Vec<&str> = keys
            .iter()
            .filter_map(|k| k.strip_suffix("class_embedding"))
            .filter(|p| p.is_empty() || p.ends_with('.'))
            .filter(|p| set.contains(format!("{p}conv1.weight").as_str()) && set.contains(format!("{p}proj").as_str()))
            .collect();
        prefixes.sort();
        if let Some(p) = prefixes.first() {
            return Some(Self::OpenClip { prefix: p.to_string() });
        }
        set.contains("vision_model.embeddings.patch_embedding.weight").then_some(Self::Transformers)
    }
}

/// sgm `FrozenOpenCLIPImageEmbedder` (vision tower + its preprocessing).
#[derive(Debug)]
pub struct ClipImageEmbedder {
    pub cfg: ClipVisionConfig,
    visual: VisionTransformer,
    /// Weights' dtype: pixels are cast to it, embeddings come back as f32.
    dtype: DType,
}

impl ClipImageEmbedder {
    /// Load from a safetensors file (layout auto-detected unless given). Strict within the vision tower:
    /// missing / unexpected / wrongly shaped keys are one error listing them; other components of a full
    /// checkpoint (UNet, VAE, text tower) are ignored. f16/bf16 are upcast to f32.
    pub fn load(path: &Path, layout: Option<ClipLayout>, cfg: &ClipVisionConfig, device: &Device) -> Result<Self, ClipError> {
        Self::load_as(path, layout, cfg, device, DType::F32)
    }

    /// [`Self::load`] computing in `dtype` (f16/bf16); embeddings come back as f32.
    pub fn load_as(path: &Path, layout: Option<ClipLayout>, cfg: &ClipVisionConfig, device: &Device, dtype: DType) -> Result<Self, ClipError> {
        cfg.validate().map_err(|msg| ClipError::Config { path: path.to_path_buf(), msg })?;
        let st = weights::open_safetensors(path)?;
        let layout = match layout {
            Some(l) => l,
            None => ClipLayout::detect(&weights::keys(&st)).ok_or_else(|| WeightsError::UnknownLayout {
                path: path.to_path_buf(),
                what: "CLIP vision".into(),
                expected: "open_clip `…visual.class_embedding` / `…visual.conv1.weight` or transformers `vision_model.embeddings.patch_embedding.weight`"
                    .into(),
            })?,
        };
        let w = match &layout {
            ClipLayout::OpenClip { prefix } => StrictWeights::own_layout(st, path, "CLIP vision", prefix, &[""], device),
            ClipLayout::Transformers => StrictWeights::mapped(
                st,
                path,
                "CLIP vision",
                |k| k.starts_with("vision_model.") || k.starts_with("visual_projection."),
                crate::keymap::clip::transformers_to_open_clip,
                device,
            ),
        };
        if w.is_empty() {
            return Err(WeightsError::UnknownLayout { path: path.to_path_buf(), what: "CLIP vision".into(), expected: format!("layout {layout:?}") }.into());
        }
        let w = w.with_dtype(dtype);
        let visual = VisionTransformer::load(&w, cfg)?;
        let dtype = w.dtype();
        w.finish()?;
        Ok(Self { cfg: cfg.clone(), visual, dtype })
    }

    /// Seeded random weights with the given config (benchmarks).
    pub fn random(cfg: &ClipVisionConfig, seed: u64, device: &Device) -> Result<Self, ClipError> {
        Self::random_as(cfg, seed, device, DType::F32)
    }

    /// [`Self::random`] computing in `dtype` (the same values, rounded).
    pub fn random_as(cfg: &ClipVisionConfig, seed: u64, device: &Device, dtype: DType) -> Result<Self, ClipError> {
        cfg.validate().map_err(|msg| ClipError::Config { path: PathBuf::from("<ClipVisionConfig>"), msg })?;
        let w = StrictWeights::random(seed, "CLIP vision", device).with_dtype(dtype);
        let visual = VisionTransformer::load(&w, cfg)?;
        Ok(Self { cfg: cfg.clone(), visual, dtype: w.dtype() })
    }

    /// Build from any weight source (crate-internal: random state dicts).
    pub(crate) fn build_with(w: &StrictWeights, cfg: &ClipVisionConfig) -> Result<Self, ClipError> {
        let visual = VisionTransformer::load(w, cfg)?;
        Ok(Self { cfg: cfg.clone(), visual, dtype: w.dtype() })
    }

    /// Already preprocessed pixels (N, 3, image_size, image_size) → (N, output_dim).
    pub fn embed_pixels(&self, pixels: &Tensor) -> Result<Tensor, ClipError> {
        let (_, c, h, w) = pixels.dims4()?;
        let s = self.cfg.image_size;
        if c != 3 || h != s || w != s {
            return Err(ClipError::Input(format!("expected (N, 3, {s}, {s}) pixels, got {:?}", pixels.dims())));
        }
        Ok(self.visual.forward(&pixels.to_dtype(self.dtype)?.contiguous()?, &self.cfg)?.to_dtype(DType::F32)?)
    }

    /// Views (N, 3, H, W) in [0, 1] → CLIP image embeddings (N, output_dim), preprocessing included.
    pub fn embed(&self, views: &Tensor) -> Result<Tensor, ClipError> {
        let pixels = clip_preprocess(views, self.cfg.image_size)?;
        self.embed_pixels(&pixels)
    }

    /// Context views (B, V, 3, H, W) in [0, 1] → mean embedding over the V views, (B, 1, output_dim):
    /// MVSplat360's cross-attention context (repeated for every frame by the UNet).
    pub fn embed_mean(&self, views: &Tensor) -> Result<Tensor, ClipError> {
        let (b, v, c, h, w) = views.dims5()?;
        let e = self.embed(&views.reshape((b * v, c, h, w))?)?;
        Ok(e.reshape((b, v, self.cfg.output_dim))?.mean_keepdim(1)?)
    }
}
