//! The refiner in the training loop (MVSplat360's SVD stage): a trainable UNet, with the first-stage VAE and
//! the CLIP vision tower frozen as in the official config (`svd_wo_mb_fps.yaml`: only the diffusion model is
//! in the optimizer). The latent-alignment target comes from the frozen VAE's encoder: officially a separate
//! `conditioner.embedders.1.encoder` (`AutoencoderKLModeOnly`), initialised from the same SVD autoencoder and
//! never trained, so the two hold the same weights.
//!
//! Weights come from one safetensors file in any sgm layout the loaders detect: Stability's
//! `svd.safetensors`, an MVSplat360 checkpoint converted by `mvsplat360 convert`, or a model folder's
//! `model.safetensors`; or from a diffusers SVD folder (`unet/`, `vae/`, `image_encoder/`, as
//! stabilityai/stable-video-diffusion-img2vid on the Hub), whose VAE and CLIP go into the model folder renamed
//! to the official keys. Without any, seeded random weights are written to `<out>/refiner-init.safetensors`
//! and loaded from there, so both cases take the same path.

use std::path::{Path, PathBuf};

use candle_core::safetensors::MmapedSafetensors;
use candle_core::{DType, Device, Tensor, Var};
use mvsplat360_pipeline::model::RefinerModelConfig;
use mvsplat360_refiner::clip::{ClipImageEmbedder, ClipLayout};
use mvsplat360_refiner::keymap;
use mvsplat360_refiner::state_dict::{random_refiner_state_dict, CLIP_PREFIX, UNET_PREFIX, VAE_PREFIX};
use mvsplat360_refiner::unet::{UNetLayout, VideoUNet, Weights};
use mvsplat360_refiner::vae::{AutoencoderKL, VaeLayout};
use mvsplat360_refiner::weights::Piece;
use rand::Rng;
use rand_distr::StandardNormal;

use crate::error::{Result, TrainError};
use crate::loss::diffusion::{self, DdpmSigmas};

/// Name of the seeded random initial weights inside the run's output folder.
pub const RANDOM_INIT: &str = "refiner-init.safetensors";

pub struct TrainRefiner {
    pub cfg: RefinerModelConfig,
    pub unet: VideoUNet,
    /// The UNet's weights by official key (`refiner.model.diffusion_model.*`), all trainable.
    pub unet_vars: Vec<(String, Var)>,
    pub vae: AutoencoderKL,
    pub clip: ClipImageEmbedder,
    /// VAE and CLIP weights by official key, copied into the model folder unchanged.
    frozen: Vec<(String, Tensor)>,
    sigmas: DdpmSigmas,
}

/// The refiner's two loss terms of one example (each a scalar with gradients).
pub struct RefinerLosses {
    pub diffusion: Tensor,
    pub alignment: Tensor,
}

impl TrainRefiner {
    /// `init`: a safetensors file, a model folder or a diffusers SVD folder; None = seeded random weights
    /// (written under `out`). The networks live on `dev`; the frozen copies for the model folder on the host.
    pub fn new(cfg: &RefinerModelConfig, init: Option<&Path>, seed: u64, out: &Path, dev: &Device) -> Result<Self> {
        let file = match init {
            Some(p) if p.join("unet").is_dir() => return Self::load_diffusers(cfg, p, dev),
            Some(p) if p.is_dir() => p.join(mvsplat360_pipeline::model::MODEL_WEIGHTS),
            Some(p) => p.to_path_buf(),
            None => write_random_init(cfg, seed, out)?,
        };
        Self::load(cfg, &file, dev)
    }

    fn load(cfg: &RefinerModelConfig, file: &Path, dev: &Device) -> Result<Self> {
        let bad = |msg: String| TrainError::Config { path: file.to_path_buf(), msg: format!("refiner init: {msg}") };
        if !file.is_file() {
            return Err(bad("no such file (train.refiner_init: a safetensors file, a model folder or a diffusers SVD folder)".into()));
        }
        let frozen = frozen_tensors(file).map_err(bad)?;
        Self::load_parts(cfg, (file, None), (file, None), (file, None), frozen, dev)
    }

    /// A diffusers SVD folder: `unet/` and `vae/` (diffusers names), `image_encoder/` (transformers CLIP).
    fn load_diffusers(cfg: &RefinerModelConfig, dir: &Path, dev: &Device) -> Result<Self> {
        let bad = |path: &Path, msg: String| TrainError::Config { path: path.to_path_buf(), msg: format!("refiner init (diffusers SVD folder): {msg}") };
        let find = |sub: &str, names: &[&str]| -> Result<PathBuf> {
            let d = dir.join(sub);
            names.iter().map(|n| d.join(n)).find(|p| p.is_file()).ok_or_else(|| bad(&d, format!("no {} here", names.join(" or "))))
        };
        let unet = find("unet", &mvsplat360_refiner::DIFFUSERS_WEIGHTS)?;
        let vae = find("vae", &mvsplat360_refiner::DIFFUSERS_WEIGHTS)?;
        let clip = find("image_encoder", &["model.safetensors", "model.fp16.safetensors"])?;
        let mut frozen = renamed(&vae, VAE_PREFIX, |k| keymap::vae::diffusers_to_sgm(k, cfg.vae.ch_mult.len()).map(Some)).map_err(|e| bad(&vae, e))?;
        frozen.extend(renamed(&clip, CLIP_PREFIX, keymap::clip::transformers_to_open_clip).map_err(|e| bad(&clip, e))?);
        Self::load_parts(cfg, (&unet, Some(UNetLayout::Diffusers)), (&vae, Some(VaeLayout::Diffusers)), (&clip, Some(ClipLayout::Transformers)), frozen, dev)
    }

    fn load_parts(
        cfg: &RefinerModelConfig,
        unet: (&Path, Option<UNetLayout>),
        vae: (&Path, Option<VaeLayout>),
        clip: (&Path, Option<ClipLayout>),
        frozen: Vec<(String, Tensor)>,
        dev: &Device,
    ) -> Result<Self> {
        let bad = |file: &Path, msg: String| TrainError::Config { path: file.to_path_buf(), msg: format!("refiner init: {msg}") };
        let w = Weights::from_file(unet.0, unet.1, &cfg.unet, dev).map_err(|e| bad(unet.0, e.to_string()))?.trainable();
        let unet_model = VideoUNet::new(&cfg.unet, &w).map_err(|e| bad(unet.0, format!("UNet: {e}")))?;
        let unet_vars = w.take_vars().into_iter().map(|(k, v)| (format!("{UNET_PREFIX}{k}"), v)).collect();
        w.finish().map_err(|e| bad(unet.0, e.to_string()))?;
        let vae_model = AutoencoderKL::load(vae.0, vae.1, &cfg.vae, dev).map_err(|e| bad(vae.0, e.to_string()))?;
        let clip_model = ClipImageEmbedder::load(clip.0, clip.1, &cfg.clip, dev).map_err(|e| bad(clip.0, e.to_string()))?;
        Ok(Self { cfg: cfg.clone(), unet: unet_model, unet_vars, vae: vae_model, clip: clip_model, frozen, sigmas: DdpmSigmas::official() })
    }

    /// VAE and CLIP tensors under official keys, for the model folder.
    pub fn frozen(&self) -> &[(String, Tensor)] {
        &self.frozen
    }

    /// Diffusion and latent-alignment losses of one example (one video of T target frames).
    /// `features`: (T, C, H, W) rendered features; `targets`: (T, 3, H, W) photos in [0, 1];
    /// `context`: (V, 3, H, W) context photos (their mean CLIP token is the cross-attention context).
    pub fn losses(&self, features: &Tensor, targets: &Tensor, context: &Tensor, rng: &mut impl Rng) -> Result<RefinerLosses> {
        let (t, _, h, w) = targets.dims4()?;
        let feats = diffusion::features_to_latent(features)?;
        let (_, _, lh, lw) = feats.dims4()?;
        let zc = self.cfg.vae.z_channels;
        let up = diffusion::TARGET_UPSAMPLE;
        // Draw every random number from the step's generator, in a fixed order, so a resumed run repeats it.
        // Drawn on the host, so a step's numbers are the same on every device.
        let dev = targets.device();
        let eps = normal(rng, &[t, zc, lh, lw], dev)?;
        let sigmas = self.sigmas.sample(rng, t);
        let noise = normal(rng, &[t, zc, lh, lw], dev)?;
        let align_noise = normal(rng, &[t, 3, h * up, w * up], dev)?;
        let latents = diffusion::target_latents(&self.vae, targets, Some(&eps))?;
        if latents.dims()[2..] != feats.dims()[2..] {
            return Err(TrainError::Data(format!(
                "refiner: latent grid {:?} of the targets differs from the features' {:?}; use a VAE with downsampling factor 8",
                &latents.dims()[2..],
                &feats.dims()[2..]
            )));
        }
        let ctx = self.clip.embed_mean(&context.unsqueeze(0)?).map_err(|e| TrainError::Data(format!("CLIP: {e}")))?.detach();
        let diffusion = diffusion::diffusion_loss(&self.unet, &latents, &feats, &ctx, &sigmas, &noise, t)?;
        let alignment = diffusion::latent_alignment_loss(&self.vae, &feats, targets, Some(&align_noise))?;
        Ok(RefinerLosses { diffusion, alignment })
    }
}

fn normal(rng: &mut impl Rng, shape: &[usize], dev: &Device) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.sample(StandardNormal)).collect();
    Ok(Tensor::from_vec(v, shape, dev)?)
}

fn write_random_init(cfg: &RefinerModelConfig, seed: u64, out: &Path) -> Result<PathBuf> {
    let path = out.join(RANDOM_INIT);
    let sd = random_refiner_state_dict(&cfg.unet, &cfg.vae, &cfg.clip, seed.wrapping_add(17))
        .map_err(|msg| TrainError::Config { path: PathBuf::from("model.refiner"), msg })?;
    let map: std::collections::HashMap<String, Tensor> = sd.into_iter().collect();
    mvsplat360_pipeline::output::atomic_write(&path, |p| candle_core::safetensors::save(&map, p).map_err(|e| e.to_string()))?;
    Ok(path)
}

/// Every tensor of `file` that `map` names (None = not this part's, `Some(None)` = a buffer to skip), renamed
/// to `prefix` + its sgm/open_clip name and rearranged as its [`Piece`] says: separate q/k/v concatenated, a
/// projection transposed, a Linear stored as a 1×1 convolution.
fn renamed(file: &Path, prefix: &str, map: impl Fn(&str) -> Option<Option<(String, Piece)>>) -> std::result::Result<Vec<(String, Tensor)>, String> {
    // SAFETY: read-only mapping of a weights file, as candle does.
    let st = unsafe { MmapedSafetensors::new(file) }.map_err(|e| e.to_string())?;
    let mut parts: std::collections::BTreeMap<String, Vec<(usize, usize, Tensor)>> = Default::default();
    let mut unknown = Vec::new();
    for (k, _) in st.tensors() {
        let Some(m) = map(&k) else {
            unknown.push(k);
            continue;
        };
        let Some((name, piece)) = m else { continue };
        let t = st.load(&k, &Device::Cpu).map_err(|e| e.to_string())?.to_dtype(DType::F32).map_err(|e| e.to_string())?;
        let e = |e: candle_core::Error| format!("{k}: {e}");
        let (index, of, t) = match piece {
            Piece::Whole => (0, 1, t),
            Piece::Reshape if t.rank() == 2 => {
                let (o, i) = t.dims2().map_err(e)?;
                (0, 1, t.reshape((o, i, 1, 1)).map_err(e)?)
            }
            Piece::Reshape => (0, 1, t),
            Piece::Transpose => (0, 1, t.t().and_then(|x| x.contiguous()).map_err(e)?),
            Piece::Concat { index, of } => (index, of, t),
        };
        parts.entry(name).or_default().push((index, of, t));
    }
    if !unknown.is_empty() {
        unknown.sort();
        return Err(format!("{} tensors with unknown names, e.g. {}", unknown.len(), unknown.iter().take(3).cloned().collect::<Vec<_>>().join(", ")));
    }
    let mut out = Vec::with_capacity(parts.len());
    for (name, mut p) in parts {
        p.sort_by_key(|x| x.0);
        let of = p[0].1;
        if p.len() != of || p.iter().enumerate().any(|(i, x)| x.0 != i) {
            return Err(format!("`{name}`: {} of its {of} parts found", p.len()));
        }
        let t = if of == 1 {
            p.pop().map(|x| x.2).expect("one part")
        } else {
            Tensor::cat(&p.iter().map(|x| &x.2).collect::<Vec<_>>(), 0).map_err(|e| e.to_string())?
        };
        out.push((format!("{prefix}{name}"), t));
    }
    Ok(out)
}

/// The VAE and CLIP vision tower of `file` renamed to the official MVSplat360 keys.
fn frozen_tensors(file: &Path) -> std::result::Result<Vec<(String, Tensor)>, String> {
    // SAFETY: read-only mapping of a weights file, as candle does.
    let st = unsafe { MmapedSafetensors::new(file) }.map_err(|e| e.to_string())?;
    let keys: Vec<String> = st.tensors().into_iter().map(|(k, _)| k).collect();
    let vae_prefix = match VaeLayout::detect(&keys) {
        Some(VaeLayout::Sgm { prefix }) if !prefix.is_empty() => prefix,
        _ => return Err("the VAE must be in an sgm layout (`[refiner.]first_stage_model.*`, as svd.safetensors or a converted MVSplat360 checkpoint)".into()),
    };
    let clip_prefix = match ClipLayout::detect(&keys) {
        Some(ClipLayout::OpenClip { prefix }) if !prefix.is_empty() => prefix,
        _ => return Err("the CLIP vision tower must be in the open_clip layout (`…open_clip.model.visual.*`, as svd.safetensors)".into()),
    };
    let mut out = Vec::new();
    for k in &keys {
        let renamed = if let Some(rest) = k.strip_prefix(vae_prefix.as_str()) {
            format!("{VAE_PREFIX}{rest}")
        } else if let Some(rest) = k.strip_prefix(clip_prefix.as_str()) {
            format!("{CLIP_PREFIX}{rest}")
        } else {
            continue;
        };
        let t = st.load(k, &Device::Cpu).map_err(|e| e.to_string())?.to_dtype(DType::F32).map_err(|e| e.to_string())?;
        out.push((renamed, t));
    }
    Ok(out)
}
