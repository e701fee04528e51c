//! Per-Gaussian projection: view transform, culling, EWA 2D covariance, conic, radius, tile rect, SH colour.

use rayon::prelude::*;

use super::simd::{Arr, Isa, F8, LANES};
use super::{tile_rect, CovInput, Frame, RasterInputs};
use crate::sh;
use crate::util::{Pooled, SharedMut, Uninit, POOL_F32, POOL_GEO, POOL_U64};

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
    /// Tile rect per Gaussian packed by [`pack_rect`] (stale for culled Gaussians).
    pub rects: Pooled<u64>,
}

/// Tile rect [xmin, ymin, xmax, ymax) in 16-bit fields (the grid is checked to fit).
#[inline(always)]
pub(crate) fn pack_rect(r: [usize; 4]) -> u64 {
    r[0] as u64 | (r[1] as u64) << 16 | (r[2] as u64) << 32 | (r[3] as u64) << 48
}

#[inline(always)]
pub(crate) fn unpack_rect(p: u64) -> [usize; 4] {
    [p as u16 as usize, (p >> 16) as u16 as usize, (p >> 32) as u16 as usize, (p >> 48) as u16 as usize]
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
    preprocess_lanes(f, inp, super::simd::isa())
}

/// Lane-parallel projection of 8 Gaussians: the scalar helpers' operations (`view_point`, `cov3d_of`, `ewa`,
/// `view_dir`, `sh::basis`) in the same order, so every lane is bit-identical to one-at-a-time evaluation (the
/// test keeps that version as its reference).
struct Lanes {
    tz: [f32; LANES],
    ndc: [[f32; LANES]; 2],
    cov2d: [[f32; LANES]; 3],
    det: [f32; LANES],
    conic: [[f32; LANES]; 3],
    rf: [f32; LANES],
    /// Colour before the clamp (after +0.5).
    col: [[f32; LANES]; 3],
}

// No closures below: they would not inherit the caller's target features, so the AVX2 intrinsics inside
// them would not be inlined.

#[inline(always)]
fn gather<V: F8>(src: &[f32], stride: usize, idx: &[usize; LANES], k: usize) -> V {
    let mut a = [0f32; LANES];
    for l in 0..LANES {
        a[l] = src[stride * idx[l] + k];
    }
    // SAFETY: `a` holds LANES values.
    unsafe { V::load(a.as_ptr()) }
}

#[inline(always)]
fn st<V: F8>(v: V) -> [f32; LANES] {
    let mut a = [0f32; LANES];
    // SAFETY: `a` holds LANES values.
    unsafe { v.store(a.as_mut_ptr()) };
    a
}

/// Row `r` of the affine map `m` applied to `p` (as `view_point`).
#[inline(always)]
fn row<V: F8>(m: &[[f32; 4]; 4], r: usize, p: &[V; 3]) -> V {
    V::splat(m[r][0]).mul(p[0]).add(V::splat(m[r][1]).mul(p[1])).add(V::splat(m[r][2]).mul(p[2])).add(V::splat(m[r][3]))
}

#[inline(always)]
fn neg<V: F8>(v: V) -> V {
    v.xor(V::splat(-0.0))
}

/// `cov3d_of` for scale + rotation.
#[inline(always)]
fn cov_scale_rot<V: F8>(s: &[V; 3], q: &[V; 4]) -> [V; 6] {
    let [qr, x, y, z] = *q;
    let two = V::splat(2.0);
    let one = V::splat(1.0);
    let r = [
        [one.sub(two.mul(y.mul(y).add(z.mul(z)))), two.mul(x.mul(y).sub(qr.mul(z))), two.mul(x.mul(z).add(qr.mul(y)))],
        [two.mul(x.mul(y).add(qr.mul(z))), one.sub(two.mul(x.mul(x).add(z.mul(z)))), two.mul(y.mul(z).sub(qr.mul(x)))],
        [two.mul(x.mul(z).sub(qr.mul(y))), two.mul(y.mul(z).add(qr.mul(x))), one.sub(two.mul(x.mul(x).add(y.mul(y))))],
    ];
    let mut m = [[V::splat(0.0); 3]; 3];
    for k in 0..3 {
        for a in 0..3 {
            m[k][a] = s[k].mul(r[a][k]);
        }
    }
    let mut e = [V::splat(0.0); 6];
    for (o, (a, b)) in [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)].into_iter().enumerate() {
        e[o] = m[0][a].mul(m[0][b]).add(m[1][a].mul(m[1][b])).add(m[2][a].mul(m[2][b]));
    }
    e
}

/// aᵀ Σ b for the symmetric Σ given as its upper triangle.
#[inline(always)]
fn quad<V: F8>(cov: &[V; 6], a: &[V; 3], b: &[V; 3]) -> V {
    let s = [[cov[0], cov[1], cov[2]], [cov[1], cov[3], cov[4]], [cov[2], cov[4], cov[5]]];
    let mut acc = V::splat(0.0);
    for i in 0..3 {
        acc = acc.add(a[i].mul(s[i][0].mul(b[0]).add(s[i][1].mul(b[1])).add(s[i][2].mul(b[2]))));
    }
    acc
}

/// `sh::basis` on lanes.
#[inline(always)]
fn sh_basis<V: F8>(d: &[V; 3], deg: usize) -> [V; 16] {
    let [x, y, z] = *d;
    let c = V::splat;
    let mut b = [c(0.0); 16];
    b[0] = c(sh::C0);
    if deg >= 1 {
        b[1] = c(-sh::C1).mul(x);
        b[2] = c(sh::C1).mul(y);
        b[3] = c(-sh::C1).mul(z);
    }
    if deg >= 2 {
        let (xx, yy, zz) = (x.mul(x), y.mul(y), z.mul(z));
        let (c2, c3) = (&sh::C2, &sh::C3);
        b[4] = c(c2[0]).mul(z).mul(x);
        b[5] = c(c2[1]).mul(x).mul(y);
        b[6] = c(c2[2]).mul(c(2.0).mul(yy).sub(zz).sub(xx));
        b[7] = c(c2[3]).mul(z).mul(y);
        b[8] = c(c2[4]).mul(zz.sub(xx));
        if deg >= 3 {
            b[9] = c(c3[0]).mul(x).mul(c(3.0).mul(zz).sub(xx));
            b[10] = c(c3[1]).mul(z).mul(x).mul(y);
            b[11] = c(c3[2]).mul(x).mul(c(4.0).mul(yy).sub(zz).sub(xx));
            b[12] = c(c3[3]).mul(y).mul(c(2.0).mul(yy).sub(c(3.0).mul(zz)).sub(c(3.0).mul(xx)));
            b[13] = c(c3[4]).mul(z).mul(c(4.0).mul(yy).sub(zz).sub(xx));
            b[14] = c(c3[5]).mul(z).mul(zz.sub(xx));
            b[15] = c(c3[6]).mul(z).mul(zz.sub(c(3.0).mul(xx)));
        }
    }
    b
}

#[inline(always)]
fn project_lanes<V: F8>(f: &Frame, inp: &RasterInputs, idx: &[usize; LANES], deg: usize) -> Lanes {
    let c = V::splat;
    let p: [V; 3] = [gather(inp.means, 3, idx, 0), gather(inp.means, 3, idx, 1), gather(inp.means, 3, idx, 2)];
    let t = [row(&f.v, 0, &p), row(&f.v, 1, &p), row(&f.v, 2, &p)];
    let pw = c(1.0).div(row(&f.fp, 3, &p).add(c(1e-7)));
    let ndc = [row(&f.fp, 0, &p).mul(pw), row(&f.fp, 1, &p).mul(pw)];
    let cov: [V; 6] = match inp.cov {
        CovInput::Cov3d(cv) => {
            let mut o = [c(0.0); 6];
            for (k, ok) in o.iter_mut().enumerate() {
                *ok = gather(cv, 6, idx, k);
            }
            o
        }
        CovInput::ScaleRot { scales, quats } => {
            let s = [gather(scales, 3, idx, 0), gather(scales, 3, idx, 1), gather(scales, 3, idx, 2)];
            let q = [gather(quats, 4, idx, 0), gather(quats, 4, idx, 1), gather(quats, 4, idx, 2), gather(quats, 4, idx, 3)];
            cov_scale_rot(&s, &q)
        }
    };
    // EWA (the steps of `ewa`).
    let limx = c(1.3 * f.tanfov[0]);
    let limy = c(1.3 * f.tanfov[1]);
    let tz = t[2];
    let tx = t[0].div(tz).max(c(0.0).sub(limx)).min(limx).mul(tz);
    let ty = t[1].div(tz).max(c(0.0).sub(limy)).min(limy).mul(tz);
    let (fx, fy) = (c(f.focal[0]), c(f.focal[1]));
    let tz2 = tz.mul(tz);
    let j00 = fx.div(tz);
    let j02 = neg(fx.mul(tx)).div(tz2);
    let j11 = fy.div(tz);
    let j12 = neg(fy.mul(ty)).div(tz2);
    let v = &f.v;
    let mut m = [[c(0.0); 3]; 2];
    for k in 0..3 {
        m[0][k] = j00.mul(c(v[0][k])).add(j02.mul(c(v[2][k])));
        m[1][k] = j11.mul(c(v[1][k])).add(j12.mul(c(v[2][k])));
    }
    let a = quad(&cov, &m[0], &m[0]).add(c(0.3));
    let b = quad(&cov, &m[0], &m[1]);
    let cc = quad(&cov, &m[1], &m[1]).add(c(0.3));
    let det = a.mul(cc).sub(b.mul(b));
    let det_inv = c(1.0).div(det);
    let conic = [cc.mul(det_inv), neg(b).mul(det_inv), a.mul(det_inv)];
    let mid = c(0.5).mul(a.add(cc));
    let disc = mid.mul(mid).sub(det).max(c(0.1)).sqrt();
    let l1 = mid.add(disc);
    let l2 = mid.sub(disc);
    let rf = c(3.0).mul(l1.max(l2).sqrt()).ceil();
    // SH colour at the unit view direction (the steps of `view_dir` and `sh::basis`).
    let d = [p[0].sub(c(f.campos[0])), p[1].sub(c(f.campos[1])), p[2].sub(c(f.campos[2]))];
    let nrm = d[0].mul(d[0]).add(d[1].mul(d[1])).add(d[2].mul(d[2])).sqrt();
    let inv = V::select(nrm.gt(c(0.0)), c(1.0).div(nrm), c(0.0));
    let bs = sh_basis(&[d[0].mul(inv), d[1].mul(inv), d[2].mul(inv)], deg);
    let kc = inp.sh_coeffs * 3;
    let mut col = [[0f32; LANES]; 3];
    for (ch, out) in col.iter_mut().enumerate() {
        let mut acc = c(0.0);
        for (k, bk) in bs.iter().enumerate().take(sh::num_coeffs(deg)) {
            acc = acc.add(bk.mul(gather(inp.sh, kc, idx, 3 * k + ch)));
        }
        *out = st(acc.add(c(0.5)));
    }
    Lanes {
        tz: st(tz),
        ndc: [st(ndc[0]), st(ndc[1])],
        cov2d: [st(a), st(b), st(cc)],
        det: st(det),
        conic: [st(conic[0]), st(conic[1]), st(conic[2])],
        rf: st(rf),
        col,
    }
}

fn preprocess_lanes(f: &Frame, inp: &RasterInputs, isa: Isa) -> Projected {
    let n = inp.len();
    let nf = inp.num_features;
    let nv = 4 + nf;
    let mut means2d = Uninit::<f32>::new(2 * n);
    let mut depths = Uninit::<f32>::new(n);
    let mut cov2d = Uninit::<f32>::new(3 * n);
    let mut conic = Uninit::<f32>::new(3 * n);
    let mut colors = Uninit::<f32>::new(3 * n);
    let mut clamped = Uninit::<u8>::new(n);
    let mut radii = Uninit::<i32>::new(n);
    let mut tiles = Uninit::<u32>::new(n);
    // Culled Gaussians' records are never read, so reused (stale) buffers need no clearing.
    let mut geo = Pooled::new(POOL_GEO.take(n, [0.0; GEO_LEN]), &POOL_GEO);
    let mut vals = Pooled::new(POOL_F32.take(nv * n, 0.0), &POOL_F32);
    let mut rects = Pooled::new(POOL_U64.take(n, 0), &POOL_U64);
    let out = Outs {
        m2: means2d.ptr(),
        dp: depths.ptr(),
        c2: cov2d.ptr(),
        co: conic.ptr(),
        cl: colors.ptr(),
        cm: clamped.ptr(),
        ra: radii.ptr(),
        tt: tiles.ptr(),
        ge: SharedMut::new(&mut geo),
        va: SharedMut::new(&mut vals),
        re: SharedMut::new(&mut rects),
    };
    (0..n.div_ceil(LANES)).into_par_iter().with_min_len(256).for_each(|blk| {
        // SAFETY: blocks write disjoint Gaussians; each ISA only where detected.
        unsafe {
            #[cfg(target_arch = "x86_64")]
            match isa {
                Isa::Avx512 => return block_avx512(f, inp, &out, blk),
                Isa::Avx2 => return block_avx2(f, inp, &out, blk),
                Isa::Portable => {}
            }
            block::<Arr>(f, inp, &out, blk)
        }
    });
    // SAFETY: every index of every buffer was written by `block`.
    unsafe {
        Projected {
            means2d: means2d.done(),
            depths: depths.done(),
            cov2d: cov2d.done(),
            conic: conic.done(),
            colors: colors.done(),
            clamped: clamped.done(),
            radii: radii.done(),
            tiles_touched: tiles.done(),
            geo,
            vals,
            rects,
        }
    }
}

/// Output views of the preprocess.
struct Outs {
    m2: SharedMut<f32>,
    dp: SharedMut<f32>,
    c2: SharedMut<f32>,
    co: SharedMut<f32>,
    cl: SharedMut<f32>,
    cm: SharedMut<u8>,
    ra: SharedMut<i32>,
    tt: SharedMut<u32>,
    ge: SharedMut<[f32; GEO_LEN]>,
    va: SharedMut<f32>,
    re: SharedMut<u64>,
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,avx512f,avx512vl")]
unsafe fn block_avx512(f: &Frame, inp: &RasterInputs, out: &Outs, blk: usize) {
    block::<super::simd::Avx>(f, inp, out, blk)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn block_avx2(f: &Frame, inp: &RasterInputs, out: &Outs, blk: usize) {
    block::<super::simd::Avx>(f, inp, out, blk)
}

/// Gaussians `8 blk .. 8 blk + 8`: every output index of each is written (zeros when culled).
///
/// # Safety
/// No other thread writes these Gaussians' outputs.
#[inline(always)]
unsafe fn block<V: F8>(f: &Frame, inp: &RasterInputs, out: &Outs, blk: usize) {
    let n = inp.len();
    let nf = inp.num_features;
    let nv = 4 + nf;
    let deg = inp.eval_degree();
    let (w, h) = (f.w as f64, f.h as f64);
    let Outs { m2, dp, c2, co, cl, cm, ra, tt, ge, va, re } = out;
    let i0 = blk * LANES;
    // Tail lanes repeat the last Gaussian and are not stored.
    let idx: [usize; LANES] = std::array::from_fn(|l| (i0 + l).min(n - 1));
    prefetch_sh(inp, i0 + 2 * LANES, deg);
    let r = project_lanes::<V>(f, inp, &idx, deg);
    for l in 0..LANES.min(n - i0) {
        let i = i0 + l;
        let visible = project_lane_finish(f, w, h, &r, l);
        // SAFETY: iteration i writes only index i (or 2i.., 3i..) of every buffer.
        unsafe {
            let Some((px, radius, rect)) = visible else {
                for k in 0..3 {
                    c2.write(3 * i + k, 0.0);
                    co.write(3 * i + k, 0.0);
                    cl.write(3 * i + k, 0.0);
                }
                m2.write(2 * i, 0.0);
                m2.write(2 * i + 1, 0.0);
                dp.write(i, 0.0);
                cm.write(i, 0);
                ra.write(i, 0);
                tt.write(i, 0);
                continue;
            };
            let o = inp.opacities[i];
            let cn = [r.conic[0][l], r.conic[1][l], r.conic[2][l]];
            let (ex, ey) = alpha_extent(cn, o);
            let mut mask = 0u8;
            for ch in 0..3 {
                let acc = r.col[ch][l];
                if acc < 0.0 {
                    mask |= 1 << ch;
                }
                cl.write(3 * i + ch, acc.max(0.0));
                va.write(nv * i + ch, acc.max(0.0));
            }
            let tz = r.tz[l];
            va.write(nv * i + 3, tz);
            for c in 0..nf {
                va.write(nv * i + 4 + c, inp.features[nf * i + c]);
            }
            ge.write(i, [px[0], px[1], cn[0], cn[1], cn[2], o, ex, ey]);
            cm.write(i, mask);
            m2.write(2 * i, px[0]);
            m2.write(2 * i + 1, px[1]);
            dp.write(i, tz);
            for k in 0..3 {
                c2.write(3 * i + k, r.cov2d[k][l]);
                co.write(3 * i + k, cn[k]);
            }
            ra.write(i, radius);
            tt.write(i, ((rect[2] - rect[0]) * (rect[3] - rect[1])) as u32);
            re.write(i, pack_rect(rect));
        }
    }
}

/// The SH rows (stride 3K floats, e.g. 300 bytes) of a later block: eight interleaved streams that the hardware
/// prefetcher follows poorly.
#[inline(always)]
fn prefetch_sh(inp: &RasterInputs, i0: usize, deg: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let row = inp.sh_coeffs * 3;
        let used = sh::num_coeffs(deg) * 3;
        for i in i0..(i0 + LANES).min(inp.len()) {
            let base = i * row;
            let mut k = 0;
            while k < used {
                // SAFETY: prefetching never faults; the address is inside the slice.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(inp.sh.as_ptr().add(base + k) as *const i8) };
                k += 16;
            }
            // SAFETY: as above (last used value of the row).
            unsafe { _mm_prefetch::<_MM_HINT_T0>(inp.sh.as_ptr().add(base + used - 1) as *const i8) };
        }
    }
}

/// Culling and the pixel-space quantities of lane `l`: `None` if the Gaussian is not rendered.
#[inline(always)]
fn project_lane_finish(f: &Frame, w: f64, h: f64, r: &Lanes, l: usize) -> Option<([f32; 2], i32, [usize; 4])> {
    // NaN-safe form of the kernel's `z <= 0.2` cull.
    if !(r.tz[l] > 0.2) {
        return None;
    }
    let det = r.det[l];
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let rf = r.rf[l];
    let ndc = [r.ndc[0][l], r.ndc[1][l]];
    if !rf.is_finite() || !ndc[0].is_finite() || !ndc[1].is_finite() {
        return None;
    }
    let radius = rf as i32;
    // Pixel coordinates in double precision, as the kernel's ndc2Pix does.
    let px = [(((ndc[0] as f64 + 1.0) * w - 1.0) * 0.5) as f32, (((ndc[1] as f64 + 1.0) * h - 1.0) * 0.5) as f32];
    let rect = tile_rect(px, radius, f.grid);
    if rect[2] == rect[0] || rect[3] == rect[1] {
        return None;
    }
    Some((px, radius, rect))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::synthetic_scene;
    use crate::cpu::simd::{set_max_isa, ISA_TEST_LOCK};

    /// The reference: one Gaussian at a time in plain scalar code.
    fn preprocess_scalar(f: &Frame, inp: &RasterInputs) -> Projected {
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
            rects: Pooled::new(POOL_U64.take(n, 0), &POOL_U64),
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
        let re = SharedMut::new(&mut out.rects);
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
                re.write(i, pack_rect(rect));
            }
        });
        out
    }

    /// The lane-parallel preprocess (AVX2 and portable) must equal the scalar reference bit for bit, including
    /// culled, degenerate and non-finite Gaussians and a partial last block.
    #[test]
    fn lanes_equal_scalar_reference() {
        let _lock = ISA_TEST_LOCK.lock().unwrap_or_else(|e| e.into_inner());
        let mut sc = synthetic_scene(3 * 40 * 24 + 5, 40, 24, 3);
        let n = sc.opacities.len();
        // At the camera centre, NaN mean, zero scale, infinite scale, NaN quaternion, zero opacity.
        let cam_pos = sc.camera.campos();
        for k in 0..3 {
            sc.means[3 * 7 + k] = cam_pos[k];
        }
        sc.means[3 * 11] = f32::NAN;
        sc.scales[3 * 13..3 * 13 + 3].copy_from_slice(&[0.0; 3]);
        sc.scales[3 * 17] = f32::INFINITY;
        sc.quats[4 * 19] = f32::NAN;
        sc.opacities[23] = 0.0;
        let f = Frame::new(&sc.camera);
        let mut inputs = vec![sc.inputs()];
        let cov: Vec<f32> = (0..n).flat_map(|i| cov3d_of(&sc.inputs(), i)).collect();
        let mut ci = sc.inputs();
        ci.cov = CovInput::Cov3d(&cov);
        inputs.push(ci);
        let mut low = sc.inputs();
        low.sh_degree = 1;
        inputs.push(low);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for inp in &inputs {
            let want = preprocess_scalar(&f, inp);
            assert!(want.radii.iter().filter(|&&r| r > 0).count() > n / 2, "scene mostly culled");
            // Record the path each cap really selects: on a CPU without AVX-512 the first two are one path.
            let mut ran_paths = Vec::new();
            for max in [Isa::Avx512, Isa::Avx2, Isa::Portable] {
                set_max_isa(max);
                let ran = crate::cpu::simd::isa();
                let got = preprocess(&f, inp);
                set_max_isa(Isa::Avx512);
                if !ran_paths.contains(&ran) {
                    ran_paths.push(ran);
                }
                assert_eq!(got.radii, want.radii);
                assert_eq!(got.tiles_touched, want.tiles_touched);
                assert_eq!(got.clamped, want.clamped);
                for (a, b) in [
                    (&got.means2d, &want.means2d),
                    (&got.depths, &want.depths),
                    (&got.cov2d, &want.cov2d),
                    (&got.conic, &want.conic),
                    (&got.colors, &want.colors),
                ] {
                    assert_eq!(bits(a), bits(b));
                }
                for i in (0..n).filter(|&i| want.radii[i] > 0) {
                    assert_eq!(bits(&got.geo[i]), bits(&want.geo[i]), "geo {i}");
                    let nv = 4 + inp.num_features;
                    assert_eq!(bits(&got.vals[nv * i..nv * i + nv]), bits(&want.vals[nv * i..nv * i + nv]));
                }
            }
            eprintln!("lane paths compared with the scalar reference: {ran_paths:?}");
            assert!(ran_paths.contains(&Isa::Portable), "the portable lane path never ran");
            #[cfg(target_arch = "x86_64")]
            if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                assert!(ran_paths.len() >= 2, "only {ran_paths:?} ran: no vector path was compared");
            }
        }
    }
}
