//! SVD first stage (sgm `AutoencodingEngine`): `Encoder` + `DiagonalGaussianRegularizer` posterior and the
//! temporal `VideoDecoder`, plus MVSplat360's resolution glue (×2 before encoding, ×0.5 after decoding).
//!
//! The model code uses sgm key names (`encoder.down.0.block.0.conv1.weight`, …). Official checkpoints
//! (`refiner.first_stage_model.*`, `first_stage_model.*`) load directly; diffusers
//! `AutoencoderKLTemporalDecoder` files load through the table in [`crate::keymap::vae`].

pub mod model;
pub mod temporal_ae;

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::weights::{self, StrictWeights, WeightsError};

pub use model::Encoder;
pub use temporal_ae::VideoDecoder;

#[derive(Debug, thiserror::Error)]
pub enum VaeError {
    #[error(transparent)]
    Weights(#[from] WeightsError),
    #[error("VAE config {path}: {msg}")]
    Config { path: PathBuf, msg: String },
    #[error("VAE input: {0}")]
    Input(String),
    #[error("VAE: {0}")]
    Tensor(#[from] candle_core::Error),
}

/// sgm `Encoder`/`VideoDecoder` parameters (official YAML names); defaults = SVD / MVSplat360 `svd_wo_mb_fps`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AutoencoderConfig {
    pub ch: usize,
    pub ch_mult: Vec<usize>,
    pub num_res_blocks: usize,
    pub z_channels: usize,
    pub double_z: bool,
    pub in_channels: usize,
    pub out_ch: usize,
    /// Latent scale of the diffusion model (`scale_factor`); [`AutoencoderKL`] works on unscaled latents.
    pub scale_factor: f64,
    /// Temporal kernel of the decoder's time mixing, (kt, 1, 1) with kt odd.
    pub video_kernel_size: [usize; 3],
    /// ResnetBlocks in the decoder mid block: 2 in sgm (block_1, attn_1, block_2). diffusers builds
    /// `layers_per_block` of them and only runs the attention between the first two.
    pub decoder_mid_res_blocks: usize,
    /// 1×1 `quant_conv` on the moments: absent in sgm `AutoencodingEngine`, present in diffusers.
    pub use_quant_conv: bool,
    /// Attention score buffer budget in floats (query chunking in the mid attention), 32 Mi floats = 128 MiB.
    pub attn_max_score_elems: usize,
}

impl Default for AutoencoderConfig {
    fn default() -> Self {
        Self {
            ch: 128,
            ch_mult: vec![1, 2, 4, 4],
            num_res_blocks: 2,
            z_channels: 4,
            double_z: true,
            in_channels: 3,
            out_ch: 3,
            scale_factor: 0.18215,
            video_kernel_size: [3, 1, 1],
            decoder_mid_res_blocks: 2,
            use_quant_conv: false,
            attn_max_score_elems: 32 << 20,
        }
    }
}

impl AutoencoderConfig {
    /// From a diffusers `AutoencoderKLTemporalDecoder` `config.json`.
    pub fn from_diffusers_json(path: &Path) -> Result<Self, VaeError> {
        let err = |msg: String| VaeError::Config { path: path.to_path_buf(), msg };
        let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
        let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| err(e.to_string()))?;
        Self::from_diffusers_value(&v, path)
    }

    pub fn from_diffusers_value(v: &serde_json::Value, path: &Path) -> Result<Self, VaeError> {
        let err = |msg: String| VaeError::Config { path: path.to_path_buf(), msg };
        let int = |k: &str, d: usize| -> Result<usize, VaeError> {
            match v.get(k) {
                None => Ok(d),
                Some(x) => x.as_u64().map(|u| u as usize).ok_or_else(|| err(format!("`{k}` must be an integer"))),
            }
        };
        let boc: Vec<usize> = v
            .get("block_out_channels")
            .and_then(|x| x.as_array())
            .ok_or_else(|| err("missing `block_out_channels`".into()))?
            .iter()
            .map(|x| x.as_u64().map(|u| u as usize).ok_or_else(|| err("`block_out_channels` must hold integers".into())))
            .collect::<Result<_, _>>()?;
        let ch = *boc.first().ok_or_else(|| err("`block_out_channels` is empty".into()))?;
        if ch == 0 || boc.iter().any(|c| c % ch != 0) {
            return Err(err(format!("block_out_channels {boc:?} must be multiples of the first")));
        }
        if let Some(types) = v.get("down_block_types").and_then(|x| x.as_array()) {
            if types.len() != boc.len() || types.iter().any(|t| t.as_str() != Some("DownEncoderBlock2D")) {
                return Err(err("down_block_types must be DownEncoderBlock2D, one per block_out_channels entry".into()));
            }
        }
        let layers = int("layers_per_block", 2)?;
        let scale_factor = v.get("scaling_factor").and_then(|x| x.as_f64()).unwrap_or(0.18215);
        let cfg = Self {
            ch,
            ch_mult: boc.iter().map(|c| c / ch).collect(),
            num_res_blocks: layers,
            z_channels: int("latent_channels", 4)?,
            double_z: true,
            in_channels: int("in_channels", 3)?,
            out_ch: int("out_channels", 3)?,
            scale_factor,
            video_kernel_size: [3, 1, 1],
            decoder_mid_res_blocks: layers,
            use_quant_conv: true,
            ..Self::default()
        };
        cfg.validate().map_err(|m| err(m))?;
        Ok(cfg)
    }

    fn validate(&self) -> Result<(), String> {
        if self.ch_mult.is_empty() || self.ch == 0 || self.num_res_blocks == 0 {
            return Err("ch, ch_mult and num_res_blocks must be non-empty / positive".into());
        }
        if self.ch_mult.iter().any(|m| (m * self.ch) % 32 != 0) {
            return Err("every level's channels (ch × ch_mult) must be a multiple of 32 (GroupNorm 32)".into());
        }
        let [kt, kh, kw] = self.video_kernel_size;
        if kt % 2 == 0 || kh != 1 || kw != 1 {
            return Err(format!("video_kernel_size must be [odd, 1, 1], got {:?}", self.video_kernel_size));
        }
        if !(1..=2).contains(&self.decoder_mid_res_blocks) {
            return Err("decoder_mid_res_blocks must be 1 or 2".into());
        }
        Ok(())
    }

    /// Spatial downsampling factor of the latent grid (8 for SVD).
    pub fn downsample_factor(&self) -> usize {
        1 << (self.ch_mult.len() - 1)
    }
}

/// How the VAE keys are spelled in a file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum VaeLayout {
    /// sgm names under a prefix: `refiner.first_stage_model.` (MVSplat360 checkpoint),
    /// `first_stage_model.` (svd.safetensors) or `` (bare `AutoencodingEngine` state dict).
    Sgm { prefix: String },
    /// diffusers `AutoencoderKLTemporalDecoder` names.
    Diffusers,
}

impl VaeLayout {
    pub fn detect(keys: &[String]) -> Option<Self> {
        let has = |k: &str| keys.iter().any(|x| x == k);
        for prefix in ["refiner.first_stage_model.", "first_stage_model.", ""] {
            if has(&format!("{prefix}encoder.conv_in.weight")) && has(&format!("{prefix}encoder.down.0.block.0.conv1.weight")) {
                return Some(Self::Sgm { prefix: prefix.to_string() });
            }
        }
        if has("encoder.down_blocks.0.resnets.0.conv1.weight") || has("decoder.time_conv_out.weight") {
            return Some(Self::Diffusers);
        }
        None
    }
}

/// sgm `AutoencodingEngine` with the temporal decoder. Latents are unscaled (the caller multiplies by
/// [`AutoencoderConfig::scale_factor`] for the diffusion model and divides before decoding).
#[derive(Debug)]
pub struct AutoencoderKL {
    pub cfg: AutoencoderConfig,
    encoder: Encoder,
    quant_conv: Option<model::Conv>,
    decoder: VideoDecoder,
    /// Weights' dtype: inputs are cast to it, outputs come back as f32.
    dtype: DType,
}

impl AutoencoderKL {
    /// Load from a safetensors file (layout auto-detected unless given). Strict within the VAE's keys:
    /// any missing, unexpected or wrongly shaped key is an error listing them; keys of other components
    /// (UNet, conditioner) in a full checkpoint are ignored. f16/bf16 are upcast to f32.
    pub fn load(path: &Path, layout: Option<VaeLayout>, cfg: &AutoencoderConfig, device: &Device) -> Result<Self, VaeError> {
        Self::load_as(path, layout, cfg, device, DType::F32)
    }

    /// [`Self::load`] computing in `dtype` (f16/bf16); encode/decode outputs come back as f32.
    pub fn load_as(path: &Path, layout: Option<VaeLayout>, cfg: &AutoencoderConfig, device: &Device, dtype: DType) -> Result<Self, VaeError> {
        let w = Self::open_weights(path, layout, cfg, device)?.with_dtype(dtype);
        let model = Self::build(&w, cfg)?;
        w.finish()?;
        Ok(model)
    }

    /// [`Self::load`] with the weights handed out as `Var`s by model name (to continue training an autoencoder).
    pub fn load_trainable(
        path: &Path,
        layout: Option<VaeLayout>,
        cfg: &AutoencoderConfig,
        device: &Device,
    ) -> Result<(Self, Vec<(String, candle_core::Var)>), VaeError> {
        let w = Self::open_weights(path, layout, cfg, device)?.trainable();
        let model = Self::build(&w, cfg)?;
        let vars = w.take_vars();
        w.finish()?;
        Ok((model, vars))
    }

    fn open_weights(path: &Path, layout: Option<VaeLayout>, cfg: &AutoencoderConfig, device: &Device) -> Result<StrictWeights, VaeError> {
        cfg.validate().map_err(|msg| VaeError::Config { path: path.to_path_buf(), msg })?;
        let st = weights::open_safetensors(path)?;
        let layout = match layout {
            Some(l) => l,
            None => VaeLayout::detect(&weights::keys(&st)).ok_or_else(|| WeightsError::UnknownLayout {
                path: path.to_path_buf(),
                what: "VAE".into(),
                expected: "sgm `[refiner.]first_stage_model.encoder.down.0.block.0.conv1.weight` or diffusers `encoder.down_blocks.0.resnets.0.conv1.weight`"
                    .into(),
            })?,
        };
        let w = match &layout {
            VaeLayout::Sgm { prefix } => StrictWeights::own_layout(st, path, "VAE", prefix, &["encoder.", "decoder.", "quant_conv."], device),
            VaeLayout::Diffusers => {
                let levels = cfg.ch_mult.len();
                StrictWeights::mapped(
                    st,
                    path,
                    "VAE",
                    |k| k.starts_with("encoder.") || k.starts_with("decoder.") || k.starts_with("quant_conv."),
                    |k| crate::keymap::vae::diffusers_to_sgm(k, levels).map(Some),
                    device,
                )
            }
        };
        if w.is_empty() {
            return Err(WeightsError::UnknownLayout { path: path.to_path_buf(), what: "VAE".into(), expected: format!("layout {layout:?}") }.into());
        }
        Ok(w)
    }

    /// Load a diffusers folder (`config.json` + `diffusion_pytorch_model[.fp16].safetensors`).
    pub fn load_diffusers_dir(dir: &Path, device: &Device) -> Result<Self, VaeError> {
        let cfg = AutoencoderConfig::from_diffusers_json(&dir.join("config.json"))?;
        let file = crate::diffusers_weights_file(dir)
            .ok_or_else(|| WeightsError::Open { path: dir.to_path_buf(), msg: "no diffusion_pytorch_model[.fp16].safetensors in folder".into() })?;
        Self::load(&file, Some(VaeLayout::Diffusers), &cfg, device)
    }

    /// Seeded random weights with the given config (benchmarks).
    pub fn random(cfg: &AutoencoderConfig, seed: u64, device: &Device) -> Result<Self, VaeError> {
        Self::random_as(cfg, seed, device, DType::F32)
    }

    /// [`Self::random`] computing in `dtype` (the same values, rounded).
    pub fn random_as(cfg: &AutoencoderConfig, seed: u64, device: &Device, dtype: DType) -> Result<Self, VaeError> {
        cfg.validate().map_err(|msg| VaeError::Config { path: PathBuf::from("<AutoencoderConfig>"), msg })?;
        Ok(Self::build(&StrictWeights::random(seed, "VAE", device).with_dtype(dtype), cfg)?)
    }

    /// Seeded random weights handed out as `Var`s (gradient tests), with the `Var`s by model name.
    pub fn random_trainable(cfg: &AutoencoderConfig, seed: u64, device: &Device) -> Result<(Self, Vec<(String, candle_core::Var)>), VaeError> {
        cfg.validate().map_err(|msg| VaeError::Config { path: PathBuf::from("<AutoencoderConfig>"), msg })?;
        let w = StrictWeights::random(seed, "VAE", device).trainable();
        let model = Self::build(&w, cfg)?;
        Ok((model, w.take_vars()))
    }

    /// Build from any weight source (crate-internal: random state dicts).
    pub(crate) fn build_with(w: &StrictWeights, cfg: &AutoencoderConfig) -> candle_core::Result<Self> {
        Self::build(w, cfg)
    }

    fn build(w: &StrictWeights, cfg: &AutoencoderConfig) -> candle_core::Result<Self> {
        let zc = if cfg.double_z { 2 * cfg.z_channels } else { cfg.z_channels };
        Ok(Self {
            cfg: cfg.clone(),
            encoder: Encoder::load(w, cfg)?,
            quant_conv: if cfg.use_quant_conv { Some(model::Conv::load(w, "quant_conv", zc, zc, 1, 1, 0)?) } else { None },
            decoder: VideoDecoder::load(w, cfg)?,
            dtype: w.dtype(),
        })
    }

    /// Posterior of `x` (N, 3, H, W) in [-1, 1], H and W multiples of 8: (mean, logvar), each (N, z, H/8, W/8);
    /// logvar clamped to [-30, 20] as in `DiagonalGaussianDistribution`.
    pub fn encode(&self, x: &Tensor) -> Result<(Tensor, Tensor), VaeError> {
        let (_, c, h, w) = x.dims4()?;
        let f = self.cfg.downsample_factor();
        if c != self.cfg.in_channels || h % f != 0 || w % f != 0 {
            return Err(VaeError::Input(format!("encode expects (N, {}, H, W) with H, W multiples of {f}, got {:?}", self.cfg.in_channels, x.dims())));
        }
        let x = x.to_dtype(self.dtype)?.contiguous()?;
        let mut moments = self.encoder.forward(&x)?;
        if let Some(q) = &self.quant_conv {
            moments = q.forward(&moments)?;
        }
        let moments = moments.to_dtype(DType::F32)?;
        if !self.cfg.double_z {
            let logvar = moments.zeros_like()?;
            return Ok((moments, logvar));
        }
        let z = self.cfg.z_channels;
        let mean = moments.narrow(1, 0, z)?.contiguous()?;
        let logvar = moments.narrow(1, z, z)?.clamp(-30f32, 20f32)?.contiguous()?;
        Ok((mean, logvar))
    }

    /// Decode unscaled latents `z` (B·T, z, h, w), all T = `num_frames` frames of each video in one call
    /// (temporal mixing across them) → (B·T, 3, 8h, 8w) in about [-1, 1] (unclamped).
    pub fn decode(&self, z: &Tensor, num_frames: usize) -> Result<Tensor, VaeError> {
        let (n, c, _, _) = z.dims4()?;
        if c != self.cfg.z_channels || num_frames == 0 || n % num_frames != 0 {
            return Err(VaeError::Input(format!("decode expects (B·{num_frames}, {}, h, w), got {:?}", self.cfg.z_channels, z.dims())));
        }
        Ok(self.decoder.forward(&z.to_dtype(self.dtype)?.contiguous()?, num_frames)?.to_dtype(DType::F32)?)
    }

    /// sgm `decode_first_stage` chunking (`en_and_decode_n_samples_a_time`): consecutive groups of
    /// `n_per_call` latents (the last may be shorter), each decoded as one video of that many frames.
    /// `None` = all at once. MVSplat360's DL3DV config uses 1.
    pub fn decode_chunked(&self, z: &Tensor, n_per_call: Option<usize>) -> Result<Tensor, VaeError> {
        let n = z.dim(0)?;
        let per = n_per_call.unwrap_or(n).max(1);
        if per >= n {
            return self.decode(z, n);
        }
        let mut parts = Vec::new();
        let mut s = 0;
        while s < n {
            let m = per.min(n - s);
            parts.push(self.decode(&z.narrow(0, s, m)?, m)?);
            s += m;
        }
        Ok(Tensor::cat(&parts, 0)?)
    }
}

/// MVSplat360's encoder input: views (N, 3, H, W) in [0, 1] → bilinear ×`factor` (align_corners=True)
/// → ×2−1. `factor` = `gs_feat_scale_factor`·8 = 2 for the released configs (1 = no resize).
pub fn prepare_encoder_input(views: &Tensor, factor: usize) -> Result<Tensor, VaeError> {
    let (_, _, h, w) = views.dims4()?;
    let x = views.to_dtype(DType::F32)?.contiguous()?;
    let x = if factor > 1 { x.upsample_bilinear2d(h * factor, w * factor, true)? } else { x };
    Ok(x.affine(2.0, -1.0)?)
}

/// MVSplat360's output frames: decoded (N, 3, H, W) in [-1, 1] → bilinear ×1/`factor` (align_corners=True,
/// output size floor(H/factor)) → clamp((x+1)/2, 0, 1).
pub fn frames_from_decoded(decoded: &Tensor, factor: usize) -> Result<Tensor, VaeError> {
    let (_, _, h, w) = decoded.dims4()?;
    let x = decoded.to_dtype(DType::F32)?.contiguous()?;
    let x = if factor > 1 { x.upsample_bilinear2d(h / factor, w / factor, true)? } else { x };
    Ok(x.affine(0.5, 0.5)?.clamp(0f32, 1f32)?)
}
