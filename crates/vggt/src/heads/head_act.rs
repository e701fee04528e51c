//! Output activations (`head_act.py`).

use candle_core::{Result, Tensor};

/// `sign(y)·(exp(|y|) − 1)` (`inverse_log_transform`).
pub fn inverse_log_transform(y: &Tensor) -> Result<Tensor> {
    let a = y.abs()?;
    y.sign()?.mul(&(a.exp()? - 1.0)?)
}

/// How the DPT head's point channels are activated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `exp` (the depth head).
    Exp,
    /// `inv_log` (the point head).
    InvLog,
}

/// `activate_head` with `conf_activation="expp1"`: `out (N, C+1, H, W)` → values `(N, H, W, C)` and confidence
/// `1 + exp(last channel)`, `(N, H, W)`.
pub fn activate_head(out: &Tensor, act: Activation) -> Result<(Tensor, Tensor)> {
    let fmap = out.permute((0, 2, 3, 1))?;
    let c = fmap.dim(3)? - 1;
    let xyz = fmap.narrow(3, 0, c)?.contiguous()?;
    let conf = fmap.narrow(3, c, 1)?.squeeze(3)?.contiguous()?;
    let pts = match act {
        Activation::Exp => xyz.exp()?,
        Activation::InvLog => inverse_log_transform(&xyz)?,
    };
    Ok((pts, (conf.exp()? + 1.0)?))
}

/// `activate_pose` with the camera head's choices: translation and quaternion linear, field of view ReLU.
pub fn activate_pose(enc: &Tensor) -> Result<Tensor> {
    let d = enc.rank() - 1;
    let tq = enc.narrow(d, 0, 7)?;
    let fl = enc.narrow(d, 7, enc.dim(d)? - 7)?.relu()?;
    Tensor::cat(&[&tq, &fl], d)
}
