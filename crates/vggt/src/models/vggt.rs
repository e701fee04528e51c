//! `VGGT`: the aggregator, then the camera head on the last layer and the DPT depth and point heads on four
//! layers. One scene per call (upstream's B = 1).

use candle_core::{DType, Result, Tensor};
use candle_nn::VarBuilder;

use super::aggregator::Aggregator;
use crate::config::VggtConfig;
use crate::heads::camera_head::CameraHead;
use crate::heads::dpt_head::DptHead;
use crate::heads::head_act::Activation;

#[derive(Debug, Clone)]
pub struct Vggt {
    pub aggregator: Aggregator,
    pub camera_head: Option<CameraHead>,
    pub depth_head: Option<DptHead>,
    pub point_head: Option<DptHead>,
    pub cfg: VggtConfig,
}

/// What one forward pass predicts for `S` frames of `H × W`.
#[derive(Debug, Clone)]
pub struct Predictions {
    /// Activated `absT_quaR_FoV` encoding of each camera-head iteration, `(S, 9)` each; the last is the answer.
    pub pose_enc_list: Vec<Tensor>,
    /// `(S, H, W, 1)` and `(S, H, W)`.
    pub depth: Option<(Tensor, Tensor)>,
    /// World points `(S, H, W, 3)` and their confidence `(S, H, W)`.
    pub world_points: Option<(Tensor, Tensor)>,
    /// The DINOv2 patch tokens `(S, h·w, C)` when asked for (parity tests).
    pub patch_tokens: Option<Tensor>,
    /// Aggregated tokens `(S, P, 2C)` of the layers asked for (parity tests).
    pub tokens: Vec<(usize, Tensor)>,
}

impl Predictions {
    pub fn pose_enc(&self) -> Option<&Tensor> {
        self.pose_enc_list.last()
    }
}

impl Vggt {
    pub fn new(vb: VarBuilder, cfg: &VggtConfig) -> Result<Self> {
        Self::with_trunk_dtype(vb, cfg, DType::F32)
    }

    /// The aggregator's weights and tokens in `trunk` (bf16 on a GPU, as upstream's autocast); the heads' tensors
    /// stay f32 whatever the trunk's dtype, as upstream runs them with autocast disabled.
    ///
    /// A bf16 trunk on a CPU with AVX512-BF16 ([`mvsplat360_nn::bf16::path`] on the calling thread, so
    /// [`mvsplat360_nn::bf16::with_bf16_masked`] around the load opts out) runs only the blocks' big linears in
    /// bf16: attention `qkv`/`proj` and MLP `fc1`/`fc2` take `nn::linear::linear_fused_bf16` (weights rounded
    /// to bf16 and packed once here, activations rounded to bf16 as they are packed, f32 accumulation), and so do
    /// attention's two products for heads of 64 (`nn::rope::qkv_attention_bf16`). The tokens stay f32, and so do
    /// the patch embedding, the norms, QK-norm, RoPE, the softmax, GELU, biases and residual sums. Each block is
    /// packed as it is built (one block's f32 weights at a time; no weight tensor kept beside the packed copy).
    /// The DPT heads' products run in bf16 too ([`DptHead::pack_bf16`]: bf16 Winograd, packed convs and
    /// linears, f32 activations); the camera head stays f32. Without the feature (or on a GPU) a bf16 trunk is
    /// candle's bf16 storage and ops throughout and the heads f32, as before; an f32 model is unchanged.
    pub fn with_trunk_dtype(vb: VarBuilder, cfg: &VggtConfig, trunk: DType) -> Result<Self> {
        cfg.validate().map_err(candle_core::Error::Msg)?;
        let dim = 2 * cfg.embed_dim;
        let heads = vb.clone().set_dtype(DType::F32);
        let vb = heads.clone();
        let cpu_dpbf16 = trunk == DType::BF16 && vb.device().is_cpu() && mvsplat360_nn::bf16::path() == mvsplat360_nn::bf16::Bf16Path::Dpbf16;
        let aggregator =
            if cpu_dpbf16 { Aggregator::new_packed_bf16(vb.pp("aggregator"), cfg)? } else { Aggregator::new(vb.pp("aggregator").set_dtype(trunk), cfg)? };
        let dpt = |name: &str, out: usize, act: Activation| -> Result<DptHead> {
            let mut h = DptHead::new(vb.pp(name), dim, cfg.patch_size, out, act, &cfg.dpt)?;
            if cpu_dpbf16 {
                h.pack_bf16()?;
            }
            Ok(h)
        };
        Ok(Self {
            aggregator,
            camera_head: if cfg.enable_camera { Some(CameraHead::new(vb.pp("camera_head"), dim, &cfg.camera_head)?) } else { None },
            point_head: if cfg.enable_point { Some(dpt("point_head", 4, Activation::InvLog)?) } else { None },
            depth_head: if cfg.enable_depth { Some(dpt("depth_head", 2, Activation::Exp)?) } else { None },
            cfg: cfg.clone(),
        })
    }

    /// `images (S, 3, H, W)` in [0, 1], H and W multiples of the patch size. `extra_layers`: aggregated layers
    /// to return besides what the heads need (tests).
    pub fn forward(&self, images: &Tensor, extra_layers: &[usize]) -> Result<Predictions> {
        let (_, c, h, w) = images.dims4()?;
        let p = self.cfg.patch_size;
        if c != 3 || h % p != 0 || w % p != 0 || h == 0 || w == 0 {
            candle_core::bail!("VGGT: images {:?} must be (S, 3, H, W) with H and W positive multiples of {p}", images.dims());
        }
        let last = self.cfg.depth - 1;
        let mut keep: Vec<usize> = extra_layers.to_vec();
        if self.camera_head.is_some() {
            keep.push(last);
        }
        if self.depth_head.is_some() || self.point_head.is_some() {
            keep.extend(self.cfg.dpt.intermediate_layer_idx);
        }
        let tokens = self.aggregator.forward(images, &keep)?;
        let _p = mvsplat360_nn::prof::scope("vggt.camera_head");
        let pose_enc_list = match &self.camera_head {
            Some(head) => head.forward(tokens.get(&last).ok_or_else(|| candle_core::Error::Msg("last layer not kept".into()))?)?,
            None => Vec::new(),
        };
        drop(_p);
        let psi = self.cfg.patch_start_idx();
        let _p = mvsplat360_nn::prof::scope("vggt.depth_head");
        let depth = self.depth_head.as_ref().map(|hd| hd.forward(&tokens, h, w, psi)).transpose()?;
        drop(_p);
        let _p = mvsplat360_nn::prof::scope("vggt.point_head");
        let world_points = self.point_head.as_ref().map(|hd| hd.forward(&tokens, h, w, psi)).transpose()?;
        drop(_p);
        let tokens = extra_layers.iter().filter_map(|i| tokens.get(i).map(|t| (*i, t.clone()))).collect();
        Ok(Predictions { pose_enc_list, depth, world_points, patch_tokens: None, tokens })
    }
}
