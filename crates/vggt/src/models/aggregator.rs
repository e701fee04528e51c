//! `Aggregator`: DINOv2 patch tokens of each frame, a camera token and register tokens in front (the first
//! frame gets its own pair, index 0; every other frame shares index 1), then `depth` groups of frame attention
//! (tokens of one frame) and global attention (tokens of all frames), each block with QK-norm and 2D RoPE.
//! Each group's output is the frame block's and the global block's tokens side by side, `(S, P, 2C)`.

use std::collections::BTreeMap;

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

use crate::config::VggtConfig;
use crate::layers::block::{Block, BlockSpec};
use crate::layers::rope::{frame_positions, RopeTables};
use crate::layers::vision_transformer::DinoVisionTransformer;
use crate::layers::TORCH_LN_EPS;

/// ImageNet statistics the images are normalised with before the patch embedding.
const RESNET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const RESNET_STD: [f32; 3] = [0.229, 0.224, 0.225];

#[derive(Debug, Clone)]
pub struct Aggregator {
    pub patch_embed: DinoVisionTransformer,
    pub frame_blocks: Vec<Block>,
    pub global_blocks: Vec<Block>,
    /// `(1, 2, 1, C)` and `(1, 2, R, C)`: index 0 for the first frame, 1 for the others.
    pub camera_token: Tensor,
    pub register_token: Tensor,
    pub cfg: VggtConfig,
}

/// The aggregated tokens the heads read, by block index (`output_list[i]` upstream), each `(S, P, 2C)`.
pub type AggregatedTokens = BTreeMap<usize, Tensor>;

impl Aggregator {
    pub fn new(vb: VarBuilder, cfg: &VggtConfig) -> Result<Self> {
        Self::build(vb, cfg, false)
    }

    /// [`Aggregator::new`] with every block's linears packed for the CPU's bf16 product as each block is built
    /// ([`Block::pack_bf16`]): the f32 weights of one block at a time, never the whole trunk's.
    pub fn new_packed_bf16(vb: VarBuilder, cfg: &VggtConfig) -> Result<Self> {
        Self::build(vb, cfg, true)
    }

    fn build(vb: VarBuilder, cfg: &VggtConfig, pack_bf16: bool) -> Result<Self> {
        let c = cfg.embed_dim;
        let patch_embed = DinoVisionTransformer::new(
            vb.pp("patch_embed"),
            cfg.img_size,
            cfg.patch_size,
            c,
            cfg.patch_embed_depth,
            cfg.patch_embed_num_heads,
            cfg.mlp_ratio,
            cfg.num_register_tokens,
            pack_bf16,
        )?;
        let spec = BlockSpec {
            dim: c,
            num_heads: cfg.num_heads,
            mlp_ratio: cfg.mlp_ratio,
            qk_norm: cfg.qk_norm,
            norm_eps: TORCH_LN_EPS,
            layer_scale: true,
            pack_bf16,
        };
        let blocks = |name: &str| (0..cfg.depth).map(|i| Block::new(vb.pp(name).pp(i), spec)).collect::<Result<Vec<_>>>();
        Ok(Self {
            patch_embed,
            frame_blocks: blocks("frame_blocks")?,
            global_blocks: blocks("global_blocks")?,
            camera_token: vb.get((1, 2, 1, c), "camera_token")?,
            register_token: vb.get((1, 2, cfg.num_register_tokens, c), "register_token")?,
            cfg: cfg.clone(),
        })
    }

    /// Packs the linears of every block (DINOv2's, the frame and the global blocks) for the CPU's bf16 product
    /// ([`Block::pack_bf16`]): bf16 weights and products, f32 everywhere else.
    pub fn pack_bf16_linears(&mut self) -> Result<()> {
        for b in self.patch_embed.blocks.iter_mut().chain(&mut self.frame_blocks).chain(&mut self.global_blocks) {
            b.pack_bf16()?;
        }
        Ok(())
    }

    /// Whether the blocks' linears run packed in bf16 ([`Aggregator::pack_bf16_linears`]).
    pub fn bf16_packed(&self) -> bool {
        self.frame_blocks.first().is_some_and(|b| b.attn.qkv.packed.is_some())
    }

    /// The normalised images' DINOv2 patch tokens, `(S, h·w, C)`, from images `(S, 3, H, W)` in [0, 1].
    pub fn patch_tokens(&self, images: &Tensor) -> Result<Tensor> {
        let dev = images.device();
        let images = &images.to_dtype(self.camera_token.dtype())?;
        let mean = Tensor::new(&RESNET_MEAN, dev)?.to_dtype(images.dtype())?.reshape((1, 3, 1, 1))?;
        let std = Tensor::new(&RESNET_STD, dev)?.to_dtype(images.dtype())?.reshape((1, 3, 1, 1))?;
        let x = images.broadcast_sub(&mean)?.broadcast_div(&std)?;
        self.patch_embed.forward_patch_tokens(&x)
    }

    /// `(S, 1 + R, C)`: frame 0 takes index 0 of the camera and register tokens, the others index 1.
    fn special_tokens(&self, s: usize) -> Result<Tensor> {
        let pick = |t: &Tensor, i: usize| -> Result<Tensor> { t.narrow(1, i, 1)?.squeeze(1) };
        let first = Tensor::cat(&[&pick(&self.camera_token, 0)?, &pick(&self.register_token, 0)?], 1)?;
        if s == 1 {
            return Ok(first);
        }
        let others = Tensor::cat(&[&pick(&self.camera_token, 1)?, &pick(&self.register_token, 1)?], 1)?;
        let n = others.dim(1)?;
        let others = others.broadcast_as((s - 1, n, self.cfg.embed_dim))?;
        Tensor::cat(&[&first, &others], 0)
    }

    /// Images `(S, 3, H, W)` in [0, 1] (one scene: upstream's B = 1) → the aggregated tokens of the blocks in
    /// `keep` (the heads' layers; upstream keeps all `depth`, which costs `depth × (S, P, 2C)` of memory).
    pub fn forward(&self, images: &Tensor, keep: &[usize]) -> Result<AggregatedTokens> {
        let (s, _, hh, ww) = images.dims4()?;
        let p = self.cfg.patch_size;
        let (h, w) = (hh / p, ww / p);
        let patch = {
            let _p = mvsplat360_nn::prof::scope("vggt.dinov2");
            self.patch_tokens(images)?
        };
        let mut tokens = Tensor::cat(&[&self.special_tokens(s)?.to_dtype(patch.dtype())?, &patch], 1)?;
        let (_, n_tok, c) = tokens.dims3()?;
        let head_dim = c / self.cfg.num_heads;
        let (frame_rope, global_rope) = if self.cfg.rope_freq > 0.0 {
            let pos = frame_positions(self.cfg.patch_start_idx(), h, w);
            let all: Vec<(u32, u32)> = (0..s).flat_map(|_| pos.iter().copied()).collect();
            let dev = images.device();
            (Some(RopeTables::new(&pos, head_dim, self.cfg.rope_freq, dev)?), Some(RopeTables::new(&all, head_dim, self.cfg.rope_freq, dev)?))
        } else {
            (None, None)
        };
        let mut out = AggregatedTokens::new();
        let (mut fi, mut gi) = (0, 0);
        for _ in 0..self.cfg.depth / self.cfg.aa_block_size {
            let mut frame_out = Vec::new();
            let mut global_out = Vec::new();
            for kind in &self.cfg.aa_order {
                for _ in 0..self.cfg.aa_block_size {
                    if kind == "frame" {
                        let _p = mvsplat360_nn::prof::scope("vggt.frame_blocks");
                        tokens = self.frame_blocks[fi].forward(&tokens.reshape((s, n_tok, c))?, frame_rope.as_ref())?;
                        fi += 1;
                        frame_out.push(tokens.clone());
                    } else {
                        let _p = mvsplat360_nn::prof::scope("vggt.global_blocks");
                        tokens = self.global_blocks[gi].forward(&tokens.reshape((1, s * n_tok, c))?, global_rope.as_ref())?;
                        gi += 1;
                        global_out.push(tokens.clone());
                    }
                }
            }
            let base = fi - frame_out.len();
            for (j, (f, g)) in frame_out.iter().zip(&global_out).enumerate() {
                if keep.contains(&(base + j)) {
                    let f = f.reshape((s, n_tok, c))?;
                    let g = g.reshape((s, n_tok, c))?;
                    out.insert(base + j, Tensor::cat(&[&f, &g], 2)?);
                }
            }
        }
        Ok(out)
    }
}
