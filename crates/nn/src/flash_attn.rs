//! FlashAttention-2 forward (scripts/build-flash-attn's `libflashattention.a`, linked by
//! `mvsplat360-flash-attn-sys`) behind a candle custom op: `softmax(q·kᵀ·scale)·v` per (batch, head) without a
//! score tensor, for CUDA f16/bf16 with head dim 64, forward only. [`crate::attention`] takes it for
//! `multi_head_attention` and `multi_head_attention_seqs` when `MVSPLAT360_GPU_OPS` selects `flash` (see
//! [`applies`]); everything else, and any error returned here, runs the composed path.
//!
//! The library discards CUDA errors (docs/research/flash-attention-build.md): a launch outside its limits leaves
//! the output unwritten and returns normally. So every limit is checked here before the call, and the first use
//! on each device and dtype runs a probe with a known answer ([`kernel_runs`]); a GPU whose SM version the library
//! holds no code for fails the probe and keeps the composed path.

use std::collections::HashMap;
use std::sync::Mutex;

use candle_core::backend::{BackendDevice, BackendStorage};
use candle_core::cuda_backend::cudarc::driver::{CudaSlice, DevicePtr, DevicePtrMut, DeviceRepr, ValidAsZeroBits};
use candle_core::cuda_backend::{Map3, WrapErr};
use candle_core::{CpuStorage, CudaDevice, CudaStorage, DType, Device, DeviceLocation, Layout, Result, Shape, Tensor, WithDType};

use crate::gpu_ops::{enabled, GpuOp};

/// The only head size the library holds kernels for (the others are stubs that abort).
pub const HEAD_DIM: usize = 64;
/// Grid y (batch) and z (heads) limit of the launch.
const MAX_GRID_YZ: usize = 65535;
/// The kernel's query/key tile (`Flash_fwd_kernel_traits<64, 128, 128, 4>`): sequence lengths are rounded to it.
const TILE: usize = 128;

/// Whether the flash path may take these operands: CUDA, all f16 or all bf16, `flash` selected, nothing that
/// needs a gradient (the op has no backward). Shapes and strides are checked by the op itself.
pub(crate) fn applies(q: &Tensor, k: &Tensor, v: &Tensor) -> bool {
    q.device().is_cuda()
        && matches!(q.dtype(), DType::F16 | DType::BF16)
        && k.dtype() == q.dtype()
        && v.dtype() == q.dtype()
        && !crate::mode::is_differentiable()
        && ![q, k, v].iter().any(|t| t.track_op())
        && enabled(GpuOp::Flash)
}

/// Reports the first error that made a caller fall back, once per process (an A/B run should know that the flash
/// path did not run).
pub(crate) fn note_fallback(e: &candle_core::Error) {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| eprintln!("flash-attn: falling back to the composed attention: {e}"));
}

/// `q (b, lq, h, 64)`, `k`/`v (b, lk, h, 64)`, all f16 or all bf16 on one CUDA device, any strides whose last one
/// is 1 → `softmax(q·kᵀ·scale)·v`, a contiguous `(b, lq, h, 64)`. Batches or heads past the launch limit run in
/// several calls. An error (the caller falls back) where the kernel cannot take the operands.
pub fn flash_attention(q: &Tensor, k: &Tensor, v: &Tensor, scale: f32) -> Result<Tensor> {
    let (b, _, h, d) = q.dims4()?;
    if !q.device().is_cuda() {
        candle_core::bail!("flash-attn: CUDA tensors only");
    }
    if d != HEAD_DIM {
        candle_core::bail!("flash-attn: head dim {d}, the library holds only {HEAD_DIM}");
    }
    if !matches!(q.dtype(), DType::F16 | DType::BF16) {
        candle_core::bail!("flash-attn: f16 or bf16 only, not {:?}", q.dtype());
    }
    if !kernel_runs(q.device(), q.dtype())? {
        candle_core::bail!("flash-attn: the kernel did not run on this GPU (no code for its SM version in libflashattention.a?)");
    }
    let op = FlashAttn { scale, zero_out: false };
    if b <= MAX_GRID_YZ && h <= MAX_GRID_YZ {
        return q.apply_op3_no_bwd(k, v, &op);
    }
    // Too many batches or heads for one grid: slices of each (views, no copy), joined.
    let chunk = |t: &Tensor, dim: usize, i: usize, n: usize| t.narrow(dim, i, n);
    let mut rows = Vec::new();
    for bi in (0..b).step_by(MAX_GRID_YZ) {
        let nb = MAX_GRID_YZ.min(b - bi);
        let mut heads = Vec::new();
        for hi in (0..h).step_by(MAX_GRID_YZ) {
            let nh = MAX_GRID_YZ.min(h - hi);
            let part = |t: &Tensor| chunk(&chunk(t, 0, bi, nb)?, 2, hi, nh);
            heads.push(part(q)?.apply_op3_no_bwd(&part(k)?, &part(v)?, &op)?);
        }
        rows.push(Tensor::cat(&heads, 2)?);
    }
    Tensor::cat(&rows, 0)
}

/// Whether the kernel computes on this device and dtype: the first call per (device, dtype) runs one small
/// attention with a known result (q = k = 0, v = 1: every output is 1) into a zeroed output, so a silent launch
/// failure (no SASS for the GPU, a context mismatch) shows as zeros; later calls return the cached answer.
fn kernel_runs(dev: &Device, dtype: DType) -> Result<bool> {
    static PROBED: Mutex<Option<HashMap<(usize, DType), bool>>> = Mutex::new(None);
    let DeviceLocation::Cuda { gpu_id } = dev.location() else { return Ok(false) };
    let key = (gpu_id, dtype);
    if let Some(&ok) = PROBED.lock().unwrap().get_or_insert_with(HashMap::new).get(&key) {
        return Ok(ok);
    }
    // 2 × 130 × 3: both kernel variants' tiling (130 rows: one full tile and a partial one), several heads.
    let shape = (2, 130, 3, HEAD_DIM);
    let z = Tensor::zeros(shape, dtype, dev)?;
    let o = z.apply_op3_no_bwd(&z, &Tensor::ones(shape, dtype, dev)?, &FlashAttn { scale: 0.125, zero_out: true })?;
    let o = o.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    // Uniform weights over 130 ones: 1 up to the rounding of 130 · (1/130) (exactly 1 after rounding to f16/bf16).
    let ok = o.iter().all(|&x| (x - 1.0).abs() < 1e-2);
    if !ok {
        eprintln!("flash-attn: the probe on cuda:{gpu_id} ({dtype:?}) returned wrong values; using the composed attention");
    }
    PROBED.lock().unwrap().get_or_insert_with(HashMap::new).insert(key, ok);
    Ok(ok)
}

/// The custom op: q, k, v as `(b, seqlen, heads, 64)` with `b`, `heads` within the grid limits.
struct FlashAttn {
    scale: f32,
    /// Zero the output before the launch (the probe).
    zero_out: bool,
}

/// One operand's (batch, row, head) strides in elements, checked against what the kernel assumes: last stride 1,
/// start and strides multiples of 8 elements (16-byte loads from a 256-byte aligned allocation), strides below
/// 2³² (`run_mha` takes u32). Dims of size 1 never move the index, so their strides are passed as 0.
fn strides(l: &Layout, what: &str) -> Result<[u32; 3]> {
    let (dims, st) = (l.dims(), l.stride());
    if st[3] != 1 {
        candle_core::bail!("flash-attn: the last dim of {what} must be contiguous (strides {st:?})");
    }
    if l.start_offset() % 8 != 0 {
        candle_core::bail!("flash-attn: {what} starts at element {}, not a multiple of 8", l.start_offset());
    }
    let mut out = [0u32; 3];
    for i in 0..3 {
        let s = if dims[i] == 1 { 0 } else { st[i] };
        if s % 8 != 0 || s > u32::MAX as usize {
            candle_core::bail!("flash-attn: stride {s} of {what} (dims {dims:?}) is not a multiple of 8 below 2^32");
        }
        out[i] = s as u32;
    }
    Ok(out)
}

impl Map3 for FlashAttn {
    fn f<T: DeviceRepr + WithDType + ValidAsZeroBits>(
        &self,
        q: &CudaSlice<T>,
        lq: &Layout,
        k: &CudaSlice<T>,
        lk: &Layout,
        v: &CudaSlice<T>,
        lv: &Layout,
        dev: &CudaDevice,
    ) -> Result<CudaSlice<T>> {
        if !matches!(T::DTYPE, DType::F16 | DType::BF16) {
            candle_core::bail!("flash-attn: f16 or bf16 only, not {:?}", T::DTYPE);
        }
        let (b, sq, h, d) = lq.shape().dims4()?;
        let (bk, sk, hk, dk) = lk.shape().dims4()?;
        if lv.shape().dims4()? != (bk, sk, hk, dk) || (bk, hk, dk) != (b, h, d) {
            candle_core::bail!("flash-attn: shapes q {:?}, k {:?}, v {:?} do not match", lq.dims(), lk.dims(), lv.dims());
        }
        if d != HEAD_DIM {
            candle_core::bail!("flash-attn: head dim {d}, the library holds only {HEAD_DIM}");
        }
        if b == 0 || h == 0 || sq == 0 || sk == 0 {
            candle_core::bail!("flash-attn: empty attention {:?} × {:?}", lq.dims(), lk.dims());
        }
        if b > MAX_GRID_YZ || h > MAX_GRID_YZ {
            candle_core::bail!("flash-attn: {b} batches × {h} heads exceed the grid limit {MAX_GRID_YZ}");
        }
        // Sizes are ints in the kernel's parameters; the row-rounded lengths and b·seqlen_q go through u32.
        let fits = |x: usize| x <= i32::MAX as usize;
        if !fits(sq.div_ceil(TILE) * TILE) || !fits(sk.div_ceil(TILE) * TILE) || !fits(b * sq) || !fits(b * h * sq) {
            candle_core::bail!("flash-attn: sequence lengths {sq}, {sk} too long for the kernel's int sizes");
        }
        let (qs, ks, vs) = (strides(lq, "q")?, strides(lk, "k")?, strides(lv, "v")?);
        let out_shape = Shape::from((b, sq, h, d));
        if !fits(out_shape.elem_count()) {
            candle_core::bail!("flash-attn: output {out_shape:?} too large");
        }
        let os = [(sq * h * d) as u32, (h * d) as u32, d as u32];

        let stream = dev.cuda_stream();
        let (qv, kv, vv) = (q.slice(lq.start_offset()..), k.slice(lk.start_offset()..), v.slice(lv.start_offset()..));
        // SAFETY (alloc): every element of `o` is written by the kernel when it runs; the probe zeroes it first, so
        // that a launch that did not happen shows.
        let mut o = if self.zero_out { dev.alloc_zeros::<T>(out_shape.elem_count())? } else { unsafe { dev.alloc::<T>(out_shape.elem_count())? } };
        let mut lse = unsafe { dev.alloc::<f32>(b * h * sq)? };
        // The library's runtime launches into the context current on this thread: make it candle's.
        stream.context().bind_to_thread().w()?;
        let is_bf16 = (T::DTYPE == DType::BF16) as i32;
        {
            let (qp, _gq) = qv.device_ptr(&stream);
            let (kp, _gk) = kv.device_ptr(&stream);
            let (vp, _gv) = vv.device_ptr(&stream);
            let (op, _go) = o.device_ptr_mut(&stream);
            let (lp, _gl) = lse.device_ptr_mut(&stream);
            let ptr = |p: u64| p as usize as *const core::ffi::c_void;
            let null = std::ptr::null::<i32>();
            // SAFETY: pointers of live allocations on this stream's context (the guards keep them recorded until
            // the launch is queued); every limit of mvsplat360-flash-attn-sys's contract was checked above: d = 64,
            // b and h ≤ 65535, strides multiples of 8 below 2³², lse of b·h·sq floats, non-causal, no window,
            // alibi, softcap, varlen or paging.
            unsafe {
                mvsplat360_flash_attn_sys::run_mha(
                    ptr(qp),
                    ptr(kp),
                    ptr(vp),
                    ptr(op),
                    ptr(lp),
                    std::ptr::null(), // alibi slopes
                    null,             // cu_seqlens_q
                    null,             // cu_seqlens_k
                    qs[0],
                    ks[0],
                    vs[0],
                    os[0],
                    0, // alibi batch stride
                    qs[1],
                    ks[1],
                    vs[1],
                    os[1],
                    qs[2],
                    ks[2],
                    vs[2],
                    os[2],
                    b as u32,
                    h as u32,
                    h as u32, // h_k: as many k/v heads as query heads
                    d as u32,
                    d as u32, // d_rounded (64 is a multiple of 32)
                    self.scale,
                    sq as u32,
                    sk as u32,
                    (sq.div_ceil(TILE) * TILE) as u32,
                    (sk.div_ceil(TILE) * TILE) as u32,
                    (b * sq) as u32, // total_q
                    is_bf16,
                    0,  // is_causal
                    0,  // unpadded_lse
                    -1, // window_size_left
                    -1, // window_size_right
                    0.0,
                    null, // block_table
                    0,
                    -1,   // page_block_size
                    null, // mm_prefix_ranges
                    0,
                    0,
                    stream.cu_stream() as *mut core::ffi::c_void,
                );
            }
        }
        drop(lse);
        Ok(o)
    }
}

impl candle_core::CustomOp3 for FlashAttn {
    fn name(&self) -> &'static str {
        "flash-attn"
    }

    fn cpu_fwd(&self, _: &CpuStorage, _: &Layout, _: &CpuStorage, _: &Layout, _: &CpuStorage, _: &Layout) -> Result<(CpuStorage, Shape)> {
        candle_core::bail!("flash-attn: CUDA tensors only (attention::multi_head_attention has the CPU path)")
    }

    fn cuda_fwd(&self, q: &CudaStorage, lq: &Layout, k: &CudaStorage, lk: &Layout, v: &CudaStorage, lv: &Layout) -> Result<(CudaStorage, Shape)> {
        if k.dtype() != q.dtype() || v.dtype() != q.dtype() {
            candle_core::bail!("flash-attn: dtypes q {:?}, k {:?}, v {:?} differ", q.dtype(), k.dtype(), v.dtype());
        }
        if k.device().location() != q.device().location() || v.device().location() != q.device().location() {
            candle_core::bail!("flash-attn: q, k, v on different devices");
        }
        let (b, sq, h, d) = lq.shape().dims4()?;
        let dev = q.device().clone();
        let slice = self.map(&q.slice, lq, &k.slice, lk, &v.slice, lv, &dev)?;
        Ok((CudaStorage { slice, device: dev }, Shape::from((b, sq, h, d))))
    }
}
