//! Convolutions on cuDNN with cached plans (`MVSPLAT360_GPU_OPS=cudnn`, see [`crate::gpu_ops`]).
//!
//! candle's own cuDNN conv rebuilds the descriptors, searches an algorithm and zeroes a fresh workspace on every
//! call and leaves the math type at its default. Here a [`ConvKey`] (dtype, shapes, strides, geometry, groups,
//! which epilogue inputs exist) maps to a plan — descriptors + algorithm + workspace size — made ONCE per device
//! by a [`ConvBackend`]; each device keeps one library handle and one workspace, grown to the largest need and
//! reused as is (cuDNN does not need a zeroed workspace). [`PlanCache`] holds that logic independent of CUDA so
//! that it is unit-tested with a fake backend; the cuDNN backend and the candle op are in `cuda.rs`.
//!
//! Math: f32 keeps full f32 products (`CUDNN_FMA_MATH`: no TF32), f16/bf16 allow tensor cores
//! (`CUDNN_TENSOR_OP_MATH`); both accumulate in f32.

use std::collections::{HashMap, HashSet};
use std::hash::Hash;
use std::sync::{Arc, Mutex, MutexGuard};

use candle_core::{Result, Tensor};

use crate::conv::Conv2dConfig;

#[cfg(feature = "cuda")]
mod cuda;

/// `residual + scale·(conv2d(x, w) + bias)` (groups 1, NCHW, f32/f16/bf16 CUDA tensors, no backward) on cuDNN,
/// or why it cannot run (no libcudnn, no CUDA build, an unsupported shape).
pub fn try_conv2d(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, residual: Option<&Tensor>, scale: f32, cfg: Conv2dConfig) -> Result<Tensor> {
    #[cfg(feature = "cuda")]
    return cuda::try_conv2d(x, w, bias, residual, scale, cfg);
    #[cfg(not(feature = "cuda"))]
    {
        let _ = (w, bias, residual, scale, cfg);
        Err(not_built(x))
    }
}

/// [`crate::conv::temporal_conv`] without the item bias (`residual + scale·(conv + bias)`, odd `kt`) on cuDNN,
/// or why it cannot run.
pub fn try_temporal(x: &Tensor, w: &Tensor, bias: &Tensor, kt: usize, frames: usize, residual: Option<&Tensor>, scale: f32) -> Result<Tensor> {
    #[cfg(feature = "cuda")]
    return cuda::try_temporal(x, w, bias, kt, frames, residual, scale);
    #[cfg(not(feature = "cuda"))]
    {
        let _ = (w, bias, kt, frames, residual, scale);
        Err(not_built(x))
    }
}

#[cfg(not(feature = "cuda"))]
fn not_built(x: &Tensor) -> candle_core::Error {
    let device = if x.device().is_cuda() { "CUDA" } else { "non-CUDA" };
    candle_core::Error::wrap(crate::NotBuilt { op: "cudnn conv (built without the `cuda` feature)", device: device.to_string() })
}

/// Warn once per distinct cause; the caller then takes candle's path.
fn fallback(r: Result<Tensor>) -> Option<Tensor> {
    match r {
        Ok(t) => Some(t),
        Err(e) => {
            static SEEN: Mutex<Option<HashSet<String>>> = Mutex::new(None);
            let msg = e.to_string();
            if lock(&SEEN).get_or_insert_with(HashSet::new).insert(msg.clone()) {
                eprintln!("warning: cuDNN convolution not used, candle's conv2d instead: {msg}");
            }
            None
        }
    }
}

/// [`try_conv2d`], None (after one warning per cause) when it cannot run.
pub(crate) fn conv2d(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, residual: Option<&Tensor>, scale: f32, cfg: Conv2dConfig) -> Option<Tensor> {
    fallback(try_conv2d(x, w, bias, residual, scale, cfg))
}

/// [`try_temporal`], None (after one warning per cause) when it cannot run.
pub(crate) fn temporal(x: &Tensor, w: &Tensor, bias: &Tensor, kt: usize, frames: usize, residual: Option<&Tensor>, scale: f32) -> Option<Tensor> {
    fallback(try_temporal(x, w, bias, kt, frames, residual, scale))
}

/// Element type of a convolution's tensors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ConvDType {
    F32,
    F16,
    BF16,
}

/// How the products may be computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MathType {
    /// Full-precision FMAs, no tensor cores (no TF32): the f32 GPU tests keep their 1e-4 bounds.
    Fma,
    /// Tensor cores allowed (f32 accumulation): the point of running half precision.
    TensorOp,
}

/// The math type a plan for `dtype` is made with.
pub fn math_type(dtype: ConvDType) -> MathType {
    match dtype {
        ConvDType::F32 => MathType::Fma,
        ConvDType::F16 | ConvDType::BF16 => MathType::TensorOp,
    }
}

/// Everything a plan depends on (besides the device). Tensors are 4-D with explicit element strides, so a
/// strided view (the temporal conv's (B, C, T, H·W) view of frame-major memory) is a key like any other.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ConvKey {
    pub dtype: ConvDType,
    /// Input (N, C, H, W) and its element strides.
    pub x: [usize; 4],
    pub x_strides: [usize; 4],
    /// Weight (Co, C / groups, kh, kw), packed NCHW.
    pub w: [usize; 4],
    /// Output element strides; the dims are [`ConvKey::out_dims`]. A residual has the output's layout.
    pub y_strides: [usize; 4],
    pub stride: [usize; 2],
    pub pad: [usize; 2],
    pub dilation: [usize; 2],
    pub groups: usize,
    pub bias: bool,
    pub residual: bool,
}

/// Row-major strides of packed `dims`.
pub fn packed_strides(d: [usize; 4]) -> [usize; 4] {
    [d[1] * d[2] * d[3], d[2] * d[3], d[3], 1]
}

impl ConvKey {
    /// A key for packed NCHW input and output.
    #[allow(clippy::too_many_arguments)]
    pub fn nchw(
        dtype: ConvDType,
        x: [usize; 4],
        w: [usize; 4],
        stride: [usize; 2],
        pad: [usize; 2],
        dilation: [usize; 2],
        bias: bool,
        residual: bool,
    ) -> Result<Self> {
        let mut key = Self { dtype, x, x_strides: packed_strides(x), w, y_strides: [0; 4], stride, pad, dilation, groups: 1, bias, residual };
        key.check()?;
        key.y_strides = packed_strides(key.out_dims());
        Ok(key)
    }

    /// Output (N, Co, Ho, Wo).
    pub fn out_dims(&self) -> [usize; 4] {
        let o = |i: usize, k: usize, s: usize, p: usize, d: usize| (i + 2 * p - d * (k - 1) - 1) / s + 1;
        [
            self.x[0],
            self.w[0],
            o(self.x[2], self.w[2], self.stride[0], self.pad[0], self.dilation[0]),
            o(self.x[3], self.w[3], self.stride[1], self.pad[1], self.dilation[1]),
        ]
    }

    /// The geometry is valid and every size fits cuDNN's `int`.
    pub fn check(&self) -> Result<()> {
        let (x, w) = (self.x, self.w);
        let ok = self.groups >= 1
            && w[1] * self.groups == x[1]
            && w[0] % self.groups == 0
            && x.iter().chain(&w).chain(&self.stride).chain(&self.dilation).all(|&v| v >= 1)
            && (0..2).all(|i| x[2 + i] + 2 * self.pad[i] > self.dilation[i] * (w[2 + i] - 1));
        let big =
            x.iter().chain(&w).chain(&self.x_strides).chain(&self.y_strides).any(|&v| v > i32::MAX as usize) || x.iter().product::<usize>() > i32::MAX as usize;
        if !ok || big {
            candle_core::bail!("cudnn conv: invalid or too large geometry {self:?}");
        }
        Ok(())
    }
}

/// What a library under [`PlanCache`] provides. `open` and `create_plan` run once per device and per key;
/// [`PlanCache::run`] hands the caller the device's handle, the plan and the workspace under one lock.
pub trait ConvBackend: Send + Sync {
    /// What a call brings to reach its device (the real backend: candle's `CudaDevice`).
    type Device;
    /// The device's identity in the caches.
    type DeviceId: Copy + Eq + Hash + std::fmt::Debug + Send + Sync;
    /// Per-device library state (cuDNN: a handle bound to the device's stream). Used under a lock only.
    type Handle: Send;
    /// Descriptors + algorithm + workspace size of one key.
    type Plan: Send + Sync;
    /// Device scratch memory.
    type Workspace: Send;

    fn device_id(device: &Self::Device) -> Self::DeviceId;
    fn open(&self, device: &Self::Device) -> Result<Self::Handle>;
    fn create_plan(&self, handle: &mut Self::Handle, key: &ConvKey, math: MathType) -> Result<Self::Plan>;
    fn workspace_bytes(plan: &Self::Plan) -> usize;
    /// Uninitialised scratch of `bytes` (never zeroed: cuDNN does not read it before writing).
    fn alloc_workspace(&self, handle: &mut Self::Handle, bytes: usize) -> Result<Self::Workspace>;
}

struct Slot<B: ConvBackend> {
    handle: B::Handle,
    workspace: Option<B::Workspace>,
    workspace_bytes: usize,
}

type Shared<T> = std::result::Result<Arc<T>, String>;

/// Plans per (device, key) and one handle + workspace per device, thread-safe. Failures (no library, an
/// unsupported shape) are cached as well, so they cost one attempt, not one per call.
pub struct PlanCache<B: ConvBackend> {
    backend: B,
    devices: Mutex<HashMap<B::DeviceId, Shared<Mutex<Slot<B>>>>>,
    plans: Mutex<HashMap<(B::DeviceId, ConvKey), Shared<B::Plan>>>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic in another thread's launch leaves the data consistent (it is only replaced whole).
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl<B: ConvBackend> PlanCache<B> {
    pub fn new(backend: B) -> Self {
        Self { backend, devices: Mutex::new(HashMap::new()), plans: Mutex::new(HashMap::new()) }
    }

    pub fn backend(&self) -> &B {
        &self.backend
    }

    fn slot(&self, device: &B::Device) -> Result<Arc<Mutex<Slot<B>>>> {
        let id = B::device_id(device);
        let mut devices = lock(&self.devices);
        let entry = devices.entry(id).or_insert_with(|| {
            self.backend.open(device).map(|handle| Arc::new(Mutex::new(Slot { handle, workspace: None, workspace_bytes: 0 }))).map_err(|e| e.to_string())
        });
        entry.clone().map_err(candle_core::Error::msg)
    }

    /// Lock order: `plans`, then a device slot; [`Self::run`] takes the slot only after releasing `plans`.
    fn plan(&self, id: B::DeviceId, slot: &Mutex<Slot<B>>, key: &ConvKey) -> Result<Arc<B::Plan>> {
        let mut plans = lock(&self.plans);
        if let Some(p) = plans.get(&(id, *key)) {
            return p.clone().map_err(candle_core::Error::msg);
        }
        // Made under the map's lock: each key is searched once even when threads race for it.
        let made = key.check().and_then(|_| self.backend.create_plan(&mut lock(slot).handle, key, math_type(key.dtype)));
        let entry = made.map(Arc::new).map_err(|e| e.to_string());
        plans.insert((id, *key), entry.clone());
        entry.map_err(candle_core::Error::msg)
    }

    /// Run `f` with the device's handle, the key's plan and a workspace of at least the plan's size (None when
    /// it needs none), all under the device's lock, so that one handle and one workspace serve every thread.
    pub fn run<R>(&self, device: &B::Device, key: &ConvKey, f: impl FnOnce(&mut B::Handle, &B::Plan, Option<&mut B::Workspace>) -> Result<R>) -> Result<R> {
        let id = B::device_id(device);
        let slot = self.slot(device)?;
        let plan = self.plan(id, &slot, key)?;
        let mut guard = lock(&slot);
        let s = &mut *guard;
        let need = B::workspace_bytes(&plan);
        if need > s.workspace_bytes {
            // Free the smaller one first (stream-ordered on CUDA, so in-flight work keeps it until done).
            s.workspace = None;
            s.workspace_bytes = 0;
            s.workspace = Some(self.backend.alloc_workspace(&mut s.handle, need)?);
            s.workspace_bytes = need;
        }
        let ws = if need > 0 { s.workspace.as_mut() } else { None };
        f(&mut s.handle, &plan, ws)
    }

    /// Number of cached plans (successful or failed).
    pub fn len(&self) -> usize {
        lock(&self.plans).len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

    /// Counts what the cache asks of a library; plans need `x[0]·100` bytes of workspace.
    #[derive(Default)]
    struct Fake {
        opens: AtomicUsize,
        plans: Mutex<Vec<(ConvKey, MathType)>>,
        allocs: Mutex<Vec<usize>>,
        fail_open: bool,
    }

    struct FakeHandle {
        busy: Arc<AtomicBool>,
    }

    struct FakePlan {
        key: ConvKey,
        math: MathType,
        bytes: usize,
    }

    impl ConvBackend for Fake {
        type Device = u32;
        type DeviceId = u32;
        type Handle = FakeHandle;
        type Plan = FakePlan;
        type Workspace = Vec<u8>;

        fn device_id(d: &u32) -> u32 {
            *d
        }

        fn open(&self, _: &u32) -> Result<FakeHandle> {
            self.opens.fetch_add(1, Ordering::SeqCst);
            if self.fail_open {
                candle_core::bail!("libfake.so.9: cannot open shared object file");
            }
            Ok(FakeHandle { busy: Arc::new(AtomicBool::new(false)) })
        }

        fn create_plan(&self, _: &mut FakeHandle, key: &ConvKey, math: MathType) -> Result<FakePlan> {
            // Slow enough that racing threads would both get here without the cache's lock.
            std::thread::sleep(std::time::Duration::from_millis(2));
            self.plans.lock().unwrap().push((*key, math));
            if key.x[1] == 13 {
                candle_core::bail!("CUDNN_STATUS_NOT_SUPPORTED");
            }
            Ok(FakePlan { key: *key, math, bytes: key.x[0] * 100 })
        }

        fn workspace_bytes(p: &FakePlan) -> usize {
            p.bytes
        }

        fn alloc_workspace(&self, _: &mut FakeHandle, bytes: usize) -> Result<Vec<u8>> {
            self.allocs.lock().unwrap().push(bytes);
            Ok(vec![0xAB; bytes])
        }
    }

    fn key(n: usize, c: usize, dtype: ConvDType, bias: bool, residual: bool) -> ConvKey {
        ConvKey::nchw(dtype, [n, c, 8, 8], [4, c, 3, 3], [1, 1], [1, 1], [1, 1], bias, residual).unwrap()
    }

    /// Runs `k` and returns (plan's key, plan's math, workspace length seen).
    fn run(cache: &PlanCache<Fake>, dev: u32, k: &ConvKey) -> (ConvKey, MathType, usize) {
        cache.run(&dev, k, |_, p, ws| Ok((p.key, p.math, ws.map_or(0, |w| w.len())))).unwrap()
    }

    #[test]
    fn same_key_searches_once() {
        let cache = PlanCache::new(Fake::default());
        let k = key(2, 3, ConvDType::F32, true, false);
        for _ in 0..5 {
            assert_eq!(run(&cache, 0, &k).0, k);
        }
        assert_eq!(cache.backend().opens.load(Ordering::SeqCst), 1);
        assert_eq!(cache.backend().plans.lock().unwrap().len(), 1);
        assert_eq!(*cache.backend().allocs.lock().unwrap(), [200]);
    }

    #[test]
    fn shapes_dtypes_flags_and_devices_get_their_own_plans_and_math() {
        let cache = PlanCache::new(Fake::default());
        let keys = [
            key(2, 3, ConvDType::F32, false, false),
            key(2, 5, ConvDType::F32, false, false),
            key(2, 3, ConvDType::BF16, false, false),
            key(2, 3, ConvDType::F16, false, false),
            key(2, 3, ConvDType::F32, true, false),
            key(2, 3, ConvDType::F32, false, true),
            key(2, 3, ConvDType::F32, true, true),
            ConvKey::nchw(ConvDType::F32, [2, 3, 8, 8], [4, 3, 3, 3], [2, 2], [1, 1], [1, 1], false, false).unwrap(),
        ];
        for k in &keys {
            let (got, math, _) = run(&cache, 0, k);
            assert_eq!(&got, k);
            assert_eq!(math, if k.dtype == ConvDType::F32 { MathType::Fma } else { MathType::TensorOp });
        }
        assert_eq!(cache.len(), keys.len());
        // Another device: its own handle and plans.
        run(&cache, 1, &keys[0]);
        assert_eq!(cache.backend().opens.load(Ordering::SeqCst), 2);
        assert_eq!(cache.len(), keys.len() + 1);
        let made = cache.backend().plans.lock().unwrap().clone();
        assert_eq!(made.len(), keys.len() + 1);
        assert!(made.iter().all(|(k, m)| *m == math_type(k.dtype)));
    }

    #[test]
    fn workspace_grows_to_the_largest_need_and_is_reused() {
        let cache = PlanCache::new(Fake::default());
        let seen: Vec<usize> = [3, 1, 5, 5, 2, 4, 5].iter().map(|&n| run(&cache, 0, &key(n, 3, ConvDType::F16, false, false)).2).collect();
        // Each run sees a buffer at least its need: the live one, replaced only when too small.
        assert_eq!(seen, [300, 300, 500, 500, 500, 500, 500]);
        assert_eq!(*cache.backend().allocs.lock().unwrap(), [300, 500]);
        // A second device has its own.
        assert_eq!(run(&cache, 7, &key(1, 3, ConvDType::F16, false, false)).2, 100);
        assert_eq!(*cache.backend().allocs.lock().unwrap(), [300, 500, 100]);
    }

    #[test]
    fn failures_are_cached_and_reported() {
        let cache = PlanCache::new(Fake::default());
        let bad = key(2, 13, ConvDType::F32, false, false);
        for _ in 0..3 {
            let e = cache.run(&0, &bad, |_, _, _| Ok(())).unwrap_err().to_string();
            assert!(e.contains("NOT_SUPPORTED"), "{e}");
        }
        assert_eq!(cache.backend().plans.lock().unwrap().len(), 1);
        // Other keys still work.
        run(&cache, 0, &key(2, 3, ConvDType::F32, false, false));

        let no_lib = PlanCache::new(Fake { fail_open: true, ..Default::default() });
        for _ in 0..3 {
            assert!(no_lib.run(&0, &bad, |_, _, _| Ok(())).unwrap_err().to_string().contains("cannot open"));
        }
        assert_eq!(no_lib.backend().opens.load(Ordering::SeqCst), 1);
        assert!(no_lib.backend().plans.lock().unwrap().is_empty());
    }

    #[test]
    fn invalid_geometry_is_an_error_not_a_plan() {
        assert!(ConvKey::nchw(ConvDType::F32, [1, 3, 2, 2], [4, 3, 5, 5], [1, 1], [0, 0], [1, 1], false, false).is_err());
        assert!(ConvKey::nchw(ConvDType::F32, [1, 3, 8, 8], [4, 2, 3, 3], [1, 1], [1, 1], [1, 1], false, false).is_err());
        let k = ConvKey::nchw(ConvDType::F32, [2, 3, 9, 11], [4, 3, 3, 3], [2, 2], [1, 1], [1, 1], false, false).unwrap();
        assert_eq!(k.out_dims(), [2, 4, 5, 6]);
        assert_eq!(k.y_strides, [120, 30, 6, 1]);
    }

    #[test]
    fn concurrent_use_is_safe_and_searches_each_key_once() {
        let cache = Arc::new(PlanCache::new(Fake::default()));
        let keys: Vec<ConvKey> = (1..=4).flat_map(|n| [key(n, 3, ConvDType::F32, true, false), key(n, 3, ConvDType::BF16, false, true)]).collect();
        let threads: Vec<_> = (0..8)
            .map(|t| {
                let (cache, keys) = (cache.clone(), keys.clone());
                std::thread::spawn(move || {
                    for i in 0..200 {
                        let k = &keys[(i * 7 + t) % keys.len()];
                        let dev = (i % 2) as u32;
                        let len = cache
                            .run(&dev, k, |h, p, ws| {
                                // The handle and workspace are never used by two threads at once.
                                assert!(!h.busy.swap(true, Ordering::SeqCst), "handle used concurrently");
                                let len = ws.map_or(0, |w| {
                                    w[0] = t as u8;
                                    std::thread::yield_now();
                                    assert_eq!(w[0], t as u8, "workspace shared while in use");
                                    w.len()
                                });
                                h.busy.store(false, Ordering::SeqCst);
                                assert!(len >= p.bytes);
                                Ok(len)
                            })
                            .unwrap();
                        assert!(len >= k.x[0] * 100);
                    }
                })
            })
            .collect();
        threads.into_iter().for_each(|t| t.join().unwrap());
        let b = cache.backend();
        assert_eq!(b.opens.load(Ordering::SeqCst), 2);
        assert_eq!(b.plans.lock().unwrap().len(), 2 * keys.len(), "each (device, key) searched once");
        // Workspaces only grow: per device, allocations are increasing.
        let allocs = b.allocs.lock().unwrap();
        assert!(allocs.len() <= 8 && allocs.iter().all(|&a| a <= 400), "{allocs:?}");
    }
}
