//! sgm `video_model.py`: `VideoResBlock` and `VideoUNet` (input_blocks / middle_block / output_blocks / out).

use candle_core::{DType, Result, Tensor};
use mvsplat360_nn::conv::{Conv2dConfig, ConvEpilogue};

use mvsplat360_nn::mode::is_differentiable;

use super::util::{blend_learned, sigmoid_scalar, timestep_embedding, ConvWeight, Linear, Norm, TemporalWeight};
use super::video_attention::{linear, norm, SpatialVideoTransformer};
use super::weights::Weights;
use super::VideoUNetConfig;

#[derive(Debug)]
struct Conv {
    w: ConvWeight,
    b: Tensor,
    cfg: Conv2dConfig,
}

impl Conv {
    fn load(w: &Weights, p: &str, i: usize, o: usize, k: usize, stride: usize) -> Result<Self> {
        Ok(Self {
            w: ConvWeight::new(w.get(&format!("{p}.weight"), &[o, i, k, k])?, w.store())?,
            b: w.get(&format!("{p}.bias"), &[o])?,
            cfg: Conv2dConfig { padding: k / 2, stride, dilation: 1 },
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_fused(x, ConvEpilogue::default())
    }

    fn forward_fused(&self, x: &Tensor, epi: ConvEpilogue) -> Result<Tensor> {
        let _p = mvsplat360_nn::prof::scope(if self.cfg.stride == 1 { "unet.conv" } else { "unet.conv_stride2" });
        self.w.conv(x, Some(&self.b), self.cfg, epi)
    }
}

/// Conv3d with kernel (kt, 1, 1), padding (kt/2, 0, 0) on (B·T, C, H, W), see `mvsplat360_nn::conv::temporal_conv`.
#[derive(Debug)]
struct TemporalConv {
    w: TemporalWeight,
    b: Tensor,
    kt: usize,
}

impl TemporalConv {
    fn load(w: &Weights, p: &str, i: usize, o: usize, kt: usize) -> Result<Self> {
        let w5 = w.get(&format!("{p}.weight"), &[o, i, kt, 1, 1])?;
        Ok(Self { w: TemporalWeight::new(w5, o, i, kt, w.is_trainable(), w.store())?, b: w.get(&format!("{p}.bias"), &[o])?, kt })
    }

    fn forward(&self, x: &Tensor, frames: usize, epi: ConvEpilogue) -> Result<Tensor> {
        let _p = mvsplat360_nn::prof::scope("unet.temporal_conv");
        self.w.conv(x, &self.b, self.kt, frames, epi.item_bias, epi.residual, epi.scale.unwrap_or(1.0))
    }
}

/// Pixels a spatial ResBlock on packed bf16 weights computes at a time (items of a frame batch): at 64×112
/// latents two frames, ≈ 55 MB for a 960-channel norm output against ≈ 0.77 GB for the bench's 2×14 frames.
const CHUNK_PIXELS: usize = 1 << 14;

/// sgm `ResBlock` (2-D) or its `time_stack` twin (3-D, kernel (kt,1,1)); no up/down, no scale-shift norm.
#[derive(Debug)]
struct ResBlock {
    norm1: Norm,
    norm2: Norm,
    conv1: Either,
    conv2: Either,
    emb: Linear,
    skip: Option<Conv>,
    temporal: bool,
}

#[derive(Debug)]
enum Either {
    Spatial(Conv),
    Temporal(TemporalConv),
}

impl Either {
    fn forward(&self, x: &Tensor, frames: usize, epi: ConvEpilogue) -> Result<Tensor> {
        match self {
            Either::Spatial(c) => c.forward_fused(x, epi),
            Either::Temporal(c) => c.forward(x, frames, epi),
        }
    }
}

impl ResBlock {
    fn load(w: &Weights, p: &str, i: usize, o: usize, emb: usize, eps: f64, kt: Option<usize>) -> Result<Self> {
        let conv = |name: &str, ci: usize| -> Result<Either> {
            Ok(match kt {
                None => Either::Spatial(Conv::load(w, &format!("{p}.{name}"), ci, o, 3, 1)?),
                Some(k) => Either::Temporal(TemporalConv::load(w, &format!("{p}.{name}"), ci, o, k)?),
            })
        };
        Ok(Self {
            norm1: norm(w, &format!("{p}.in_layers.0"), i, eps)?,
            conv1: conv("in_layers.2", i)?,
            emb: linear(w, &format!("{p}.emb_layers.1"), emb, o, true)?,
            norm2: norm(w, &format!("{p}.out_layers.0"), o, eps)?,
            conv2: conv("out_layers.3", o)?,
            skip: if i != o { Some(Conv::load(w, &format!("{p}.skip_connection"), i, o, 1, 1)?) } else { None },
            temporal: kt.is_some(),
        })
    }

    /// `emb_act` = SiLU(emb), shared by every block. Returns `skip(x) + out_scale·h` (out_scale folds the
    /// AlphaBlender of a `time_stack` into the last conv).
    fn forward(&self, x: &Tensor, emb_act: &Tensor, frames: usize, out_scale: Option<f32>) -> Result<Tensor> {
        self.forward_chunked(x, emb_act, frames, out_scale, CHUNK_PIXELS)
    }

    /// A spatial block on packed bf16 weights runs a few items at a time (≈ `chunk_pixels` pixels): its norm
    /// outputs and first conv exist for those items only — at the bench size the up path's 960-channel norm
    /// was the step's largest activation (issue 73). Items are independent here (norms per item, 2D convs), so
    /// the chunking does not change the arithmetic.
    fn forward_chunked(&self, x: &Tensor, emb_act: &Tensor, frames: usize, out_scale: Option<f32>, chunk_pixels: usize) -> Result<Tensor> {
        let _p = mvsplat360_nn::prof::scope(if self.temporal { "unet.resblock_temporal" } else { "unet.resblock_spatial" });
        let e = self.emb.forward(emb_act)?;
        let packed = matches!(&self.conv1, Either::Spatial(Conv { w: ConvWeight::Bf16(_), .. }));
        let (n, _, h, w) = x.dims4()?;
        let per = (chunk_pixels / (h * w).max(1)).max(1);
        if self.temporal || !packed || is_differentiable() || per >= n || e.dim(0)? != n {
            return self.forward_items(x, &e, frames, out_scale);
        }
        let mut out: Option<Tensor> = None;
        for i in (0..n).step_by(per) {
            let m = per.min(n - i);
            let y = self.forward_items(&x.narrow(0, i, m)?, &e.narrow(0, i, m)?, frames, out_scale)?;
            let o = match out.take() {
                Some(o) => o,
                None => Tensor::zeros((n, y.dim(1)?, y.dim(2)?, y.dim(3)?), y.dtype(), y.device())?,
            };
            o.slice_set(&y, 0, i)?;
            out = Some(o);
        }
        out.ok_or_else(|| candle_core::Error::Msg("ResBlock: empty batch".into()))
    }

    fn forward_items(&self, x: &Tensor, e: &Tensor, frames: usize, out_scale: Option<f32>) -> Result<Tensor> {
        let f = if self.temporal { frames } else { 1 };
        let epi1 = ConvEpilogue { item_bias: Some(e), ..Default::default() };
        let h = self.conv1.forward(&self.norm1.group_norm(x, 32, f, true)?, frames, epi1)?;
        let skip = match &self.skip {
            Some(s) => s.forward(x)?,
            None => x.clone(),
        };
        let hn = self.norm2.group_norm(&h, 32, f, true)?;
        drop(h);
        self.conv2.forward(&hn, frames, ConvEpilogue { residual: Some(&skip), scale: out_scale, ..Default::default() })
    }
}

/// sgm `VideoResBlock`: spatial ResBlock, temporal `time_stack`, AlphaBlender (`time_mixer`).
#[derive(Debug)]
pub struct VideoResBlock {
    spatial: ResBlock,
    time_stack: ResBlock,
    alpha: f64,
    /// `time_mixer.mix_factor` (1 element): alpha = sigmoid(mix) is recomputed from it in differentiable mode,
    /// and at every call for trainable weights (so that the fast path sees the `Var`'s updates).
    mix: Tensor,
    trainable: bool,
}

impl VideoResBlock {
    fn load(w: &Weights, p: &str, i: usize, o: usize, cfg: &VideoUNetConfig, eps: f64) -> Result<Self> {
        let emb = cfg.model_channels * 4;
        // Weights are requested in this order (seeded random weights depend on it).
        let spatial = ResBlock::load(w, p, i, o, emb, eps, None)?;
        let time_stack = ResBlock::load(w, &format!("{p}.time_stack"), o, o, emb, eps, Some(cfg.video_kernel_size[0]))?;
        let mix = w.get(&format!("{p}.time_mixer.mix_factor"), &[1])?;
        Ok(Self { spatial, time_stack, alpha: sigmoid_scalar(&mix)?, mix, trainable: w.is_trainable() })
    }

    /// alpha·xs + (1−alpha)·(xs + h_t) = xs + (1−alpha)·h_t, folded into the temporal block's last conv.
    /// Takes `x` by value: on the way up it is the skip concatenation, freed once the spatial block has read it.
    fn forward(&self, x: Tensor, emb_act: &Tensor, frames: usize) -> Result<Tensor> {
        let xs = self.spatial.forward(&x, emb_act, frames, None)?;
        drop(x);
        if is_differentiable() {
            // time_stack returns xs + h_t (identity skip): alpha·xs + (1 − alpha)·(xs + h_t), alpha a tensor.
            let xt = self.time_stack.forward(&xs, emb_act, frames, None)?;
            return blend_learned(&xs, &xt, &self.mix);
        }
        let alpha = if self.trainable { sigmoid_scalar(&self.mix)? } else { self.alpha };
        self.time_stack.forward(&xs, emb_act, frames, Some((1.0 - alpha) as f32))
    }
}

#[derive(Debug)]
enum Layer {
    Conv(Conv),
    Res(VideoResBlock),
    Attn(SpatialVideoTransformer),
    Down(Conv),
    Up(Conv),
}

/// Per-call inputs of [`VideoUNet::forward`].
pub struct UNetInputs<'a> {
    /// (B·F, in_channels, h, w): noisy latent × c_in, then the concat condition.
    pub x: &'a Tensor,
    /// c_noise per sample, length B·F.
    pub timesteps: &'a [f32],
    /// (B·F, Lc, context_dim) cross-attention tokens.
    pub context: &'a Tensor,
    /// (B·F, adm_in_channels) vector condition (`label_emb` input).
    pub y: Option<&'a Tensor>,
    /// Frames per video (F); the batch is B·F.
    pub num_video_frames: usize,
    /// Temporal self-attention in `num_splits` local windows of F/num_splits frames (MVSplat360 video mode).
    pub num_splits: Option<usize>,
}

/// Spatio-temporal UNet of Stable Video Diffusion, sgm layout. `image_only_indicator` is all zeros
/// (MVSplat360 inference), so every AlphaBlender uses sigmoid(mix_factor).
#[derive(Debug)]
pub struct VideoUNet {
    pub cfg: VideoUNetConfig,
    time_embed: (Linear, Linear),
    label_emb: Option<(Linear, Linear)>,
    input_blocks: Vec<Vec<Layer>>,
    middle_block: Vec<Layer>,
    output_blocks: Vec<Vec<Layer>>,
    out_norm: Norm,
    out_conv: Conv,
    /// Weights' dtype: inputs are cast to it, the output comes back as f32.
    dtype: DType,
}

impl VideoUNet {
    /// Build from a weight source (sgm names). Call [`Weights::finish`] afterwards for the strict check.
    pub fn new(cfg: &VideoUNetConfig, w: &Weights) -> Result<Self> {
        let mc = cfg.model_channels;
        let ted = mc * 4;
        let time_embed = (linear(w, "time_embed.0", mc, ted, true)?, linear(w, "time_embed.2", ted, ted, true)?);
        let label_emb = match cfg.adm_in_channels {
            Some(adm) => Some((linear(w, "label_emb.0.0", adm, ted, true)?, linear(w, "label_emb.0.2", ted, ted, true)?)),
            None => None,
        };
        let attn = |p: &str, ch: usize| -> Result<Layer> {
            let heads = ch / cfg.num_head_channels;
            Ok(Layer::Attn(SpatialVideoTransformer::load(
                w,
                p,
                ch,
                heads,
                cfg.num_head_channels,
                cfg.transformer_depth,
                cfg.context_dim,
                cfg.max_ddpm_temb_period,
            )?))
        };
        let mut input_blocks = vec![vec![Layer::Conv(Conv::load(w, "input_blocks.0.0", cfg.in_channels, mc, 3, 1)?)]];
        let mut chans = vec![mc];
        let mut ch = mc;
        let mut ds = 1;
        let levels = cfg.channel_mult.len();
        for (level, &mult) in cfg.channel_mult.iter().enumerate() {
            let has_attn = cfg.attention_resolutions.contains(&ds);
            let eps = if has_attn { cfg.down_attn_resnet_eps } else { cfg.resnet_eps };
            for _ in 0..cfg.num_res_blocks {
                let idx = input_blocks.len();
                let out = mult * mc;
                let mut layers = vec![Layer::Res(VideoResBlock::load(w, &format!("input_blocks.{idx}.0"), ch, out, cfg, eps)?)];
                ch = out;
                if has_attn {
                    layers.push(attn(&format!("input_blocks.{idx}.1"), ch)?);
                }
                input_blocks.push(layers);
                chans.push(ch);
            }
            if level != levels - 1 {
                let idx = input_blocks.len();
                input_blocks.push(vec![Layer::Down(Conv::load(w, &format!("input_blocks.{idx}.0.op"), ch, ch, 3, 2)?)]);
                chans.push(ch);
                ds *= 2;
            }
        }
        let middle_block = vec![
            Layer::Res(VideoResBlock::load(w, "middle_block.0", ch, ch, cfg, cfg.resnet_eps)?),
            attn("middle_block.1", ch)?,
            Layer::Res(VideoResBlock::load(w, "middle_block.2", ch, ch, cfg, cfg.resnet_eps)?),
        ];
        let mut output_blocks = Vec::new();
        for (level, &mult) in cfg.channel_mult.iter().enumerate().rev() {
            for i in 0..=cfg.num_res_blocks {
                let idx = output_blocks.len();
                let Some(ich) = chans.pop() else { candle_core::bail!("VideoUNet: skip-channel stack underflow") };
                let out = mc * mult;
                let mut layers = vec![Layer::Res(VideoResBlock::load(w, &format!("output_blocks.{idx}.0"), ch + ich, out, cfg, cfg.up_resnet_eps)?)];
                ch = out;
                if cfg.attention_resolutions.contains(&ds) {
                    layers.push(attn(&format!("output_blocks.{idx}.1"), ch)?);
                }
                if level > 0 && i == cfg.num_res_blocks {
                    let j = layers.len();
                    layers.push(Layer::Up(Conv::load(w, &format!("output_blocks.{idx}.{j}.conv"), ch, ch, 3, 1)?));
                    ds /= 2;
                }
                output_blocks.push(layers);
            }
        }
        Ok(Self {
            cfg: cfg.clone(),
            time_embed,
            label_emb,
            input_blocks,
            middle_block,
            output_blocks,
            out_norm: norm(w, "out.0", ch, cfg.resnet_eps)?,
            out_conv: Conv::load(w, "out.2", mc, cfg.out_channels, 3, 1)?,
            dtype: w.dtype(),
        })
    }

    /// The dtype the model computes in.
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// `up_size`: the spatial size an upsampler must produce (the next skip connection's), when known.
    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        layers: &[Layer],
        h: Tensor,
        emb_act: &Tensor,
        ctx: &Tensor,
        frames: usize,
        splits: usize,
        up_size: Option<(usize, usize)>,
    ) -> Result<Tensor> {
        let max = self.cfg.attn_max_score_elems;
        let mut h = h;
        for l in layers {
            h = match l {
                Layer::Conv(c) | Layer::Down(c) => c.forward(&h)?,
                Layer::Res(r) => r.forward(h, emb_act, frames)?,
                Layer::Attn(a) => a.forward(&h, ctx, frames, splits, max)?,
                Layer::Up(c) => {
                    let (_, _, hh, ww) = h.dims4()?;
                    match up_size {
                        // Odd sizes on the way down (stride-2 convs round up): like diffusers, upsample by
                        // nearest to the skip's size instead of ×2 (PyTorch legacy nearest: src = ⌊dst·in/out⌋).
                        // With out = 2·in − 1 that is ×2 minus the last row/column — before the conv, whose
                        // zero padding then sees the new border (cropping the fused ×2 conv's output differs).
                        Some((th, tw)) if (th, tw) != (2 * hh, 2 * ww) => c.forward(&h.upsample_nearest2d(th, tw)?)?,
                        _ => c.forward_fused(&h, ConvEpilogue { upsample2x: true, ..Default::default() })?,
                    }
                }
            };
        }
        Ok(h)
    }

    /// Model output (v-prediction) of shape (B·F, out_channels, h, w).
    pub fn forward(&self, inp: &UNetInputs) -> Result<Tensor> {
        if self.dtype != DType::F32 {
            // Half precision runs inside the model; callers (sampler, losses) keep f32.
            let cast = |t: &Tensor| t.to_dtype(self.dtype);
            let (x, context, y) = (cast(inp.x)?, cast(inp.context)?, inp.y.map(cast).transpose()?);
            let half = UNetInputs { x: &x, context: &context, y: y.as_ref(), ..*inp };
            return self.forward_native(&half)?.to_dtype(DType::F32);
        }
        self.forward_native(inp)
    }

    fn forward_native(&self, inp: &UNetInputs) -> Result<Tensor> {
        let x = inp.x;
        let n = x.dim(0)?;
        let frames = inp.num_video_frames.max(1);
        if n % frames != 0 || inp.timesteps.len() != n {
            candle_core::bail!("VideoUNet: batch {n} is not B·F with F = {frames}, or {} timesteps given", inp.timesteps.len());
        }
        let splits = inp.num_splits.unwrap_or(1).max(1);
        let t_emb = timestep_embedding(inp.timesteps, self.cfg.model_channels, 10000.0, x.device())?.to_dtype(x.dtype())?;
        let mut emb = self.time_embed.1.forward(&self.time_embed.0.forward(&t_emb)?.silu()?)?;
        if let Some((l1, l2)) = &self.label_emb {
            let Some(y) = inp.y else { candle_core::bail!("VideoUNet: this model needs the vector condition y (adm_in_channels)") };
            emb = (emb + l2.forward(&l1.forward(y)?.silu()?)?)?;
        }
        let emb_act = emb.silu()?;
        let mut hs = Vec::with_capacity(self.input_blocks.len());
        let mut h = x.clone();
        for b in &self.input_blocks {
            h = self.run(b, h, &emb_act, inp.context, frames, splits, None)?;
            hs.push(h.clone());
        }
        h = self.run(&self.middle_block, h, &emb_act, inp.context, frames, splits, None)?;
        for b in &self.output_blocks {
            let Some(skip) = hs.pop() else { candle_core::bail!("VideoUNet: skip stack underflow") };
            h = Tensor::cat(&[&h, &skip], 1)?;
            drop(skip);
            let up_size = match hs.last() {
                Some(t) => Some(t.dims4().map(|(_, _, th, tw)| (th, tw))?),
                None => None,
            };
            h = self.run(b, h, &emb_act, inp.context, frames, splits, up_size)?;
        }
        let h = self.out_norm.group_norm(&h, 32, 1, true)?;
        self.out_conv.forward(&h)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// The bf16 spatial ResBlock computed a few items at a time against the f32 block on the same weights.
    /// Error model (`tests/half.rs`): ≈ 0.82u relative per product with both operands rounded, independent
    /// products adding in quadrature; the longest chain here is conv1 → conv2 beside the 1×1 skip, ≤ 3
    /// products, so √3·0.82u ≈ 1.4u, and the bound takes twice that. A chunk written at the wrong items or
    /// with another item's embedding is an O(1) error.
    #[test]
    fn chunked_bf16_resblock_matches_f32() {
        let dev = Device::Cpu;
        // 3 channels a norm group: a per-item bias is not normalised away.
        let (i, o, emb) = (128, 96, 48);
        for seed in [4u64, 10] {
            let load = |w: &Weights| ResBlock::load(w, "r", i, o, emb, 1e-5, None).unwrap();
            let f32b = load(&Weights::random(seed, &dev));
            let bf16b = load(&Weights::random(seed, &dev).with_dtype(DType::BF16));
            assert!(matches!(&bf16b.conv1, Either::Spatial(Conv { w: ConvWeight::Bf16(_), .. })));
            let (n, h, w) = (5, 6, 7);
            let x = Tensor::randn(0f32, 1.0, (n, i, h, w), &dev).unwrap();
            let e = Tensor::randn(0f32, 1.0, (n, emb), &dev).unwrap();
            let want = f32b.forward(&x, &e, n, None).unwrap();
            let whole = bf16b.forward_chunked(&x, &e, n, None, usize::MAX).unwrap();
            let u = 1.0f32 / 256.0;
            for items in [1, 2, n] {
                let got = bf16b.forward_chunked(&x, &e, n, None, items * h * w).unwrap();
                let err = (&got - &want).unwrap().sqr().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap().sqrt();
                let rel = err / want.sqr().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap().sqrt();
                eprintln!("seed {seed}, {items} items a chunk: relative L2 {rel:.2e} ({:.2} u)", rel / u);
                assert!(rel > 0.0 && rel <= 2.0 * 3f32.sqrt() * 0.82 * u, "seed {seed}, {items} items: {rel:.2e} ({:.2} u)", rel / u);
                // Items are independent: the chunks give the whole batch's numbers.
                let d = (&got - &whole).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
                assert_eq!(d, 0.0, "seed {seed}, {items} items a chunk differs from the whole batch");
            }
        }
    }
}
