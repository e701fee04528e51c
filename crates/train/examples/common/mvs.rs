//! Plane-sweep stereo on the context photos (exploration): for every context pixel, the distance along its ray
//! whose projections into the other context views agree best with it in colour (windowed absolute difference,
//! the best `topk` views per candidate so that a view where the point is hidden does not count).
#![allow(dead_code)]

use rayon::prelude::*;

pub struct SweepSettings {
    /// Candidate distances, uniform in inverse distance.
    pub candidates: usize,
    /// Window radius (pixels) of the cost aggregation.
    pub radius: usize,
    /// Views averaged per candidate (the lowest costs).
    pub topk: usize,
    /// Search around the prior distance within this factor (≤ 1: the whole near…far range).
    pub range: f64,
    /// Weight of |ln t − ln prior| added to the cost.
    pub prior: f64,
    /// Colour differences are truncated at this value (per channel).
    pub trunc: f32,
}

pub struct Sweep {
    /// Per view-major pixel: the best distance along the ray.
    pub dist: Vec<f32>,
    /// Its aggregated cost.
    pub cost: Vec<f32>,
    /// Best cost / the best cost outside ±2 candidates of it (lower = more distinct).
    pub ratio: Vec<f32>,
}

/// Bilinear sample of a (3,H,W) image at continuous pixel coordinates whose pixel centres are at integer + 0.5.
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

/// `images`: per view (3,H,W) row-major; `prior`: per view-major pixel, a distance along its ray and the ray's
/// unit direction (world).
pub fn sweep(
    images: &[Vec<f32>],
    cams: &[mvsplat360_camera::Camera],
    w: usize,
    h: usize,
    prior: &[f32],
    dirs: &[[f64; 3]],
    near: f64,
    far: f64,
    s: &SweepSettings,
) -> Sweep {
    let v = cams.len();
    let hw = w * h;
    let d = s.candidates;
    let mut dist = vec![0f32; v * hw];
    let mut cost = vec![0f32; v * hw];
    let mut ratio = vec![1f32; v * hw];
    let w2c: Vec<_> = cams.iter().map(|c| c.w2c_matrix()).collect();
    for r in 0..v {
        let centre = cams[r].center();
        let cand = |i: usize, k: usize| -> f64 {
            let t = if s.range > 1.0 {
                let p = prior[r * hw + i] as f64;
                let (lo, hi) = (p / s.range, p * s.range);
                1.0 / (1.0 / lo + k as f64 / (d - 1) as f64 * (1.0 / hi - 1.0 / lo))
            } else {
                1.0 / (1.0 / near + k as f64 / (d - 1) as f64 * (1.0 / far - 1.0 / near))
            };
            t
        };
        // Per candidate, per source view, per pixel: the truncated colour difference (NaN: not visible there).
        let raw: Vec<Vec<f32>> = (0..d)
            .into_par_iter()
            .map(|k| {
                let mut out = vec![f32::NAN; (v - 1) * hw];
                for i in 0..hw {
                    let t = cand(i, k);
                    let dir = dirs[r * hw + i];
                    let p = nalgebra::Point3::new(centre.x + dir[0] * t, centre.y + dir[1] * t, centre.z + dir[2] * t);
                    let refc = [images[r][i], images[r][hw + i], images[r][2 * hw + i]];
                    for (si, src) in (0..v).filter(|&j| j != r).enumerate() {
                        let q = w2c[src].transform_point(&p);
                        if q.z <= 1e-6 {
                            continue;
                        }
                        let c = &cams[src];
                        let (u, vv) = (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy);
                        if let Some(col) = sample(&images[src], w, h, u, vv) {
                            out[si * hw + i] = (0..3).map(|ch| (col[ch] - refc[ch]).abs().min(s.trunc)).sum::<f32>() / 3.0;
                        }
                    }
                }
                out
            })
            .collect();
        // Window aggregation (valid entries only), then the best `topk` views.
        let rad = s.radius as isize;
        let agg: Vec<Vec<f32>> = raw
            .par_iter()
            .enumerate()
            .map(|(k, c)| {
                let mut out = vec![f32::NAN; hw];
                for y in 0..h as isize {
                    for x in 0..w as isize {
                        let i = y as usize * w + x as usize;
                        let mut per = Vec::with_capacity(v - 1);
                        for si in 0..v - 1 {
                            if c[si * hw + i].is_nan() {
                                continue;
                            }
                            let (mut sum, mut n) = (0f32, 0u32);
                            for dy in -rad..=rad {
                                for dx in -rad..=rad {
                                    let (yy, xx) = (y + dy, x + dx);
                                    if yy < 0 || xx < 0 || yy >= h as isize || xx >= w as isize {
                                        continue;
                                    }
                                    let e = c[si * hw + yy as usize * w + xx as usize];
                                    if !e.is_nan() {
                                        sum += e;
                                        n += 1;
                                    }
                                }
                            }
                            per.push(sum / n as f32);
                        }
                        if per.is_empty() {
                            continue;
                        }
                        per.sort_by(f32::total_cmp);
                        let m = per.len().min(s.topk);
                        let mut e = per[..m].iter().sum::<f32>() / m as f32;
                        if s.prior > 0.0 {
                            e += (s.prior * (cand(i, k) / prior[r * hw + i] as f64).ln().abs()) as f32;
                        }
                        out[i] = e;
                    }
                }
                out
            })
            .collect();
        for i in 0..hw {
            let mut best = (f32::INFINITY, usize::MAX);
            for (k, a) in agg.iter().enumerate() {
                if a[i] < best.0 {
                    best = (a[i], k);
                }
            }
            let o = r * hw + i;
            if best.1 == usize::MAX {
                dist[o] = prior[o];
                cost[o] = f32::INFINITY;
                continue;
            }
            let k = best.1;
            let second = agg.iter().enumerate().filter(|(j, _)| j.abs_diff(k) > 2).map(|(_, a)| a[i]).filter(|x| !x.is_nan()).fold(f32::INFINITY, f32::min);
            // Sub-candidate refinement by a parabola through the neighbours (in candidate index).
            let mut kf = k as f64;
            if k > 0 && k + 1 < d && !agg[k - 1][i].is_nan() && !agg[k + 1][i].is_nan() {
                let (a, b, c) = (agg[k - 1][i] as f64, best.0 as f64, agg[k + 1][i] as f64);
                let den = a - 2.0 * b + c;
                if den > 1e-12 {
                    kf += (0.5 * (a - c) / den).clamp(-0.5, 0.5);
                }
            }
            let (lo, hi) = (cand(i, kf.floor() as usize), cand(i, (kf.floor() as usize + 1).min(d - 1)));
            let f = kf - kf.floor();
            dist[o] = (1.0 / ((1.0 - f) / lo + f / hi)) as f32;
            cost[o] = best.0;
            ratio[o] = if second.is_finite() && second > 0.0 { best.0 / second } else { 1.0 };
        }
    }
    Sweep { dist, cost, ratio }
}

/// Per view-major pixel: in how many other views the sweep's point is confirmed — it projects inside that view
/// onto a pixel whose own sweep point lands back within `px` pixels of the start and within a factor `rel` in
/// distance.
pub fn consistency(dist: &[f32], dirs: &[[f64; 3]], cams: &[mvsplat360_camera::Camera], w: usize, h: usize, px: f64, rel: f64) -> Vec<u32> {
    let v = cams.len();
    let hw = w * h;
    let w2c: Vec<_> = cams.iter().map(|c| c.w2c_matrix()).collect();
    let point = |o: usize| {
        let c = cams[o / hw].center();
        let d = dirs[o];
        let t = dist[o] as f64;
        nalgebra::Point3::new(c.x + d[0] * t, c.y + d[1] * t, c.z + d[2] * t)
    };
    let proj = |k: usize, p: &nalgebra::Point3<f64>| {
        let q = w2c[k].transform_point(p);
        let c = &cams[k];
        (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy, q.z)
    };
    (0..v * hw)
        .into_par_iter()
        .map(|o| {
            let r = o / hw;
            let (x0, y0) = ((o % hw % w) as f64 + 0.5, (o % hw / w) as f64 + 0.5);
            let p = point(o);
            let zr = proj(r, &p).2;
            let mut n = 0;
            for s in (0..v).filter(|&s| s != r) {
                let (u, vv, z) = proj(s, &p);
                if z <= 1e-6 || u < 0.0 || vv < 0.0 || u >= w as f64 || vv >= h as f64 {
                    continue;
                }
                let os = s * hw + (vv as usize) * w + u as usize;
                let q = point(os);
                let (ub, vb, zb) = proj(r, &q);
                if zb <= 1e-6 {
                    continue;
                }
                let e = ((ub - x0).powi(2) + (vb - y0).powi(2)).sqrt();
                if e < px && (zb / zr).ln().abs() < rel.ln() {
                    n += 1;
                }
            }
            n
        })
        .collect()
}
