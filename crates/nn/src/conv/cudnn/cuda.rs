//! The cuDNN backend of [`PlanCache`] and the candle op that runs a plan on CUDA tensors.
//!
//! libcudnn is opened at run time (dlopen of `libcudnn.so.9`), not through cudarc's `cudnn` bindings: candle-core
//! 0.11.1 builds cudarc with `dynamic-linking`, under which cudarc's cuDNN symbols are resolved at link time —
//! every CUDA binary would then need libcudnn to link and to start, and a missing library could not fall back.
//! Here a missing or unusable library is one warning and candle's conv2d, as before. The few legacy-API entry
//! points used are declared below with the values of cuDNN 9's headers (stable since cuDNN 7).
//!
//! Epilogue: `y = scale·conv(x, w) + bias + z` (`bias` already multiplied by `scale` by the caller).
//! `cudnnConvolutionBiasActivationForward` with the identity activation is only allowed with
//! IMPLICIT_PRECOMP_GEMM, so a plan fuses bias and residual into the conv only when the heuristic's first
//! choice is that algorithm (the usual case for tensor-op convolutions); otherwise it keeps the best algorithm
//! and adds bias and residual with `cudnnAddTensor` (two more passes over the output, as candle's path does) —
//! as it does from then on for a plan whose fused call cuDNN refuses.

use std::ffi::{c_char, c_int, c_void, CStr};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};

use candle_core::cuda::cudarc::driver::{CudaSlice, CudaStream, DevicePtr, DevicePtrMut, DeviceRepr};
use candle_core::cuda::{CudaStorageSlice, DeviceId};
use candle_core::{CudaDevice, CudaStorage, CustomOp2, CustomOp3, DType, Layout, Result, Shape, Storage, Tensor};

use super::{packed_strides, ConvBackend, ConvDType, ConvKey, MathType, PlanCache};
use crate::conv::Conv2dConfig;

type Status = c_int;
type Ptr = *mut c_void;

// cudnnDataType_t, cudnnTensorFormat_t, cudnnConvolutionMode_t, cudnnMathType_t, cudnnActivationMode_t,
// cudnnNanPropagation_t, cudnnConvolutionFwdAlgo_t (cudnn_graph.h / cudnn_cnn.h of cuDNN 9).
const DATA_FLOAT: c_int = 0;
const DATA_HALF: c_int = 2;
const DATA_BFLOAT16: c_int = 9;
const TENSOR_NCHW: c_int = 0;
const CROSS_CORRELATION: c_int = 1;
const TENSOR_OP_MATH: c_int = 1;
const TENSOR_OP_MATH_ALLOW_CONVERSION: c_int = 2;
const FMA_MATH: c_int = 3;
const ACTIVATION_IDENTITY: c_int = 5;
const NOT_PROPAGATE_NAN: c_int = 0;
const ALGO_IMPLICIT_PRECOMP_GEMM: c_int = 1;
const ALGO_COUNT: usize = 8;

/// cudnnConvolutionFwdAlgoPerf_t.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
struct AlgoPerf {
    algo: c_int,
    status: Status,
    time: f32,
    memory: usize,
    determinism: c_int,
    math_type: c_int,
    reserved: [c_int; 3],
}

type Fwd = unsafe extern "C" fn(Ptr, *const c_void, Ptr, *const c_void, Ptr, *const c_void, Ptr, c_int, Ptr, usize, *const c_void, Ptr, Ptr) -> Status;
#[rustfmt::skip]
type BiasActFwd = unsafe extern "C" fn(Ptr, *const c_void, Ptr, *const c_void, Ptr, *const c_void, Ptr, c_int, Ptr, usize, *const c_void, Ptr, *const c_void, Ptr, *const c_void, Ptr, Ptr, Ptr) -> Status;

/// The entry points used, resolved once from libcudnn.
struct Api {
    _lib: libloading::Library,
    get_version: unsafe extern "C" fn() -> usize,
    error_string: unsafe extern "C" fn(Status) -> *const c_char,
    create: unsafe extern "C" fn(*mut Ptr) -> Status,
    destroy: unsafe extern "C" fn(Ptr) -> Status,
    set_stream: unsafe extern "C" fn(Ptr, Ptr) -> Status,
    create_tensor: unsafe extern "C" fn(*mut Ptr) -> Status,
    set_tensor_4d_ex: unsafe extern "C" fn(Ptr, c_int, c_int, c_int, c_int, c_int, c_int, c_int, c_int, c_int) -> Status,
    destroy_tensor: unsafe extern "C" fn(Ptr) -> Status,
    create_filter: unsafe extern "C" fn(*mut Ptr) -> Status,
    set_filter_4d: unsafe extern "C" fn(Ptr, c_int, c_int, c_int, c_int, c_int, c_int) -> Status,
    destroy_filter: unsafe extern "C" fn(Ptr) -> Status,
    create_conv: unsafe extern "C" fn(*mut Ptr) -> Status,
    set_conv_2d: unsafe extern "C" fn(Ptr, c_int, c_int, c_int, c_int, c_int, c_int, c_int, c_int) -> Status,
    set_conv_math: unsafe extern "C" fn(Ptr, c_int) -> Status,
    set_conv_groups: unsafe extern "C" fn(Ptr, c_int) -> Status,
    destroy_conv: unsafe extern "C" fn(Ptr) -> Status,
    create_activation: unsafe extern "C" fn(*mut Ptr) -> Status,
    set_activation: unsafe extern "C" fn(Ptr, c_int, c_int, f64) -> Status,
    destroy_activation: unsafe extern "C" fn(Ptr) -> Status,
    get_algorithm_v7: unsafe extern "C" fn(Ptr, Ptr, Ptr, Ptr, Ptr, c_int, *mut c_int, *mut AlgoPerf) -> Status,
    get_workspace_size: unsafe extern "C" fn(Ptr, Ptr, Ptr, Ptr, Ptr, c_int, *mut usize) -> Status,
    forward: Fwd,
    bias_act_forward: BiasActFwd,
    add_tensor: unsafe extern "C" fn(Ptr, *const c_void, Ptr, *const c_void, *const c_void, Ptr, Ptr) -> Status,
}

impl Api {
    fn load() -> std::result::Result<Api, String> {
        let mut errors = Vec::new();
        let lib = ["libcudnn.so.9", "libcudnn.so"].iter().find_map(|name| {
            // SAFETY: loading runs libcudnn's initialisers, which have no preconditions.
            unsafe { libloading::Library::new(*name) }.map_err(|e| errors.push(e.to_string())).ok()
        });
        let lib = lib.ok_or_else(|| format!("libcudnn not loadable ({}); put PyPI's nvidia-cudnn lib folder on LD_LIBRARY_PATH", errors.join("; ")))?;
        fn sym<T: Copy>(lib: &libloading::Library, name: &str) -> std::result::Result<T, String> {
            // SAFETY: T is the field's type, the C signature of this cuDNN entry point.
            unsafe { lib.get::<T>(name.as_bytes()) }.map(|s| *s).map_err(|e| format!("libcudnn: {name}: {e}"))
        }
        let api = Api {
            get_version: sym(&lib, "cudnnGetVersion")?,
            error_string: sym(&lib, "cudnnGetErrorString")?,
            create: sym(&lib, "cudnnCreate")?,
            destroy: sym(&lib, "cudnnDestroy")?,
            set_stream: sym(&lib, "cudnnSetStream")?,
            create_tensor: sym(&lib, "cudnnCreateTensorDescriptor")?,
            set_tensor_4d_ex: sym(&lib, "cudnnSetTensor4dDescriptorEx")?,
            destroy_tensor: sym(&lib, "cudnnDestroyTensorDescriptor")?,
            create_filter: sym(&lib, "cudnnCreateFilterDescriptor")?,
            set_filter_4d: sym(&lib, "cudnnSetFilter4dDescriptor")?,
            destroy_filter: sym(&lib, "cudnnDestroyFilterDescriptor")?,
            create_conv: sym(&lib, "cudnnCreateConvolutionDescriptor")?,
            set_conv_2d: sym(&lib, "cudnnSetConvolution2dDescriptor")?,
            set_conv_math: sym(&lib, "cudnnSetConvolutionMathType")?,
            set_conv_groups: sym(&lib, "cudnnSetConvolutionGroupCount")?,
            destroy_conv: sym(&lib, "cudnnDestroyConvolutionDescriptor")?,
            create_activation: sym(&lib, "cudnnCreateActivationDescriptor")?,
            set_activation: sym(&lib, "cudnnSetActivationDescriptor")?,
            destroy_activation: sym(&lib, "cudnnDestroyActivationDescriptor")?,
            get_algorithm_v7: sym(&lib, "cudnnGetConvolutionForwardAlgorithm_v7")?,
            get_workspace_size: sym(&lib, "cudnnGetConvolutionForwardWorkspaceSize")?,
            forward: sym(&lib, "cudnnConvolutionForward")?,
            bias_act_forward: sym(&lib, "cudnnConvolutionBiasActivationForward")?,
            add_tensor: sym(&lib, "cudnnAddTensor")?,
            _lib: lib,
        };
        // SAFETY: no arguments.
        let version = unsafe { (api.get_version)() };
        if version < 8000 {
            return Err(format!("libcudnn version {version} is older than 8"));
        }
        Ok(api)
    }

    fn check(&self, status: Status, what: &str) -> Result<()> {
        if status == 0 {
            return Ok(());
        }
        // SAFETY: cudnnGetErrorString returns a static NUL-terminated string for any status.
        let msg = unsafe { CStr::from_ptr((self.error_string)(status)) }.to_string_lossy();
        candle_core::bail!("cudnn {what}: {msg} ({status})")
    }
}

fn api() -> Result<&'static Api> {
    static API: OnceLock<std::result::Result<Api, String>> = OnceLock::new();
    API.get_or_init(Api::load).as_ref().map_err(|e| candle_core::Error::msg(e.clone()))
}

/// A cuDNN handle bound to one candle device's stream.
pub(super) struct Handle {
    raw: Ptr,
    stream: Arc<CudaStream>,
    api: &'static Api,
}

// SAFETY: a cuDNN handle may be used from any thread, one at a time; PlanCache keeps it under its device's lock.
unsafe impl Send for Handle {}

impl Drop for Handle {
    fn drop(&mut self) {
        // SAFETY: created by cudnnCreate, destroyed once.
        unsafe { (self.api.destroy)(self.raw) };
    }
}

/// Descriptors, algorithm and workspace size of one [`ConvKey`] (null descriptors are not created).
pub(super) struct Plan {
    api: &'static Api,
    x: Ptr,
    y: Ptr,
    w: Ptr,
    conv: Ptr,
    bias: Ptr,
    act: Ptr,
    algo: c_int,
    workspace: usize,
    /// Bias and residual in the conv call (cudnnConvolutionBiasActivationForward); cleared if cuDNN refuses it
    /// (e.g. a dtype configuration it lacks), then the plan runs the separate passes.
    fused: AtomicBool,
}

// SAFETY: host-side descriptors, written only while the plan is made and read under the device's lock.
unsafe impl Send for Plan {}
unsafe impl Sync for Plan {}

impl Drop for Plan {
    fn drop(&mut self) {
        let a = self.api;
        // SAFETY: each non-null descriptor was created by the matching cudnnCreate* and is destroyed once.
        unsafe {
            for (d, f) in [(self.x, a.destroy_tensor), (self.y, a.destroy_tensor), (self.bias, a.destroy_tensor)] {
                if !d.is_null() {
                    f(d);
                }
            }
            if !self.w.is_null() {
                (a.destroy_filter)(self.w);
            }
            if !self.conv.is_null() {
                (a.destroy_conv)(self.conv);
            }
            if !self.act.is_null() {
                (a.destroy_activation)(self.act);
            }
        }
    }
}

fn data_type(d: ConvDType) -> c_int {
    match d {
        ConvDType::F32 => DATA_FLOAT,
        ConvDType::F16 => DATA_HALF,
        ConvDType::BF16 => DATA_BFLOAT16,
    }
}

/// The cuDNN backend (stateless: the library is process-wide).
pub(super) struct Cudnn;

impl ConvBackend for Cudnn {
    type Device = CudaDevice;
    type DeviceId = DeviceId;
    type Handle = Handle;
    type Plan = Plan;
    type Workspace = CudaSlice<u8>;

    fn device_id(d: &CudaDevice) -> DeviceId {
        d.id()
    }

    fn open(&self, device: &CudaDevice) -> Result<Handle> {
        let api = api()?;
        let stream = device.cuda_stream();
        stream.context().bind_to_thread().map_err(candle_core::Error::wrap)?;
        let mut raw = std::ptr::null_mut();
        // SAFETY: out-pointer to a handle; the device's context is current.
        api.check(unsafe { (api.create)(&mut raw) }, "create")?;
        let h = Handle { raw, stream, api };
        // SAFETY: a live handle and the device's stream (one per candle device, so set once).
        api.check(unsafe { (api.set_stream)(h.raw, h.stream.cu_stream() as Ptr) }, "set stream")?;
        Ok(h)
    }

    fn create_plan(&self, h: &mut Handle, key: &ConvKey, math: MathType) -> Result<Plan> {
        let a = h.api;
        let i = |v: usize| v as c_int; // ConvKey::check bounds every size by i32::MAX
        let dt = data_type(key.dtype);
        let mut p =
            Plan { api: a, x: null(), y: null(), w: null(), conv: null(), bias: null(), act: null(), algo: 0, workspace: 0, fused: AtomicBool::new(false) };
        let tensor = |d: &mut Ptr, dims: [usize; 4], st: [usize; 4]| -> Result<()> {
            // SAFETY: out-pointer, then a live descriptor with in-range sizes.
            unsafe {
                a.check((a.create_tensor)(d), "create tensor")?;
                a.check((a.set_tensor_4d_ex)(*d, dt, i(dims[0]), i(dims[1]), i(dims[2]), i(dims[3]), i(st[0]), i(st[1]), i(st[2]), i(st[3])), "tensor")
            }
        };
        tensor(&mut p.x, key.x, key.x_strides)?;
        tensor(&mut p.y, key.out_dims(), key.y_strides)?;
        let mut algo_math = match math {
            MathType::Fma => FMA_MATH,
            MathType::TensorOp => TENSOR_OP_MATH,
        };
        let (wd, (pd, st, dl)) = (key.w, (key.pad, key.stride, key.dilation));
        // SAFETY: out-pointers, then live descriptors with in-range values; f32 accumulation for every dtype
        // (bf16 has no other configuration; f16 keeps f32 sums like PyTorch).
        unsafe {
            a.check((a.create_filter)(&mut p.w), "create filter")?;
            a.check((a.set_filter_4d)(p.w, dt, TENSOR_NCHW, i(wd[0]), i(wd[1]), i(wd[2]), i(wd[3])), "filter")?;
            a.check((a.create_conv)(&mut p.conv), "create conv")?;
            a.check((a.set_conv_2d)(p.conv, i(pd[0]), i(pd[1]), i(st[0]), i(st[1]), i(dl[0]), i(dl[1]), CROSS_CORRELATION, DATA_FLOAT), "conv")?;
            a.check((a.set_conv_groups)(p.conv, i(key.groups)), "groups")?;
            a.check((a.set_conv_math)(p.conv, algo_math), "math type")?;
        }
        let mut perf = [AlgoPerf::default(); ALGO_COUNT];
        let mut n: c_int = 0;
        // SAFETY: live descriptors; `perf` holds ALGO_COUNT results.
        a.check(unsafe { (a.get_algorithm_v7)(h.raw, p.x, p.w, p.conv, p.y, ALGO_COUNT as c_int, &mut n, perf.as_mut_ptr()) }, "algorithm heuristic")?;
        let tensor_op = |m: c_int| m == TENSOR_OP_MATH || m == TENSOR_OP_MATH_ALLOW_CONVERSION;
        // Heuristic order, skipping failures and, in f32, anything on tensor cores (TF32).
        let candidates = perf[..(n.max(0) as usize).min(ALGO_COUNT)].iter().filter(|r| r.status == 0 && !(math == MathType::Fma && tensor_op(r.math_type)));
        let mut chosen = None;
        for r in candidates {
            if math == MathType::TensorOp {
                // The math type the heuristic ranked this algorithm with (what PyTorch sets too).
                algo_math = r.math_type;
                // SAFETY: live descriptor.
                a.check(unsafe { (a.set_conv_math)(p.conv, algo_math) }, "math type")?;
            }
            let mut bytes = 0usize;
            // SAFETY: live descriptors and an out-pointer.
            if unsafe { (a.get_workspace_size)(h.raw, p.x, p.w, p.conv, p.y, r.algo, &mut bytes) } == 0 {
                chosen = Some((r.algo, bytes));
                break;
            }
        }
        let Some((algo, bytes)) = chosen else {
            candle_core::bail!("cudnn: no forward algorithm for {key:?} ({n} heuristic results)");
        };
        (p.algo, p.workspace) = (algo, bytes);
        p.fused = AtomicBool::new(key.bias && algo == ALGO_IMPLICIT_PRECOMP_GEMM);
        if key.bias {
            tensor(&mut p.bias, [1, key.w[0], 1, 1], packed_strides([1, key.w[0], 1, 1]))?;
        }
        if p.fused.load(Ordering::Relaxed) {
            // SAFETY: out-pointer, then a live descriptor.
            unsafe {
                a.check((a.create_activation)(&mut p.act), "create activation")?;
                a.check((a.set_activation)(p.act, ACTIVATION_IDENTITY, NOT_PROPAGATE_NAN, 0.0), "activation")?;
            }
        }
        Ok(p)
    }

    fn workspace_bytes(p: &Plan) -> usize {
        p.workspace
    }

    fn alloc_workspace(&self, h: &mut Handle, bytes: usize) -> Result<CudaSlice<u8>> {
        // SAFETY: scratch memory that cuDNN writes before it reads; never zeroed on purpose.
        unsafe { h.stream.alloc::<u8>(bytes) }.map_err(candle_core::Error::wrap)
    }
}

fn null() -> Ptr {
    std::ptr::null_mut()
}

fn cache() -> &'static PlanCache<Cudnn> {
    static CACHE: OnceLock<PlanCache<Cudnn>> = OnceLock::new();
    CACHE.get_or_init(|| PlanCache::new(Cudnn))
}

/// The candle op: inputs x, w, then bias (if `key.bias`), then the residual (if `key.residual`; the fourth
/// input rides in `fourth` because candle's custom ops take at most three tensors).
struct ConvOp {
    key: ConvKey,
    out_shape: Shape,
    scale: f32,
    fourth: Option<Tensor>,
}

impl ConvOp {
    fn fwd(&self, args: &[(&CudaStorage, &Layout)]) -> Result<(CudaStorage, Shape)> {
        let dev = args[0].0.device.clone();
        macro_rules! go {
            ($v:ident) => {{
                let slices = args
                    .iter()
                    .map(|(s, _)| match &s.slice {
                        CudaStorageSlice::$v(v) => Ok(v),
                        _ => candle_core::bail!("cudnn conv: inputs of mixed dtypes"),
                    })
                    .collect::<Result<Vec<_>>>()?;
                CudaStorageSlice::$v(self.launch(&dev, &slices, args)?)
            }};
        }
        let slice = match self.key.dtype {
            ConvDType::F32 => go!(F32),
            ConvDType::F16 => go!(F16),
            ConvDType::BF16 => go!(BF16),
        };
        Ok((CudaStorage { slice, device: dev }, self.out_shape.clone()))
    }

    fn launch<T: DeviceRepr>(&self, dev: &CudaDevice, slices: &[&CudaSlice<T>], args: &[(&CudaStorage, &Layout)]) -> Result<CudaSlice<T>> {
        let k = &self.key;
        let expected = 2 + k.bias as usize + k.residual as usize;
        if slices.len() != expected || args.iter().any(|(_, l)| !l.is_contiguous()) {
            candle_core::bail!("cudnn conv: expected {expected} contiguous inputs");
        }
        // The descriptors address exactly these many elements of each input (x and y views are permutations).
        let count = |d: [usize; 4]| d.iter().product::<usize>();
        let mut sizes = vec![count(k.x), count(k.w)];
        if k.bias {
            sizes.push(k.w[0]);
        }
        if k.residual {
            sizes.push(count(k.out_dims()));
        }
        if self.out_shape.elem_count() != count(k.out_dims()) || args.iter().zip(&sizes).any(|((_, l), &n)| l.shape().elem_count() != n) {
            candle_core::bail!("cudnn conv: input sizes {:?} do not match {k:?}", args.iter().map(|(_, l)| l.dims().to_vec()).collect::<Vec<_>>());
        }
        let stream = dev.cuda_stream();
        // SAFETY: every element is written by the convolution (beta = 0 / alpha2 applies to z, not y).
        let mut y = unsafe { stream.alloc::<T>(self.out_shape.elem_count()) }.map_err(candle_core::Error::wrap)?;
        let views: Vec<_> = slices.iter().zip(args).map(|(s, (_, l))| s.slice(l.start_offset()..)).collect();
        cache().run(dev, k, |h, p, ws| {
            let a = h.api;
            stream.context().bind_to_thread().map_err(candle_core::Error::wrap)?;
            let ptrs: Vec<_> = views.iter().map(|v| v.device_ptr(&stream)).collect();
            let ptr = |i: usize| ptrs[i].0 as usize as *const c_void;
            let bias = k.bias.then(|| ptr(2));
            let z = k.residual.then(|| ptr(2 + k.bias as usize));
            let (ws_ptr, _ws_sync) = match ws {
                Some(w) => {
                    let (d, s) = w.device_ptr_mut(&stream);
                    (d as usize as Ptr, Some(s))
                }
                None => (null(), None),
            };
            let (yp, _y_sync) = y.device_ptr_mut(&stream);
            let yp = yp as usize as Ptr;
            let (one, zero, scale) = (1f32, 0f32, self.scale);
            // Scaling factors are host f32 for f32, f16 and bf16 tensors.
            let f = |v: &f32| v as *const f32 as *const c_void;
            // SAFETY: pointers to live device buffers of the sizes the plan's descriptors describe (checked
            // above), on the handle's stream, with a workspace of at least the plan's size.
            unsafe {
                let fused_ok = p.fused.load(Ordering::Relaxed) && {
                    // Without a residual z = y with alpha2 = 0: y is not read (cuDNN's blending rule; what
                    // TensorFlow's fused conv does with no side input).
                    let (alpha2, zp) = match z {
                        Some(z) => (&one, z),
                        None => (&zero, yp as *const c_void),
                    };
                    let status = (a.bias_act_forward)(
                        h.raw,
                        f(&scale),
                        p.x,
                        ptr(0),
                        p.w,
                        ptr(1),
                        p.conv,
                        p.algo,
                        ws_ptr,
                        p.workspace,
                        f(alpha2),
                        p.y,
                        zp,
                        p.bias,
                        bias.unwrap_or(std::ptr::null()),
                        p.act,
                        p.y,
                        yp,
                    );
                    if status != 0 {
                        p.fused.store(false, Ordering::Relaxed);
                        let e = a.check(status, "conv + bias forward").unwrap_err();
                        eprintln!("warning: {e}; this shape adds bias and residual in separate passes from now on");
                    }
                    status == 0
                };
                if !fused_ok {
                    a.check((a.forward)(h.raw, f(&scale), p.x, ptr(0), p.w, ptr(1), p.conv, p.algo, ws_ptr, p.workspace, f(&zero), p.y, yp), "conv forward")?;
                    if let Some(b) = bias {
                        a.check((a.add_tensor)(h.raw, f(&one), p.bias, b, f(&one), p.y, yp), "add bias")?;
                    }
                    if let Some(z) = z {
                        a.check((a.add_tensor)(h.raw, f(&one), p.y, z, f(&one), p.y, yp), "add residual")?;
                    }
                }
            }
            Ok(())
        })?;
        Ok(y)
    }
}

impl CustomOp2 for ConvOp {
    fn name(&self) -> &'static str {
        "cudnn-conv"
    }

    fn cpu_fwd(&self, _: &candle_core::CpuStorage, _: &Layout, _: &candle_core::CpuStorage, _: &Layout) -> Result<(candle_core::CpuStorage, Shape)> {
        candle_core::bail!("cudnn-conv: CUDA tensors only")
    }

    fn cuda_fwd(&self, s1: &CudaStorage, l1: &Layout, s2: &CudaStorage, l2: &Layout) -> Result<(CudaStorage, Shape)> {
        self.fwd(&[(s1, l1), (s2, l2)])
    }
}

impl CustomOp3 for ConvOp {
    fn name(&self) -> &'static str {
        "cudnn-conv"
    }

    fn cpu_fwd(
        &self,
        _: &candle_core::CpuStorage,
        _: &Layout,
        _: &candle_core::CpuStorage,
        _: &Layout,
        _: &candle_core::CpuStorage,
        _: &Layout,
    ) -> Result<(candle_core::CpuStorage, Shape)> {
        candle_core::bail!("cudnn-conv: CUDA tensors only")
    }

    fn cuda_fwd(&self, s1: &CudaStorage, l1: &Layout, s2: &CudaStorage, l2: &Layout, s3: &CudaStorage, l3: &Layout) -> Result<(CudaStorage, Shape)> {
        match &self.fourth {
            None => self.fwd(&[(s1, l1), (s2, l2), (s3, l3)]),
            Some(t) => {
                let (st, l4) = t.storage_and_layout();
                match &*st {
                    Storage::Cuda(s4) => self.fwd(&[(s1, l1), (s2, l2), (s3, l3), (s4, l4)]),
                    _ => candle_core::bail!("cudnn-conv: CUDA tensors only"),
                }
            }
        }
    }
}

fn conv_dtype(t: DType) -> Result<ConvDType> {
    Ok(match t {
        DType::F32 => ConvDType::F32,
        DType::F16 => ConvDType::F16,
        DType::BF16 => ConvDType::BF16,
        d => candle_core::bail!("cudnn conv: unsupported dtype {d:?}"),
    })
}

/// Apply the op to contiguous inputs: `scale·conv(x, w) + scale·bias + residual` with the key's layouts.
fn apply(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, residual: Option<&Tensor>, scale: f32, key: ConvKey, out_shape: Shape) -> Result<Tensor> {
    let dt = x.dtype();
    let prep = |t: &Tensor| -> Result<Tensor> { t.to_dtype(dt)?.contiguous() };
    let bias = match bias {
        Some(b) if scale != 1.0 => Some(prep(&(b.to_dtype(DType::F32)? * scale as f64)?)?),
        Some(b) => Some(prep(b)?),
        None => None,
    };
    let residual = match residual {
        Some(r) if r.dims() != out_shape.dims() => candle_core::bail!("cudnn conv: residual {:?}, output {:?}", r.dims(), out_shape.dims()),
        Some(r) => Some(prep(r)?),
        None => None,
    };
    let (x, w) = (x.contiguous()?, prep(w)?);
    let mut op = ConvOp { key, out_shape, scale, fourth: None };
    match (bias, residual) {
        (None, None) => x.apply_op2_no_bwd(&w, &op),
        (Some(t), None) | (None, Some(t)) => x.apply_op3_no_bwd(&w, &t, &op),
        (Some(b), Some(r)) => {
            op.fourth = Some(r);
            x.apply_op3_no_bwd(&w, &b, &op)
        }
    }
}

/// See [`super::try_conv2d`].
pub(super) fn try_conv2d(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, residual: Option<&Tensor>, scale: f32, cfg: Conv2dConfig) -> Result<Tensor> {
    let (x4, w4) = (x.dims4()?, w.dims4()?);
    let (s, p, d) = (cfg.stride, cfg.padding, cfg.dilation);
    let key = ConvKey::nchw(conv_dtype(x.dtype())?, x4.into(), w4.into(), [s, s], [p, p], [d, d], bias.is_some(), residual.is_some())?;
    let out = Shape::from(key.out_dims().to_vec());
    apply(x, w, bias, residual, scale, key, out)
}

/// See [`super::try_temporal`]: a 2-D conv with kernel (kt, 1) and padding (kt/2, 0) over the strided
/// (B, C, T, H·W) view of frame-major x (B·T, C, H, W), written straight into the frame-major output; the
/// tap-major weight (Co, kt·C) is reordered to (Co, C, kt, 1) per call.
pub(super) fn try_temporal(x: &Tensor, w: &Tensor, bias: &Tensor, kt: usize, frames: usize, residual: Option<&Tensor>, scale: f32) -> Result<Tensor> {
    let (n, c, h, wd) = x.dims4()?;
    let co = w.dim(0)?;
    let (b, s) = (n / frames, h * wd);
    let w4 = w.reshape((co, kt, c))?.transpose(1, 2)?.contiguous()?.reshape((co, c, kt, 1))?;
    let key = ConvKey {
        dtype: conv_dtype(x.dtype())?,
        x: [b, c, frames, s],
        x_strides: [frames * c * s, s, c * s, 1],
        w: [co, c, kt, 1],
        y_strides: [frames * co * s, s, co * s, 1],
        stride: [1, 1],
        pad: [kt / 2, 0],
        dilation: [1, 1],
        groups: 1,
        bias: true,
        residual: residual.is_some(),
    };
    key.check()?;
    if key.out_dims() != [b, co, frames, s] {
        candle_core::bail!("cudnn temporal conv: kt {kt} must be odd");
    }
    apply(x, &w4, Some(bias), residual, scale, key, Shape::from((n, co, h, wd)))
}
