//! Encoder configuration. Field names follow the official YAML (`config/model/encoder/costvolume.yaml`
//! overridden by `+experiment=dl3dv_mvsplat360`); `Default` is the DL3DV 5-view experiment.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct OpacityMappingCfg {
    pub initial: f32,
    pub r#final: f32,
    pub warm_up: u64,
}

impl Default for OpacityMappingCfg {
    fn default() -> Self {
        Self { initial: 0.0, r#final: 0.0, warm_up: 1 }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GaussianAdapterCfg {
    pub gaussian_scale_min: f32,
    pub gaussian_scale_max: f32,
    pub sh_degree: usize,
    pub feature_sh_degree: usize,
    pub n_feature_channels: usize,
}

impl Default for GaussianAdapterCfg {
    fn default() -> Self {
        Self { gaussian_scale_min: 0.5, gaussian_scale_max: 15.0, sh_degree: 4, feature_sh_degree: 2, n_feature_channels: 4 }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EncoderCostVolumeCfg {
    pub d_feature: usize,
    pub num_depth_candidates: usize,
    pub num_surfaces: usize,
    pub gaussians_per_pixel: usize,
    pub gaussian_adapter: GaussianAdapterCfg,
    pub opacity_mapping: OpacityMappingCfg,
    pub downscale_factor: usize,
    pub shim_patch_size: usize,
    pub multiview_trans_attn_split: usize,
    /// Self + nearest other views whose tokens are the transformer's cross-attention keys/values.
    pub multiview_trans_nearest_n_views: usize,
    /// Self + nearest other views used to build each view's cost volume.
    pub costvolume_nearest_n_views: usize,
    pub costvolume_unet_feat_dim: usize,
    pub costvolume_unet_channel_mult: Vec<usize>,
    pub costvolume_unet_attn_res: Vec<usize>,
    pub depth_unet_feat_dim: usize,
    pub depth_unet_channel_mult: Vec<usize>,
    pub depth_unet_attn_res: Vec<usize>,
    /// Transformer blocks in the multi-view backbone.
    pub num_transformer_layers: usize,
    pub ffn_dim_expansion: usize,
    /// Context views (the UNets' cross-view attention frame count).
    pub num_views: usize,
    pub near: f32,
    pub far: f32,
    /// Widths of the backbone CNN's three stages: not in the official YAML (unimatch hard-codes [64, 96, 128]);
    /// only narrower test models set it.
    #[serde(skip_serializing_if = "is_official_cnn")]
    pub cnn_feature_dims: [usize; 3],
}

fn is_official_cnn(d: &[usize; 3]) -> bool {
    *d == crate::backbone::unimatch::backbone::FEATURE_DIMS
}

impl Default for EncoderCostVolumeCfg {
    fn default() -> Self {
        Self {
            d_feature: 128,
            num_depth_candidates: 128,
            num_surfaces: 1,
            gaussians_per_pixel: 1,
            gaussian_adapter: GaussianAdapterCfg::default(),
            opacity_mapping: OpacityMappingCfg::default(),
            downscale_factor: 4,
            shim_patch_size: 16,
            multiview_trans_attn_split: 2,
            multiview_trans_nearest_n_views: 3,
            costvolume_nearest_n_views: 3,
            costvolume_unet_feat_dim: 128,
            costvolume_unet_channel_mult: vec![1, 1, 1],
            costvolume_unet_attn_res: vec![4],
            depth_unet_feat_dim: 32,
            depth_unet_channel_mult: vec![1, 1, 1, 1, 1],
            depth_unet_attn_res: vec![16],
            num_transformer_layers: 6,
            ffn_dim_expansion: 4,
            num_views: 5,
            near: 1.0,
            far: 100.0,
            cnn_feature_dims: crate::backbone::unimatch::backbone::FEATURE_DIMS,
        }
    }
}

impl EncoderCostVolumeCfg {
    /// A small configuration for fast tests with random weights (same code paths as DL3DV: windows, shifted
    /// blocks, nearest-view selection, both UNets with attention). Use 3 views and H, W multiples of 32.
    pub fn tiny() -> Self {
        Self {
            d_feature: 32,
            num_depth_candidates: 16,
            costvolume_unet_feat_dim: 32,
            costvolume_unet_channel_mult: vec![1, 1],
            costvolume_unet_attn_res: vec![2],
            depth_unet_feat_dim: 32,
            depth_unet_channel_mult: vec![1, 1],
            depth_unet_attn_res: vec![2],
            num_transformer_layers: 2,
            num_views: 3,
            ..Self::default()
        }
    }

    /// Images must be a multiple of this size (the official data shim crops to `shim_patch_size ·
    /// downscale_factor`).
    pub fn image_multiple(&self) -> usize {
        self.shim_patch_size * self.downscale_factor
    }
}
