//! The encoder stage's image losses: MSE and the scheduled LPIPS term.

use super::*;

/// The 3DGS losses of one example: (total, mse, lpips).
pub fn losses(cfg: &TrainConfig, lpips: Option<&Lpips>, step: u64, pred: &Tensor, gt: &Tensor) -> Result<(Tensor, Tensor, Option<Tensor>)> {
    let mse = crate::loss::mse(pred, gt)?;
    let mut total = (&mse * cfg.train.mse_weight)?;
    let lp = lpips_term(cfg, lpips, step, pred, gt)?;
    if let Some(v) = &lp {
        total = (total + (v * cfg.train.lpips_weight)?)?;
    }
    Ok((total, mse, lp))
}

/// LPIPS of `pred` against `gt` (unweighted) when the term is on at this step.
pub(super) fn lpips_term(cfg: &TrainConfig, lpips: Option<&Lpips>, step: u64, pred: &Tensor, gt: &Tensor) -> Result<Option<Tensor>> {
    match lpips.filter(|_| step >= cfg.train.lpips_after_step && cfg.train.lpips_weight > 0.0) {
        Some(l) => Ok(Some(crate::loss::lpips(l, pred, gt)?)),
        None => Ok(None),
    }
}
