//! sgm `attention.py` (BasicTransformerBlock, CrossAttention, FeedForward) and `video_attention.py`
//! (VideoTransformerBlock, SpatialVideoTransformer), in sgm key names.

use candle_core::{Result, Tensor};

use super::util::{attention, blend, geglu, sigmoid_scalar, timestep_embedding, Linear, Norm};
use super::weights::Weights;

pub(crate) fn linear(w: &Weights, name: &str, i: usize, o: usize, bias: bool) -> Result<Linear> {
    let weight = w.get(&format!("{name}.weight"), &[o, i])?;
    let bias = if bias { Some(w.get(&format!("{name}.bias"), &[o])?) } else { None };
    Ok(Linear { weight, bias })
}

pub(crate) fn norm(w: &Weights, name: &str, c: usize, eps: f64) -> Result<Norm> {
    Ok(Norm { weight: w.get(&format!("{name}.weight"), &[c])?, bias: w.get(&format!("{name}.bias"), &[c])?, eps })
}

/// sgm `CrossAttention` / `MemoryEfficientCrossAttention` (same weights): q/k/v without bias, `to_out.0` with bias.
#[derive(Debug)]
pub struct CrossAttention {
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: usize,
}

impl CrossAttention {
    fn load(w: &Weights, p: &str, dim: usize, ctx_dim: usize, heads: usize, d_head: usize) -> Result<Self> {
        let inner = heads * d_head;
        Ok(Self {
            to_q: linear(w, &format!("{p}.to_q"), dim, inner, false)?,
            to_k: linear(w, &format!("{p}.to_k"), ctx_dim, inner, false)?,
            to_v: linear(w, &format!("{p}.to_v"), ctx_dim, inner, false)?,
            to_out: linear(w, &format!("{p}.to_out.0"), inner, dim, true)?,
            heads,
        })
    }

    /// x: (N, L, C); context: (N', Lc, D) with N divisible by N' — the N/N' consecutive query rows of one
    /// context item share its keys, so they are folded into the query length (one big matmul, no repeat).
    fn forward(&self, x: &Tensor, context: Option<&Tensor>, max_elems: usize) -> Result<Tensor> {
        let q = self.to_q.forward(x)?;
        let (n, l, inner) = q.dims3()?;
        let out = match context {
            None => {
                let k = self.to_k.forward(x)?;
                let v = self.to_v.forward(x)?;
                attention(&q, &k, &v, self.heads, max_elems)?
            }
            Some(ctx) => {
                let nc = ctx.dim(0)?;
                let k = self.to_k.forward(ctx)?;
                let v = self.to_v.forward(ctx)?;
                let q = q.reshape((nc, (n / nc) * l, inner))?;
                attention(&q, &k, &v, self.heads, max_elems)?.reshape((n, l, inner))?
            }
        };
        self.to_out.forward(&out)
    }

    /// Self-attention restricted to `splits` consecutive windows of the sequence (MVSplat360 `num_splits`).
    fn forward_windows(&self, x: &Tensor, splits: usize, max_elems: usize) -> Result<Tensor> {
        let q = self.to_q.forward(x)?;
        let k = self.to_k.forward(x)?;
        let v = self.to_v.forward(x)?;
        let (n, l, inner) = q.dims3()?;
        if splits <= 1 {
            return self.to_out.forward(&attention(&q, &k, &v, self.heads, max_elems)?);
        }
        if l % splits != 0 {
            candle_core::bail!("num_splits {splits} does not divide the {l} video frames");
        }
        let win = |t: &Tensor| t.reshape((n * splits, l / splits, inner));
        let o = attention(&win(&q)?, &win(&k)?, &win(&v)?, self.heads, max_elems)?.reshape((n, l, inner))?;
        self.to_out.forward(&o)
    }
}

/// GEGLU feed-forward: `net.0.proj` (dim → 2·inner), `net.2` (inner → out).
#[derive(Debug)]
pub struct FeedForward {
    proj: Linear,
    out: Linear,
}

impl FeedForward {
    fn load(w: &Weights, p: &str, dim: usize, dim_out: usize) -> Result<Self> {
        let inner = dim * 4;
        Ok(Self {
            proj: linear(w, &format!("{p}.net.0.proj"), dim, inner * 2, true)?,
            out: linear(w, &format!("{p}.net.2"), inner, dim_out, true)?,
        })
    }

    /// Rows are processed in chunks so the 8·dim-wide hidden activation stays ≈ 128 MiB.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let c = *dims.last().unwrap_or(&1);
        let rows = x.elem_count() / c.max(1);
        let hidden = self.proj.weight.dim(0)?;
        let chunk = ((32usize << 20) / hidden.max(1)).max(1);
        if rows <= chunk {
            return self.out.forward(&geglu(&self.proj.forward(x)?)?);
        }
        let x2 = x.reshape((rows, c))?;
        let mut parts = Vec::with_capacity(rows.div_ceil(chunk));
        let mut i = 0;
        while i < rows {
            let m = chunk.min(rows - i);
            parts.push(self.out.forward(&geglu(&self.proj.forward(&x2.narrow(0, i, m)?)?)?)?);
            i += m;
        }
        let mut od = dims;
        if let Some(l) = od.last_mut() {
            *l = self.out.weight.dim(0)?;
        }
        Tensor::cat(&parts, 0)?.reshape(od)
    }
}

/// sgm `BasicTransformerBlock` (spatial): self-attn, cross-attn on the CLIP token, GEGLU FF; pre-LayerNorm.
#[derive(Debug)]
pub struct BasicTransformerBlock {
    attn1: CrossAttention,
    attn2: CrossAttention,
    ff: FeedForward,
    norm1: Norm,
    norm2: Norm,
    norm3: Norm,
}

impl BasicTransformerBlock {
    fn load(w: &Weights, p: &str, dim: usize, heads: usize, d_head: usize, ctx: usize) -> Result<Self> {
        Ok(Self {
            attn1: CrossAttention::load(w, &format!("{p}.attn1"), dim, dim, heads, d_head)?,
            attn2: CrossAttention::load(w, &format!("{p}.attn2"), dim, ctx, heads, d_head)?,
            ff: FeedForward::load(w, &format!("{p}.ff"), dim, dim)?,
            norm1: norm(w, &format!("{p}.norm1"), dim, 1e-5)?,
            norm2: norm(w, &format!("{p}.norm2"), dim, 1e-5)?,
            norm3: norm(w, &format!("{p}.norm3"), dim, 1e-5)?,
        })
    }

    fn forward(&self, x: &Tensor, context: &Tensor, max_elems: usize) -> Result<Tensor> {
        let x = (self.attn1.forward(&self.norm1.layer_norm(x)?, None, max_elems)? + x)?;
        let x = (self.attn2.forward(&self.norm2.layer_norm(&x)?, Some(context), max_elems)? + &x)?;
        self.ff.forward(&self.norm3.layer_norm(&x)?)? + &x
    }
}

/// sgm `VideoTransformerBlock` with `ff_in` (extra_ff_mix_layer): attention over frames per pixel.
#[derive(Debug)]
pub struct VideoTransformerBlock {
    norm_in: Norm,
    ff_in: FeedForward,
    attn1: CrossAttention,
    attn2: CrossAttention,
    ff: FeedForward,
    norm1: Norm,
    norm2: Norm,
    norm3: Norm,
}

impl VideoTransformerBlock {
    fn load(w: &Weights, p: &str, dim: usize, heads: usize, d_head: usize, ctx: usize) -> Result<Self> {
        Ok(Self {
            norm_in: norm(w, &format!("{p}.norm_in"), dim, 1e-5)?,
            ff_in: FeedForward::load(w, &format!("{p}.ff_in"), dim, dim)?,
            attn1: CrossAttention::load(w, &format!("{p}.attn1"), dim, dim, heads, d_head)?,
            attn2: CrossAttention::load(w, &format!("{p}.attn2"), dim, ctx, heads, d_head)?,
            ff: FeedForward::load(w, &format!("{p}.ff"), dim, dim)?,
            norm1: norm(w, &format!("{p}.norm1"), dim, 1e-5)?,
            norm2: norm(w, &format!("{p}.norm2"), dim, 1e-5)?,
            norm3: norm(w, &format!("{p}.norm3"), dim, 1e-5)?,
        })
    }

    /// x: (B·T, S, C); time_context: (B, Lc, D) (first frame's context of each video).
    fn forward(&self, x: &Tensor, time_context: &Tensor, frames: usize, splits: usize, max_elems: usize) -> Result<Tensor> {
        let (n, s, c) = x.dims3()?;
        let b = n / frames;
        // (b t) s c -> (b s) t c
        let h = x.reshape((b, frames, s, c))?.transpose(1, 2)?.contiguous()?.reshape((b * s, frames, c))?;
        let h = (self.ff_in.forward(&self.norm_in.layer_norm(&h)?)? + &h)?;
        let h = (self.attn1.forward_windows(&self.norm1.layer_norm(&h)?, splits, max_elems)? + &h)?;
        let h = (self.attn2.forward(&self.norm2.layer_norm(&h)?, Some(time_context), max_elems)? + &h)?;
        let h = (self.ff.forward(&self.norm3.layer_norm(&h)?)? + &h)?;
        h.reshape((b, s, frames, c))?.transpose(1, 2)?.contiguous()?.reshape((n, s, c))
    }
}

/// sgm `SpatialVideoTransformer` (use_linear, use_spatial_context, learned_with_images merge).
#[derive(Debug)]
pub struct SpatialVideoTransformer {
    norm: Norm,
    proj_in: Linear,
    proj_out: Linear,
    blocks: Vec<BasicTransformerBlock>,
    time_stack: Vec<VideoTransformerBlock>,
    time_pos_embed: (Linear, Linear),
    alpha: f64,
    channels: usize,
    max_period: f32,
}

impl SpatialVideoTransformer {
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn load(w: &Weights, p: &str, ch: usize, heads: usize, d_head: usize, depth: usize, ctx: usize, max_period: f32) -> Result<Self> {
        let inner = heads * d_head;
        let mut blocks = Vec::new();
        let mut time_stack = Vec::new();
        for d in 0..depth {
            blocks.push(BasicTransformerBlock::load(w, &format!("{p}.transformer_blocks.{d}"), inner, heads, d_head, ctx)?);
            time_stack.push(VideoTransformerBlock::load(w, &format!("{p}.time_stack.{d}"), inner, heads, d_head, ctx)?);
        }
        Ok(Self {
            norm: norm(w, &format!("{p}.norm"), ch, 1e-6)?,
            proj_in: linear(w, &format!("{p}.proj_in"), ch, inner, true)?,
            proj_out: linear(w, &format!("{p}.proj_out"), inner, ch, true)?,
            blocks,
            time_stack,
            time_pos_embed: (
                linear(w, &format!("{p}.time_pos_embed.0"), ch, ch * 4, true)?,
                linear(w, &format!("{p}.time_pos_embed.2"), ch * 4, ch, true)?,
            ),
            alpha: sigmoid_scalar(&w.get(&format!("{p}.time_mixer.mix_factor"), &[1])?)?,
            channels: ch,
            max_period,
        })
    }

    /// x: (B·T, C, H, W); context: (B·T, Lc, D).
    pub fn forward(&self, x: &Tensor, context: &Tensor, frames: usize, splits: usize, max_elems: usize) -> Result<Tensor> {
        let (n, c, hh, ww) = x.dims4()?;
        let b = n / frames;
        let (_, lc, dc) = context.dims3()?;
        let time_context = context.reshape((b, frames, lc, dc))?.narrow(1, 0, 1)?.reshape((b, lc, dc))?;
        let h = self.norm.group_norm(x, 32, 1, false)?;
        let h = h.permute((0, 2, 3, 1))?.contiguous()?.reshape((n, hh * ww, c))?;
        let mut h = self.proj_in.forward(&h)?;
        let idx: Vec<f32> = (0..n).map(|i| (i % frames) as f32).collect();
        let t_emb = timestep_embedding(&idx, self.channels, self.max_period, x.device())?.to_dtype(x.dtype())?;
        let emb = self.time_pos_embed.1.forward(&self.time_pos_embed.0.forward(&t_emb)?.silu()?)?.unsqueeze(1)?;
        for (block, mix) in self.blocks.iter().zip(&self.time_stack) {
            h = block.forward(&h, context, max_elems)?;
            let hm = h.broadcast_add(&emb)?;
            let hm = mix.forward(&hm, &time_context, frames, splits, max_elems)?;
            h = blend(&h, &hm, self.alpha)?;
        }
        let h = self.proj_out.forward(&h)?;
        let h = h.reshape((n, hh, ww, c))?.permute((0, 3, 1, 2))?;
        h + x
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn windowed_self_attention_equals_attention_per_window() {
        let dev = Device::Cpu;
        let w = Weights::random(3, &dev);
        let a = CrossAttention::load(&w, "a", 32, 32, 2, 16).unwrap();
        // 3 sequences of 8 frames, 4 windows of 2 (as 56 frames = 4 windows of 14).
        let x = Tensor::randn(0f32, 1.0, (3, 8, 32), &dev).unwrap();
        let win = a.forward_windows(&x, 4, usize::MAX).unwrap();
        let parts: Vec<Tensor> = (0..4).map(|i| a.forward(&x.narrow(1, 2 * i, 2).unwrap(), None, usize::MAX).unwrap()).collect();
        let reference = Tensor::cat(&parts, 1).unwrap();
        let d = (win - &reference).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-6, "{d}");
        let full = a.forward_windows(&x, 1, usize::MAX).unwrap();
        let d = (full - reference).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d > 1e-3, "windows must differ from global attention");
        assert!(a.forward_windows(&x, 3, usize::MAX).is_err());
    }
}
