//! Backward: per-pair gradients from the tile kernel, a deterministic per-channel reduction into
//! per-Gaussian sums, then the per-Gaussian chain rule (conic → 2D cov → 3D cov / mean, SH → mean).

use rayon::prelude::*;

use super::composite::{backward_pairs, pair_stride, P_CA, P_CB, P_CC, P_COL, P_DEPTH, P_FEAT, P_MX, P_MY, P_OP};
use super::preprocess::{cov3d_of, ewa, mean_of, quat_to_rot, view_dir, view_point};
use super::{CovInput, ForwardOutput, Frame, GradMode, Gradients, PixelGrads, RasterInputs, RasterSettings};
use crate::error::{input_err, Result};
use crate::sh;
use crate::util::{SharedMut, Uninit, POOL_F32};

/// The per-pair gradient buffer, kept between calls: reusing it avoids page-faulting tens of MB per backward
/// (its size is bounded by the largest pair count seen; a concurrent second call just allocates).
static PAIR_POOL: std::sync::Mutex<Vec<f32>> = std::sync::Mutex::new(Vec::new());

/// Gradients of the loss w.r.t. every input, given the forward result of the same inputs and settings.
pub fn backward(inp: &RasterInputs, s: &RasterSettings, fwd: &ForwardOutput, grads: &PixelGrads, mode: GradMode) -> Result<Gradients> {
    inp.validate()?;
    let n = inp.len();
    if fwd.radii.len() != n || fwd.width != s.camera.width || fwd.height != s.camera.height {
        return Err(input_err("forward output", "does not belong to these inputs / this camera (rerun forward)"));
    }
    let nf = inp.num_features;
    let f = Frame::new(&s.camera);
    let timing = std::env::var_os("MVSPLAT360_RASTER_TIMING").is_some();
    let t0 = std::time::Instant::now();
    let mut buf = PAIR_POOL.lock().map(|mut b| std::mem::take(&mut *b)).unwrap_or_default();
    backward_pairs(inp, s, fwd, grads, mode, &mut buf)?;
    let t1 = std::time::Instant::now();
    let ps = pair_stride(nf);
    // Per Gaussian, its (contiguous) pair rows in a fixed order: deterministic sums.
    // Only visible Gaussians' rows are written and read, so a reused buffer needs no clearing.
    let mut sums = POOL_F32.take(n * ps, 0.0);
    {
        let so = SharedMut::new(&mut sums);
        let buf = &buf;
        fwd.order.par_iter().enumerate().with_min_len(1024).for_each(|(m, &g)| {
            let rows = &buf[fwd.pstart[m] as usize * ps..fwd.pstart[m + 1] as usize * ps];
            let mut acc = [0f32; 64];
            let (head, _) = acc.split_at_mut(ps.min(64));
            for r in rows.chunks_exact(ps) {
                for (a, v) in head.iter_mut().zip(r) {
                    *a += *v;
                }
            }
            let g = g as usize;
            // SAFETY: every Gaussian appears once in `order`, so rows g·ps.. are written by one iteration.
            unsafe {
                for (k, &a) in head.iter().enumerate() {
                    so.write(g * ps + k, a);
                }
                // Rare wide feature sets: the channels past the stack buffer.
                for k in head.len()..ps {
                    let v: f32 = rows.chunks_exact(ps).map(|r| r[k]).sum();
                    so.write(g * ps + k, v);
                }
            }
        });
    }
    if let Ok(mut pool) = PAIR_POOL.lock() {
        *pool = buf;
    }
    let t2 = std::time::Instant::now();
    let sum = |ch: usize, i: usize| sums[i * ps + ch];

    let k = inp.sh_coeffs;
    let visible = |i: usize| fwd.radii[i] > 0;
    let opacities: Vec<f32> = (0..n).map(|i| if visible(i) { sum(P_OP, i) } else { 0.0 }).collect();
    let features: Vec<f32> = (0..n * nf).map(|j| if visible(j / nf.max(1)) { sum(P_FEAT + j % nf, j / nf) } else { 0.0 }).collect();
    let scale_rot = matches!(inp.cov, CovInput::ScaleRot { .. });
    // Every value of these is written below (zeros for culled Gaussians and unused SH degrees): no zero pass.
    let mut means = Uninit::<f32>::new(3 * n);
    let mut cov3d = Uninit::<f32>::new(6 * n);
    let mut shg = Uninit::<f32>::new(n * k * 3);
    let mut m2 = Uninit::<f32>::new(2 * n);
    let mut gs = Uninit::<f32>::new(if scale_rot { 3 * n } else { 0 });
    let mut gq = Uninit::<f32>::new(if scale_rot { 4 * n } else { 0 });
    let exact = mode == GradMode::Exact;
    let deg = inp.eval_degree();
    let ncoef = sh::num_coeffs(deg);
    let (wf, hf) = (f.w as f32, f.h as f32);
    let (o_means, o_cov, o_sh, o_m2, o_s, o_q) = (means.ptr(), cov3d.ptr(), shg.ptr(), m2.ptr(), gs.ptr(), gq.ptr());
    let sum = &sum;
    (0..n).into_par_iter().with_min_len(1024).for_each(|i| {
        if !visible(i) {
            // SAFETY: Gaussian i writes only its own rows of every output.
            unsafe {
                for j in 0..3 {
                    o_means.write(3 * i + j, 0.0);
                }
                for j in 0..6 {
                    o_cov.write(6 * i + j, 0.0);
                }
                for j in 0..k * 3 {
                    o_sh.write(i * k * 3 + j, 0.0);
                }
                o_m2.write(2 * i, 0.0);
                o_m2.write(2 * i + 1, 0.0);
                if scale_rot {
                    for j in 0..3 {
                        o_s.write(3 * i + j, 0.0);
                    }
                    for j in 0..4 {
                        o_q.write(4 * i + j, 0.0);
                    }
                }
            }
            return;
        }
        let p = mean_of(inp, i);
        let mut dmean = [0f32; 3];

        // Screen-space mean: pixel gradient → ndc → world.
        let g_ndc = [sum(P_MX, i) * 0.5 * wf, sum(P_MY, i) * 0.5 * hf];
        let fp = &f.fp;
        let hom = |r: usize| fp[r][0] * p[0] + fp[r][1] * p[1] + fp[r][2] * p[2] + fp[r][3];
        let m_w = 1.0 / (hom(3) + 1e-7);
        let (hx, hy) = (hom(0), hom(1));
        for j in 0..3 {
            dmean[j] += (fp[0][j] * m_w - fp[3][j] * hx * m_w * m_w) * g_ndc[0] + (fp[1][j] * m_w - fp[3][j] * hy * m_w * m_w) * g_ndc[1];
        }

        // Conic → 2D covariance → 3D covariance and view-space mean.
        let t_view = view_point(&f.v, p);
        let cov = cov3d_of(inp, i);
        let e = ewa(&f, t_view, &cov);
        let [a, b, c] = e.cov2d;
        let det = a * c - b * b;
        let (ga, gb, gc) = (sum(P_CA, i), sum(P_CB, i), sum(P_CC, i));
        let denom2inv = if exact { 1.0 / (det * det) } else { 1.0 / (det * det + 1e-7) };
        let (dl_da, dl_db, dl_dc) = if denom2inv != 0.0 && denom2inv.is_finite() {
            (
                denom2inv * (-c * c * ga + 2.0 * b * c * gb + (det - a * c) * gc),
                denom2inv * 2.0 * (b * c * ga - (det + 2.0 * b * b) * gb + a * b * gc),
                denom2inv * (-a * a * gc + 2.0 * a * b * gb + (det - a * c) * ga),
            )
        } else {
            (0.0, 0.0, 0.0)
        };
        let m = &e.m;
        // dL/dSigma = M^T Gc M with Gc = [[da, db/2], [db/2, dc]].
        let gcm = |r: usize| -> [f32; 3] {
            let (g0, g1) = if r == 0 { (dl_da, 0.5 * dl_db) } else { (0.5 * dl_db, dl_dc) };
            [g0 * m[0][0] + g1 * m[1][0], g0 * m[0][1] + g1 * m[1][1], g0 * m[0][2] + g1 * m[1][2]]
        };
        let gm = [gcm(0), gcm(1)]; // Gc M (2×3)
        let dsig = |u: usize, v: usize| m[0][u] * gm[0][v] + m[1][u] * gm[1][v];
        let dcov = [dsig(0, 0), 2.0 * dsig(0, 1), 2.0 * dsig(0, 2), dsig(1, 1), 2.0 * dsig(1, 2), dsig(2, 2)];
        // dL/dM = 2 Gc M Sigma
        let sg = super::preprocess::sym(&cov);
        let mut dm = [[0f32; 3]; 2];
        for r in 0..2 {
            for col in 0..3 {
                dm[r][col] = 2.0 * (gm[r][0] * sg[0][col] + gm[r][1] * sg[1][col] + gm[r][2] * sg[2][col]);
            }
        }
        let v = &f.v;
        let row = |r: usize| [v[r][0], v[r][1], v[r][2]];
        let dot = |x: [f32; 3], y: [f32; 3]| x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
        let dj00 = dot(dm[0], row(0));
        let dj02 = dot(dm[0], row(2));
        let dj11 = dot(dm[1], row(1));
        let dj12 = dot(dm[1], row(2));
        let [fx, fy] = f.focal;
        let [tx, ty, tz] = e.t;
        let tz2 = 1.0 / (tz * tz);
        let tz3 = tz2 / tz;
        let dl_dtxc = -fx * tz2 * dj02;
        let dl_dtyc = -fy * tz2 * dj12;
        let mut dt = [0f32; 3];
        dt[2] = -fx * tz2 * dj00 - fy * tz2 * dj11 + 2.0 * fx * tx * tz3 * dj02 + 2.0 * fy * ty * tz3 * dj12;
        if e.clamp_x {
            // Official: clamped t.x is a constant. Exact: t.x = ±lim·t.z.
            if exact {
                dt[2] += dl_dtxc * (tx / tz);
            }
        } else {
            dt[0] = dl_dtxc;
        }
        if e.clamp_y {
            if exact {
                dt[2] += dl_dtyc * (ty / tz);
            }
        } else {
            dt[1] = dl_dtyc;
        }
        if exact {
            dt[2] += sum(P_DEPTH, i);
        }
        for j in 0..3 {
            dmean[j] += v[0][j] * dt[0] + v[1][j] * dt[1] + v[2][j] * dt[2];
        }

        // SH colour → coefficients and view direction.
        let (dir, dvec) = view_dir(&f, p);
        let mut basis = [0f32; 16];
        let mut bgrad = [[0f32; 3]; 16];
        sh::basis_backward(dir, deg, !exact, &mut basis, &mut bgrad);
        let mask = fwd.clamped[i];
        let mut dcol = [0f32; 3];
        for ch in 0..3 {
            dcol[ch] = if mask & (1 << ch) != 0 { 0.0 } else { sum(P_COL + ch, i) };
        }
        let shi = &inp.sh[i * k * 3..(i + 1) * k * 3];
        let mut ddir = [0f32; 3];
        // SAFETY: Gaussian i writes only its own rows of every output.
        unsafe {
            for kk in 0..ncoef {
                let mut proj = 0f32;
                for ch in 0..3 {
                    o_sh.write(i * k * 3 + 3 * kk + ch, basis[kk] * dcol[ch]);
                    proj += shi[3 * kk + ch] * dcol[ch];
                }
                for a in 0..3 {
                    ddir[a] += bgrad[kk][a] * proj;
                }
            }
            // Degrees the fork does not evaluate get exactly zero.
            for j in ncoef * 3..k * 3 {
                o_sh.write(i * k * 3 + j, 0.0);
            }
        }
        let sum2 = dot(dvec, dvec);
        if sum2 > 0.0 {
            let inv32 = 1.0 / (sum2 * sum2 * sum2).sqrt();
            let vd = dot(dvec, ddir);
            for a in 0..3 {
                dmean[a] += (sum2 * ddir[a] - dvec[a] * vd) * inv32;
            }
        }

        unsafe {
            for a in 0..3 {
                o_means.write(3 * i + a, dmean[a]);
            }
            for a in 0..6 {
                o_cov.write(6 * i + a, dcov[a]);
            }
            o_m2.write(2 * i, g_ndc[0]);
            o_m2.write(2 * i + 1, g_ndc[1]);
        }

        if let CovInput::ScaleRot { scales, quats } = inp.cov {
            let sc = [scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]];
            let q = [quats[4 * i], quats[4 * i + 1], quats[4 * i + 2], quats[4 * i + 3]];
            let (ds, dq) = scale_rot_backward(sc, q, &dcov);
            unsafe {
                for a in 0..3 {
                    o_s.write(3 * i + a, ds[a]);
                }
                for a in 0..4 {
                    o_q.write(4 * i + a, dq[a]);
                }
            }
        }
    });
    // SAFETY: the loop above wrote every index of every buffer (both branches).
    let out = unsafe {
        Gradients {
            means: means.done(),
            cov3d: cov3d.done(),
            scales: if scale_rot { Some(gs.done()) } else { None },
            quats: if scale_rot { Some(gq.done()) } else { None },
            opacities,
            sh: shg.done(),
            features,
            means2d_ndc: m2.done(),
        }
    };
    if timing {
        eprintln!(
            "raster backward: tiles {:.1} ms, reduce {:.1} ms, per-Gaussian chain rule {:.1} ms",
            (t1 - t0).as_secs_f64() * 1e3,
            (t2 - t1).as_secs_f64() * 1e3,
            t2.elapsed().as_secs_f64() * 1e3
        );
    }
    POOL_F32.put(sums);
    Ok(out)
}

/// Sigma = R diag(s²) R^T: gradients w.r.t. s and the raw quaternion (w, x, y, z) from dL/dcov6.
pub(crate) fn scale_rot_backward(s: [f32; 3], q: [f32; 4], dcov: &[f32; 6]) -> ([f32; 3], [f32; 4]) {
    let r = quat_to_rot(q);
    // Symmetric dL/dSigma: off-diagonal entries share the parameter, so each position gets half.
    let g = [[dcov[0], 0.5 * dcov[1], 0.5 * dcov[2]], [0.5 * dcov[1], dcov[3], 0.5 * dcov[4]], [0.5 * dcov[2], 0.5 * dcov[4], dcov[5]]];
    // G R
    let mut gr = [[0f32; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            gr[a][b] = g[a][0] * r[0][b] + g[a][1] * r[1][b] + g[a][2] * r[2][b];
        }
    }
    let mut ds = [0f32; 3];
    for kk in 0..3 {
        // (R^T G R)_kk
        let rtgr = r[0][kk] * gr[0][kk] + r[1][kk] * gr[1][kk] + r[2][kk] * gr[2][kk];
        ds[kk] = 2.0 * s[kk] * rtgr;
    }
    // dL/dR = 2 G R D
    let mut dr = [[0f32; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            dr[a][b] = 2.0 * gr[a][b] * s[b] * s[b];
        }
    }
    let [w, x, y, z] = q;
    let dw = 2.0 * (-z * dr[0][1] + y * dr[0][2] + z * dr[1][0] - x * dr[1][2] - y * dr[2][0] + x * dr[2][1]);
    let dx = 2.0 * (y * dr[0][1] + z * dr[0][2] + y * dr[1][0] - 2.0 * x * dr[1][1] - w * dr[1][2] + z * dr[2][0] + w * dr[2][1] - 2.0 * x * dr[2][2]);
    let dy = 2.0 * (-2.0 * y * dr[0][0] + x * dr[0][1] + w * dr[0][2] + x * dr[1][0] + z * dr[1][2] - w * dr[2][0] + z * dr[2][1] - 2.0 * y * dr[2][2]);
    let dz = 2.0 * (-2.0 * z * dr[0][0] - w * dr[0][1] + x * dr[0][2] + w * dr[1][0] - 2.0 * z * dr[1][1] + y * dr[1][2] + x * dr[2][0] + y * dr[2][1]);
    (ds, [dw, dx, dy, dz])
}
