//! candle glue: the rasterizer as a `CustomOp1` over one packed per-Gaussian tensor, so that candle's own
//! `cat`/`index_select` backward routes the gradient to means, covariances, opacities, SH and features.

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp1, DType, Device, Layout, Shape, Tensor};

use crate::camera::RasterCamera;
use crate::cpu::{self, CovInput, ForwardOutput, GradMode, PixelGrads, RasterInputs, RasterSettings};
use crate::error::{input_err, Result};
use crate::gaussians::Gaussians;
use crate::sh;

/// Options of [`render`].
#[derive(Debug, Clone, Copy)]
pub struct RenderOptions {
    /// RGB background (features get none).
    pub background: [f32; 3],
    /// Active SH degree passed to the kernel (MVSplat360 passes 4; degrees > 3 are ignored like the fork does).
    pub sh_degree: usize,
    pub grad_mode: GradMode,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self { background: [0.0; 3], sh_degree: 4, grad_mode: GradMode::Official }
    }
}

/// One rendered view.
#[derive(Debug, Clone)]
pub struct RenderOutput {
    /// (3,H,W)
    pub rgb: Tensor,
    /// (C,H,W), no background.
    pub features: Tensor,
    /// (1,H,W)
    pub alpha: Tensor,
    /// (1,H,W) expected z-depth Σ w z (not divided by alpha).
    pub depth: Tensor,
    /// (N,) u32 pixel radii (0 = not visible).
    pub radii: Tensor,
}

/// Column layout of the packed per-Gaussian tensor: means 3 | cov 6 | opacity 1 | SH K·3 | features C. With
/// `held`, the tensor has the first 10 columns only and the SH and feature columns (rows of K·3 + C) travel in the
/// op: constants then cost no gradient buffers.
#[derive(Debug)]
struct Packing {
    n: usize,
    k: usize,
    nf: usize,
    held: Option<Vec<f32>>,
}

impl Packing {
    fn width(&self) -> usize {
        if self.held.is_some() {
            10
        } else {
            10 + 3 * self.k + self.nf
        }
    }
    fn unpack(&self, data: &[f32]) -> [Vec<f32>; 5] {
        let (n, k, nf, d) = (self.n, self.k, self.nf, self.width());
        let r = 3 * k + nf;
        let mut means = Vec::with_capacity(3 * n);
        let mut cov = Vec::with_capacity(6 * n);
        let mut op = Vec::with_capacity(n);
        let mut shv = Vec::with_capacity(3 * k * n);
        let mut feat = Vec::with_capacity(nf * n);
        for (i, row) in data.chunks_exact(d).enumerate() {
            means.extend_from_slice(&row[0..3]);
            cov.extend_from_slice(&row[3..9]);
            op.push(row[9]);
            let rest = match &self.held {
                Some(h) => &h[r * i..r * (i + 1)],
                None => &row[10..],
            };
            shv.extend_from_slice(&rest[..3 * k]);
            feat.extend_from_slice(&rest[3 * k..]);
        }
        [means, cov, op, shv, feat]
    }
}

struct RasterOp {
    settings: RasterSettings,
    mode: GradMode,
    sh_degree: usize,
    packing: Packing,
    /// Forward buffers kept for the backward pass (and to read radii).
    state: Arc<Mutex<Option<ForwardOutput>>>,
    /// The same for a forward on the GPU: device buffers and the radii (host).
    #[cfg(feature = "cuda")]
    cuda_state: Arc<Mutex<Option<gpu::GpuForward>>>,
}

fn inputs<'a>(p: &Packing, sh_degree: usize, u: &'a [Vec<f32>; 5]) -> RasterInputs<'a> {
    RasterInputs { means: &u[0], cov: CovInput::Cov3d(&u[1]), opacities: &u[2], sh: &u[3], sh_coeffs: p.k, sh_degree, features: &u[4], num_features: p.nf }
}

fn to_candle(e: crate::error::SplatError) -> candle_core::Error {
    candle_core::Error::Msg(e.to_string())
}

impl CustomOp1 for RasterOp {
    fn name(&self) -> &'static str {
        "gaussian-rasterizer"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let CpuStorage::F32(data) = storage else { candle_core::bail!("gaussian-rasterizer: packed input must be f32") };
        let Some((a, b)) = layout.contiguous_offsets() else { candle_core::bail!("gaussian-rasterizer: packed input must be contiguous") };
        let u = self.packing.unpack(&data[a..b]);
        let inp = inputs(&self.packing, self.sh_degree, &u);
        let fwd = cpu::forward(&inp, &self.settings).map_err(to_candle)?;
        let (w, h, nf) = (fwd.width, fwd.height, fwd.num_features);
        let mut out = Vec::with_capacity((5 + nf) * w * h);
        out.extend_from_slice(&fwd.rgb);
        out.extend_from_slice(&fwd.features);
        out.extend_from_slice(&fwd.alpha);
        out.extend_from_slice(&fwd.depth);
        if let Ok(mut st) = self.state.lock() {
            *st = Some(fwd);
        }
        Ok((CpuStorage::F32(out), Shape::from((5 + nf, h, w))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(&self, storage: &candle_core::CudaStorage, layout: &Layout) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        gpu::forward(self, storage, layout)
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> candle_core::Result<Option<Tensor>> {
        #[cfg(feature = "cuda")]
        if arg.device().is_cuda() {
            let op = gpu::RasterGradOp { mode: self.mode, rows: self.packing.n, width: self.packing.width(), state: self.cuda_state.clone() };
            return Ok(Some(arg.apply_op2_no_bwd(&grad_res.to_dtype(DType::F32)?.contiguous()?, &op)?));
        }
        let dev = arg.device().clone();
        let data = arg.to_device(&Device::Cpu)?.flatten_all()?.to_vec1::<f32>()?;
        let u = self.packing.unpack(&data);
        let inp = inputs(&self.packing, self.sh_degree, &u);
        let g = grad_res.to_device(&Device::Cpu)?.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        let (w, h) = (self.settings.camera.width, self.settings.camera.height);
        let (hw, nf) = (w * h, self.packing.nf);
        let pg = PixelGrads {
            rgb: &g[..3 * hw],
            features: &g[3 * hw..(3 + nf) * hw],
            alpha: Some(&g[(3 + nf) * hw..(4 + nf) * hw]),
            depth: Some(&g[(4 + nf) * hw..(5 + nf) * hw]),
        };
        // Taken, not cloned: a backward runs once per forward (a second one recomputes the forward below).
        let cached = self.state.lock().ok().and_then(|mut s| s.take());
        let fwd = match cached {
            Some(f) => f,
            None => cpu::forward(&inp, &self.settings).map_err(to_candle)?,
        };
        let gr = cpu::backward(&inp, &self.settings, &fwd, &pg, self.mode).map_err(to_candle)?;
        let p = &self.packing;
        let d = p.width();
        let mut packed = vec![0f32; p.n * d];
        for (i, row) in packed.chunks_exact_mut(d).enumerate() {
            row[0..3].copy_from_slice(&gr.means[3 * i..3 * i + 3]);
            row[3..9].copy_from_slice(&gr.cov3d[6 * i..6 * i + 6]);
            row[9] = gr.opacities[i];
            if p.held.is_none() {
                row[10..10 + 3 * p.k].copy_from_slice(&gr.sh[3 * p.k * i..3 * p.k * (i + 1)]);
                row[10 + 3 * p.k..].copy_from_slice(&gr.features[nf * i..nf * (i + 1)]);
            }
        }
        Ok(Some(Tensor::from_vec(packed, (p.n, d), &dev)?))
    }
}

fn check_dims(name: &'static str, t: &Tensor, want: &[Option<usize>]) -> Result<()> {
    let dims = t.dims();
    let ok = dims.len() == want.len() && dims.iter().zip(want).all(|(d, w)| w.is_none_or(|w| *d == w));
    if !ok {
        return Err(input_err(name, format!("shape {dims:?} does not match expected {want:?} (None = any)")));
    }
    Ok(())
}

/// Unit view directions (N,3) from the camera centre (differentiable).
fn view_dirs(means: &Tensor, campos: [f32; 3]) -> Result<Tensor> {
    let c = Tensor::new(&campos, means.device())?.to_dtype(means.dtype())?.unsqueeze(0)?;
    let d = means.broadcast_sub(&c)?;
    let norm = (d.sqr()?.sum_keepdim(1)? + 1e-30)?.sqrt()?;
    Ok(d.broadcast_div(&norm)?)
}

/// Render one view of `g` (RGB + latent features), differentiable w.r.t. every field of `g`.
pub fn render(g: &Gaussians, camera: &RasterCamera, opts: &RenderOptions) -> Result<RenderOutput> {
    camera.validate()?;
    let n = g.means.dims().first().copied().unwrap_or(0);
    check_dims("means", &g.means, &[Some(n), Some(3)])?;
    check_dims("covariances", &g.covariances, &[Some(n), Some(3), Some(3)])?;
    check_dims("opacities", &g.opacities, &[Some(n)])?;
    check_dims("harmonics", &g.harmonics, &[Some(n), Some(3), None])?;
    check_dims("feature_harmonics", &g.feature_harmonics, &[Some(n), None, None])?;
    let dev = g.means.device().clone();
    let k = g.harmonics.dim(2)?;
    let nf = g.feature_harmonics.dim(1)?;
    let (w, h) = (camera.width, camera.height);
    if k == 0 {
        return Err(input_err("harmonics", "need at least the DC coefficient"));
    }
    if n == 0 {
        let bg = Tensor::new(&opts.background, &dev)?.reshape((3, 1, 1))?.broadcast_as((3, h, w))?.contiguous()?;
        return Ok(RenderOutput {
            rgb: bg,
            features: Tensor::zeros((nf, h, w), DType::F32, &dev)?,
            alpha: Tensor::zeros((1, h, w), DType::F32, &dev)?,
            depth: Tensor::zeros((1, h, w), DType::F32, &dev)?,
            radii: Tensor::zeros(0, DType::U32, &dev)?,
        });
    }
    let f32t = |t: &Tensor| t.to_dtype(DType::F32);
    let means = f32t(&g.means)?;
    let dirs = view_dirs(&means, camera.campos())?;
    let feats = sh::eval_feature_sh(&f32t(&g.feature_harmonics)?, &dirs)?;
    let idx = Tensor::new(&[0u32, 1, 2, 4, 5, 8], &dev)?;
    // The official wrapper passes the upper triangle of the covariance (cov3D_precomp).
    let cov6 = f32t(&g.covariances)?.reshape((n, 9))?.index_select(&idx, 1)?;
    let shc = f32t(&g.harmonics)?.transpose(1, 2)?.reshape((n, 3 * k))?;
    let opac = f32t(&g.opacities)?.reshape((n, 1))?;
    // With the CUDA kernels built, a GPU tensor stays on its device; anything else runs on the CPU kernels.
    let on_gpu = cfg!(feature = "cuda") && dev.is_cuda();
    // Where only the geometry takes gradients (test-time fitting), the constant colours and features are held by
    // the op: autograd's concatenation would otherwise allocate, zero and sum a gradient for each of their columns
    // at every render. Without any gradient the one concatenation below is cheaper.
    let geometry_grads = means.track_op() || cov6.track_op() || opac.track_op();
    let hold = !on_gpu && geometry_grads && !shc.track_op() && (nf == 0 || !feats.track_op());
    let (packed, held) = if hold {
        let rest = Tensor::cat(&[&shc, &feats], 1)?.to_device(&Device::Cpu)?.flatten_all()?.to_vec1::<f32>()?;
        (Tensor::cat(&[&means, &cov6, &opac], 1)?, Some(rest))
    } else {
        (Tensor::cat(&[&means, &cov6, &opac, &shc, &feats], 1)?, None)
    };
    let packed = if on_gpu { packed } else { packed.to_device(&Device::Cpu)? }.contiguous()?;
    let state = Arc::new(Mutex::new(None));
    #[cfg(feature = "cuda")]
    let cuda_state = Arc::new(Mutex::new(None));
    let op = RasterOp {
        settings: RasterSettings { camera: *camera, background: opts.background },
        mode: opts.grad_mode,
        sh_degree: opts.sh_degree,
        packing: Packing { n, k, nf, held },
        state: state.clone(),
        #[cfg(feature = "cuda")]
        cuda_state: cuda_state.clone(),
    };
    let out = packed.apply_op1_arc(Arc::new(Box::new(op)))?.to_device(&dev)?;
    let visible = |r: &[i32]| r.iter().map(|&r| r.max(0) as u32).collect::<Vec<u32>>();
    let radii = state.lock().ok().and_then(|s| s.as_ref().map(|f| visible(&f.radii)));
    #[cfg(feature = "cuda")]
    let radii = radii.or_else(|| cuda_state.lock().ok().and_then(|s| s.as_ref().map(|f| visible(&f.radii))));
    let radii = radii.unwrap_or_else(|| vec![0; n]);
    Ok(RenderOutput {
        rgb: out.narrow(0, 0, 3)?,
        features: out.narrow(0, 3, nf)?,
        alpha: out.narrow(0, 3 + nf, 1)?,
        depth: out.narrow(0, 4 + nf, 1)?,
        radii: Tensor::from_vec(radii, n, &dev)?,
    })
}

/// Render several views of one scene (each render is itself tile-parallel).
pub fn render_views(g: &Gaussians, cameras: &[RasterCamera], opts: &RenderOptions) -> Result<Vec<RenderOutput>> {
    cameras.iter().map(|c| render(g, c, opts)).collect()
}

/// The GPU path of the op: the kernels of `cuda/rasterize.cu` on candle's own stream, so encoder → rasterizer
/// → refiner stay on the device (only the radii and the pair count are read back).
#[cfg(feature = "cuda")]
mod gpu {
    use std::sync::{Arc, Mutex, OnceLock};

    use candle_core::cuda::{CudaDevice, CudaStorage, DeviceId};
    use candle_core::{CpuStorage, CustomOp2, Layout, Shape};

    use super::{to_candle, RasterOp};
    use crate::cpu::GradMode;
    use crate::cuda::{CudaRasterizer, DeviceState};

    pub(super) struct GpuForward {
        pub radii: Vec<i32>,
        pub state: DeviceState,
    }

    /// One loaded rasterizer per GPU (loading the PTX costs a JIT compile).
    fn rasterizer(dev: &CudaDevice) -> candle_core::Result<Arc<CudaRasterizer>> {
        static LOADED: OnceLock<Mutex<Vec<(DeviceId, Arc<CudaRasterizer>)>>> = OnceLock::new();
        let mut loaded = LOADED.get_or_init(|| Mutex::new(Vec::new())).lock().map_err(|_| candle_core::Error::msg("rasterizer cache poisoned"))?;
        if let Some((_, r)) = loaded.iter().find(|(id, _)| *id == dev.id()) {
            return Ok(r.clone());
        }
        let r = Arc::new(CudaRasterizer::on_stream(dev.cuda_stream()).map_err(to_candle)?);
        loaded.push((dev.id(), r.clone()));
        Ok(r)
    }

    pub(super) fn forward(op: &RasterOp, storage: &CudaStorage, layout: &Layout) -> candle_core::Result<(CudaStorage, Shape)> {
        let Some((a, b)) = layout.contiguous_offsets() else { candle_core::bail!("gaussian-rasterizer: packed input must be contiguous") };
        let packed = storage.as_cuda_slice::<f32>()?.slice(a..b);
        let r = rasterizer(&storage.device)?;
        let p = &op.packing;
        let (out, radii, state) = r.forward_packed(&packed, p.n, p.k, p.nf, op.sh_degree, &op.settings).map_err(to_candle)?;
        if let Ok(mut st) = op.cuda_state.lock() {
            *st = Some(GpuForward { radii, state });
        }
        let (w, h) = (op.settings.camera.width, op.settings.camera.height);
        Ok((CudaStorage::wrap_cuda_slice(out, storage.device.clone()), Shape::from((5 + p.nf, h, w))))
    }

    /// Gradient of the packed input from the output's gradient (second argument), with the forward's state.
    pub(super) struct RasterGradOp {
        pub mode: GradMode,
        pub rows: usize,
        pub width: usize,
        pub state: Arc<Mutex<Option<GpuForward>>>,
    }

    impl CustomOp2 for RasterGradOp {
        fn name(&self) -> &'static str {
            "gaussian-rasterizer-backward"
        }

        fn cpu_fwd(&self, _: &CpuStorage, _: &Layout, _: &CpuStorage, _: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
            candle_core::bail!("gaussian-rasterizer-backward: GPU tensors only (the CPU backward runs in the op's bwd)")
        }

        fn cuda_fwd(&self, _: &CudaStorage, _: &Layout, g: &CudaStorage, lg: &Layout) -> candle_core::Result<(CudaStorage, Shape)> {
            let Some((a, b)) = lg.contiguous_offsets() else { candle_core::bail!("gaussian-rasterizer-backward: gradient must be contiguous") };
            let grad = g.as_cuda_slice::<f32>()?.slice(a..b);
            let st = self.state.lock().map_err(|_| candle_core::Error::msg("rasterizer state poisoned"))?;
            let Some(fwd) = st.as_ref() else { candle_core::bail!("gaussian-rasterizer-backward: no forward state (the forward did not run on this GPU)") };
            let r = rasterizer(&g.device)?;
            let packed = r.backward_packed(&fwd.state, &grad, self.mode).map_err(to_candle)?;
            Ok((CudaStorage::wrap_cuda_slice(packed, g.device.clone()), Shape::from((self.rows, self.width))))
        }
    }
}
