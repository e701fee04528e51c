//! Flags shared by several commands: which views are context (`render`, `export`, `inspect`), which model and
//! refiner settings (`render`, `eval`).

use std::path::PathBuf;

use mvsplat360_pipeline::compute::{parse_dtype, parse_encoder_dtype, Compute, DeviceSpec};
use mvsplat360_pipeline::model::{ModelArgs, RefinerArg};
use mvsplat360_pipeline::preprocess::InputSize;
use mvsplat360_pipeline::render::RefineSettings;
use mvsplat360_pipeline::scale::SceneScale;
use mvsplat360_pipeline::views::{parse_list, ContextSpec};

use super::names::{self, Freshness};

/// A comma-separated list of view indices (one clap value, so clap does not treat it as repeated values).
#[derive(Debug, Clone)]
pub struct ViewList(pub Vec<usize>);

pub fn view_list(s: &str) -> Result<ViewList, String> {
    parse_list(s).map(ViewList)
}

#[derive(clap::Args, Debug, Clone)]
pub struct ContextArgs {
    /// Context views by index in the scene, e.g. `--context 3,17,40` (0-based, the scene's view order).
    #[arg(long, value_parser = view_list, conflicts_with_all = ["num_context", "index"])]
    pub context: Option<ViewList>,
    /// Number of context views picked by farthest-point sampling of the camera centres (first view first).
    #[arg(long, default_value_t = 5)]
    pub num_context: usize,
    /// Evaluation index (JSON `{scene: {"context": [...], "target": [...]}}`): take this scene's views from it.
    #[arg(long)]
    pub index: Option<PathBuf>,
    /// Scene key: the scene inside a multi-scene `.torch` chunk, and its entry in `--index`
    /// (default: the first scene of a chunk; the scene's name in the index).
    #[arg(long)]
    pub scene_key: Option<String>,
}

impl ContextArgs {
    pub fn spec(&self) -> ContextSpec {
        if let Some(v) = &self.context {
            ContextSpec::Views(v.0.clone())
        } else if let Some(f) = &self.index {
            ContextSpec::Index { file: f.clone(), scene_key: self.scene_key.clone() }
        } else {
            ContextSpec::Count(self.num_context)
        }
    }
}

/// Which weights, and how a scene is fed to them (`render`, `eval`).
#[derive(clap::Args, Debug, Clone)]
pub struct ModelFlags {
    /// Model: an official MVSplat360 Lightning `.ckpt` (encoder + refiner, DL3DV config) or a model folder
    /// (`config.json` + `model.safetensors`); a path, or a name fetched into the Hugging Face cache: `dl3dv` (the
    /// official checkpoint), `default`, `hf:OWNER/REPO[/FILE][@REV]`, a Hub URL (`mvsplat360 weights list`; an
    /// existing path wins). Default: `assets/models/default/`.
    #[arg(long, value_name = "PATH|NAME")]
    pub ckpt: Option<PathBuf>,
    /// Encoder weights alone (safetensors / `.ckpt` with `encoder.*` keys, DL3DV config), a path or a name as
    /// for --ckpt; needs `--refiner`.
    #[arg(long, value_name = "PATH|NAME")]
    pub encoder: Option<PathBuf>,
    /// `none` for the 3DGS-only result, or the refiner's weights (an official `.ckpt`, its safetensors copy, or
    /// Stability's `svd.safetensors`): a path or a name as for --ckpt (`dl3dv`, `svd`, `hf:…`).
    #[arg(long, value_name = "none|PATH|NAME")]
    pub refiner: Option<RefinerArg>,
    /// Data conventions for weights without a config (`dl3dv`: 480×270 → 448×256, `re10k`: 320×180 → 320×176,
    /// all-view cost volume).
    #[arg(long)]
    pub experiment: Option<String>,
    /// Size WIDTHxHEIGHT the photos are scaled to cover and centre-cropped to (then cropped to the encoder's size
    /// multiple), or `native`. Default: the model's training size.
    #[arg(long)]
    pub size: Option<InputSize>,
    /// Scene units → model units: `none` (the official protocol: the model expects content between its near and
    /// far planes in the scene's own units), `auto` (median camera distance to the looked-at point becomes
    /// √(near·far) of the official model, 10) or a factor. Default: `auto` for scenes posed by VGGT (its
    /// normalised units), else the model folder's `scene_scale` (the shipped model: `auto`), else `none` (official
    /// checkpoints). See docs/cameras.md.
    #[arg(long)]
    pub scene_scale: Option<SceneScale>,
    /// Where the model runs: `auto` (GPU 0 when this binary has CUDA and a GPU is present, else the CPU),
    /// `cpu`, `cuda` (GPU 0) or `cuda:N`. CUDA needs a binary built with `--features cuda` (see docs/gpu.md).
    #[arg(long, default_value = "auto")]
    pub device: DeviceSpec,
    /// Precision of the refiner (UNet, VAE, CLIP): `f32`, `f16` or `bf16`. Half precision halves the refiner's
    /// weights' memory and on a GPU is faster. On the CPU, bf16 multiplies bf16 weights (packed at load) by
    /// f32 activations rounded to bf16, with f32 sums, where the CPU has AVX512-BF16 (≈ 2× the f32 rate), and
    /// is storage only elsewhere (said once, recorded in run.json). The encoder: --encoder-dtype; the
    /// rasterizer runs in f32.
    #[arg(long, default_value = "f32", value_parser = parse_dtype)]
    pub dtype: candle_core::DType,
    /// Precision of the encoder (backbone, multi-view transformer, cost-volume and depth UNets) and, when a
    /// video or photo folder is posed first, of VGGT: `f32` (as the official code) or `bf16` (CPU only: weights
    /// packed once in bf16, f32 activations, bf16 products with f32 sums where the CPU has AVX512-BF16; norms,
    /// attention, the cost volume and the Gaussian adapter stay f32). The encoder's depth places the Gaussians,
    /// so bf16 there is its own choice; run.json records it (`encoder_dtype`).
    #[arg(long, default_value = "f32", value_parser = parse_encoder_dtype)]
    pub encoder_dtype: candle_core::DType,
    /// Steps of test-time fitting: the Gaussians' distances along their pixel rays and opacities are adjusted
    /// so that each context photo is reproduced by the other views' Gaussians (not in the official pipeline).
    /// Default: the model's own setting (the shipped model: see its MODEL.md; official weights: 0 = off).
    #[arg(long)]
    pub fit_steps: Option<usize>,
    /// Skip the model's learned blending of the 3DGS renders with the context photos (a model folder's `blend`
    /// key; not in the official pipeline): the frames are then the plain 3DGS renders.
    #[arg(long)]
    pub no_blend: bool,
}

impl ModelFlags {
    /// Names in `--ckpt`, `--encoder` and `--refiner` → local paths (fetched into the Hugging Face cache when
    /// needed; see [`super::names`]). `fresh`: [`Freshness::CachedFirst`] in ranks a command started.
    pub fn resolve_names(&mut self, fresh: Freshness, quiet: bool) -> anyhow::Result<()> {
        names::resolve_opt(&mut self.ckpt, "--ckpt", names::Default::ModelFolder, fresh, quiet)?;
        names::resolve_opt(&mut self.encoder, "--encoder", names::Default::Refuse("encoder weights alone (give --ckpt default)"), fresh, quiet)?;
        if let Some(RefinerArg::File(f)) = &self.refiner {
            let p = names::resolve(f, "--refiner", names::Default::Refuse("refiner weights (the shipped model has no refiner)"), fresh, quiet)?;
            self.refiner = Some(RefinerArg::File(p));
        }
        Ok(())
    }

    pub fn model_args(&self) -> ModelArgs {
        ModelArgs {
            ckpt: self.ckpt.clone(),
            encoder: self.encoder.clone(),
            refiner: self.refiner.clone(),
            experiment: self.experiment.clone(),
            compute: Compute { device: self.device, refiner_dtype: self.dtype, encoder_dtype: self.encoder_dtype },
            fit_steps: self.fit_steps,
            no_blend: self.no_blend,
        }
    }
}

/// Refiner sampling settings (`render`, `eval`); defaults = the official DL3DV evaluation.
#[derive(clap::Args, Debug, Clone)]
pub struct RefineFlags {
    /// Diffusion sampling steps (EDM Euler).
    #[arg(long, default_value_t = 25)]
    pub steps: usize,
    /// Classifier-free guidance scale of a window's first frame (linear ramp to --guidance-max).
    #[arg(long, default_value_t = 1.0)]
    pub guidance_min: f32,
    /// Guidance scale of a window's last frame.
    #[arg(long, default_value_t = 2.5)]
    pub guidance_max: f32,
    /// Seed of the initial noise (drawn once, reused for every window and scene).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Frames per refiner window (a short last window is padded by repeating its last frame).
    #[arg(long, default_value_t = 14)]
    pub window: usize,
    /// Refine all frames in one UNet call with temporal attention split into --window-sized groups (the
    /// official video mode; more memory).
    #[arg(long)]
    pub video_mode: bool,
    /// Frames per VAE decode call. 1 = the official setting; larger is faster but the temporal decoder then
    /// mixes neighbouring frames, which changes the output slightly.
    #[arg(long, default_value_t = 1)]
    pub vae_chunk: usize,
}

impl RefineFlags {
    pub fn settings(&self) -> RefineSettings {
        RefineSettings {
            steps: self.steps,
            guidance_min: self.guidance_min,
            guidance_max: self.guidance_max,
            seed: self.seed,
            window: self.window,
            video_mode: self.video_mode,
            vae_chunk: self.vae_chunk,
        }
    }
}
