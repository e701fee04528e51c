//! `UNetModel` of `ldm_unet/unet.py` with the depth predictor's settings: `num_res_blocks` ResBlocks per level,
//! `postnorm=True`, `num_head_channels=32`, conv resampling, middle block ResBlock–Identity–ResBlock, and
//! `use_cross_view_self_attn=True` (attention over the tokens of all views of a batch element jointly).
//!
//! The batch dimension is `(v b)` (view-major), as the depth predictor feeds it.

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

use super::util::{Act, Conv1x1, Conv2d, GroupNorm};
use mvsplat360_nn::attention::fused_attention;
use mvsplat360_nn::attention_bf16::fused_attention_bf16;
use mvsplat360_nn::softmax::softmax_last;

/// Post-norm residual block: `skip(x) + SiLU(GN(conv(SiLU(GN(conv(x))))))`.
#[derive(Debug, Clone)]
pub struct ResBlock {
    in_conv: Conv2d,
    in_norm: GroupNorm,
    out_conv: Conv2d,
    out_norm: GroupNorm,
    skip: Option<Conv2d>,
}

impl ResBlock {
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize) -> Result<Self> {
        Ok(Self {
            in_conv: Conv2d::same3(vb.pp("in_layers").pp("0"), c_in, c_out)?,
            in_norm: GroupNorm::unet(vb.pp("in_layers").pp("1"), c_out)?,
            out_conv: Conv2d::same3(vb.pp("out_layers").pp("0"), c_out, c_out)?,
            out_norm: GroupNorm::unet(vb.pp("out_layers").pp("1"), c_out)?,
            skip: if c_in != c_out { Some(Conv2d::new(vb.pp("skip_connection"), c_in, c_out, 1, 1, 0)?) } else { None },
        })
    }

    pub fn pack_bf16(&mut self) -> Result<()> {
        self.in_conv.pack_bf16()?;
        self.out_conv.pack_bf16()?;
        self.skip.as_mut().map(Conv2d::pack_bf16).transpose()?;
        Ok(())
    }
}

impl Module for ResBlock {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = self.in_norm.forward_act(&self.in_conv.forward(x)?, Act::Silu)?;
        let h = self.out_norm.forward_act(&self.out_conv.forward(&h)?, Act::Silu)?;
        match &self.skip {
            Some(s) => s.forward(x)? + h,
            None => x + h,
        }
    }
}

/// Post-norm self-attention block with the legacy QKV split (heads first, then q/k/v), q and k each scaled
/// by ch^(-1/4), over the tokens of all `num_frames` views jointly.
#[derive(Debug, Clone)]
pub struct AttentionBlock {
    qkv: Conv1x1,
    proj_out: Conv1x1,
    norm: GroupNorm,
    num_heads: usize,
    num_frames: usize,
}

impl AttentionBlock {
    pub fn new(vb: VarBuilder, channels: usize, num_head_channels: usize, num_frames: usize) -> Result<Self> {
        if num_head_channels == 0 || channels % num_head_channels != 0 {
            candle_core::bail!("AttentionBlock at `{}`: {channels} channels not divisible by {num_head_channels}", vb.prefix());
        }
        Ok(Self {
            qkv: Conv1x1::new(vb.pp("qkv"), channels, 3 * channels)?,
            proj_out: Conv1x1::new(vb.pp("proj_out"), channels, channels)?,
            norm: GroupNorm::unet(vb.pp("norm"), channels)?,
            num_heads: channels / num_head_channels,
            num_frames: num_frames.max(1),
        })
    }

    /// qkv and proj_out packed in bf16; the attention then multiplies in bf16 too (see [`crate::bf16`]).
    pub fn pack_bf16(&mut self) -> Result<()> {
        self.qkv.pack_bf16()?;
        self.proj_out.pack_bf16()
    }

    /// `qkv [(v b), 3C, T]` → attention output `[(v b), C, T]`.
    fn attention(&self, qkv: &Tensor, num_frames: usize) -> Result<Tensor> {
        let (vb, width, t) = qkv.dims3()?;
        let v = num_frames.max(1);
        if vb % v != 0 {
            candle_core::bail!("AttentionBlock: batch {vb} is not a multiple of the {v} views it attends across");
        }
        let b = vb / v;
        // "(v b) n t -> b n (v t)"
        let qkv = qkv.reshape((v, b, width, t))?.permute((1, 2, 0, 3))?.reshape((b, width, v * t))?;
        let l = v * t;
        let ch = width / (3 * self.num_heads);
        let qkv = qkv.reshape((b * self.num_heads, 3 * ch, l))?;
        let scale = 1.0 / (ch as f64).sqrt().sqrt();
        let q = (qkv.narrow(1, 0, ch)? * scale)?;
        let k = (qkv.narrow(1, ch, ch)? * scale)?;
        let vv = qkv.narrow(1, 2 * ch, ch)?;
        let a = if ![&q, &k, &vv].iter().any(|t| t.track_op()) {
            // Inference: token-major operands, scores never materialised.
            let tok = |x: &Tensor| x.transpose(1, 2)?.contiguous();
            let _prof = mvsplat360_nn::prof::scope("encoder.unet.attention.kernel");
            let (q, k, vv) = (tok(&q)?, tok(&k)?, tok(&vv)?);
            // A packed block multiplies attention in bf16 too (f32 where the CPU lacks the feature).
            let a = if self.qkv.weight.is_bf16() { fused_attention_bf16(&q, &k, &vv, None)? } else { fused_attention(&q, &k, &vv, None)? };
            a.transpose(1, 2)?.contiguous()?
        } else {
            // weight[b, t, s] = Σ_c q[b,c,t] k[b,c,s]
            let w = q.transpose(1, 2)?.contiguous()?.matmul(&k.contiguous()?)?;
            let w = softmax_last(&w)?;
            // a[b, c, t] = Σ_s w[b,t,s] v[b,c,s]
            vv.contiguous()?.matmul(&w.transpose(1, 2)?.contiguous()?)?
        };
        let a = a.reshape((b, self.num_heads * ch, l))?;
        // "b n (v t) -> (v b) n t"
        a.reshape((b, self.num_heads * ch, v, t))?.permute((2, 0, 1, 3))?.reshape((vb, self.num_heads * ch, t))
    }
}

impl AttentionBlock {
    /// `x [(v b), C, ...]`, attending jointly over the `num_frames` views of each batch element.
    pub fn forward_frames(&self, x: &Tensor, num_frames: usize) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let (n, c) = (dims[0], dims[1]);
        let xf = x.reshape((n, c, ()))?;
        let _prof = mvsplat360_nn::prof::scope("encoder.unet.attention_block");
        let h = self.attention(&self.qkv.forward(&xf)?, num_frames)?;
        let h = self.norm.forward_act(&self.proj_out.forward(&h)?, Act::None)?;
        (xf + h)?.reshape(dims.as_slice())
    }
}

impl Module for AttentionBlock {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_frames(x, self.num_frames)
    }
}

#[derive(Debug, Clone)]
enum Layer {
    Conv(Conv2d),
    Res(ResBlock),
    Attn(AttentionBlock),
    Down(Conv2d),
    /// Nearest ×2 then 3×3 conv.
    Up(Conv2d),
}

impl Layer {
    fn forward(&self, x: &Tensor, num_frames: usize) -> Result<Tensor> {
        match self {
            Layer::Conv(c) | Layer::Down(c) => c.forward(x),
            Layer::Res(r) => r.forward(x),
            Layer::Attn(a) => a.forward_frames(x, num_frames),
            Layer::Up(c) => c.forward_up2(x),
        }
    }

    fn pack_bf16(&mut self) -> Result<()> {
        match self {
            Layer::Conv(c) | Layer::Down(c) | Layer::Up(c) => c.pack_bf16(),
            Layer::Res(r) => r.pack_bf16(),
            Layer::Attn(a) => a.pack_bf16(),
        }
    }
}

/// Settings of one UNet instance.
#[derive(Debug, Clone)]
pub struct UNetCfg {
    pub in_channels: usize,
    pub model_channels: usize,
    pub out_channels: usize,
    pub num_res_blocks: usize,
    pub attention_resolutions: Vec<usize>,
    pub channel_mult: Vec<usize>,
    pub num_head_channels: usize,
    pub num_frames: usize,
}

#[derive(Debug, Clone)]
pub struct UNetModel {
    input_blocks: Vec<Vec<Layer>>,
    middle_block: (ResBlock, ResBlock),
    output_blocks: Vec<Vec<Layer>>,
    out_conv: Conv2d,
    out_norm: GroupNorm,
    /// Spatial sizes must be multiples of this (one factor 2 per down-sampling).
    pub size_multiple: usize,
    num_frames: usize,
}

impl UNetModel {
    pub fn new(vb: VarBuilder, cfg: &UNetCfg) -> Result<Self> {
        let mc = cfg.model_channels;
        let nh = cfg.num_head_channels;
        let attn = |ds: usize| cfg.attention_resolutions.contains(&ds);
        let vin = vb.pp("input_blocks");
        let mut input_blocks = vec![vec![Layer::Conv(Conv2d::same3(vin.pp("0").pp("0"), cfg.in_channels, mc)?)]];
        let mut chans = vec![mc];
        let mut ch = mc;
        let mut ds = 1;
        for (level, &mult) in cfg.channel_mult.iter().enumerate() {
            for _ in 0..cfg.num_res_blocks {
                let vbk = vin.pp(input_blocks.len().to_string());
                let mut layers = vec![Layer::Res(ResBlock::new(vbk.pp("0"), ch, mult * mc)?)];
                ch = mult * mc;
                if attn(ds) {
                    layers.push(Layer::Attn(AttentionBlock::new(vbk.pp("1"), ch, nh, cfg.num_frames)?));
                }
                input_blocks.push(layers);
                chans.push(ch);
            }
            if level + 1 != cfg.channel_mult.len() {
                let vbk = vin.pp(input_blocks.len().to_string());
                input_blocks.push(vec![Layer::Down(Conv2d::new(vbk.pp("0").pp("op"), ch, ch, 3, 2, 1)?)]);
                chans.push(ch);
                ds *= 2;
            }
        }
        let vm = vb.pp("middle_block");
        let middle_block = (ResBlock::new(vm.pp("0"), ch, ch)?, ResBlock::new(vm.pp("2"), ch, ch)?);
        let vout = vb.pp("output_blocks");
        let mut output_blocks = Vec::new();
        for (level, &mult) in cfg.channel_mult.iter().enumerate().rev() {
            for i in 0..=cfg.num_res_blocks {
                let ich = chans.pop().ok_or_else(|| candle_core::Error::Msg("UNet: skip-channel bookkeeping".into()))?;
                let vbk = vout.pp(output_blocks.len().to_string());
                let mut layers = vec![Layer::Res(ResBlock::new(vbk.pp("0"), ch + ich, mc * mult)?)];
                ch = mc * mult;
                if attn(ds) {
                    layers.push(Layer::Attn(AttentionBlock::new(vbk.pp("1"), ch, nh, cfg.num_frames)?));
                }
                if level > 0 && i == cfg.num_res_blocks {
                    let idx = layers.len().to_string();
                    layers.push(Layer::Up(Conv2d::same3(vbk.pp(idx).pp("conv"), ch, ch)?));
                    ds /= 2;
                }
                output_blocks.push(layers);
            }
        }
        let vo = vb.pp("out");
        Ok(Self {
            input_blocks,
            middle_block,
            output_blocks,
            out_conv: Conv2d::same3(vo.pp("0"), mc, cfg.out_channels)?,
            out_norm: GroupNorm::unet(vo.pp("1"), cfg.out_channels)?,
            size_multiple: 1 << cfg.channel_mult.len().saturating_sub(1),
            num_frames: cfg.num_frames.max(1),
        })
    }
}

impl Module for UNetModel {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_frames(x, self.num_frames)
    }
}

impl UNetModel {
    /// Every convolution (and the attention blocks' 1×1 projections) packed in bf16 (CPU inference).
    pub fn pack_bf16(&mut self) -> Result<()> {
        for l in self.input_blocks.iter_mut().chain(self.output_blocks.iter_mut()).flatten() {
            l.pack_bf16()?;
        }
        self.middle_block.0.pack_bf16()?;
        self.middle_block.1.pack_bf16()?;
        self.out_conv.pack_bf16()
    }

    /// `x [(v b), C, H, W]`; attention layers attend across the `num_frames` views of each batch element.
    pub fn forward_frames(&self, x: &Tensor, num_frames: usize) -> Result<Tensor> {
        let (_, _, h, w) = x.dims4()?;
        if h % self.size_multiple != 0 || w % self.size_multiple != 0 {
            candle_core::bail!("UNet: input {h}x{w} must be a multiple of {} in both dimensions", self.size_multiple);
        }
        let mut hs = Vec::with_capacity(self.input_blocks.len());
        let mut h = x.clone();
        for block in &self.input_blocks {
            for l in block {
                h = l.forward(&h, num_frames)?;
            }
            hs.push(h.clone());
        }
        h = self.middle_block.0.forward(&h)?;
        h = self.middle_block.1.forward(&h)?;
        for block in &self.output_blocks {
            let skip = hs.pop().ok_or_else(|| candle_core::Error::Msg("UNet: skip stack empty".into()))?;
            h = Tensor::cat(&[&h, &skip], 1)?;
            for l in block {
                h = l.forward(&h, num_frames)?;
            }
        }
        self.out_norm.forward_act(&self.out_conv.forward(&h)?, Act::Silu)
    }
}
