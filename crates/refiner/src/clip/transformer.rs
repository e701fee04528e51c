//! open_clip `transformer.py` `VisionTransformer` (conv1, class_embedding, positional_embedding, ln_pre,
//! transformer.resblocks.N, ln_post, proj), the pooled/projected output only. Inference only.

use candle_core::{Result, Tensor, D};

use super::{ClipAct, ClipVisionConfig};
use crate::unet::util::{attention, Linear, Norm};
use crate::weights::StrictWeights;

fn linear(w: &StrictWeights, p: &str, i: usize, o: usize) -> Result<Linear> {
    Linear::stored(w.get(&format!("{p}.weight"), &[o, i])?, Some(w.get(&format!("{p}.bias"), &[o])?), w.store())
}

fn layer_norm(w: &StrictWeights, p: &str, c: usize, eps: f64) -> Result<Norm> {
    Ok(Norm { weight: w.get(&format!("{p}.weight"), &[c])?, bias: w.get(&format!("{p}.bias"), &[c])?, eps })
}

/// `ResidualAttentionBlock` (no layer scale: ViT-H/14 has `ls_init_value` None).
#[derive(Debug)]
struct ResidualAttentionBlock {
    ln_1: Norm,
    in_proj: Linear,
    out_proj: Linear,
    ln_2: Norm,
    c_fc: Linear,
    c_proj: Linear,
}

impl ResidualAttentionBlock {
    fn load(w: &StrictWeights, p: &str, cfg: &ClipVisionConfig) -> Result<Self> {
        let d = cfg.width;
        Ok(Self {
            ln_1: layer_norm(w, &format!("{p}.ln_1"), d, cfg.layer_norm_eps)?,
            in_proj: Linear::stored(
                w.get(&format!("{p}.attn.in_proj_weight"), &[3 * d, d])?,
                Some(w.get(&format!("{p}.attn.in_proj_bias"), &[3 * d])?),
                w.store(),
            )?,
            out_proj: linear(w, &format!("{p}.attn.out_proj"), d, d)?,
            ln_2: layer_norm(w, &format!("{p}.ln_2"), d, cfg.layer_norm_eps)?,
            c_fc: linear(w, &format!("{p}.mlp.c_fc"), d, cfg.mlp_width)?,
            c_proj: linear(w, &format!("{p}.mlp.c_proj"), cfg.mlp_width, d)?,
        })
    }

    fn forward(&self, x: &Tensor, cfg: &ClipVisionConfig) -> Result<Tensor> {
        let _p = mvsplat360_nn::prof::scope("clip.block");
        let d = cfg.width;
        let qkv = self.in_proj.forward(&self.ln_1.layer_norm(x)?)?;
        let (q, k, v) = (qkv.narrow(D::Minus1, 0, d)?, qkv.narrow(D::Minus1, d, d)?, qkv.narrow(D::Minus1, 2 * d, d)?);
        let a = attention(&q.contiguous()?, &k.contiguous()?, &v.contiguous()?, cfg.heads, cfg.attn_max_score_elems)?;
        let x = self.out_proj.forward_fused(&a, 1.0, &[(x, 1.0)])?;
        let _m = mvsplat360_nn::prof::scope("clip.mlp");
        let h = self.c_fc.forward(&self.ln_2.layer_norm(&x)?)?;
        let h = match cfg.act {
            ClipAct::Gelu => mvsplat360_nn::activation::gelu_inference(&h)?,
            ClipAct::QuickGelu => (&h * candle_nn::ops::sigmoid(&(&h * 1.702)?)?)?,
        };
        self.c_proj.forward_fused(&h, 1.0, &[(&x, 1.0)])
    }
}

/// open_clip `VisionTransformer`: CLIP-normalised pixels → projected pooled (class-token) embedding.
#[derive(Debug)]
pub struct VisionTransformer {
    /// conv1 as a (width, 3·p·p) matrix (stride = kernel: patchify + matmul).
    conv1: Tensor,
    class_embedding: Tensor,
    positional_embedding: Tensor,
    ln_pre: Norm,
    resblocks: Vec<ResidualAttentionBlock>,
    ln_post: Norm,
    /// (width, output_dim)
    proj: Tensor,
}

impl VisionTransformer {
    pub(crate) fn load(w: &StrictWeights, cfg: &ClipVisionConfig) -> Result<Self> {
        let (d, p) = (cfg.width, cfg.patch_size);
        let grid = cfg.image_size / p;
        Ok(Self {
            conv1: w.get("conv1.weight", &[d, 3, p, p])?.reshape((d, 3 * p * p))?,
            class_embedding: w.get("class_embedding", &[d])?,
            positional_embedding: w.get("positional_embedding", &[grid * grid + 1, d])?,
            ln_pre: layer_norm(w, "ln_pre", d, cfg.layer_norm_eps)?,
            resblocks: (0..cfg.layers).map(|i| ResidualAttentionBlock::load(w, &format!("transformer.resblocks.{i}"), cfg)).collect::<Result<_>>()?,
            ln_post: layer_norm(w, "ln_post", d, cfg.layer_norm_eps)?,
            proj: w.get("proj", &[d, cfg.output_dim])?,
        })
    }

    /// (N, 3, image_size, image_size) → (N, output_dim).
    pub fn forward(&self, x: &Tensor, cfg: &ClipVisionConfig) -> Result<Tensor> {
        let (n, _, h, w) = x.dims4()?;
        let p = cfg.patch_size;
        let (gh, gw) = (h / p, w / p);
        let patches = x.reshape((n, 3, gh, p, gw, p))?.permute((0, 2, 4, 1, 3, 5))?.contiguous()?.reshape((n * gh * gw, 3 * p * p))?;
        let tokens = patches.matmul(&self.conv1.t()?)?.reshape((n, gh * gw, cfg.width))?;
        let cls = self.class_embedding.reshape((1, 1, cfg.width))?.broadcast_as((n, 1, cfg.width))?;
        let mut x = Tensor::cat(&[&cls, &tokens], 1)?.broadcast_add(&self.positional_embedding.unsqueeze(0)?)?;
        x = self.ln_pre.layer_norm(&x)?;
        for b in &self.resblocks {
            x = b.forward(&x, cfg)?;
        }
        let pooled = self.ln_post.layer_norm(&x.narrow(1, 0, 1)?.squeeze(1)?)?;
        pooled.matmul(&self.proj)
    }
}
