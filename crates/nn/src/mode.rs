//! Which path a kernel takes. Inference on CPU f32 runs the hand-written kernels; the refiner's training
//! switches them off per thread ("differentiable mode") so its forward records a backward graph.

use candle_core::{CpuStorage, DType, Layout, Result, Storage, Tensor};

thread_local! {
    static DIFFERENTIABLE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Switch this thread's differentiable mode (returns the previous setting). While on, the mode-aware kernels
/// (refiner UNet, VAE, CLIP) take their composed candle-op path, so inputs and `Var` weights receive gradients.
pub fn set_differentiable(on: bool) -> bool {
    DIFFERENTIABLE.with(|d| d.replace(on))
}

/// Whether differentiable mode is on for this thread (see [`set_differentiable`]).
pub fn is_differentiable() -> bool {
    DIFFERENTIABLE.with(|d| d.get())
}

/// Differentiable mode for a scope: on while the guard lives, then back to the previous setting.
#[must_use = "differentiable mode ends when the guard is dropped"]
pub struct DifferentiableGuard(bool);

/// Turn differentiable mode on until the returned guard is dropped.
pub fn differentiable() -> DifferentiableGuard {
    DifferentiableGuard(set_differentiable(true))
}

impl Drop for DifferentiableGuard {
    fn drop(&mut self) {
        set_differentiable(self.0);
    }
}

/// The mode-aware kernels' fast path applies: a CPU f32 tensor outside differentiable mode.
pub(crate) fn is_cpu_f32(t: &Tensor) -> bool {
    cpu_f32(t) && !is_differentiable()
}

/// A CPU f32 tensor (the only kind the hand-written kernels read).
pub(crate) fn cpu_f32(t: &Tensor) -> bool {
    t.device().is_cpu() && t.dtype() == DType::F32
}

/// Run `f` on the contiguous f32 data of a CPU tensor (no copy when already contiguous).
pub(crate) fn with_f32<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> R) -> Result<R> {
    let t = if t.is_contiguous() { t.clone() } else { t.contiguous()? };
    let (st, l) = t.storage_and_layout();
    match &*st {
        Storage::Cpu(CpuStorage::F32(v)) => match l.contiguous_offsets() {
            Some((a, b)) => Ok(f(&v[a..b])),
            None => candle_core::bail!("kernels: tensor not contiguous"),
        },
        _ => candle_core::bail!("kernels: expected a CPU f32 tensor"),
    }
}

/// The contiguous f32 slice of a custom op's CPU argument; `op` names the kernel in the error.
pub(crate) fn f32_slice<'a>(s: &'a CpuStorage, l: &Layout, op: &str) -> Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&v[a..b]),
        (CpuStorage::F32(_), None) => candle_core::bail!("{op}: input must be contiguous"),
        _ => candle_core::bail!("{op}: input must be f32"),
    }
}

/// A kernel asked to run on a device whose path is not built yet (only its CPU kernel exists).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NotBuilt {
    pub op: &'static str,
    pub device: String,
}

impl std::fmt::Display for NotBuilt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: the {} path is not built yet (only the CPU kernel exists); call the dispatching op or move the tensors to the CPU", self.op, self.device)
    }
}

impl std::error::Error for NotBuilt {}

/// [`NotBuilt`] for `op` unless `t` is on the CPU.
pub(crate) fn require_cpu(op: &'static str, t: &Tensor) -> Result<()> {
    if t.device().is_cpu() {
        return Ok(());
    }
    let device = if t.device().is_cuda() { "CUDA" } else { "non-CPU" };
    Err(candle_core::Error::wrap(NotBuilt { op, device: device.to_string() }))
}
