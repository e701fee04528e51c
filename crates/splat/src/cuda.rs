//! CUDA rasterizer (feature `cuda-raster`, also enabled by `cuda`): the kernels of `cuda/rasterize.cu`,
//! compiled to PTX by build.rs and embedded, driven through cudarc with the launch sequence of
//! `cuda/emulate_main.cpp` (whose CPU emulation tests/cuda_emulated.rs checks against [`crate::cpu`]).
//! Slice-level API like `cpu`: host slices in, host vectors out; both gradient modes.
//!
//! Gradients are accumulated with atomicAdd, so they vary in the last bits from run to run.

use std::sync::Arc;

use cudarc::driver::{CudaContext, CudaFunction, CudaModule, CudaSlice, CudaStream, CudaView, DeviceRepr, LaunchConfig, PushKernelArg, ValidAsZeroBits};
use cudarc::nvrtc::Ptx;

use crate::cpu::{CovInput, GradMode, Gradients, PixelGrads, RasterInputs, RasterSettings, TILE};
use crate::error::{input_err, Result, SplatError};

/// PTX of `cuda/rasterize.cu` for sm_80 (built by build.rs).
pub const PTX: &str = include_str!(concat!(env!("OUT_DIR"), "/rasterize.ptx"));

/// Threads per 1-D block; the scan kernel assumes exactly this (BLOCK_SIZE in rasterize.cu).
const BLOCK: u32 = 256;
/// Feature channels the tile kernels support (MAX_FEAT in rasterize.cu).
pub const MAX_FEATURES: usize = 16;

fn cuda_err(e: impl std::fmt::Display) -> SplatError {
    SplatError::Candle(candle_core::Error::msg(format!("CUDA rasterizer: {e}")))
}

/// 1-D launch over `n` threads.
fn lin(n: usize) -> LaunchConfig {
    LaunchConfig { grid_dim: ((n as u32).div_ceil(BLOCK).max(1), 1, 1), block_dim: (BLOCK, 1, 1), shared_mem_bytes: 0 }
}

/// Camera and background in the kernels' `params` layout (P_* in rasterize.cu).
fn params_of(s: &RasterSettings) -> Vec<f32> {
    let cam = &s.camera;
    let mut p = Vec::with_capacity(P_LEN);
    p.extend(cam.viewmatrix.iter().flatten()); // P_VIEW = 0
    p.extend(cam.full_proj().iter().flatten()); // P_PROJ = 16
    p.extend(cam.campos()); // P_CAMPOS = 32
    p.extend(cam.focal()); // P_FOCAL = 35
    p.extend(cam.tanfov()); // P_TANFOV = 37
    p.extend(s.background); // P_BG = 39
    debug_assert_eq!(p.len(), P_LEN);
    p
}

/// Length of `params` (P_LEN in rasterize.cu).
const P_LEN: usize = 42;

/// Largest pair count the binning handles: the bitonic sort pads to a power of two that must fit the
/// kernels' `unsigned` indices (and the host's u32 stage/distance loop).
const MAX_PAIRS: u64 = 1 << 31;

/// `.version` and `.target` lines of the PTX, for load errors (a driver older than the nvcc that built the
/// PTX rejects it).
fn ptx_header() -> String {
    PTX.lines().map(str::trim).filter(|l| l.starts_with(".version") || l.starts_with(".target")).collect::<Vec<_>>().join(", ")
}

struct Kernels {
    preprocess: CudaFunction,
    scan_block: CudaFunction,
    scan_add: CudaFunction,
    duplicate: CudaFunction,
    fill_pad: CudaFunction,
    bitonic_step: CudaFunction,
    tile_ranges: CudaFunction,
    render_fwd: CudaFunction,
    render_bwd: CudaFunction,
    preprocess_bwd: CudaFunction,
    unpack_cols: CudaFunction,
    pack_cols: CudaFunction,
}

/// The loaded kernels and the stream they run on.
pub struct CudaRasterizer {
    stream: Arc<CudaStream>,
    k: Kernels,
    _module: Arc<CudaModule>,
}

/// Device copies of the inputs and the forward state the backward reuses.
pub struct DeviceState {
    n: usize,
    k: usize,
    deg: i32,
    nf: usize,
    width: usize,
    height: usize,
    params: CudaSlice<f32>,
    means: CudaSlice<f32>,
    /// cov3d (6 per Gaussian) or scales (3) + quats (4).
    cov: CudaSlice<f32>,
    rot: Option<CudaSlice<f32>>,
    sh: CudaSlice<f32>,
    features: CudaSlice<f32>,
    depths: CudaSlice<f32>,
    radii: CudaSlice<i32>,
    clamped: CudaSlice<i32>,
    means2d: CudaSlice<f32>,
    conic_opacity: CudaSlice<f32>,
    colors: CudaSlice<f32>,
    ranges: CudaSlice<u32>,
    point_list: CudaSlice<u32>,
    final_t: CudaSlice<f32>,
    n_contrib: CudaSlice<u32>,
}

/// Forward results (host copies, planar images) plus the device state for [`CudaRasterizer::backward`].
pub struct CudaForward {
    pub width: usize,
    pub height: usize,
    pub num_features: usize,
    /// (3,H,W) incl. background.
    pub rgb: Vec<f32>,
    /// (C,H,W), no background.
    pub features: Vec<f32>,
    /// (H,W)
    pub alpha: Vec<f32>,
    /// (H,W) Σ w z.
    pub depth: Vec<f32>,
    /// (H,W)
    pub final_t: Vec<f32>,
    /// (H,W)
    pub n_contrib: Vec<u32>,
    /// (N,) 0 = culled.
    pub radii: Vec<i32>,
    pub tiles_touched: Vec<u32>,
    /// (N,2)
    pub means2d: Vec<f32>,
    pub depths: Vec<f32>,
    /// (N,3)
    pub cov2d: Vec<f32>,
    /// (N,3) A, B, C (the device keeps A, B, C, opacity).
    pub conic: Vec<f32>,
    /// (N,3)
    pub colors: Vec<f32>,
    pub num_pairs: usize,
    dev: DeviceState,
}

impl CudaRasterizer {
    /// Load the kernels on GPU `ordinal` (own stream).
    pub fn new(ordinal: usize) -> Result<Self> {
        let ctx = CudaContext::new(ordinal).map_err(cuda_err)?;
        let stream = ctx.new_stream().map_err(cuda_err)?;
        Self::on_stream(stream)
    }

    /// Load the kernels into the context of `stream` and launch them on it (candle's stream, so that the
    /// rasterizer is ordered with candle's ops without synchronising).
    pub fn on_stream(stream: Arc<CudaStream>) -> Result<Self> {
        let module = stream.context().load_module(Ptx::from_src(PTX)).map_err(|e| {
            cuda_err(format!(
                "loading the kernels' PTX ({}) failed: {e} (a driver older than the nvcc that built it cannot \
                 JIT it; MVSPLAT360_CUDA_ARCH picks the target)",
                ptx_header()
            ))
        })?;
        let f = |name: &str| module.load_function(name).map_err(cuda_err);
        let k = Kernels {
            preprocess: f("rast_preprocess")?,
            scan_block: f("rast_scan_block")?,
            scan_add: f("rast_scan_add")?,
            duplicate: f("rast_duplicate")?,
            fill_pad: f("rast_fill_pad")?,
            bitonic_step: f("rast_bitonic_step")?,
            tile_ranges: f("rast_tile_ranges")?,
            render_fwd: f("rast_render_fwd")?,
            render_bwd: f("rast_render_bwd")?,
            preprocess_bwd: f("rast_preprocess_bwd")?,
            unpack_cols: f("rast_unpack_cols")?,
            pack_cols: f("rast_pack_cols")?,
        };
        Ok(Self { stream, k, _module: module })
    }

    /// The stream the kernels run on (to place inputs for [`Self::forward_packed`]).
    pub fn stream(&self) -> &Arc<CudaStream> {
        &self.stream
    }

    /// Upload; empty slices become one zero so every pointer is valid.
    fn up<T: DeviceRepr + ValidAsZeroBits + Copy>(&self, v: &[T]) -> Result<CudaSlice<T>> {
        if v.is_empty() {
            self.zeros(1)
        } else {
            self.stream.clone_htod(v).map_err(cuda_err)
        }
    }

    fn zeros<T: DeviceRepr + ValidAsZeroBits>(&self, len: usize) -> Result<CudaSlice<T>> {
        self.stream.alloc_zeros::<T>(len.max(1)).map_err(cuda_err)
    }

    /// Download `d[..len]`. cudarc 0.19 issues the copy into a `Vec` asynchronously and relies on the driver
    /// treating pageable memory synchronously, which CUDA documents only as "might be" (HMM/ATS systems):
    /// synchronize before the host reads it.
    fn down<T: DeviceRepr + Default + Clone>(&self, d: &CudaSlice<T>, len: usize) -> Result<Vec<T>> {
        if len == 0 {
            return Ok(Vec::new());
        }
        let v = self.stream.clone_dtoh(&d.slice(..len)).map_err(cuda_err)?;
        self.stream.synchronize().map_err(cuda_err)?;
        Ok(v)
    }

    /// Exclusive scan of `input[..n]` into `out` (block scans, block sums scanned recursively, added back).
    fn exclusive_scan(&self, input: &CudaSlice<u32>, out: &mut CudaSlice<u32>, n: usize) -> Result<()> {
        let nb = n.div_ceil(BLOCK as usize);
        let mut sums = self.zeros::<u32>(nb)?;
        let n_i = n as i32;
        let mut b = self.stream.launch_builder(&self.k.scan_block);
        b.arg(input).arg(&mut *out).arg(&mut sums).arg(&n_i);
        // SAFETY: argument types and lengths match rast_scan_block.
        unsafe { b.launch(lin(n)) }.map_err(cuda_err)?;
        if nb > 1 {
            let mut scanned = self.zeros::<u32>(nb)?;
            self.exclusive_scan(&sums, &mut scanned, nb)?;
            let mut b = self.stream.launch_builder(&self.k.scan_add);
            b.arg(&mut *out).arg(&scanned).arg(&n_i);
            // SAFETY: as above.
            unsafe { b.launch(lin(n)) }.map_err(cuda_err)?;
        }
        Ok(())
    }

    /// Forward rasterization of one view.
    pub fn forward(&self, inp: &RasterInputs, s: &RasterSettings) -> Result<CudaForward> {
        inp.validate()?;
        s.camera.validate()?;
        let (n, nf, kc) = (inp.len(), inp.num_features, inp.sh_coeffs);
        check_limits(n, nf, s)?;
        let (cov, rot) = match inp.cov {
            CovInput::Cov3d(c) => (self.up(c)?, None),
            CovInput::ScaleRot { scales, quats } => (self.up(scales)?, Some(self.up(quats)?)),
        };
        let di = DeviceInputs {
            n,
            k: kc,
            deg: inp.eval_degree() as i32,
            nf,
            means: self.up(inp.means)?,
            cov,
            rot,
            opacities: self.up(inp.opacities)?,
            sh: self.up(inp.sh)?,
            features: self.up(inp.features)?,
        };
        let f = self.run_forward(di, s)?;
        let hw = s.camera.width * s.camera.height;
        let d = &f.state;
        let conic4 = self.down(&d.conic_opacity, 4 * n)?;
        Ok(CudaForward {
            width: s.camera.width,
            height: s.camera.height,
            num_features: nf,
            rgb: self.down(&f.rgb, 3 * hw)?,
            features: self.down(&f.feat, nf * hw)?,
            alpha: self.down(&f.alpha, hw)?,
            depth: self.down(&f.depth, hw)?,
            final_t: self.down(&d.final_t, hw)?,
            n_contrib: self.down(&d.n_contrib, hw)?,
            radii: self.down(&d.radii, n)?,
            tiles_touched: f.tiles_touched,
            means2d: self.down(&d.means2d, 2 * n)?,
            depths: self.down(&d.depths, n)?,
            cov2d: self.down(&f.cov2d, 3 * n)?,
            conic: conic4.chunks(4).flat_map(|c| [c[0], c[1], c[2]]).collect(),
            colors: self.down(&d.colors, 3 * n)?,
            num_pairs: f.pairs,
            dev: f.state,
        })
    }

    /// The launch sequence of the forward on inputs already on the device. Synchronises once, to read the
    /// pair count.
    fn run_forward(&self, inp: DeviceInputs, s: &RasterSettings) -> Result<DeviceForward> {
        let DeviceInputs { n, k: kc, deg, nf, means, cov, rot, opacities: opac, sh, features } = inp;
        let (w, h) = (s.camera.width, s.camera.height);
        let (gx, gy) = (w.div_ceil(TILE), h.div_ceil(TILE));
        let hw = w * h;
        let (n_i, k_i, nf_i, w_i, h_i) = (n as i32, kc as i32, nf as i32, w as i32, h as i32);

        // Kept alive until the download of `tiles` below synchronizes the stream (the upload reads it).
        let params_host = params_of(s);
        let params = self.up(&params_host)?;

        let mut radii = self.zeros::<i32>(n)?;
        let mut means2d = self.zeros::<f32>(2 * n)?;
        let mut depths = self.zeros::<f32>(n)?;
        let mut cov2d = self.zeros::<f32>(3 * n)?;
        let mut conic_opacity = self.zeros::<f32>(4 * n)?;
        let mut colors = self.zeros::<f32>(3 * n)?;
        let mut clamped = self.zeros::<i32>(n)?;
        let mut tiles = self.zeros::<u32>(n)?;
        let null = 0u64;
        if n > 0 {
            let mut b = self.stream.launch_builder(&self.k.preprocess);
            b.arg(&n_i).arg(&means);
            // cov3d_in, scales, quats: the unused ones are null pointers.
            match &rot {
                None => b.arg(&cov).arg(&null).arg(&null),
                Some(q) => b.arg(&null).arg(&cov).arg(q),
            };
            b.arg(&opac).arg(&sh).arg(&k_i).arg(&deg).arg(&params).arg(&w_i).arg(&h_i);
            b.arg(&mut radii).arg(&mut means2d).arg(&mut depths).arg(&mut cov2d).arg(&mut conic_opacity);
            b.arg(&mut colors).arg(&mut clamped).arg(&mut tiles);
            // SAFETY: argument types and lengths match rast_preprocess.
            unsafe { b.launch(lin(n)) }.map_err(cuda_err)?;
        }

        // Binning. The pair count (emulate_main.cpp: offsets[n-1] + tiles[n-1] after the scan) is the sum of
        // tiles_touched, summed here in u64, so a total past the kernels' u32 range is an error instead of a
        // wrapped scan.
        let tiles_touched = self.down(&tiles, n)?;
        drop(params_host);
        let pairs64: u64 = tiles_touched.iter().map(|&t| u64::from(t)).sum();
        if pairs64 > MAX_PAIRS {
            return Err(input_err("means", format!("{pairs64} (tile, Gaussian) pairs exceed the CUDA binning's {MAX_PAIRS}")));
        }
        let pairs = pairs64 as usize;
        let mut offsets = self.zeros::<u32>(n)?;
        if pairs > 0 {
            self.exclusive_scan(&tiles, &mut offsets, n)?;
        }
        let npow2 = pairs.next_power_of_two().max(1);
        let mut keys = self.zeros::<u64>(npow2)?;
        let mut vals = self.zeros::<u32>(npow2)?;
        let mut ranges = self.zeros::<u32>(2 * gx * gy)?;
        if pairs > 0 {
            let mut b = self.stream.launch_builder(&self.k.duplicate);
            b.arg(&n_i).arg(&radii).arg(&means2d).arg(&depths).arg(&offsets).arg(&w_i).arg(&h_i);
            b.arg(&mut keys).arg(&mut vals);
            // SAFETY: argument types and lengths match rast_duplicate.
            unsafe { b.launch(lin(n)) }.map_err(cuda_err)?;
            if npow2 > pairs {
                let (from, to) = (pairs as u32, npow2 as u32);
                let mut b = self.stream.launch_builder(&self.k.fill_pad);
                b.arg(&mut keys).arg(&mut vals).arg(&from).arg(&to);
                // SAFETY: as above.
                unsafe { b.launch(lin(npow2 - pairs)) }.map_err(cuda_err)?;
            }
            // Stage k = 2, 4, .., npow2 (<= 2^31), distance j = k/2 .. 1; counted in usize so the last
            // doubling cannot wrap.
            let np = npow2 as u32;
            let mut k = 2usize;
            while k <= npow2 {
                let mut j = k >> 1;
                while j > 0 {
                    let (j_u, k_u) = (j as u32, k as u32);
                    let mut b = self.stream.launch_builder(&self.k.bitonic_step);
                    b.arg(&mut keys).arg(&mut vals).arg(&np).arg(&j_u).arg(&k_u);
                    // SAFETY: as above.
                    unsafe { b.launch(lin(npow2)) }.map_err(cuda_err)?;
                    j >>= 1;
                }
                k <<= 1;
            }
            let count = pairs as u32;
            let mut b = self.stream.launch_builder(&self.k.tile_ranges);
            b.arg(&count).arg(&keys).arg(&mut ranges);
            // SAFETY: as above.
            unsafe { b.launch(lin(pairs)) }.map_err(cuda_err)?;
        }

        // Render.
        let mut rgb = self.zeros::<f32>(3 * hw)?;
        let mut feat = self.zeros::<f32>(nf * hw)?;
        let mut alpha = self.zeros::<f32>(hw)?;
        let mut depth = self.zeros::<f32>(hw)?;
        let mut final_t = self.zeros::<f32>(hw)?;
        let mut n_contrib = self.zeros::<u32>(hw)?;
        {
            let mut b = self.stream.launch_builder(&self.k.render_fwd);
            b.arg(&ranges).arg(&vals).arg(&w_i).arg(&h_i).arg(&means2d).arg(&conic_opacity).arg(&colors);
            b.arg(&depths).arg(&features).arg(&nf_i).arg(&params);
            b.arg(&mut rgb).arg(&mut feat).arg(&mut alpha).arg(&mut depth).arg(&mut final_t).arg(&mut n_contrib);
            // SAFETY: argument types and lengths match rast_render_fwd.
            unsafe { b.launch(tiles_grid(w, h)) }.map_err(cuda_err)?;
        }
        Ok(DeviceForward {
            rgb,
            feat,
            alpha,
            depth,
            cov2d,
            tiles_touched,
            pairs,
            state: DeviceState {
                n,
                k: kc,
                deg,
                nf,
                width: w,
                height: h,
                params,
                means,
                cov,
                rot,
                sh,
                features,
                depths,
                radii,
                clamped,
                means2d,
                conic_opacity,
                colors,
                ranges,
                point_list: vals,
                final_t,
                n_contrib,
            },
        })
    }

    /// Backward, given the forward of the same inputs and settings. `grads.alpha` / `grads.depth` are used
    /// by [`GradMode::Exact`] only (the official backward ignores them).
    pub fn backward(&self, fwd: &CudaForward, grads: &PixelGrads, mode: GradMode) -> Result<Gradients> {
        let d = &fwd.dev;
        let (n, nf, kc) = (d.n, d.nf, d.k);
        let hw = fwd.width * fwd.height;
        if grads.rgb.len() != 3 * hw || grads.features.len() != nf * hw {
            return Err(input_err("pixel gradients", format!("expected 3x{hw} rgb and {nf}x{hw} feature values")));
        }
        let exact = mode == GradMode::Exact;
        let extra = |g: Option<&[f32]>| -> Result<Option<CudaSlice<f32>>> {
            match g {
                Some(v) if exact => {
                    if v.len() != hw {
                        return Err(input_err("pixel gradients", format!("alpha/depth gradients need {hw} values")));
                    }
                    Ok(Some(self.up(v)?))
                }
                _ => Ok(None),
            }
        };
        let dl_rgb = self.up(grads.rgb)?;
        let dl_feat = self.up(grads.features)?;
        let dl_alpha = extra(grads.alpha)?;
        let dl_depth = extra(grads.depth)?;
        let g = self.run_backward(
            d,
            &dl_rgb.slice(..),
            &dl_feat.slice(..),
            dl_alpha.as_ref().map(|a| a.slice(..)).as_ref(),
            dl_depth.as_ref().map(|a| a.slice(..)).as_ref(),
            exact,
        )?;
        let scale_rot = d.rot.is_some();
        Ok(Gradients {
            means: self.down(&g.means, 3 * n)?,
            cov3d: self.down(&g.cov, 6 * n)?,
            scales: if scale_rot { Some(self.down(&g.scales, 3 * n)?) } else { None },
            quats: if scale_rot { Some(self.down(&g.quats, 4 * n)?) } else { None },
            opacities: self.down(&g.opacities, n)?,
            sh: self.down(&g.sh, n * kc * 3)?,
            features: self.down(&g.features, n * nf)?,
            means2d_ndc: self.down(&g.means2d, 2 * n)?,
        })
    }

    /// The launch sequence of the backward, pixel gradients on the device (planar, as the forward's images).
    fn run_backward(
        &self,
        d: &DeviceState,
        dl_rgb: &CudaView<f32>,
        dl_feat: &CudaView<f32>,
        dl_alpha: Option<&CudaView<f32>>,
        dl_depth: Option<&CudaView<f32>>,
        exact: bool,
    ) -> Result<DeviceGrads> {
        let (n, nf, kc) = (d.n, d.nf, d.k);
        let (w_i, h_i, nf_i, n_i, k_i) = (d.width as i32, d.height as i32, nf as i32, n as i32, kc as i32);
        let exact = i32::from(exact);
        let mut g_depth = self.zeros::<f32>(n)?;
        let mut g_m2 = self.zeros::<f32>(2 * n)?;
        let mut g_conic = self.zeros::<f32>(3 * n)?;
        let mut g_op = self.zeros::<f32>(n)?;
        let mut g_col = self.zeros::<f32>(3 * n)?;
        let mut g_feat = self.zeros::<f32>(n * nf)?;
        let null = 0u64;
        {
            let mut b = self.stream.launch_builder(&self.k.render_bwd);
            b.arg(&d.ranges).arg(&d.point_list).arg(&w_i).arg(&h_i).arg(&d.means2d).arg(&d.conic_opacity);
            b.arg(&d.colors).arg(&d.depths).arg(&d.features).arg(&nf_i).arg(&d.params).arg(&d.final_t).arg(&d.n_contrib).arg(dl_rgb).arg(dl_feat);
            // dl_alpha, dl_depth: null when absent (the official mode never reads them).
            match (dl_alpha, exact) {
                (Some(a), 1) => b.arg(a),
                _ => b.arg(&null),
            };
            match (dl_depth, exact) {
                (Some(a), 1) => b.arg(a),
                _ => b.arg(&null),
            };
            b.arg(&exact).arg(&mut g_m2).arg(&mut g_conic).arg(&mut g_op).arg(&mut g_col).arg(&mut g_feat).arg(&mut g_depth);
            // SAFETY: argument types and lengths match rast_render_bwd.
            unsafe { b.launch(tiles_grid(d.width, d.height)) }.map_err(cuda_err)?;
        }
        let mut d_means = self.zeros::<f32>(3 * n)?;
        let mut d_cov = self.zeros::<f32>(6 * n)?;
        let mut d_scales = self.zeros::<f32>(if d.rot.is_some() { 3 * n } else { 0 })?;
        let mut d_quats = self.zeros::<f32>(if d.rot.is_some() { 4 * n } else { 0 })?;
        let mut d_sh = self.zeros::<f32>(n * kc * 3)?;
        if n > 0 {
            let mut b = self.stream.launch_builder(&self.k.preprocess_bwd);
            b.arg(&n_i).arg(&d.means);
            match &d.rot {
                None => b.arg(&d.cov).arg(&null).arg(&null),
                Some(q) => b.arg(&null).arg(&d.cov).arg(q),
            };
            b.arg(&d.sh).arg(&k_i).arg(&d.deg).arg(&d.params).arg(&d.radii).arg(&d.clamped);
            b.arg(&g_m2).arg(&g_conic).arg(&g_col).arg(&g_depth).arg(&exact);
            b.arg(&mut d_means).arg(&mut d_cov).arg(&mut d_scales).arg(&mut d_quats).arg(&mut d_sh);
            // SAFETY: argument types and lengths match rast_preprocess_bwd.
            unsafe { b.launch(lin(n)) }.map_err(cuda_err)?;
        }
        Ok(DeviceGrads { means: d_means, cov: d_cov, scales: d_scales, quats: d_quats, opacities: g_op, sh: d_sh, features: g_feat, means2d: g_m2 })
    }

    /// Columns `[c0, c0 + cw)` of the row-major `n × d` matrix `packed` as a contiguous `n × cw` buffer.
    fn unpack_cols(&self, packed: &CudaView<f32>, n: usize, d: usize, c0: usize, cw: usize) -> Result<CudaSlice<f32>> {
        let mut out = self.zeros::<f32>(n * cw)?;
        if n * cw > 0 {
            let (n_i, d_i, c0_i, cw_i) = (n as i32, d as i32, c0 as i32, cw as i32);
            let mut b = self.stream.launch_builder(&self.k.unpack_cols);
            b.arg(&n_i).arg(&d_i).arg(&c0_i).arg(&cw_i).arg(packed).arg(&mut out);
            // SAFETY: packed holds n·d values, out n·cw; argument types match rast_unpack_cols.
            unsafe { b.launch(lin(n * cw)) }.map_err(cuda_err)?;
        }
        Ok(out)
    }

    /// Write the contiguous `n × cw` buffer `src` into columns `[c0, c0 + cw)` of the `n × d` matrix `packed`.
    fn pack_cols(&self, src: &CudaSlice<f32>, packed: &mut CudaSlice<f32>, n: usize, d: usize, c0: usize, cw: usize) -> Result<()> {
        if n * cw == 0 {
            return Ok(());
        }
        let (n_i, d_i, c0_i, cw_i) = (n as i32, d as i32, c0 as i32, cw as i32);
        let mut b = self.stream.launch_builder(&self.k.pack_cols);
        b.arg(&n_i).arg(&d_i).arg(&c0_i).arg(&cw_i).arg(src).arg(packed);
        // SAFETY: src holds n·cw values, packed n·d; argument types match rast_pack_cols.
        unsafe { b.launch(lin(n * cw)) }.map_err(cuda_err)?;
        Ok(())
    }

    /// Forward on the candle op's packed per-Gaussian matrix (`n` rows of means 3 | cov 6 | opacity 1 |
    /// SH `k`·3 | features `nf`, already on this stream): the planar output rgb 3 | features `nf` | alpha 1 |
    /// depth 1 (`(5 + nf)·H·W`, on the device), the radii (host) and the state for [`Self::backward_packed`].
    pub fn forward_packed(
        &self,
        packed: &CudaView<f32>,
        n: usize,
        k: usize,
        nf: usize,
        sh_degree: usize,
        s: &RasterSettings,
    ) -> Result<(CudaSlice<f32>, Vec<i32>, DeviceState)> {
        s.camera.validate()?;
        check_limits(n, nf, s)?;
        let d = 10 + 3 * k + nf;
        if packed.len() != n * d || n.saturating_mul(d) > i32::MAX as usize {
            return Err(input_err("packed Gaussians", format!("{} values for {n} rows of {d} (at most {} in all)", packed.len(), i32::MAX)));
        }
        if k == 0 {
            return Err(input_err("harmonics", "need at least the DC coefficient"));
        }
        let mut deg = sh_degree.min(3);
        while (deg + 1) * (deg + 1) > k && deg > 0 {
            deg -= 1;
        }
        let di = DeviceInputs {
            n,
            k,
            deg: deg as i32,
            nf,
            means: self.unpack_cols(packed, n, d, 0, 3)?,
            cov: self.unpack_cols(packed, n, d, 3, 6)?,
            rot: None,
            opacities: self.unpack_cols(packed, n, d, 9, 1)?,
            sh: self.unpack_cols(packed, n, d, 10, 3 * k)?,
            features: self.unpack_cols(packed, n, d, 10 + 3 * k, nf)?,
        };
        let f = self.run_forward(di, s)?;
        let hw = s.camera.width * s.camera.height;
        let mut out = self.zeros::<f32>((5 + nf) * hw)?;
        let mut at = 0;
        for (part, len) in [(&f.rgb, 3 * hw), (&f.feat, nf * hw), (&f.alpha, hw), (&f.depth, hw)] {
            if len > 0 {
                self.stream.memcpy_dtod(&part.slice(..len), &mut out.slice_mut(at..at + len)).map_err(cuda_err)?;
            }
            at += len;
        }
        let radii = self.down(&f.state.radii, n)?;
        Ok((out, radii, f.state))
    }

    /// Backward of [`Self::forward_packed`]: `grad_out` is the gradient of its output (same layout) →
    /// the gradient of the packed matrix (`n × (10 + 3k + nf)`, on the device).
    pub fn backward_packed(&self, d: &DeviceState, grad_out: &CudaView<f32>, mode: GradMode) -> Result<CudaSlice<f32>> {
        let (n, k, nf) = (d.n, d.k, d.nf);
        let hw = d.width * d.height;
        if grad_out.len() != (5 + nf) * hw {
            return Err(input_err("pixel gradients", format!("expected {} values, got {}", (5 + nf) * hw, grad_out.len())));
        }
        let g = self.run_backward(
            d,
            &grad_out.slice(..3 * hw),
            &grad_out.slice(3 * hw..(3 + nf) * hw),
            Some(&grad_out.slice((3 + nf) * hw..(4 + nf) * hw)),
            Some(&grad_out.slice((4 + nf) * hw..(5 + nf) * hw)),
            mode == GradMode::Exact,
        )?;
        let width = 10 + 3 * k + nf;
        let mut packed = self.zeros::<f32>(n * width)?;
        for (src, c0, cw) in [(&g.means, 0, 3), (&g.cov, 3, 6), (&g.opacities, 9, 1), (&g.sh, 10, 3 * k), (&g.features, 10 + 3 * k, nf)] {
            self.pack_cols(src, &mut packed, n, width, c0, cw)?;
        }
        Ok(packed)
    }
}

/// The kernels' size limits (32-bit indices, feature channels per thread).
fn check_limits(n: usize, nf: usize, s: &RasterSettings) -> Result<()> {
    if nf > MAX_FEATURES {
        return Err(input_err("features", format!("the CUDA kernels take at most {MAX_FEATURES} channels")));
    }
    // The kernels index with 32-bit `int`: 6 * n (d_cov3d), 3 * W * H (planar rgb).
    if n > i32::MAX as usize / 6 {
        return Err(input_err("means", format!("the CUDA kernels take at most {} Gaussians", i32::MAX / 6)));
    }
    if s.camera.width * s.camera.height > i32::MAX as usize / 3 {
        return Err(input_err("camera", format!("the CUDA kernels take at most {} pixels", i32::MAX / 3)));
    }
    Ok(())
}

/// Grid of 16×16 tiles, one thread per pixel.
fn tiles_grid(w: usize, h: usize) -> LaunchConfig {
    LaunchConfig { grid_dim: (w.div_ceil(TILE) as u32, h.div_ceil(TILE) as u32, 1), block_dim: (TILE as u32, TILE as u32, 1), shared_mem_bytes: 0 }
}

/// Per-Gaussian inputs on the device.
struct DeviceInputs {
    n: usize,
    k: usize,
    deg: i32,
    nf: usize,
    means: CudaSlice<f32>,
    /// cov3d (6 per Gaussian) or scales (3) with `rot` quats (4).
    cov: CudaSlice<f32>,
    rot: Option<CudaSlice<f32>>,
    opacities: CudaSlice<f32>,
    sh: CudaSlice<f32>,
    features: CudaSlice<f32>,
}

/// A forward's images and buffers, on the device.
struct DeviceForward {
    rgb: CudaSlice<f32>,
    feat: CudaSlice<f32>,
    alpha: CudaSlice<f32>,
    depth: CudaSlice<f32>,
    cov2d: CudaSlice<f32>,
    /// Host copy (read for the pair count).
    tiles_touched: Vec<u32>,
    pairs: usize,
    state: DeviceState,
}

/// Per-Gaussian gradients on the device (`scales`/`quats` are placeholders on the cov3d path).
struct DeviceGrads {
    means: CudaSlice<f32>,
    cov: CudaSlice<f32>,
    scales: CudaSlice<f32>,
    quats: CudaSlice<f32>,
    opacities: CudaSlice<f32>,
    sh: CudaSlice<f32>,
    features: CudaSlice<f32>,
    means2d: CudaSlice<f32>,
}
