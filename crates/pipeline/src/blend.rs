//! Learned image-based blending of the 3DGS renders (not in the official pipeline; a model folder turns it on
//! with its `config.json` key `blend` and weights under `blend.*`).
//!
//! The Gaussians' colours are blurred by splatting, while the context photos hold the sharp ones: each target
//! pixel is lifted to a few depths around its rendered one and coloured from the nearest context photos there
//! (bilinear). A small CNN sees the render, its opacity and those candidates, and outputs per pixel a softmax
//! choice among the render and the candidates plus an RGB residual. Its weights are trained on rendered targets of
//! the training scenes (docs/research/learned-blending.md says how).

use std::path::Path;

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{conv2d, Conv2d, Conv2dConfig, VarBuilder};
use mvsplat360_camera::Camera;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::error::{compute, PipelineError, Result};

/// Key prefix of the blender's weights in a model's safetensors.
pub const PREFIX: &str = "blend";

/// The blender's shape (a model folder's `config.json` key `blend`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BlendSettings {
    /// Depths per context view: the rendered z-depth × span^t for `planes` values of t evenly in [−1, 1] (where
    /// the render's opacity is below 0.5: near…far, log-uniform).
    pub planes: usize,
    pub span: f64,
    /// Context views sampled per target, nearest camera centres first.
    pub views: usize,
    /// Channels of the CNN.
    pub width: usize,
}

/// Keys that `blend` once had, measured and not adopted (see [`crate::fit::REMOVED_KEYS`]).
pub const REMOVED_KEYS: &[(&str, &str)] = &[("visibility", "visibility-blender.md")];

impl Default for BlendSettings {
    fn default() -> Self {
        Self { planes: 7, span: 1.6, views: 2, width: 16 }
    }
}

impl BlendSettings {
    pub fn validate(&self) -> std::result::Result<(), String> {
        if self.planes == 0 || self.views == 0 || self.width == 0 {
            return Err(format!("planes ({}), views ({}) and width ({}) must be at least 1", self.planes, self.views, self.width));
        }
        if !(self.span.is_finite() && self.span >= 1.0) {
            return Err(format!("span must be a finite number ≥ 1, got {}", self.span));
        }
        Ok(())
    }

    /// Input channels of the CNN: render (3), opacity (1), 3 per candidate.
    pub fn channels(&self) -> usize {
        4 + 3 * self.views * self.planes
    }
}

/// Bilinear sample of a (3,H,W) image at pixel coordinates (centres at +0.5), clamped at the border.
pub fn bilinear(img: &[f32], w: usize, h: usize, x: f64, y: f64) -> [f32; 3] {
    let (x, y) = ((x - 0.5).clamp(0.0, w as f64 - 1.0), (y - 0.5).clamp(0.0, h as f64 - 1.0));
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let mut out = [0f32; 3];
    for (c, o) in out.iter_mut().enumerate() {
        let p = &img[c * w * h..];
        let a = p[y0 * w + x0] * (1.0 - fx) + p[y0 * w + x1] * fx;
        let b = p[y1 * w + x0] * (1.0 - fx) + p[y1 * w + x1] * fx;
        *o = a * (1.0 - fy) + b * fy;
    }
    out
}

/// Colours of the photo `img` (3,H,W at `v`'s size) of camera `v` at the points that target pixels reach at
/// z-depths `z`; `fallback` where a point is behind `v` or outside its image.
fn sample_view(t: &Camera, z: &[f64], v: &Camera, img: &[f32], fallback: &[f32], out: &mut [f32]) {
    let (w, h) = (t.width as usize, t.height as usize);
    let (vw, vh) = (v.width as usize, v.height as usize);
    out.copy_from_slice(fallback);
    let (rot, c, m) = (t.rotation(), t.center(), v.w2c_matrix());
    for py in 0..h {
        for px in 0..w {
            let i = py * w + px;
            let d = Vector3::new((px as f64 + 0.5 - t.cx) / t.fx, (py as f64 + 0.5 - t.cy) / t.fy, 1.0);
            let p = m.transform_point(&(c + rot * (d * z[i])).into());
            if p.z <= 1e-6 {
                continue;
            }
            let (u, vv) = (v.fx * p.x / p.z + v.cx, v.fy * p.y / p.z + v.cy);
            if u < 0.0 || vv < 0.0 || u >= vw as f64 || vv >= vh as f64 {
                continue;
            }
            let col = bilinear(img, vw, vh, u, vv);
            for (k, c) in col.iter().enumerate() {
                out[k * w * h + i] = *c;
            }
        }
    }
}

/// The CNN's input for one target, (C,H,W) flattened: the render `rgb` (3,H,W, clamped to [0, 1]), its opacity
/// `alpha` (H,W), then per context view (nearest camera centre first) and per plane the sampled colours.
/// `depth` is the rasterizer's Σ w·z (not divided by alpha); each context photo is (3,H,W) at its camera's size.
#[allow(clippy::too_many_arguments)]
pub fn candidates(
    s: &BlendSettings,
    target: &Camera,
    rgb: &[f32],
    alpha: &[f32],
    depth: &[f32],
    context: &[Camera],
    photos: &[&[f32]],
    near: f64,
    far: f64,
) -> Vec<f32> {
    let n = (target.width * target.height) as usize;
    let mut order: Vec<usize> = (0..context.len()).collect();
    order.sort_by(|&i, &j| (context[i].center() - target.center()).norm().total_cmp(&(context[j].center() - target.center()).norm()));
    let mut out = vec![0f32; s.channels() * n];
    out[..3 * n].copy_from_slice(rgb);
    out[3 * n..4 * n].copy_from_slice(alpha);
    let mut at = 4 * n;
    let mut z = vec![0f64; n];
    for &vi in order.iter().cycle().take(s.views) {
        for k in 0..s.planes {
            let f = k as f64 / (s.planes - 1).max(1) as f64;
            for (i, zi) in z.iter_mut().enumerate() {
                *zi = if alpha[i] >= 0.5 { (depth[i] / alpha[i]) as f64 * s.span.powf(2.0 * f - 1.0) } else { near * (far / near).powf(f) };
            }
            sample_view(target, &z, &context[vi], photos[vi], rgb, &mut out[at..at + 3 * n]);
            at += 3 * n;
        }
    }
    out
}

/// Two full-resolution convs, one level at half resolution, a skip; heads: one logit per candidate (the render
/// first, biased by +2 so that it starts favoured) and an RGB residual.
pub struct BlendNet {
    inp: Conv2d,
    a: Conv2d,
    down: [Conv2d; 3],
    fuse: Conv2d,
    b: Conv2d,
    out: Conv2d,
    ncand: usize,
}

impl BlendNet {
    /// Layers under `vb` (keys `inp`, `a`, `d0`–`d2`, `fuse`, `b`, `out`).
    pub fn new(vb: VarBuilder, s: &BlendSettings) -> candle_core::Result<Self> {
        let (cin, c) = (s.channels(), s.width);
        let k3 = Conv2dConfig { padding: 1, ..Default::default() };
        let ncand = 1 + s.views * s.planes;
        Ok(Self {
            inp: conv2d(cin, c, 3, k3, vb.pp("inp"))?,
            a: conv2d(c, c, 3, k3, vb.pp("a"))?,
            down: [conv2d(c, 2 * c, 3, k3, vb.pp("d0"))?, conv2d(2 * c, 2 * c, 3, k3, vb.pp("d1"))?, conv2d(2 * c, c, 3, k3, vb.pp("d2"))?],
            fuse: conv2d(2 * c, c, 3, k3, vb.pp("fuse"))?,
            b: conv2d(c, c, 3, k3, vb.pp("b"))?,
            out: conv2d(c, ncand + 3, 3, k3, vb.pp("out"))?,
            ncand,
        })
    }

    /// Blends a batch of [`candidates`] (N,C,H,W) into frames (N,3,H,W) (not clamped).
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let (n, _, h, w) = x.dims4()?;
        let (wts, residual) = self.heads(x)?;
        let k = self.ncand;
        let cands = Tensor::cat(&[x.narrow(1, 0, 3)?, x.narrow(1, 4, 3 * (k - 1))?], 1)?.reshape((n, k, 3, h, w))?;
        let pick = cands.broadcast_mul(&wts.unsqueeze(2)?)?.sum(1)?;
        pick + residual
    }

    /// The two heads for a batch of [`candidates`]: the softmax weights of the candidates (N,1+views·planes,H,W;
    /// the render first, then the candidates in their input order) and the RGB residual (N,3,H,W).
    fn heads(&self, x: &Tensor) -> candle_core::Result<(Tensor, Tensor)> {
        let (_, _, h, w) = x.dims4()?;
        let y0 = self.inp.forward(&(x - 0.5)?)?.gelu()?;
        let y0 = self.a.forward(&y0)?.gelu()?;
        let mut y = y0.avg_pool2d(2)?;
        for c in &self.down {
            y = c.forward(&y)?.gelu()?;
        }
        let y = y.upsample_nearest2d(h, w)?;
        let z = self.fuse.forward(&Tensor::cat(&[&y0, &y], 1)?)?.gelu()?;
        let z = self.b.forward(&z)?.gelu()?;
        let o = self.out.forward(&z)?;
        let k = self.ncand;
        let bias = Tensor::from_vec((0..k).map(|i| if i == 0 { 2f32 } else { 0.0 }).collect(), (1, k, 1, 1), x.device())?;
        let wts = candle_nn::ops::softmax(&o.narrow(1, 0, k)?.broadcast_add(&bias)?, 1)?;
        Ok((wts, o.narrow(1, k, 3)?))
    }

    /// The blender of a model's weights file (keys `blend.*`).
    pub fn load(weights: &Path, s: &BlendSettings, device: &Device) -> Result<Self> {
        let merr = |e: &dyn std::fmt::Display| PipelineError::Model { path: weights.to_path_buf(), msg: format!("blend weights: {e}") };
        // SAFETY: the file is memory-mapped read-only; model files are not modified while a render runs.
        let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[weights], DType::F32, device) }.map_err(|e| merr(&e))?;
        Self::new(vb.pp(PREFIX), s).map_err(|e| merr(&e))
    }

    /// Frames for the targets, one (3,H,W) tensor each, from their [`candidates`], in batches of `batch`.
    pub fn blend_all(&self, inputs: &[Vec<f32>], s: &BlendSettings, h: usize, w: usize, device: &Device, batch: usize) -> Result<Vec<Tensor>> {
        let mut out = Vec::with_capacity(inputs.len());
        for chunk in inputs.chunks(batch.max(1)) {
            let data: Vec<f32> = chunk.iter().flat_map(|x| x.iter().copied()).collect();
            let x = Tensor::from_vec(data, (chunk.len(), s.channels(), h, w), device).map_err(compute("blend"))?;
            let y = self.forward(&x).map_err(compute("blend"))?.clamp(0f32, 1f32).map_err(compute("blend"))?;
            for i in 0..chunk.len() {
                out.push(y.get(i).map_err(compute("blend"))?);
            }
        }
        Ok(out)
    }
}
