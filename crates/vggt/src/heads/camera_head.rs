//! `CameraHead`: each frame's camera token of the last aggregated layer, normalised, refined `num_iterations`
//! times: the current encoding (zeros → `empty_pose_tokens` at first) is embedded and modulates the tokens
//! adaLN-style (shift, scale, gate), a trunk of blocks attends across frames, and a small MLP adds a delta to
//! the (pre-activation) encoding. Each iteration's encoding is returned activated (`absT_quaR_FoV`: translation
//! and quaternion linear, fields of view ReLU). f32 whatever the trunk's dtype, as upstream.

use candle_core::{DType, Result, Tensor};
use candle_nn::VarBuilder;

use super::head_act::activate_pose;
use crate::config::CameraHeadConfig;
use crate::layers::block::{Block, BlockSpec};
use crate::layers::mlp::Mlp;
use crate::layers::{LayerNorm, Linear, DINO_LN_EPS, TORCH_LN_EPS};

/// `absT_quaR_FoV`: 3 translation, 4 quaternion (xyzw), 2 fields of view (vertical, horizontal).
pub const TARGET_DIM: usize = 9;

#[derive(Debug, Clone)]
pub struct CameraHead {
    pub trunk: Vec<Block>,
    pub token_norm: LayerNorm,
    pub trunk_norm: LayerNorm,
    pub empty_pose_tokens: Tensor,
    pub embed_pose: Linear,
    /// `poseLN_modulation.1` (after a SiLU).
    pub pose_ln_modulation: Linear,
    pub adaln_norm: LayerNorm,
    pub pose_branch: Mlp,
    pub num_iterations: usize,
}

impl CameraHead {
    pub fn new(vb: VarBuilder, dim_in: usize, cfg: &CameraHeadConfig) -> Result<Self> {
        let spec = BlockSpec {
            dim: dim_in,
            num_heads: cfg.num_heads,
            mlp_ratio: cfg.mlp_ratio,
            qk_norm: false,
            norm_eps: TORCH_LN_EPS,
            layer_scale: true,
            pack_bf16: false,
        };
        Ok(Self {
            trunk: (0..cfg.trunk_depth).map(|i| Block::new(vb.pp("trunk").pp(i), spec)).collect::<Result<Vec<_>>>()?,
            token_norm: LayerNorm::new(vb.pp("token_norm"), dim_in, TORCH_LN_EPS)?,
            trunk_norm: LayerNorm::new(vb.pp("trunk_norm"), dim_in, TORCH_LN_EPS)?,
            empty_pose_tokens: vb.get((1, 1, TARGET_DIM), "empty_pose_tokens")?,
            embed_pose: Linear::new(vb.pp("embed_pose"), TARGET_DIM, dim_in, true)?,
            pose_ln_modulation: Linear::new(vb.pp("poseLN_modulation").pp(1), dim_in, 3 * dim_in, true)?,
            adaln_norm: LayerNorm::no_affine(dim_in, DINO_LN_EPS, vb.device())?,
            pose_branch: Mlp::new(vb.pp("pose_branch"), dim_in, dim_in / 2, TARGET_DIM, true)?,
            num_iterations: cfg.num_iterations,
        })
    }

    /// `last (S, P, 2C)`: the last aggregated layer → the activated encoding of every iteration, `(S, 9)` each.
    pub fn forward(&self, last: &Tensor) -> Result<Vec<Tensor>> {
        let (s, _, c) = last.dims3()?;
        let pose_tokens = self.token_norm.forward(&last.narrow(1, 0, 1)?.to_dtype(DType::F32)?.reshape((1, s, c))?)?;
        let normed = self.adaln_norm.forward(&pose_tokens)?;
        let mut enc: Option<Tensor> = None;
        let mut out = Vec::with_capacity(self.num_iterations);
        for _ in 0..self.num_iterations {
            let input = match &enc {
                None => self.embed_pose.forward(&self.empty_pose_tokens.broadcast_as((1, s, TARGET_DIM))?.contiguous()?)?,
                Some(e) => self.embed_pose.forward(e)?,
            };
            let m = self.pose_ln_modulation.forward(&candle_nn::ops::silu(&input)?)?;
            let (shift, scale, gate) = (m.narrow(2, 0, c)?, m.narrow(2, c, c)?, m.narrow(2, 2 * c, c)?);
            // gate · (norm(x)·(1 + scale) + shift) + x
            let modulated = ((gate * (normed.mul(&(scale + 1.0)?)? + shift)?)? + &pose_tokens)?;
            let mut x = modulated;
            for b in &self.trunk {
                x = b.forward(&x, None)?;
            }
            let delta = self.pose_branch.forward(&self.trunk_norm.forward(&x)?)?;
            let e = match enc {
                None => delta,
                Some(e) => (e + delta)?,
            };
            out.push(activate_pose(&e)?.reshape((s, TARGET_DIM))?);
            enc = Some(e);
        }
        Ok(out)
    }
}
