//! Plane-sweep stereo on the context photos, run before the test-time fit when a model asks for it (`fit.sweep`;
//! not in the official pipeline). The encoder matches features at a quarter of the image size between nearby
//! views; here every context pixel tries distances along its ray over the whole near…far range against all the
//! other photos at full size. A pixel takes the sweep's distance only where the result is confirmed by another
//! view's own sweep (its point lands back on the pixel, at the same distance): elsewhere — untextured or
//! view-dependent surfaces, points no other view sees — the encoder's distance stays.

use mvsplat360_camera::Camera;
use mvsplat360_dataset::ImageF32;
use nalgebra::{Matrix4, Point3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{flag, Result};

/// A model folder's `config.json` key `fit.sweep`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SweepSettings {
    /// Candidate distances per pixel, uniform in inverse distance.
    pub candidates: usize,
    /// The candidates span the current (encoder's) distance ÷ `range` … × `range`; 0: near … far. A repeated
    /// texture matches at several distances, and the encoder's depth tells which of them is plausible.
    pub range: f64,
    /// Radius in pixels of the window over which colour differences are averaged.
    pub radius: usize,
    /// A candidate's cost is the mean of its `views` lowest per-view costs (a view where the point is hidden
    /// should not count against it).
    pub views: usize,
    /// Per-channel colour differences are capped at this (specular highlights, occlusion edges).
    pub truncation: f32,
    /// A pixel takes the sweep's distance when at least this many other views confirm it.
    pub confirmations: u32,
    /// Confirmation: the other view's point lands back within this many pixels…
    pub reprojection_px: f64,
    /// …and within this factor of the pixel's own depth.
    pub depth_ratio: f64,
}

impl Default for SweepSettings {
    fn default() -> Self {
        Self { candidates: 64, range: 0.0, radius: 2, views: 2, truncation: 0.2, confirmations: 1, reprojection_px: 1.0, depth_ratio: 1.03 }
    }
}

impl SweepSettings {
    pub fn validate(&self) -> Result<()> {
        if !(2..=1024).contains(&self.candidates) {
            return Err(flag("fit.sweep.candidates", format!("must be in 2…1024, got {}", self.candidates)));
        }
        if !(self.range == 0.0 || (self.range.is_finite() && self.range > 1.0)) {
            return Err(flag("fit.sweep.range", format!("must be 0 (near … far) or a factor > 1, got {}", self.range)));
        }
        if self.radius > 16 {
            return Err(flag("fit.sweep.radius", format!("at most 16 pixels, got {}", self.radius)));
        }
        if self.views == 0 {
            return Err(flag("fit.sweep.views", "must be ≥ 1".to_string()));
        }
        if !(self.truncation.is_finite() && self.truncation > 0.0) {
            return Err(flag("fit.sweep.truncation", format!("must be a positive number, got {}", self.truncation)));
        }
        if self.confirmations == 0 {
            return Err(flag("fit.sweep.confirmations", "must be ≥ 1 (0 would take every pixel's sweep, confirmed or not)".to_string()));
        }
        if !(self.reprojection_px.is_finite() && self.reprojection_px > 0.0) {
            return Err(flag("fit.sweep.reprojection_px", format!("must be a positive number, got {}", self.reprojection_px)));
        }
        if !(self.depth_ratio.is_finite() && self.depth_ratio > 1.0) {
            return Err(flag("fit.sweep.depth_ratio", format!("must be > 1, got {}", self.depth_ratio)));
        }
        Ok(())
    }
}

/// What a sweep found, per view-major pixel.
pub struct Sweep {
    /// The best distance along the pixel's ray (the prior's where no other view sees any candidate).
    pub distance: Vec<f32>,
    /// How many other views confirm it.
    pub confirmations: Vec<u32>,
}

impl Sweep {
    /// Whether pixel `i` takes the sweep's distance.
    pub fn accepted(&self, i: usize, s: &SweepSettings) -> bool {
        self.confirmations[i] >= s.confirmations
    }
}

/// Bilinear sample of a (3,H,W) image at continuous pixel coordinates (pixel centres at integer + 0.5); None
/// outside the centres' hull.
fn sample(img: &[f32], w: usize, h: usize, u: f64, v: f64) -> Option<[f32; 3]> {
    let (x, y) = (u - 0.5, v - 0.5);
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
        return None;
    }
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
    Some(out)
}

fn project(w2c: &Matrix4<f64>, c: &Camera, p: &Point3<f64>) -> (f64, f64, f64) {
    let q = w2c.transform_point(p);
    (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy, q.z)
}

/// Sweeps every pixel of every context view. `prior`: per view-major pixel, the current distance along its ray
/// (kept where nothing is seen); `dirs`: the ray's unit direction (world). Photos are (3,H,W), all one size.
pub fn sweep(photos: &[ImageF32], cams: &[Camera], prior: &[f32], dirs: &[[f64; 3]], near: f64, far: f64, s: &SweepSettings) -> Sweep {
    let v = cams.len();
    let (w, h) = (photos[0].width as usize, photos[0].height as usize);
    let hw = w * h;
    let d = s.candidates;
    let w2c: Vec<Matrix4<f64>> = cams.iter().map(|c| c.w2c_matrix()).collect();
    // Candidate `k` (fractional after refinement) of view-major pixel `o`.
    let cand = |o: usize, k: f64| {
        let (lo, hi) = if s.range > 1.0 { (prior[o] as f64 / s.range, prior[o] as f64 * s.range) } else { (near, far) };
        1.0 / (1.0 / lo + k / (d - 1) as f64 * (1.0 / hi - 1.0 / lo))
    };
    let mut distance = prior.to_vec();
    for r in 0..v {
        let centre = cams[r].center();
        let img = &photos[r].data;
        // Per candidate: per other view and pixel, the capped colour difference (NaN where that view does not
        // see the point); then averaged over the window and reduced to the best `views` views.
        let cost: Vec<Vec<f32>> = (0..d)
            .into_par_iter()
            .map(|k| {
                let mut raw = vec![f32::NAN; (v - 1) * hw];
                for i in 0..hw {
                    let t = cand(r * hw + i, k as f64);
                    let dir = dirs[r * hw + i];
                    let p = Point3::new(centre.x + dir[0] * t, centre.y + dir[1] * t, centre.z + dir[2] * t);
                    for (si, src) in (0..v).filter(|&j| j != r).enumerate() {
                        let (u, vv, z) = project(&w2c[src], &cams[src], &p);
                        if z <= 1e-6 {
                            continue;
                        }
                        if let Some(col) = sample(&photos[src].data, w, h, u, vv) {
                            raw[si * hw + i] = (0..3).map(|ch| (col[ch] - img[ch * hw + i]).abs().min(s.truncation)).sum::<f32>() / 3.0;
                        }
                    }
                }
                let rad = s.radius as isize;
                let mut out = vec![f32::NAN; hw];
                let mut per = Vec::with_capacity(v - 1);
                for y in 0..h as isize {
                    for x in 0..w as isize {
                        per.clear();
                        for si in 0..v - 1 {
                            let plane = &raw[si * hw..(si + 1) * hw];
                            if plane[y as usize * w + x as usize].is_nan() {
                                continue;
                            }
                            let (mut sum, mut n) = (0f32, 0u32);
                            for yy in (y - rad).max(0)..=(y + rad).min(h as isize - 1) {
                                for xx in (x - rad).max(0)..=(x + rad).min(w as isize - 1) {
                                    let e = plane[yy as usize * w + xx as usize];
                                    if !e.is_nan() {
                                        sum += e;
                                        n += 1;
                                    }
                                }
                            }
                            per.push(sum / n as f32);
                        }
                        if !per.is_empty() {
                            per.sort_by(f32::total_cmp);
                            let m = per.len().min(s.views);
                            out[y as usize * w + x as usize] = per[..m].iter().sum::<f32>() / m as f32;
                        }
                    }
                }
                out
            })
            .collect();
        for i in 0..hw {
            let mut best = (f32::INFINITY, usize::MAX);
            for (k, c) in cost.iter().enumerate() {
                if c[i] < best.0 {
                    best = (c[i], k);
                }
            }
            let k = best.1;
            if k == usize::MAX {
                continue;
            }
            // Sub-candidate refinement: the vertex of the parabola through the neighbours' costs.
            let mut kf = k as f64;
            if k > 0 && k + 1 < d && !cost[k - 1][i].is_nan() && !cost[k + 1][i].is_nan() {
                let (a, b, c) = (cost[k - 1][i] as f64, best.0 as f64, cost[k + 1][i] as f64);
                let den = a - 2.0 * b + c;
                if den > 1e-12 {
                    kf += (0.5 * (a - c) / den).clamp(-0.5, 0.5);
                }
            }
            distance[r * hw + i] = cand(r * hw + i, kf) as f32;
        }
    }
    let confirmations = confirm(&distance, dirs, cams, w, h, s);
    Sweep { distance, confirmations }
}

/// Per view-major pixel: in how many other views its point is confirmed — it projects inside that view onto a
/// pixel whose own point projects back within `reprojection_px` of the start, at a depth within `depth_ratio`.
fn confirm(dist: &[f32], dirs: &[[f64; 3]], cams: &[Camera], w: usize, h: usize, s: &SweepSettings) -> Vec<u32> {
    let v = cams.len();
    let hw = w * h;
    let w2c: Vec<Matrix4<f64>> = cams.iter().map(|c| c.w2c_matrix()).collect();
    let point = |o: usize| {
        let c = cams[o / hw].center();
        let (d, t) = (dirs[o], dist[o] as f64);
        Point3::new(c.x + d[0] * t, c.y + d[1] * t, c.z + d[2] * t)
    };
    let max_log = s.depth_ratio.ln();
    (0..v * hw)
        .into_par_iter()
        .map(|o| {
            let r = o / hw;
            let (x0, y0) = ((o % hw % w) as f64 + 0.5, (o % hw / w) as f64 + 0.5);
            let p = point(o);
            let zr = project(&w2c[r], &cams[r], &p).2;
            let mut n = 0;
            for src in (0..v).filter(|&j| j != r) {
                let (u, vv, z) = project(&w2c[src], &cams[src], &p);
                if z <= 1e-6 || !(u >= 0.0 && vv >= 0.0 && u < w as f64 && vv < h as f64) {
                    continue;
                }
                let q = point(src * hw + vv as usize * w + u as usize);
                let (ub, vb, zb) = project(&w2c[r], &cams[r], &q);
                if zb > 1e-6 && ((ub - x0).powi(2) + (vb - y0).powi(2)).sqrt() < s.reprojection_px && (zb / zr).ln().abs() < max_log {
                    n += 1;
                }
            }
            n
        })
        .collect()
}
