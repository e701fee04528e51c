//! cuda/fused.cu behind candle custom ops: GroupNorm + affine (+ SiLU) and the GEGLU gate, each replacing a
//! chain of candle ops (each a full pass over the tensor) on CUDA f32/f16/bf16 inference. Chosen at run time
//! with `MVSPLAT360_GPU_OPS=fused` ([`crate::gpu_ops`]); no backward, so never in differentiable mode or on
//! tracked tensors. tests/cuda_emulated.rs runs the same kernels and launch sequence on the CPU.

use candle_core::backend::BackendStorage;
use candle_core::cuda_backend::cudarc::driver::{CudaSlice, CudaView, DeviceRepr, LaunchConfig, PushKernelArg, ValidAsZeroBits};
use candle_core::cuda_backend::{kernel_name, Map1, WrapErr};
use candle_core::{CpuStorage, CudaDevice, CudaStorage, DType, Layout, Result, Shape, Tensor, WithDType};

use crate::gpu_ops::{enabled, GpuOp};

/// PTX of cuda/fused.cu (built by build.rs).
const PTX: &str = include_str!(concat!(env!("OUT_DIR"), "/fused.ptx"));
const MODULE: &str = "mvsplat360_nn_fused";
/// fused.cu's GN_THREADS / GN_CHUNK / EW_THREADS.
const GN_THREADS: u32 = 256;
const GN_CHUNK: usize = 4096;
const EW_THREADS: u32 = 256;

/// Whether the fused kernels take `x` (and the other operands): CUDA, f32/f16/bf16, `fused` selected, nothing
/// that needs a gradient.
pub(crate) fn applies(x: &Tensor, others: &[&Tensor]) -> bool {
    x.device().is_cuda()
        && matches!(x.dtype(), DType::F32 | DType::F16 | DType::BF16)
        && !crate::mode::is_differentiable()
        && !x.track_op()
        && !others.iter().any(|t| t.track_op())
        && enabled(GpuOp::Fused)
}

/// [`crate::norm::group_norm`] on (N, C, ...) as three kernels (chunk statistics, merge, apply). `None` where
/// a size exceeds the launch limits (the caller then takes the composed path).
#[allow(clippy::too_many_arguments)]
pub(crate) fn group_norm(x: &Tensor, groups: usize, frames: usize, weight: &Tensor, bias: &Tensor, eps: f64, silu: bool) -> Result<Option<Tensor>> {
    let dims = x.dims().to_vec();
    let (n, c) = (dims[0], dims[1]);
    let s: usize = dims[2..].iter().product();
    let (cg, bn) = (c / groups, n / frames);
    let cpr = (cg * s).div_ceil(GN_CHUNK);
    let fits = |v: usize, max: usize| v <= max;
    if x.elem_count() == 0
        || weight.elem_count() != c
        || bias.elem_count() != c
        || !fits(bn * groups, 65535)
        || !fits(frames * cpr, i32::MAX as usize)
        || !fits(n * c, i32::MAX as usize)
        || !fits(frames * cpr * bn * groups, i32::MAX as usize / 4)
    {
        return Ok(None);
    }
    let op = GroupNormFused { groups, frames, eps: eps as f32, silu };
    let w = weight.to_dtype(DType::F32)?.contiguous()?.flatten_all()?;
    let b = bias.to_dtype(DType::F32)?.contiguous()?.flatten_all()?;
    let y = x.contiguous()?.reshape((n, c, s))?.apply_op3_no_bwd(&w, &b, &op)?;
    Ok(Some(y.reshape(dims)?))
}

/// GEGLU gate of h (rows, 2·inner) (the first projection, before its bias) and the bias b (2·inner):
/// `(h₁ + b₁) · gelu_erf(h₂ + b₂)` → (rows, inner). `None` past the launch limits.
pub(crate) fn geglu(h: &Tensor, bias: &Tensor) -> Result<Option<Tensor>> {
    let (rows, two) = h.dims2()?;
    if two % 2 != 0 || rows == 0 || rows > i32::MAX as usize || bias.elem_count() != two {
        return Ok(None);
    }
    let b = bias.to_dtype(DType::F32)?.contiguous()?.flatten_all()?;
    Ok(Some(h.contiguous()?.apply_op2_no_bwd(&b, &GegluFused)?))
}

fn f32_view<'a>(s: &'a CudaStorage, l: &Layout, what: &str) -> Result<CudaView<'a, f32>> {
    let Some((a, b)) = l.contiguous_offsets() else { candle_core::bail!("fused {what}: must be contiguous") };
    Ok(s.as_cuda_slice::<f32>()?.slice(a..b))
}

fn cfg(grid: (u32, u32), block: u32) -> LaunchConfig {
    LaunchConfig { grid_dim: (grid.0, grid.1, 1), block_dim: (block, 1, 1), shared_mem_bytes: 0 }
}

struct GroupNormFused {
    groups: usize,
    frames: usize,
    eps: f32,
    silu: bool,
}

struct GroupNormLaunch<'a> {
    op: &'a GroupNormFused,
    w: CudaView<'a, f32>,
    b: CudaView<'a, f32>,
}

impl Map1 for GroupNormLaunch<'_> {
    fn f<T: DeviceRepr + WithDType + ValidAsZeroBits>(&self, src: &CudaSlice<T>, dev: &CudaDevice, layout: &Layout) -> Result<CudaSlice<T>> {
        let Some((o1, o2)) = layout.contiguous_offsets() else { candle_core::bail!("fused group_norm: input must be contiguous") };
        let x = src.slice(o1..o2);
        let (n, c, s) = layout.shape().dims3()?;
        let GroupNormFused { groups, frames, eps, silu } = *self.op;
        let (cg, bn) = (c / groups, n / frames);
        let cpr = (cg * s).div_ceil(GN_CHUNK);
        let chunks = frames * cpr;
        // SAFETY: every element is written by the kernels below before it is read.
        let part = unsafe { dev.alloc::<f32>(4 * bn * groups * chunks)? };
        let stats = unsafe { dev.alloc::<f32>(2 * bn * groups)? };
        let y = unsafe { dev.alloc::<T>(n * c * s)? };
        let (groups_i, frames_i, c_i, cg_i, s_i) = (groups as i32, frames as i32, c as i32, cg as i32, s as i64);

        let func = dev.get_or_load_custom_func(&kernel_name::<T>("gn_partial"), MODULE, PTX)?;
        let mut b = func.builder();
        b.arg(&x);
        b.arg(&part);
        candle_core::builder_arg!(b, groups_i, frames_i, c_i, cg_i, s_i, GN_CHUNK as i32, cpr as i32);
        // SAFETY: argument types and order as gn_partial_* in fused.cu; grid within the checked limits.
        unsafe { b.launch(cfg((chunks as u32, (bn * groups) as u32), GN_THREADS)) }.w()?;

        let func = dev.get_or_load_custom_func("gn_finalize", MODULE, PTX)?;
        let mut b = func.builder();
        b.arg(&part);
        b.arg(&stats);
        candle_core::builder_arg!(b, chunks as i32, eps);
        // SAFETY: as gn_finalize.
        unsafe { b.launch(cfg(((bn * groups) as u32, 1), GN_THREADS)) }.w()?;

        let func = dev.get_or_load_custom_func(&kernel_name::<T>("gn_apply"), MODULE, PTX)?;
        let mut b = func.builder();
        b.arg(&x);
        b.arg(&y);
        b.arg(&stats);
        b.arg(&self.w);
        b.arg(&self.b);
        candle_core::builder_arg!(b, groups_i, frames_i, c_i, cg_i, s_i, silu as i32);
        let by = s.div_ceil(4 * EW_THREADS as usize).min(65535) as u32;
        // SAFETY: as gn_apply_*; n·c ≤ i32::MAX checked by the caller.
        unsafe { b.launch(cfg(((n * c) as u32, by), EW_THREADS)) }.w()?;
        Ok(y)
    }
}

impl candle_core::CustomOp3 for GroupNormFused {
    fn name(&self) -> &'static str {
        "fused-group-norm"
    }

    fn cpu_fwd(&self, _: &CpuStorage, _: &Layout, _: &CpuStorage, _: &Layout, _: &CpuStorage, _: &Layout) -> Result<(CpuStorage, Shape)> {
        candle_core::bail!("fused-group-norm: CUDA tensors only (norm::group_norm has the CPU path)")
    }

    fn cuda_fwd(&self, x: &CudaStorage, lx: &Layout, w: &CudaStorage, lw: &Layout, b: &CudaStorage, lb: &Layout) -> Result<(CudaStorage, Shape)> {
        let dev = x.device().clone();
        let launch = GroupNormLaunch { op: self, w: f32_view(w, lw, "group_norm weight")?, b: f32_view(b, lb, "group_norm bias")? };
        let slice = launch.map(&x.slice, &dev, lx)?;
        Ok((CudaStorage { slice, device: dev }, lx.shape().clone()))
    }
}

struct GegluFused;

struct GegluLaunch<'a> {
    b: CudaView<'a, f32>,
}

impl Map1 for GegluLaunch<'_> {
    fn f<T: DeviceRepr + WithDType + ValidAsZeroBits>(&self, src: &CudaSlice<T>, dev: &CudaDevice, layout: &Layout) -> Result<CudaSlice<T>> {
        let Some((o1, o2)) = layout.contiguous_offsets() else { candle_core::bail!("fused geglu: input must be contiguous") };
        let h = src.slice(o1..o2);
        let (rows, two) = layout.shape().dims2()?;
        let inner = two / 2;
        // SAFETY: every element is written by the kernel.
        let y = unsafe { dev.alloc::<T>(rows * inner)? };
        let func = dev.get_or_load_custom_func(&kernel_name::<T>("geglu"), MODULE, PTX)?;
        let mut b = func.builder();
        b.arg(&h);
        b.arg(&self.b);
        b.arg(&y);
        candle_core::builder_arg!(b, inner as i32);
        // SAFETY: as geglu_* in fused.cu; rows ≤ i32::MAX checked by the caller.
        unsafe { b.launch(cfg((rows as u32, 1), EW_THREADS)) }.w()?;
        Ok(y)
    }
}

impl candle_core::CustomOp2 for GegluFused {
    fn name(&self) -> &'static str {
        "fused-geglu"
    }

    fn cpu_fwd(&self, _: &CpuStorage, _: &Layout, _: &CpuStorage, _: &Layout) -> Result<(CpuStorage, Shape)> {
        candle_core::bail!("fused-geglu: CUDA tensors only (linear::geglu_ff has the CPU path)")
    }

    fn cuda_fwd(&self, h: &CudaStorage, lh: &Layout, b: &CudaStorage, lb: &Layout) -> Result<(CudaStorage, Shape)> {
        let dev = h.device().clone();
        let (rows, two) = lh.shape().dims2()?;
        let slice = GegluLaunch { b: f32_view(b, lb, "geglu bias")? }.map(&h.slice, &dev, lh)?;
        Ok((CudaStorage { slice, device: dev }, Shape::from((rows, two / 2))))
    }
}
