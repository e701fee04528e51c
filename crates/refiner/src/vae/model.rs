//! sgm `diffusionmodules/model.py`: `ResnetBlock`, `AttnBlock`, `Downsample`, `Upsample`, `Encoder`.
//! Fast inference kernels by default; composed differentiable ops in the kernels' differentiable mode.

use candle_core::{Result, Tensor};
use mvsplat360_nn::conv::{Conv2dConfig, ConvEpilogue};

use super::AutoencoderConfig;
use crate::unet::util::{attention, group_norm, ConvWeight};
use crate::weights::StrictWeights;

/// sgm `Normalize`: GroupNorm(32, eps 1e-6).
pub(crate) const NORM_EPS: f64 = 1e-6;

#[derive(Debug)]
pub(crate) struct Conv {
    pub w: ConvWeight,
    pub b: Tensor,
    pub cfg: Conv2dConfig,
}

impl Conv {
    pub fn load(w: &StrictWeights, p: &str, i: usize, o: usize, k: usize, stride: usize, padding: usize) -> Result<Self> {
        Ok(Self {
            w: ConvWeight::new(w.get(&format!("{p}.weight"), &[o, i, k, k])?, w.store())?,
            b: w.get(&format!("{p}.bias"), &[o])?,
            cfg: Conv2dConfig { padding, stride, dilation: 1 },
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_fused(x, ConvEpilogue::default())
    }

    pub fn forward_fused(&self, x: &Tensor, epi: ConvEpilogue) -> Result<Tensor> {
        let _p = mvsplat360_nn::prof::scope(if self.cfg.stride == 1 { "vae.conv" } else { "vae.conv_stride2" });
        self.w.conv(x, Some(&self.b), self.cfg, epi)
    }
}

#[derive(Debug)]
pub(crate) struct GroupNorm {
    pub w: Tensor,
    pub b: Tensor,
    pub eps: f64,
}

impl GroupNorm {
    pub fn load(w: &StrictWeights, p: &str, c: usize, eps: f64) -> Result<Self> {
        Ok(Self { w: w.get(&format!("{p}.weight"), &[c])?, b: w.get(&format!("{p}.bias"), &[c])?, eps })
    }

    /// GroupNorm(32) with statistics pooled over `frames` consecutive items (a 3-D norm on (B,C,T,H,W)).
    pub fn forward(&self, x: &Tensor, frames: usize, silu: bool) -> Result<Tensor> {
        group_norm(x, 32, frames, &self.w, &self.b, self.eps, silu)
    }
}

/// sgm `ResnetBlock` without time embedding (the VAE passes temb = None).
#[derive(Debug)]
pub(crate) struct ResnetBlock {
    norm1: GroupNorm,
    conv1: Conv,
    norm2: GroupNorm,
    conv2: Conv,
    nin_shortcut: Option<Conv>,
}

impl ResnetBlock {
    pub fn load(w: &StrictWeights, p: &str, i: usize, o: usize) -> Result<Self> {
        Ok(Self {
            norm1: GroupNorm::load(w, &format!("{p}.norm1"), i, NORM_EPS)?,
            conv1: Conv::load(w, &format!("{p}.conv1"), i, o, 3, 1, 1)?,
            norm2: GroupNorm::load(w, &format!("{p}.norm2"), o, NORM_EPS)?,
            conv2: Conv::load(w, &format!("{p}.conv2"), o, o, 3, 1, 1)?,
            nin_shortcut: if i != o { Some(Conv::load(w, &format!("{p}.nin_shortcut"), i, o, 1, 1, 0)?) } else { None },
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = self.conv1.forward(&self.norm1.forward(x, 1, true)?)?;
        let hn = self.norm2.forward(&h, 1, true)?;
        drop(h);
        let skip = match &self.nin_shortcut {
            Some(s) => s.forward(x)?,
            None => x.clone(),
        };
        self.conv2.forward_fused(&hn, ConvEpilogue { residual: Some(&skip), ..Default::default() })
    }
}

/// sgm `AttnBlock` / `MemoryEfficientAttnBlock` (same weights): single-head self-attention over H·W,
/// computed in query chunks so that the score buffer stays below `max_score_elems` floats.
#[derive(Debug)]
pub(crate) struct AttnBlock {
    norm: GroupNorm,
    /// q, k, v, proj_out as (out, in) matrices.
    q: (Tensor, Tensor),
    k: (Tensor, Tensor),
    v: (Tensor, Tensor),
    proj_out: (Tensor, Tensor),
    max_score_elems: usize,
}

impl AttnBlock {
    pub fn load(w: &StrictWeights, p: &str, c: usize, max_score_elems: usize) -> Result<Self> {
        let lin = |n: &str| -> Result<(Tensor, Tensor)> {
            Ok((w.get(&format!("{p}.{n}.weight"), &[c, c, 1, 1])?.reshape((c, c))?, w.get(&format!("{p}.{n}.bias"), &[c])?))
        };
        Ok(Self {
            norm: GroupNorm::load(w, &format!("{p}.norm"), c, NORM_EPS)?,
            q: lin("q")?,
            k: lin("k")?,
            v: lin("v")?,
            proj_out: lin("proj_out")?,
            max_score_elems,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let _p = mvsplat360_nn::prof::scope("vae.attn");
        let (n, c, h, w) = x.dims4()?;
        let tokens = self.norm.forward(x, 1, false)?.reshape((n, c, h * w))?.transpose(1, 2)?.contiguous()?;
        let lin = |t: &Tensor, (wt, b): &(Tensor, Tensor)| -> Result<Tensor> {
            t.reshape((n * h * w, c))?.matmul(&wt.t()?)?.broadcast_add(b)?.reshape((n, h * w, c))
        };
        let q = lin(&tokens, &self.q)?;
        let k = lin(&tokens, &self.k)?;
        let v = lin(&tokens, &self.v)?;
        drop(tokens);
        let a = attention(&q, &k, &v, 1, self.max_score_elems)?;
        let o = lin(&a, &self.proj_out)?;
        x + o.transpose(1, 2)?.reshape((n, c, h, w))?
    }
}

/// sgm `Downsample` with conv: zero-pad right/bottom by one, 3×3 conv stride 2.
#[derive(Debug)]
pub(crate) struct Downsample {
    conv: Conv,
}

impl Downsample {
    pub fn load(w: &StrictWeights, p: &str, c: usize) -> Result<Self> {
        Ok(Self { conv: Conv::load(w, &format!("{p}.conv"), c, c, 3, 2, 0)? })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let x = x.pad_with_zeros(3, 0, 1)?.pad_with_zeros(2, 0, 1)?;
        self.conv.forward(&x)
    }
}

/// sgm `Upsample` with conv: nearest ×2, 3×3 conv.
#[derive(Debug)]
pub(crate) struct Upsample {
    conv: Conv,
}

impl Upsample {
    pub fn load(w: &StrictWeights, p: &str, c: usize) -> Result<Self> {
        Ok(Self { conv: Conv::load(w, &format!("{p}.conv"), c, c, 3, 1, 1)? })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.conv.forward_fused(x, ConvEpilogue { upsample2x: true, ..Default::default() })
    }
}

/// sgm `Encoder` (no attention inside the levels: SVD's `attn_resolutions` is empty).
#[derive(Debug)]
pub struct Encoder {
    conv_in: Conv,
    /// Per level: its ResnetBlocks and the optional Downsample.
    down: Vec<(Vec<ResnetBlock>, Option<Downsample>)>,
    mid_block_1: ResnetBlock,
    mid_attn_1: AttnBlock,
    mid_block_2: ResnetBlock,
    norm_out: GroupNorm,
    conv_out: Conv,
}

impl Encoder {
    pub(crate) fn load(w: &StrictWeights, cfg: &AutoencoderConfig) -> Result<Self> {
        let ch = cfg.ch;
        let conv_in = Conv::load(w, "encoder.conv_in", cfg.in_channels, ch, 3, 1, 1)?;
        let mut block_in = ch;
        let mut down = Vec::new();
        let levels = cfg.ch_mult.len();
        for (l, &mult) in cfg.ch_mult.iter().enumerate() {
            let block_out = ch * mult;
            let mut blocks = Vec::new();
            for j in 0..cfg.num_res_blocks {
                blocks.push(ResnetBlock::load(w, &format!("encoder.down.{l}.block.{j}"), block_in, block_out)?);
                block_in = block_out;
            }
            let ds = if l + 1 != levels { Some(Downsample::load(w, &format!("encoder.down.{l}.downsample"), block_in)?) } else { None };
            down.push((blocks, ds));
        }
        let zc = if cfg.double_z { 2 * cfg.z_channels } else { cfg.z_channels };
        Ok(Self {
            conv_in,
            down,
            mid_block_1: ResnetBlock::load(w, "encoder.mid.block_1", block_in, block_in)?,
            mid_attn_1: AttnBlock::load(w, "encoder.mid.attn_1", block_in, cfg.attn_max_score_elems)?,
            mid_block_2: ResnetBlock::load(w, "encoder.mid.block_2", block_in, block_in)?,
            norm_out: GroupNorm::load(w, "encoder.norm_out", block_in, NORM_EPS)?,
            conv_out: Conv::load(w, "encoder.conv_out", block_in, zc, 3, 1, 1)?,
        })
    }

    /// (N, 3, H, W) in [-1, 1] → (N, 2z, H/2^(L-1), W/2^(L-1)) moments.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut h = self.conv_in.forward(x)?;
        for (blocks, ds) in &self.down {
            for b in blocks {
                h = b.forward(&h)?;
            }
            if let Some(d) = ds {
                h = d.forward(&h)?;
            }
        }
        h = self.mid_block_1.forward(&h)?;
        h = self.mid_attn_1.forward(&h)?;
        h = self.mid_block_2.forward(&h)?;
        self.conv_out.forward(&self.norm_out.forward(&h, 1, true)?)
    }
}
