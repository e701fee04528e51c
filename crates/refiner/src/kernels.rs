//! The refiner's kernels live in `mvsplat360_nn`; this keeps the differentiable-mode switch where training
//! code looks for it.

pub use mvsplat360_nn::mode::{differentiable, is_differentiable, set_differentiable, DifferentiableGuard};
