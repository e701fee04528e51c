//! `mvsplat360 bench raster`: forward and forward+backward time of the CPU rasterizer on a synthetic,
//! MVSplat-like scene (one Gaussian per context pixel, depth-layered; the spec shared with the PyTorch reference
//! in scripts/bench-reference/README.md), rendered into one view.

use std::time::Instant;

use rayon::prelude::*;

use crate::camera::RasterCamera;
use crate::cpu::{self, CovInput, GradMode, PixelGrads, RasterInputs, RasterSettings};
use crate::error::{input_err, Result};
use mvsplat360_nn::bench::median;

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

/// The benchmark scene in plain buffers (see [`synthetic_scene`]).
pub struct SyntheticScene {
    pub means: Vec<f32>,
    /// (N,3) linear scales
    pub scales: Vec<f32>,
    /// (N,4) unit quaternions (w,x,y,z)
    pub quats: Vec<f32>,
    pub opacities: Vec<f32>,
    /// (N,25,3)
    pub sh: Vec<f32>,
    pub features: Vec<f32>,
    pub num_features: usize,
    pub camera: RasterCamera,
    /// Loss weights as planar pixel gradients: (3,H,W) and (C,H,W).
    pub w1: Vec<f32>,
    pub w2: Vec<f32>,
}

impl SyntheticScene {
    pub fn inputs(&self) -> RasterInputs<'_> {
        RasterInputs {
            means: &self.means,
            cov: CovInput::ScaleRot { scales: &self.scales, quats: &self.quats },
            opacities: &self.opacities,
            sh: &self.sh,
            sh_coeffs: 25,
            sh_degree: 4,
            features: &self.features,
            num_features: self.num_features,
        }
    }
}

fn lowbias32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^ (x >> 16)
}

/// u(k, i) in [0,1) of the shared bench spec.
fn unit(k: u32, i: u64) -> f32 {
    (lowbias32((i as u32) ^ lowbias32(k)) >> 8) as f32 * (1.0 / 16_777_216.0)
}

fn norm3(v: [f32; 3]) -> [f32; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// Camera at (2 sin θ, h, −2 cos θ) looking at the origin (OpenCV axes): (rotation columns x, y, z; centre).
fn look_at(theta: f32, h: f32) -> ([[f32; 3]; 3], [f32; 3]) {
    let c = [2.0 * (theta as f64).sin() as f32, h, -2.0 * (theta as f64).cos() as f32];
    let z = norm3([-c[0], -c[1], -c[2]]);
    let x = norm3(cross([0.0, 1.0, 0.0], z));
    let y = cross(z, x);
    ([x, y, z], c)
}

const LAYER_DEPTHS: [f32; 4] = [1.5, 2.5, 4.0, 8.0];

/// The shared raster bench scene (scripts/bench-reference/README.md, "Synthetic raster scene"; the PyTorch
/// reference generates the same): N pixel-aligned, depth-layered Gaussians from source views of W×H pixels
/// (5 views by default), rendered into one W×H view.
pub fn synthetic_scene(n: usize, w: usize, h: usize, nf: usize) -> SyntheticScene {
    let (fx, fy, cx, cy) = (0.75 * w as f32, 1.3 * h as f32, 0.5 * w as f32, 0.5 * h as f32);
    let hw = (w * h).max(1);
    let n_src = n.div_ceil(hw);
    let srcs: Vec<_> = (0..n_src).map(|v| look_at(-0.5 + 0.25 * (v % 5) as f32, 0.05 * (v / 5) as f32)).collect();
    let (rr, rc) = look_at(0.1, 0.0);
    // viewmatrix = inverse(c2w) = [Rᵀ | −Rᵀ c] (R's columns are the camera axes).
    let mut v = [[0f32; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            v[i][j] = rr[i][j];
        }
        v[i][3] = -(rr[i][0] * rc[0] + rr[i][1] * rc[1] + rr[i][2] * rc[2]);
    }
    v[3][3] = 1.0;
    let camera = RasterCamera { viewmatrix: v, fx, fy, cx, cy, width: w, height: h, near: 0.01, far: 100.0 };
    let mut s = SyntheticScene {
        means: vec![0.0; 3 * n],
        scales: vec![0.0; 3 * n],
        quats: vec![0.0; 4 * n],
        opacities: vec![0.0; n],
        sh: vec![0.0; 75 * n],
        features: vec![0.0; nf * n],
        num_features: nf,
        camera,
        w1: vec![0.0; 3 * w * h],
        w2: vec![0.0; nf * w * h],
    };
    s.means
        .par_chunks_mut(3)
        .zip(s.scales.par_chunks_mut(3))
        .zip(s.quats.par_chunks_mut(4))
        .zip(s.opacities.par_iter_mut())
        .zip(s.sh.par_chunks_mut(75))
        .enumerate()
        .for_each(|(g, ((((m, sc), q), o), shc))| {
            let gi = g as u64;
            let (sv, p) = (g / hw, g % hw);
            let (px, py) = (p % w, p / w);
            let (r, c) = &srcs[sv];
            let ray = norm3([(px as f32 + unit(0, gi) - cx) / fx, (py as f32 + unit(1, gi) - cy) / fy, 1.0]);
            let block = (sv * 1_000_000 + (py / 32) * 1000 + px / 32) as u64;
            let layer = ((5.0 * unit(2, block)) as usize).min(3);
            let d = LAYER_DEPTHS[layer] * (0.95 + 0.1 * unit(3, gi));
            for i in 0..3 {
                let rw = r[0][i] * ray[0] + r[1][i] * ray[1] + r[2][i] * ray[2];
                m[i] = c[i] + d * rw;
            }
            let foot = d / fx;
            for j in 0..3 {
                sc[j] = foot * (0.5 + 1.5 * unit(4 + j as u32, gi));
            }
            let qr: [f32; 4] = std::array::from_fn(|j| 2.0 * unit(7 + j as u32, gi) - 1.0);
            let qn = qr.iter().map(|x| x * x).sum::<f32>().sqrt();
            if qn > 1e-6 {
                for j in 0..4 {
                    q[j] = qr[j] / qn;
                }
            } else {
                q.copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
            }
            *o = 0.05 + 0.9 * unit(11, gi);
            for k in 0..25usize {
                let l = (k as f32).sqrt().floor() as i32;
                for ch in 0..3 {
                    shc[3 * k + ch] = if k == 0 {
                        let base = 0.5 + 0.4 * (px as f32 * 0.05 + py as f32 * 0.03 + sv as f32 * 0.7 + ch as f32).sin();
                        (base - 0.5) / crate::sh::C0
                    } else {
                        0.1 * 0.25f32.powi(l) * (2.0 * unit(12, 75 * gi + 3 * k as u64 + ch as u64) - 1.0)
                    };
                }
            }
        });
    s.features.par_iter_mut().enumerate().for_each(|(j, f)| *f = 2.0 * unit(13, j as u64) - 1.0);
    let npx = w * h;
    for pix in 0..npx {
        for c in 0..3 {
            s.w1[c * npx + pix] = 2.0 * unit(14, (3 * pix + c) as u64) - 1.0;
        }
        for c in 0..nf {
            s.w2[c * npx + pix] = 2.0 * unit(15, (nf * pix + c) as u64) - 1.0;
        }
    }
    s
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
        // dL/dimage of L = Σ rgb·W1 + Σ feat·W2.
        let pg = PixelGrads { rgb: &scene.w1, features: &scene.w2, alpha: None, depth: None };
        let runs = opts.runs.max(5);
        // Warm-up (page faults, thread start-up).
        let warm = cpu::forward(&inp, &st)?;
        let pairs = warm.num_pairs();
        let visible = warm.radii.iter().filter(|&&r| r > 0).count();
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
            "visible": visible,
            "threads": rayon::current_num_threads(),
        }))
    })
}
