//! sgm `autoencoding/temporal_ae.py`: `VideoResBlock`, `AE3DConv`, `VideoDecoder` (`time_mode: conv-only`,
//! i.e. temporal mixing in every ResnetBlock and after the last conv; the mid attention is spatial only).

use candle_core::{Result, Tensor};

use super::model::{AttnBlock, Conv, GroupNorm, ResnetBlock, Upsample, NORM_EPS};
use super::AutoencoderConfig;
use crate::unet::util::{blend_learned, sigmoid_scalar, TemporalWeight};
use crate::weights::StrictWeights;

/// GroupNorm eps of the temporal `time_stack` (openaimodel `normalization` = GroupNorm32 default 1e-5).
const TIME_NORM_EPS: f64 = 1e-5;

/// Conv3d with kernel (kt, 1, 1), zero padding (kt/2, 0, 0), on (B·T, C, H, W) frames.
/// One gemm per output frame over the stacked valid neighbour frames: no buffer larger than one frame
/// beyond the output, which matters at 14 frames × 128 channels × 512×896.
#[derive(Debug)]
pub(crate) struct TemporalConv {
    w: TemporalWeight,
    b: Tensor,
    kt: usize,
    cin: usize,
}

impl TemporalConv {
    pub fn load(w: &StrictWeights, p: &str, i: usize, o: usize, kt: usize) -> Result<Self> {
        let w5 = w.get(&format!("{p}.weight"), &[o, i, kt, 1, 1])?;
        Ok(Self { w: TemporalWeight::new(w5, o, i, kt, w.is_trainable(), w.store())?, b: w.get(&format!("{p}.bias"), &[o])?, kt, cin: i })
    }

    pub fn forward(&self, x: &Tensor, frames: usize) -> Result<Tensor> {
        self.forward_fused(x, frames, None, 1.0)
    }

    /// `residual + scale·conv(x)`.
    pub fn forward_fused(&self, x: &Tensor, frames: usize, residual: Option<&Tensor>, scale: f32) -> Result<Tensor> {
        let _p = mvsplat360_nn::prof::scope("vae.temporal_conv");
        let (_, c, _, _) = x.dims4()?;
        if c != self.cin {
            candle_core::bail!("temporal conv: input {:?}, expected {} channels", x.dims(), self.cin);
        }
        self.w.conv(x, &self.b, self.kt, frames, None, residual, scale)
    }
}

/// openaimodel `ResBlock` with dims=3, no time embedding, same in/out channels (`time_stack`).
#[derive(Debug)]
struct TimeStack {
    in_norm: GroupNorm,
    in_conv: TemporalConv,
    out_norm: GroupNorm,
    out_conv: TemporalConv,
}

impl TimeStack {
    fn load(w: &StrictWeights, p: &str, c: usize, kt: usize) -> Result<Self> {
        Ok(Self {
            in_norm: GroupNorm::load(w, &format!("{p}.in_layers.0"), c, TIME_NORM_EPS)?,
            in_conv: TemporalConv::load(w, &format!("{p}.in_layers.2"), c, c, kt)?,
            out_norm: GroupNorm::load(w, &format!("{p}.out_layers.0"), c, TIME_NORM_EPS)?,
            out_conv: TemporalConv::load(w, &format!("{p}.out_layers.3"), c, c, kt)?,
        })
    }

    /// `x + scale·h` (scale folds the AlphaBlender into the last conv).
    fn forward(&self, x: &Tensor, frames: usize, scale: f32) -> Result<Tensor> {
        let h = self.in_conv.forward(&self.in_norm.forward(x, frames, true)?, frames)?;
        let hn = self.out_norm.forward(&h, frames, true)?;
        drop(h);
        self.out_conv.forward_fused(&hn, frames, Some(x), scale)
    }
}

/// `VideoResBlock`: spatial `ResnetBlock`, then `time_stack`, merged as
/// α·temporal + (1−α)·spatial with α = sigmoid(mix_factor) (merge_strategy `learned`).
#[derive(Debug)]
pub(crate) struct VideoResBlock {
    spatial: ResnetBlock,
    time_stack: TimeStack,
    alpha: f64,
    /// Trainable weights: the stored `mix_factor` `Var`, blended as a tensor per call so that it gets a gradient
    /// and its updates are seen.
    mix: Option<Tensor>,
}

impl VideoResBlock {
    pub fn load(w: &StrictWeights, p: &str, i: usize, o: usize, kt: usize) -> Result<Self> {
        let mix = w.get(&format!("{p}.mix_factor"), &[1])?;
        Ok(Self {
            spatial: ResnetBlock::load(w, p, i, o)?,
            time_stack: TimeStack::load(w, &format!("{p}.time_stack"), o, kt)?,
            alpha: sigmoid_scalar(&mix)?,
            mix: w.is_trainable().then_some(mix),
        })
    }

    pub fn forward(&self, x: &Tensor, frames: usize) -> Result<Tensor> {
        let spatial = {
            let _p = mvsplat360_nn::prof::scope("vae.resblock_spatial");
            self.spatial.forward(x)?
        };
        let _p = mvsplat360_nn::prof::scope("vae.resblock_temporal+blend");
        if let Some(mix) = &self.mix {
            let temporal = self.time_stack.forward(&spatial, frames, 1.0)?;
            return blend_learned(&temporal, &spatial, mix);
        }
        // alpha·(xs + h) + (1 − alpha)·xs = xs + alpha·h
        self.time_stack.forward(&spatial, frames, self.alpha as f32)
    }
}

/// sgm `VideoDecoder` (`Decoder` with VideoResBlocks and an `AE3DConv` output conv).
#[derive(Debug)]
pub struct VideoDecoder {
    conv_in: Conv,
    mid_block_1: VideoResBlock,
    mid_attn_1: AttnBlock,
    /// None only for diffusers configs with `layers_per_block` 1 (their mid block then never runs the attention).
    mid_block_2: Option<VideoResBlock>,
    /// Levels from lowest resolution to highest (sgm `up[L-1] … up[0]`).
    up: Vec<(Vec<VideoResBlock>, Option<Upsample>)>,
    norm_out: GroupNorm,
    conv_out: Conv,
    time_mix_conv: TemporalConv,
}

impl VideoDecoder {
    pub(crate) fn load(w: &StrictWeights, cfg: &AutoencoderConfig) -> Result<Self> {
        let ch = cfg.ch;
        let kt = cfg.video_kernel_size[0];
        let levels = cfg.ch_mult.len();
        let mut block_in = ch * cfg.ch_mult[levels - 1];
        let conv_in = Conv::load(w, "decoder.conv_in", cfg.z_channels, block_in, 3, 1, 1)?;
        let mid_block_1 = VideoResBlock::load(w, "decoder.mid.block_1", block_in, block_in, kt)?;
        let mid_attn_1 = AttnBlock::load(w, "decoder.mid.attn_1", block_in, cfg.attn_max_score_elems)?;
        let mid_block_2 = if cfg.decoder_mid_res_blocks >= 2 { Some(VideoResBlock::load(w, "decoder.mid.block_2", block_in, block_in, kt)?) } else { None };
        let mut up = Vec::new();
        for l in (0..levels).rev() {
            let block_out = ch * cfg.ch_mult[l];
            let mut blocks = Vec::new();
            for j in 0..=cfg.num_res_blocks {
                blocks.push(VideoResBlock::load(w, &format!("decoder.up.{l}.block.{j}"), block_in, block_out, kt)?);
                block_in = block_out;
            }
            let us = if l != 0 { Some(Upsample::load(w, &format!("decoder.up.{l}.upsample"), block_in)?) } else { None };
            up.push((blocks, us));
        }
        Ok(Self {
            conv_in,
            mid_block_1,
            mid_attn_1,
            mid_block_2,
            up,
            norm_out: GroupNorm::load(w, "decoder.norm_out", block_in, NORM_EPS)?,
            conv_out: Conv::load(w, "decoder.conv_out", block_in, cfg.out_ch, 3, 1, 1)?,
            time_mix_conv: TemporalConv::load(w, "decoder.conv_out.time_mix_conv", cfg.out_ch, cfg.out_ch, kt)?,
        })
    }

    /// z (B·T, z, h, w), frames = T (the `timesteps` of one decode call) → (B·T, out_ch, 8h, 8w).
    pub fn forward(&self, z: &Tensor, frames: usize) -> Result<Tensor> {
        let _p = mvsplat360_nn::prof::scope("vae.decoder_total");
        let mut h = self.conv_in.forward(z)?;
        h = self.mid_block_1.forward(&h, frames)?;
        if let Some(b2) = &self.mid_block_2 {
            h = self.mid_attn_1.forward(&h)?;
            h = b2.forward(&h, frames)?;
        }
        for (blocks, us) in &self.up {
            for b in blocks {
                h = b.forward(&h, frames)?;
            }
            if let Some(u) = us {
                h = u.forward(&h)?;
            }
        }
        let _u = mvsplat360_nn::prof::scope("vae.out");
        let h = self.conv_out.forward(&self.norm_out.forward(&h, 1, true)?)?;
        self.time_mix_conv.forward(&h, frames)
    }
}
