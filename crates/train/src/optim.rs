//! Adam with parameter groups, PyTorch's `OneCycleLR` (cosine, no momentum cycling) and gradient-norm clipping,
//! as the official Lightning setup uses them; the state saves to and loads from safetensors exactly.

use std::collections::HashMap;

use candle_core::{DType, Tensor, Var};

use crate::error::{Result, TrainError};

/// PyTorch `OneCycleLR(max_lr, total_steps, pct_start, anneal_strategy="cos", cycle_momentum=False)` with the
/// default `div_factor = 25`, `final_div_factor = 1e4`, `three_phase = False`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OneCycle {
    pub max_lr: f64,
    pub total_steps: u64,
    pub pct_start: f64,
    pub div_factor: f64,
    pub final_div_factor: f64,
}

impl OneCycle {
    pub fn new(max_lr: f64, total_steps: u64, pct_start: f64) -> Self {
        Self { max_lr, total_steps, pct_start, div_factor: 25.0, final_div_factor: 1e4 }
    }

    /// The learning rate used by optimizer step `step` (0-based), as `get_lr()` after `step` scheduler steps.
    pub fn lr(&self, step: u64) -> f64 {
        let initial = self.max_lr / self.div_factor;
        let min = initial / self.final_div_factor;
        let total = self.total_steps.max(1) as f64;
        // PyTorch's phase ends: pct_start·total − 1 and total − 1 (float).
        let end1 = self.pct_start * total - 1.0;
        let end2 = total - 1.0;
        let s = (step as f64).min(end2);
        let cos = |start: f64, end: f64, pct: f64| end + (start - end) / 2.0 * ((std::f64::consts::PI * pct).cos() + 1.0);
        if s <= end1 {
            let pct = if end1 > 0.0 { s / end1 } else { 1.0 };
            cos(initial, self.max_lr, pct)
        } else {
            let pct = (s - end1) / (end2 - end1).max(f64::MIN_POSITIVE);
            cos(self.max_lr, min, pct)
        }
    }
}

/// One trainable tensor with its learning-rate multiplier (the group's lr = schedule lr × `lr_scale`).
pub struct Param {
    pub name: String,
    pub var: Var,
    pub lr_scale: f64,
}

/// Adam (PyTorch defaults: betas 0.9/0.999, eps 1e-8, no weight decay), with bias correction.
pub struct Adam {
    pub params: Vec<Param>,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub weight_decay: f64,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    /// Optimizer steps taken.
    pub t: u64,
}

impl Adam {
    pub fn new(params: Vec<Param>) -> Result<Self> {
        let zeros = |p: &Param| Tensor::zeros_like(p.var.as_tensor());
        let m = params.iter().map(zeros).collect::<candle_core::Result<Vec<_>>>()?;
        let v = params.iter().map(zeros).collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self { params, beta1: 0.9, beta2: 0.999, eps: 1e-8, weight_decay: 0.0, m, v, t: 0 })
    }

    /// One update with gradients `grads[i]` for `params[i]` (None = no gradient this step: left unchanged, as
    /// PyTorch skips parameters whose `.grad` is None).
    pub fn step(&mut self, grads: &[Option<Tensor>], lr: f64) -> Result<()> {
        self.t += 1;
        let bc1 = 1.0 - self.beta1.powi(self.t as i32);
        let bc2 = 1.0 - self.beta2.powi(self.t as i32);
        for (i, p) in self.params.iter().enumerate() {
            let Some(g) = &grads[i] else { continue };
            let w = p.var.as_tensor();
            let g = if self.weight_decay > 0.0 { (g + (w * self.weight_decay)?)? } else { g.clone() };
            let m = ((&self.m[i] * self.beta1)? + (&g * (1.0 - self.beta1))?)?;
            let v = ((&self.v[i] * self.beta2)? + (g.sqr()? * (1.0 - self.beta2))?)?;
            // PyTorch: p -= lr/bc1 · m / (sqrt(v)/sqrt(bc2) + eps)
            let denom = ((v.sqrt()? / bc2.sqrt())? + self.eps)?;
            let upd = ((&m / denom)? * (lr * p.lr_scale / bc1))?;
            p.var.set(&(w - upd)?.detach())?;
            self.m[i] = m.detach();
            self.v[i] = v.detach();
        }
        Ok(())
    }

    /// Moments and the step counter as named tensors (`m.<name>`, `v.<name>`, `t`).
    pub fn state_tensors(&self) -> Result<Vec<(String, Tensor)>> {
        let mut out = Vec::with_capacity(2 * self.params.len() + 1);
        for (i, p) in self.params.iter().enumerate() {
            out.push((format!("m.{}", p.name), self.m[i].to_device(&candle_core::Device::Cpu)?));
            out.push((format!("v.{}", p.name), self.v[i].to_device(&candle_core::Device::Cpu)?));
        }
        // u64 as two u32 words keeps the count exact in a float-free tensor.
        let t = Tensor::new(&[(self.t & 0xffff_ffff) as u32, (self.t >> 32) as u32], &candle_core::Device::Cpu)?;
        out.push(("t".into(), t));
        Ok(out)
    }

    pub fn load_state(&mut self, state: &HashMap<String, Tensor>) -> Result<()> {
        let missing = |k: String| TrainError::Checkpoint(format!("optimizer state has no `{k}` (was the checkpoint written with another config?)"));
        for (i, p) in self.params.iter().enumerate() {
            for (slot, key) in [(0, format!("m.{}", p.name)), (1, format!("v.{}", p.name))] {
                let t = state.get(&key).ok_or_else(|| missing(key.clone()))?;
                if t.dims() != p.var.dims() {
                    return Err(TrainError::Checkpoint(format!("optimizer `{key}` has shape {:?}, the model {:?}", t.dims(), p.var.dims())));
                }
                let t = t.to_dtype(DType::F32)?.to_device(p.var.device())?;
                if slot == 0 {
                    self.m[i] = t;
                } else {
                    self.v[i] = t;
                }
            }
        }
        let t = state.get("t").ok_or_else(|| missing("t".into()))?.to_vec1::<u32>()?;
        self.t = t[0] as u64 | ((t.get(1).copied().unwrap_or(0) as u64) << 32);
        Ok(())
    }
}

/// Total L2 norm of all gradients (PyTorch `clip_grad_norm_`, norm type 2).
pub fn grad_norm(grads: &[Option<Tensor>]) -> Result<f64> {
    let mut s = 0f64;
    for g in grads.iter().flatten() {
        s += g.sqr()?.sum_all()?.to_dtype(DType::F64)?.to_scalar::<f64>()?;
    }
    Ok(s.sqrt())
}

/// Scale gradients so their total norm is at most `max_norm` (`clip_coef = max_norm / (norm + 1e-6)`, applied
/// only when below 1, as PyTorch). Returns the norm before clipping.
pub fn clip_grad_norm(grads: &mut [Option<Tensor>], max_norm: f64) -> Result<f64> {
    let norm = grad_norm(grads)?;
    let coef = max_norm / (norm + 1e-6);
    if coef < 1.0 {
        for g in grads.iter_mut().flatten() {
            *g = (&*g * coef)?;
        }
    }
    Ok(norm)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Values of `torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=1e-3, total_steps=100, pct_start=0.1,
    /// anneal_strategy="cos", cycle_momentum=False)`: the lr after k scheduler steps, from the closed form of
    /// PyTorch's documented phases (start max_lr/25, peak at step 9, end (max_lr/25)/1e4 at step 99).
    #[test]
    fn one_cycle_closed_form() {
        let s = OneCycle::new(1e-3, 100, 0.1);
        assert!((s.lr(0) - 4e-5).abs() < 1e-12);
        assert!((s.lr(9) - 1e-3).abs() < 1e-12);
        assert!((s.lr(99) - 4e-9).abs() < 1e-15);
        // Step 4 of the warm-up: pct = 4/9 on PyTorch's cosine from 4e-5 up to 1e-3.
        let want = 1e-3 + (4e-5 - 1e-3) / 2.0 * ((std::f64::consts::PI * 4.0 / 9.0).cos() + 1.0);
        assert!((s.lr(4) - want).abs() < 1e-12);
        // Step 54: pct = 45/90 of the descent, the midpoint of 1e-3 and 4e-9.
        assert!((s.lr(54) - (1e-3 + 4e-9) / 2.0).abs() < 1e-12);
        // Second phase: monotone decreasing.
        let lrs: Vec<f64> = (9..100).map(|k| s.lr(k)).collect();
        assert!(lrs.windows(2).all(|w| w[1] <= w[0]));
    }

    /// Two Adam steps on f(w) = ½ w² against the update written out by hand.
    #[test]
    fn adam_matches_hand_computation() {
        let var = Var::new(&[1.0f32, -2.0], &Device::Cpu).unwrap();
        let mut opt = Adam::new(vec![Param { name: "w".into(), var: var.clone(), lr_scale: 2.0 }]).unwrap();
        let (lr, b1, b2, eps) = (0.1f64, 0.9f64, 0.999f64, 1e-8f64);
        let mut w = [1.0f64, -2.0];
        let (mut m, mut v) = ([0f64; 2], [0f64; 2]);
        for t in 1..=2 {
            let g = var.as_tensor().clone();
            opt.step(&[Some(g)], lr).unwrap();
            for i in 0..2 {
                let g = w[i];
                m[i] = b1 * m[i] + (1.0 - b1) * g;
                v[i] = b2 * v[i] + (1.0 - b2) * g * g;
                let mh = m[i] / (1.0 - b1.powi(t));
                let vh = v[i] / (1.0 - b2.powi(t));
                w[i] -= 2.0 * lr * mh / (vh.sqrt() + eps);
            }
        }
        let got: Vec<f32> = var.as_tensor().to_vec1().unwrap();
        for i in 0..2 {
            assert!((got[i] as f64 - w[i]).abs() < 1e-6, "{got:?} vs {w:?}");
        }
    }

    #[test]
    fn clipping_scales_to_max_norm() {
        let mut g = vec![Some(Tensor::new(&[3.0f32, 4.0], &Device::Cpu).unwrap()), None];
        let n = clip_grad_norm(&mut g, 0.5).unwrap();
        assert!((n - 5.0).abs() < 1e-6);
        let after = grad_norm(&g).unwrap();
        assert!((after - 0.5).abs() < 1e-5, "{after}");
        let mut small = vec![Some(Tensor::new(&[0.1f32], &Device::Cpu).unwrap())];
        clip_grad_norm(&mut small, 0.5).unwrap();
        assert_eq!(small[0].as_ref().unwrap().to_vec1::<f32>().unwrap(), vec![0.1]);
    }
}
