//! The model's shape, under the official constructor argument names (`VGGT(...)`, `Aggregator(...)`,
//! `CameraHead(...)`, `DPTHead(...)`); the defaults are VGGT-1B's. `config.json` of a VGGT model folder holds
//! this struct; reduced configs (fewer, narrower blocks) run the same code paths (tests, outside checks).

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VggtConfig {
    /// Training image size: the DINOv2 positional embedding is a (img_size/patch_size)² grid.
    pub img_size: usize,
    pub patch_size: usize,
    pub embed_dim: usize,
    /// Frame blocks = global blocks = `depth` (VGGT-1B: 24 + 24).
    pub depth: usize,
    pub num_heads: usize,
    pub mlp_ratio: f64,
    pub num_register_tokens: usize,
    /// Upstream's choice of DINOv2 ViT (`dinov2_vitl14_reg` for VGGT-1B); only DINOv2 patch embeds are built.
    pub patch_embed: String,
    /// Blocks and heads of that DINOv2 (upstream fixes them by the name: ViT-L = 24 blocks, 16 heads).
    pub patch_embed_depth: usize,
    pub patch_embed_num_heads: usize,
    /// Order of the attention kinds inside each group (`["frame", "global"]`).
    pub aa_order: Vec<String>,
    /// Blocks of one kind before switching to the other.
    pub aa_block_size: usize,
    pub qk_norm: bool,
    /// RoPE base frequency; ≤ 0 disables RoPE.
    pub rope_freq: f64,
    pub camera_head: CameraHeadConfig,
    pub dpt: DptConfig,
    pub enable_camera: bool,
    pub enable_depth: bool,
    pub enable_point: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraHeadConfig {
    pub trunk_depth: usize,
    pub num_heads: usize,
    pub mlp_ratio: f64,
    /// Iterative refinements at inference (`num_iterations`).
    pub num_iterations: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DptConfig {
    pub features: usize,
    pub out_channels: [usize; 4],
    pub intermediate_layer_idx: [usize; 4],
    /// Frames per chunk of the DPT heads (upstream's `frames_chunk_size`): bounds memory, not results.
    pub frames_chunk_size: usize,
}

impl Default for VggtConfig {
    fn default() -> Self {
        Self {
            img_size: 518,
            patch_size: 14,
            embed_dim: 1024,
            depth: 24,
            num_heads: 16,
            mlp_ratio: 4.0,
            num_register_tokens: 4,
            patch_embed: "dinov2_vitl14_reg".into(),
            patch_embed_depth: 24,
            patch_embed_num_heads: 16,
            aa_order: vec!["frame".into(), "global".into()],
            aa_block_size: 1,
            qk_norm: true,
            rope_freq: 100.0,
            camera_head: CameraHeadConfig::default(),
            dpt: DptConfig::default(),
            enable_camera: true,
            enable_depth: true,
            enable_point: true,
        }
    }
}

impl Default for CameraHeadConfig {
    fn default() -> Self {
        Self { trunk_depth: 4, num_heads: 16, mlp_ratio: 4.0, num_iterations: 4 }
    }
}

impl Default for DptConfig {
    fn default() -> Self {
        Self { features: 256, out_channels: [256, 512, 1024, 1024], intermediate_layer_idx: [4, 11, 17, 23], frames_chunk_size: 8 }
    }
}

impl VggtConfig {
    /// Why this config cannot be built, if it cannot (names the field).
    pub fn validate(&self) -> Result<(), String> {
        let head_dim = self.embed_dim / self.num_heads.max(1);
        if self.num_heads == 0 || self.embed_dim % self.num_heads != 0 {
            return Err(format!("embed_dim {} is not a multiple of num_heads {}", self.embed_dim, self.num_heads));
        }
        if self.rope_freq > 0.0 && head_dim % 4 != 0 {
            return Err(format!("2D RoPE needs a head size divisible by 4; embed_dim/num_heads = {head_dim}"));
        }
        if self.patch_embed_num_heads == 0 || self.embed_dim % self.patch_embed_num_heads != 0 {
            return Err(format!("embed_dim {} is not a multiple of patch_embed_num_heads {}", self.embed_dim, self.patch_embed_num_heads));
        }
        if !self.patch_embed.starts_with("dinov2") {
            return Err(format!("patch_embed `{}`: only the DINOv2 patch embeds are supported", self.patch_embed));
        }
        if self.patch_size == 0 || self.img_size % self.patch_size != 0 {
            return Err(format!("img_size {} is not a multiple of patch_size {}", self.img_size, self.patch_size));
        }
        if self.aa_block_size == 0 || self.depth % self.aa_block_size != 0 {
            return Err(format!("depth ({}) must be divisible by aa_block_size ({})", self.depth, self.aa_block_size));
        }
        if self.aa_order.is_empty() || self.aa_order.iter().any(|k| k != "frame" && k != "global") {
            return Err(format!("aa_order {:?}: each entry must be \"frame\" or \"global\"", self.aa_order));
        }
        if self.enable_depth || self.enable_point {
            if let Some(i) = self.dpt.intermediate_layer_idx.iter().find(|&&i| i >= self.depth) {
                return Err(format!("dpt.intermediate_layer_idx {i} is past the {} aggregated blocks", self.depth));
            }
        }
        if self.enable_camera {
            let c = &self.camera_head;
            if c.num_heads == 0 || (2 * self.embed_dim) % c.num_heads != 0 {
                return Err(format!("camera_head.num_heads {} does not divide 2·embed_dim {}", c.num_heads, 2 * self.embed_dim));
            }
            if c.num_iterations == 0 {
                return Err("camera_head.num_iterations must be at least 1".into());
            }
        }
        if self.dpt.frames_chunk_size == 0 {
            return Err("dpt.frames_chunk_size must be at least 1".into());
        }
        Ok(())
    }

    /// First token of the patch tokens (camera + registers before them).
    pub fn patch_start_idx(&self) -> usize {
        1 + self.num_register_tokens
    }
}
