//! Per-Gaussian projection: view transform, culling, EWA 2D covariance, conic, radius, tile rect, SH colour.

use rayon::prelude::*;

use super::{tile_rect, CovInput, Frame, RasterInputs};
use crate::sh;
use crate::util::{Pooled, SharedMut, POOL_F32, POOL_GEO};

/// Projected per-Gaussian data (SoA).
pub(crate) struct Projected {
    pub means2d: Vec<f32>,
    pub depths: Vec<f32>,
    pub cov2d: Vec<f32>,
    pub conic: Vec<f32>,
    pub colors: Vec<f32>,
    pub clamped: Vec<u8>,
    pub radii: Vec<i32>,
    pub tiles_touched: Vec<u32>,
    /// Packed per-Gaussian record for the tile kernels (see [`GEO_LEN`]).
    pub geo: Pooled<[f32; GEO_LEN]>,
    /// (N, 4+C) values composited per Gaussian: r, g, b, view depth, features.
    pub vals: Pooled<f32>,
}

/// Kernel record: mx, my, conic A, B, C, opacity, and the half-extents (px) of the alpha ≥ 1/255 ellipse's
/// bounding box (negative = never visible, infinite = unknown, use the whole tile).
pub(crate) const GEO_LEN: usize = 8;

/// Conservative half-extents of the region where `o·exp(-q/2) ≥ 1/255` (q the conic quadratic form).
#[inline]
pub(crate) fn alpha_extent(conic: [f32; 3], o: f32) -> (f32, f32) {
    if !(o >= 1.0 / 255.0) {
        return (-1.0, -1.0);
    }
    let [a, b, c] = conic;
    let r2 = 2.0 * (255.0 * o).ln().max(0.0);
    let detq = a * c - b * b;
    if detq > 0.0 && a > 0.0 && c > 0.0 {
        // 1 % (2 % in q, i.e. alpha ≥ 2 % below the threshold at the edge) + 0.05 px margin, far above the f32
        // rounding of the per-pixel test, so no pixel with alpha ≥ 1/255 falls outside the box.
        ((r2 * c / detq).sqrt() * 1.01 + 0.05, (r2 * a / detq).sqrt() * 1.01 + 0.05)
    } else {
        (f32::INFINITY, f32::INFINITY)
    }
}

#[inline]
pub(crate) fn view_point(v: &[[f32; 4]; 4], p: [f32; 3]) -> [f32; 3] {
    let mut t = [0f32; 3];
    for (i, ti) in t.iter_mut().enumerate() {
        *ti = v[i][0] * p[0] + v[i][1] * p[1] + v[i][2] * p[2] + v[i][3];
    }
    t
}

#[inline]
pub(crate) fn mean_of(inp: &RasterInputs, i: usize) -> [f32; 3] {
    [inp.means[3 * i], inp.means[3 * i + 1], inp.means[3 * i + 2]]
}

/// Standard rotation matrix of an (unnormalised) quaternion (w, x, y, z).
#[inline]
pub(crate) fn quat_to_rot(q: [f32; 4]) -> [[f32; 3]; 3] {
    let [r, x, y, z] = q;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - r * z), 2.0 * (x * z + r * y)],
        [2.0 * (x * y + r * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - r * x)],
        [2.0 * (x * z - r * y), 2.0 * (y * z + r * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// Upper-triangular 3D covariance of Gaussian `i`.
#[inline]
pub(crate) fn cov3d_of(inp: &RasterInputs, i: usize) -> [f32; 6] {
    match inp.cov {
        CovInput::Cov3d(c) => {
            let mut o = [0f32; 6];
            o.copy_from_slice(&c[6 * i..6 * i + 6]);
            o
        }
        CovInput::ScaleRot { scales, quats } => {
            let s = [scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]];
            let r = quat_to_rot([quats[4 * i], quats[4 * i + 1], quats[4 * i + 2], quats[4 * i + 3]]);
            // Sigma = M^T M with M = S R^T, as the CUDA kernel forms it.
            let m = |k: usize, a: usize| s[k] * r[a][k];
            let e = |a: usize, b: usize| m(0, a) * m(0, b) + m(1, a) * m(1, b) + m(2, a) * m(2, b);
            [e(0, 0), e(0, 1), e(0, 2), e(1, 1), e(1, 2), e(2, 2)]
        }
    }
}

#[inline]
pub(crate) fn sym(c: &[f32; 6]) -> [[f32; 3]; 3] {
    [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]]
}

/// Intermediates of the EWA projection, shared by forward and backward.
pub(crate) struct Ewa {
    /// t with clamped x, y (what the Jacobian sees).
    pub t: [f32; 3],
    pub clamp_x: bool,
    pub clamp_y: bool,
    /// M = J R_view (2×3).
    pub m: [[f32; 3]; 2],
    /// (a, b, c) incl. +0.3.
    pub cov2d: [f32; 3],
}

#[inline]
pub(crate) fn ewa(f: &Frame, t_view: [f32; 3], cov: &[f32; 6]) -> Ewa {
    let limx = 1.3 * f.tanfov[0];
    let limy = 1.3 * f.tanfov[1];
    let tz = t_view[2];
    let txtz = t_view[0] / tz;
    let tytz = t_view[1] / tz;
    let clamp_x = txtz < -limx || txtz > limx;
    let clamp_y = tytz < -limy || tytz > limy;
    let tx = txtz.max(-limx).min(limx) * tz;
    let ty = tytz.max(-limy).min(limy) * tz;
    let [fx, fy] = f.focal;
    let j00 = fx / tz;
    let j02 = -(fx * tx) / (tz * tz);
    let j11 = fy / tz;
    let j12 = -(fy * ty) / (tz * tz);
    let v = &f.v;
    let m = [
        [j00 * v[0][0] + j02 * v[2][0], j00 * v[0][1] + j02 * v[2][1], j00 * v[0][2] + j02 * v[2][2]],
        [j11 * v[1][0] + j12 * v[2][0], j11 * v[1][1] + j12 * v[2][1], j11 * v[1][2] + j12 * v[2][2]],
    ];
    let s = sym(cov);
    let quad = |a: &[f32; 3], b: &[f32; 3]| -> f32 {
        let mut acc = 0f32;
        for i in 0..3 {
            acc += a[i] * (s[i][0] * b[0] + s[i][1] * b[1] + s[i][2] * b[2]);
        }
        acc
    };
    let cov2d = [quad(&m[0], &m[0]) + 0.3, quad(&m[0], &m[1]), quad(&m[1], &m[1]) + 0.3];
    Ewa { t: [tx, ty, tz], clamp_x, clamp_y, m, cov2d }
}

/// Unit view direction from the camera centre to the Gaussian, and the unnormalised vector.
#[inline]
pub(crate) fn view_dir(f: &Frame, p: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let d = [p[0] - f.campos[0], p[1] - f.campos[1], p[2] - f.campos[2]];
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let inv = if n > 0.0 { 1.0 / n } else { 0.0 };
    ([d[0] * inv, d[1] * inv, d[2] * inv], d)
}

pub(crate) fn preprocess(f: &Frame, inp: &RasterInputs) -> Projected {
    #[cfg(target_arch = "x86_64")]
    if super::simd::has_avx2() {
        // SAFETY: AVX2/FMA detected (FMA is not contracted into mul+add, so results equal the portable build).
        return unsafe { preprocess_avx2(f, inp) };
    }
    preprocess_impl(f, inp)
}

/// Same code with AVX2 enabled (inline rounding instructions instead of libm calls, wider moves).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn preprocess_avx2(f: &Frame, inp: &RasterInputs) -> Projected {
    preprocess_impl(f, inp)
}

#[inline(always)]
fn preprocess_impl(f: &Frame, inp: &RasterInputs) -> Projected {
    let n = inp.len();
    let mut out = Projected {
        means2d: vec![0.0; 2 * n],
        depths: vec![0.0; n],
        cov2d: vec![0.0; 3 * n],
        conic: vec![0.0; 3 * n],
        colors: vec![0.0; 3 * n],
        clamped: vec![0; n],
        radii: vec![0; n],
        tiles_touched: vec![0; n],
        // Culled Gaussians' records are never read, so reused (stale) buffers need no clearing.
        geo: Pooled::new(POOL_GEO.take(n, [0.0; GEO_LEN]), &POOL_GEO),
        vals: Pooled::new(POOL_F32.take((4 + inp.num_features) * n, 0.0), &POOL_F32),
    };
    let nf = inp.num_features;
    let nv = 4 + nf;
    let deg = inp.eval_degree();
    let ncoef = sh::num_coeffs(deg);
    let (w, h) = (f.w as f64, f.h as f64);
    let m2 = SharedMut::new(&mut out.means2d);
    let dp = SharedMut::new(&mut out.depths);
    let c2 = SharedMut::new(&mut out.cov2d);
    let co = SharedMut::new(&mut out.conic);
    let cl = SharedMut::new(&mut out.colors);
    let cm = SharedMut::new(&mut out.clamped);
    let ra = SharedMut::new(&mut out.radii);
    let tt = SharedMut::new(&mut out.tiles_touched);
    let ge = SharedMut::new(&mut out.geo);
    let va = SharedMut::new(&mut out.vals);
    (0..n).into_par_iter().with_min_len(2048).for_each(|i| {
        let p = mean_of(inp, i);
        let t = view_point(&f.v, p);
        // NaN-safe form of the kernel's `z <= 0.2` cull.
        if !(t[2] > 0.2) {
            return;
        }
        let fp = &f.fp;
        let hom = |r: usize| fp[r][0] * p[0] + fp[r][1] * p[1] + fp[r][2] * p[2] + fp[r][3];
        let pw = 1.0 / (hom(3) + 1e-7);
        let ndc = [hom(0) * pw, hom(1) * pw];
        let cov = cov3d_of(inp, i);
        let e = ewa(f, t, &cov);
        let [a, b, c] = e.cov2d;
        let det = a * c - b * b;
        if det == 0.0 || !det.is_finite() {
            return;
        }
        let det_inv = 1.0 / det;
        let conic = [c * det_inv, -b * det_inv, a * det_inv];
        let mid = 0.5 * (a + c);
        let disc = (mid * mid - det).max(0.1).sqrt();
        let l1 = mid + disc;
        let l2 = mid - disc;
        let rf = (3.0 * l1.max(l2).sqrt()).ceil();
        if !rf.is_finite() || !ndc[0].is_finite() || !ndc[1].is_finite() {
            return;
        }
        let radius = rf as i32;
        // Pixel coordinates in double precision, as the kernel's ndc2Pix does.
        let px = [(((ndc[0] as f64 + 1.0) * w - 1.0) * 0.5) as f32, (((ndc[1] as f64 + 1.0) * h - 1.0) * 0.5) as f32];
        let rect = tile_rect(px, radius, f.grid);
        let area = (rect[2] - rect[0]) * (rect[3] - rect[1]);
        if area == 0 {
            return;
        }
        let (dir, _) = view_dir(f, p);
        let mut basis = [0f32; 16];
        sh::basis(dir, deg, &mut basis);
        let shi = &inp.sh[i * inp.sh_coeffs * 3..];
        let mut mask = 0u8;
        let o = inp.opacities[i];
        let (ex, ey) = alpha_extent(conic, o);
        // SAFETY: iteration i writes only index i (or 2i.., 3i..) of every buffer.
        unsafe {
            for ch in 0..3 {
                let mut acc = 0f32;
                for k in 0..ncoef {
                    acc += basis[k] * shi[3 * k + ch];
                }
                acc += 0.5;
                if acc < 0.0 {
                    mask |= 1 << ch;
                }
                cl.write(3 * i + ch, acc.max(0.0));
                va.write(nv * i + ch, acc.max(0.0));
            }
            va.write(nv * i + 3, t[2]);
            for c in 0..nf {
                va.write(nv * i + 4 + c, inp.features[nf * i + c]);
            }
            ge.write(i, [px[0], px[1], conic[0], conic[1], conic[2], o, ex, ey]);
            cm.write(i, mask);
            m2.write(2 * i, px[0]);
            m2.write(2 * i + 1, px[1]);
            dp.write(i, t[2]);
            for k in 0..3 {
                c2.write(3 * i + k, e.cov2d[k]);
                co.write(3 * i + k, conic[k]);
            }
            ra.write(i, radius);
            tt.write(i, area as u32);
        }
    });
    out
}
