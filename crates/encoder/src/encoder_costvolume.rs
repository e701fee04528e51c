//! `EncoderCostVolume` (`encoder_costvolume.py`): backbone → depth predictor → Gaussian adapter.

use std::path::Path;

use candle_core::{DType, Device, IndexOp, Result, Tensor};
use candle_nn::VarBuilder;

use crate::backbone::{camera_distances, index_tensor, BackboneMultiview, BackboneOutput};
use crate::common::gaussian_adapter::{gaussians_from_prediction, EncoderGaussians};
use crate::config::EncoderCostVolumeCfg;
use crate::costvolume::{DepthPredictorInput, DepthPredictorMultiView, DepthPredictorOutput};
use crate::weights::{load_strict, WeightsError};

/// Key prefix of the encoder in the official Lightning checkpoint (`ModelWrapper.encoder`).
pub const ENCODER_PREFIX: &str = "encoder.";

pub struct EncoderCostVolume {
    pub cfg: EncoderCostVolumeCfg,
    pub backbone: BackboneMultiview,
    pub depth_predictor: DepthPredictorMultiView,
    /// F32, or BF16 once [`Self::pack_bf16`] packed the products' weights.
    dtype: DType,
}

/// Camera-distance products computed before the backbone (kept for inspection and tests).
#[derive(Debug, Clone)]
pub struct ViewRanking {
    /// `[B, V, V]` camera-centre distances.
    pub camera_distances: Tensor,
    /// `cameras_dist_index[b][v]`: views by increasing distance, column 0 = the view itself.
    pub index: Vec<Vec<Vec<u32>>>,
}

impl ViewRanking {
    /// Rows cut to the first `n` columns (self + n−1 nearest); `n` is clamped to the number of views.
    pub fn nearest(&self, n: usize) -> Vec<Vec<Vec<u32>>> {
        self.index.iter().map(|b| b.iter().map(|r| r[..n.min(r.len())].to_vec()).collect()).collect()
    }
}

/// Full forward result with the backbone's products (for tests and visualisation).
pub struct EncoderOutput {
    pub gaussians: EncoderGaussians,
    pub ranking: ViewRanking,
    pub backbone: BackboneOutput,
    /// Depth-predictor outputs (with `intermediates` when requested).
    pub depth: DepthPredictorOutput,
}

impl EncoderCostVolume {
    /// `vb` = the encoder's root (`root.pp("encoder")`), keys as in the official state dict.
    pub fn new(vb: VarBuilder, cfg: &EncoderCostVolumeCfg) -> Result<Self> {
        let backbone =
            BackboneMultiview::with_cnn_dims(vb.pp("backbone"), cfg.cnn_feature_dims, cfg.d_feature, cfg.num_transformer_layers, cfg.ffn_dim_expansion)?;
        let depth_predictor = DepthPredictorMultiView::new(vb.pp("depth_predictor"), cfg)?;
        Ok(Self { cfg: cfg.clone(), backbone, depth_predictor, dtype: DType::F32 })
    }

    /// Load from a safetensors file or a Lightning `.ckpt`/`.pth` (keys `encoder.*`), strictly: zero missing and
    /// zero unexpected encoder keys.
    pub fn load(path: impl AsRef<Path>, cfg: &EncoderCostVolumeCfg, device: &Device) -> std::result::Result<Self, WeightsError> {
        load_strict(path, ENCODER_PREFIX, device, |vb| Self::new(vb, cfg))
    }

    /// [`Self::load`] for inference in `dtype`: F32, or BF16 on the CPU (weights packed as they are built, see
    /// [`Self::pack_bf16`]). bf16 on another device is refused: the GPU encoder runs f32.
    pub fn load_as(path: impl AsRef<Path>, cfg: &EncoderCostVolumeCfg, device: &Device, dtype: DType) -> std::result::Result<Self, WeightsError> {
        match dtype {
            DType::F32 => Self::load(path, cfg, device),
            DType::BF16 if device.is_cpu() => load_strict(path, ENCODER_PREFIX, device, |vb| {
                let mut e = Self::new(vb, cfg)?;
                e.pack_bf16()?;
                Ok(e)
            }),
            _ => Err(WeightsError::Build {
                path: path.as_ref().to_path_buf(),
                source: candle_core::Error::Msg(format!("the encoder runs in f32, or in bf16 on the CPU; not {dtype:?} on {device:?}")),
            }),
        }
    }

    /// Packs every linear and convolution weight in bf16 for CPU inference, dropping the f32 copies
    /// (what runs in bf16 and what stays f32: [`crate::bf16`]). Refused for trainable weights.
    pub fn pack_bf16(&mut self) -> Result<()> {
        self.backbone.pack_bf16()?;
        self.depth_predictor.pack_bf16()?;
        self.dtype = DType::BF16;
        Ok(())
    }

    /// The precision of the products' weights: F32, or BF16 after [`Self::pack_bf16`].
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// Check the context batch against the configuration; the error says what to change.
    pub fn check_inputs(&self, images: &Tensor, intrinsics: &Tensor, extrinsics: &Tensor, near: &Tensor, far: &Tensor) -> Result<()> {
        let (b, v, c, h, w) = images.dims5()?;
        if c != 3 {
            candle_core::bail!("images must be [B,V,3,H,W], got {:?}", images.dims());
        }
        if v < 2 {
            candle_core::bail!("the encoder needs at least 2 context views, got {v}");
        }
        if v != self.cfg.num_views {
            candle_core::bail!("the encoder was built for {} context views (num_views), got {v}; build it with num_views = {v}", self.cfg.num_views);
        }
        let m = self.required_multiple();
        if h % m != 0 || w % m != 0 {
            candle_core::bail!("image size {h}x{w} must be a multiple of {m} (crop to a multiple of {})", self.cfg.image_multiple());
        }
        for (t, name, dims) in
            [(intrinsics, "intrinsics", vec![b, v, 3, 3]), (extrinsics, "extrinsics", vec![b, v, 4, 4]), (near, "near", vec![b, v]), (far, "far", vec![b, v])]
        {
            if t.dims() != dims.as_slice() {
                candle_core::bail!("{name} must have shape {dims:?}, got {:?}", t.dims());
            }
        }
        Ok(())
    }

    /// Smallest H, W granularity the network accepts: windows at 1/downscale, and every UNet down-sampling.
    pub fn required_multiple(&self) -> usize {
        let cfg = &self.cfg;
        let cv_levels = 1usize << cfg.costvolume_unet_channel_mult.len().saturating_sub(1);
        let depth_levels = 1usize << cfg.depth_unet_channel_mult.len().saturating_sub(1);
        let feat = cfg.downscale_factor * lcm(cv_levels, 2 * cfg.multiview_trans_attn_split.max(1));
        lcm(feat, depth_levels)
    }

    /// Nearest-view ranking from the c2w translations.
    pub fn rank_views(extrinsics: &Tensor) -> Result<ViewRanking> {
        let (camera_distances, index) = camera_distances(extrinsics)?;
        Ok(ViewRanking { camera_distances, index })
    }

    /// `images [B,V,3,H,W]` in [0,1], normalised `intrinsics [B,V,3,3]`, c2w `extrinsics [B,V,4,4]` (OpenCV),
    /// `near`, `far [B,V]` → per-pixel Gaussians (G = V·H·W per batch element, view-major).
    pub fn forward(&self, images: &Tensor, intrinsics: &Tensor, extrinsics: &Tensor, near: &Tensor, far: &Tensor) -> Result<EncoderGaussians> {
        Ok(self.forward_full(images, intrinsics, extrinsics, near, far, false)?.gaussians)
    }

    pub fn forward_full(
        &self,
        images: &Tensor,
        intrinsics: &Tensor,
        extrinsics: &Tensor,
        near: &Tensor,
        far: &Tensor,
        intermediates: bool,
    ) -> Result<EncoderOutput> {
        self.check_inputs(images, intrinsics, extrinsics, near, far)?;
        let (_, _, _, h, w) = images.dims5()?;
        let ranking = Self::rank_views(extrinsics)?;
        let nn_trans = ranking.nearest(self.cfg.multiview_trans_nearest_n_views);
        let backbone = self.backbone.forward(images, self.cfg.multiview_trans_attn_split, Some(&nn_trans), intermediates)?;
        // The depth predictor takes the full ranking and uses its first `costvolume_nearest_n_views` columns.
        let nn_cv = index_tensor(&ranking.index, images.device())?;
        let inp = DepthPredictorInput {
            features_cnn: &backbone.cnn_features,
            features_trans: &backbone.trans_features,
            images,
            intrinsics,
            extrinsics,
            near,
            far,
            cameras_dist_index: &nn_cv,
        };
        let depth = if intermediates { self.depth_predictor.forward_with_intermediates(&inp)? } else { self.depth_predictor.forward(&inp)? };
        let mut t = std::time::Instant::now();
        let gaussians = gaussians_from_prediction(&self.cfg, &depth, extrinsics, intrinsics, (h, w))?;
        mvsplat360_nn::prof::lap("encoder.gaussian_adapter", &mut t);
        Ok(EncoderOutput { gaussians, ranking, backbone, depth })
    }
}

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

fn lcm(a: usize, b: usize) -> usize {
    a / gcd(a, b).max(1) * b
}

/// One `mvsplat360_splat::Gaussians` per batch element (detached copies of the encoder outputs).
pub fn to_splat_gaussians(g: &EncoderGaussians) -> Result<Vec<mvsplat360_splat::Gaussians>> {
    let b = g.means.dim(0)?;
    (0..b)
        .map(|i| {
            Ok(mvsplat360_splat::Gaussians {
                means: g.means.i(i)?.contiguous()?,
                covariances: g.covariances.i(i)?.contiguous()?,
                opacities: g.opacities.i(i)?.contiguous()?,
                harmonics: g.harmonics.i(i)?.contiguous()?,
                feature_harmonics: g.feature_harmonics.i(i)?.contiguous()?,
            })
        })
        .collect()
}

/// Convenience for callers holding f64 camera data: stack per-view arrays into the encoder's input tensors.
/// `k_norm[v] = [fx/W, fy/H, cx/W, cy/H]`, `c2w[v]` row-major 4×4 (OpenCV axes).
pub fn camera_tensors(k_norm: &[[f64; 4]], c2w: &[[[f64; 4]; 4]], device: &Device) -> Result<(Tensor, Tensor)> {
    let v = k_norm.len();
    let mut k = Vec::with_capacity(v * 9);
    for [fx, fy, cx, cy] in k_norm {
        k.extend_from_slice(&[*fx as f32, 0.0, *cx as f32, 0.0, *fy as f32, *cy as f32, 0.0, 0.0, 1.0]);
    }
    let e: Vec<f32> = c2w.iter().flatten().flatten().map(|&x| x as f32).collect();
    Ok((Tensor::from_vec(k, (1, v, 3, 3), device)?, Tensor::from_vec(e, (1, v, 4, 4), device)?.to_dtype(DType::F32)?))
}
