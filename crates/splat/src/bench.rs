//! `mvsplat360 bench raster`: forward and forward+backward time of the CPU rasterizer on a synthetic,
//! MVSplat-like scene (one Gaussian per context pixel, depth-layered), rendered into one view.

use std::time::Instant;

use rayon::prelude::*;

use crate::camera::RasterCamera;
use crate::cpu::{self, CovInput, GradMode, PixelGrads, RasterInputs, RasterSettings};
use crate::error::{input_err, Result};

/// Workload of [`run_raster_bench`].
#[derive(Debug, Clone)]
pub struct RasterBenchOpts {
    /// Number of Gaussians (default 5 × 256 × 448 = 573,440: five pixel-aligned context views).
    pub gaussians: usize,
    pub width: usize,
    pub height: usize,
    /// Feature channels (4 in the pipeline).
    pub features: usize,
    /// Worker threads (0 = rayon's default).
    pub threads: usize,
    /// Timed runs after one warm-up (median reported; at least 5).
    pub runs: usize,
}

impl Default for RasterBenchOpts {
    fn default() -> Self {
        Self { gaussians: 5 * 256 * 448, width: 448, height: 256, features: 4, threads: 0, runs: 5 }
    }
}

/// A synthetic scene in plain buffers (see [`synthetic_scene`]).
pub struct SyntheticScene {
    pub means: Vec<f32>,
    pub cov3d: Vec<f32>,
    pub opacities: Vec<f32>,
    /// (N,16,3)
    pub sh: Vec<f32>,
    pub features: Vec<f32>,
    pub num_features: usize,
    pub camera: RasterCamera,
}

impl SyntheticScene {
    pub fn inputs(&self) -> RasterInputs<'_> {
        RasterInputs {
            means: &self.means,
            cov: CovInput::Cov3d(&self.cov3d),
            opacities: &self.opacities,
            sh: &self.sh,
            sh_coeffs: 16,
            sh_degree: 3,
            features: &self.features,
            num_features: self.num_features,
        }
    }
}

fn hash(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

fn unit(i: u64, k: u64) -> f32 {
    (hash(i.wrapping_mul(31).wrapping_add(k)) >> 40) as f32 / (1u64 << 24) as f32
}

/// Depth-layered scene seen by `ceil(n / (w·h))` context cameras (small baselines), one Gaussian per
/// context pixel sized to its pixel footprint, rendered from the centre camera.
pub fn synthetic_scene(n: usize, w: usize, h: usize, nf: usize) -> SyntheticScene {
    let (fx, fy) = (0.8 * w as f32, 0.8 * w as f32);
    let (cx, cy) = (w as f32 / 2.0, h as f32 / 2.0);
    let mut ident = [[0f32; 4]; 4];
    for (i, r) in ident.iter_mut().enumerate() {
        r[i] = 1.0;
    }
    let camera = RasterCamera { viewmatrix: ident, fx, fy, cx, cy, width: w, height: h, near: 0.5, far: 100.0 };
    let px = (w * h).max(1);
    let mut s = SyntheticScene {
        means: vec![0.0; 3 * n],
        cov3d: vec![0.0; 6 * n],
        opacities: vec![0.0; n],
        sh: vec![0.0; 48 * n],
        features: vec![0.0; nf * n],
        num_features: nf,
        camera,
    };
    s.means
        .par_chunks_mut(3)
        .zip(s.cov3d.par_chunks_mut(6))
        .zip(s.opacities.par_iter_mut())
        .zip(s.sh.par_chunks_mut(48))
        .enumerate()
        .for_each(|(i, (((m, c), o), shc))| {
            let view = i / px;
            let (u, v) = ((i % px) % w, (i % px) / w);
            let iu = i as u64;
            // Context camera centres on a small circle around the target camera (translation only).
            let ang = view as f32 * 1.3;
            let off = if view == 0 { [0.0, 0.0] } else { [0.15 * ang.cos(), 0.08 * ang.sin()] };
            // Layers: far wall, two blocky mid layers, a near slab in one corner.
            let (uf, vf) = (u as f32 / w as f32, v as f32 / h as f32);
            let mut d = 8.0 + 0.5 * (uf * 6.0).sin();
            if ((uf * 5.0) as i32 + (vf * 3.0) as i32) % 2 == 0 {
                d = 4.0 + vf;
            }
            if uf < 0.35 && vf > 0.55 {
                d = 2.0 + 0.3 * uf;
            }
            d *= 1.0 + 0.01 * (unit(iu, 1) - 0.5);
            let x = (u as f32 + 0.5 - cx) / fx * d + off[0];
            let y = (v as f32 + 0.5 - cy) / fy * d + off[1];
            m.copy_from_slice(&[x, y, d]);
            let sx = d / fx * (0.6 + 0.6 * unit(iu, 2));
            let sy = d / fy * (0.6 + 0.6 * unit(iu, 3));
            let sz = 0.5 * (sx + sy);
            let rho = 0.3 * (unit(iu, 4) - 0.5);
            c.copy_from_slice(&[sx * sx, rho * sx * sy, 0.0, sy * sy, 0.0, sz * sz]);
            *o = 0.2 + 0.8 * unit(iu, 5);
            for (k, e) in shc.iter_mut().enumerate() {
                let r = unit(iu, 10 + k as u64) - 0.5;
                *e = if k < 3 { 2.0 * r } else { 0.2 * r };
            }
        });
    s.features.par_iter_mut().enumerate().for_each(|(j, f)| *f = unit(j as u64, 99) - 0.5);
    s
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Run the benchmark; returns `{"bench":"raster","gaussians":N,"width":W,"height":H,"features":C,
/// "forward_ms":…,"forward_backward_ms":…}` (plus `pairs`, the tile-Gaussian pair count, and `threads`).
pub fn run_raster_bench(opts: &RasterBenchOpts) -> Result<serde_json::Value> {
    if opts.width == 0 || opts.height == 0 {
        return Err(input_err("bench", "--width and --height must be positive"));
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.threads)
        .build()
        .map_err(|e| input_err("bench", format!("cannot build a {}-thread pool: {e}", opts.threads)))?;
    pool.install(|| {
        let scene = synthetic_scene(opts.gaussians, opts.width, opts.height, opts.features);
        let inp = scene.inputs();
        let st = RasterSettings { camera: scene.camera, background: [0.0; 3] };
        let hw = opts.width * opts.height;
        let grad_rgb: Vec<f32> = (0..3 * hw).map(|i| unit(i as u64, 7) - 0.5).collect();
        let grad_feat: Vec<f32> = (0..opts.features * hw).map(|i| unit(i as u64, 8) - 0.5).collect();
        let pg = PixelGrads { rgb: &grad_rgb, features: &grad_feat, alpha: None, depth: None };
        let runs = opts.runs.max(5);
        // Warm-up (page faults, thread start-up).
        let warm = cpu::forward(&inp, &st)?;
        let pairs = warm.num_pairs();
        cpu::backward(&inp, &st, &warm, &pg, GradMode::Official)?;
        drop(warm);
        let mut fwd_ms = Vec::with_capacity(runs);
        let mut fb_ms = Vec::with_capacity(runs);
        for _ in 0..runs {
            let t0 = Instant::now();
            let out = cpu::forward(&inp, &st)?;
            fwd_ms.push(t0.elapsed().as_secs_f64() * 1e3);
            drop(out);
            let t0 = Instant::now();
            let out = cpu::forward(&inp, &st)?;
            let g = cpu::backward(&inp, &st, &out, &pg, GradMode::Official)?;
            fb_ms.push(t0.elapsed().as_secs_f64() * 1e3);
            drop(g);
        }
        Ok(serde_json::json!({
            "bench": "raster",
            "gaussians": opts.gaussians,
            "width": opts.width,
            "height": opts.height,
            "features": opts.features,
            "forward_ms": median(fwd_ms),
            "forward_backward_ms": median(fb_ms),
            "pairs": pairs,
            "threads": rayon::current_num_threads(),
        }))
    })
}
