//! Fixture reading and comparison helpers shared by the rasterizer's integration tests.
#![allow(dead_code)] // each test binary uses a different subset

use std::collections::HashMap;

use candle_core::{DType, Tensor};
use mvsplat360_splat::cpu::{CovInput, RasterInputs, RasterSettings};
use mvsplat360_splat::RasterCamera;
use mvsplat360_testkit::{get, load};

pub fn v32(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

pub fn vi(t: &Tensor) -> Vec<i64> {
    t.to_dtype(DType::I64).unwrap().flatten_all().unwrap().to_vec1::<i64>().unwrap()
}

/// (H,W,C) → planar (C,H,W)
pub fn to_planar(v: &[f32], h: usize, w: usize, c: usize) -> Vec<f32> {
    let mut o = vec![0f32; v.len()];
    for p in 0..h * w {
        for ch in 0..c {
            o[ch * h * w + p] = v[p * c + ch];
        }
    }
    o
}

pub fn camera(m: &HashMap<String, Tensor>) -> RasterCamera {
    let size = vi(get(m, "image_size"));
    let intr = v32(get(m, "intrinsics"));
    let nf = v32(get(m, "near_far"));
    RasterCamera {
        viewmatrix: RasterCamera::viewmatrix_from_slice(&v32(get(m, "viewmatrix"))).unwrap(),
        fx: intr[0],
        fy: intr[1],
        cx: intr[2],
        cy: intr[3],
        width: size[1] as usize,
        height: size[0] as usize,
        near: nf[0],
        far: nf[1],
    }
}

/// A rasterizer fixture's inputs as owned buffers, with the loss weights as planar pixel gradients.
pub struct Fixture {
    pub m: HashMap<String, Tensor>,
    pub settings: RasterSettings,
    pub means: Vec<f32>,
    pub cov3d: Vec<f32>,
    pub scales: Vec<f32>,
    pub quats: Vec<f32>,
    pub opacities: Vec<f32>,
    pub sh: Vec<f32>,
    pub sh_coeffs: usize,
    pub sh_degree: usize,
    pub features: Vec<f32>,
    pub nf: usize,
    /// (3,H,W) and (C,H,W): dL/d image of the fixture's loss.
    pub w1: Vec<f32>,
    pub w2: Vec<f32>,
}

/// The two covariance input paths.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CovPath {
    Cov3d,
    ScaleRot,
}

impl Fixture {
    /// `file` inside `rasterizer/` of the fixture folder.
    pub fn load(file: &str) -> Self {
        let m = load(&format!("rasterizer/{file}"));
        let cam = camera(&m);
        let (h, w) = (cam.height, cam.width);
        let sh_t = get(&m, "sh");
        let feats_t = get(&m, "features");
        let nf = feats_t.dim(1).unwrap();
        let bg = v32(get(&m, "background"));
        Fixture {
            settings: RasterSettings { camera: cam, background: [bg[0], bg[1], bg[2]] },
            means: v32(get(&m, "means")),
            cov3d: v32(get(&m, "cov3d")),
            scales: v32(get(&m, "scales")),
            quats: v32(get(&m, "quats")),
            opacities: v32(get(&m, "opacities")),
            sh_coeffs: sh_t.dim(1).unwrap(),
            sh: v32(sh_t),
            sh_degree: vi(get(&m, "sh_degree"))[0] as usize,
            features: v32(feats_t),
            nf,
            w1: to_planar(&v32(get(&m, "W1")), h, w, 3),
            w2: to_planar(&v32(get(&m, "W2")), h, w, nf),
            m,
        }
    }

    pub fn inputs(&self, path: CovPath) -> RasterInputs<'_> {
        RasterInputs {
            means: &self.means,
            cov: match path {
                CovPath::Cov3d => CovInput::Cov3d(&self.cov3d),
                CovPath::ScaleRot => CovInput::ScaleRot { scales: &self.scales, quats: &self.quats },
            },
            opacities: &self.opacities,
            sh: &self.sh,
            sh_coeffs: self.sh_coeffs,
            sh_degree: self.sh_degree,
            features: &self.features,
            num_features: self.nf,
        }
    }

    /// A fixture tensor as f32 values.
    pub fn f(&self, name: &str) -> Vec<f32> {
        v32(get(&self.m, name))
    }

    /// A fixture image (H,W,C) as planar (C,H,W).
    pub fn planar(&self, name: &str) -> Vec<f32> {
        let t = get(&self.m, name);
        let c = if t.rank() == 3 { t.dim(2).unwrap() } else { 1 };
        to_planar(&v32(t), self.settings.camera.height, self.settings.camera.width, c)
    }
}

/// max |a-b| and max |b|; panics on a length mismatch or a non-finite `a`.
pub fn diff(a: &[f32], b: &[f32]) -> (f64, f64) {
    assert_eq!(a.len(), b.len(), "length");
    let mut d = 0f64;
    let mut m = 0f64;
    for (x, y) in a.iter().zip(b) {
        assert!(x.is_finite(), "non-finite output");
        d = d.max((*x as f64 - *y as f64).abs());
        m = m.max((*y as f64).abs());
    }
    (d, m)
}

/// max |a-b| ≤ tol (the reference must not be all zeros: that would make the check vacuous).
pub fn check_abs(name: &str, a: &[f32], b: &[f32], tol: f64) {
    let (d, m) = diff(a, b);
    eprintln!("{name}: max abs diff {d:.3e} (max |ref| {m:.3e})");
    assert!(m > 0.0, "{name}: reference is all zeros");
    assert!(d <= tol, "{name}: max abs diff {d:.3e} > {tol:.1e}");
}

/// max |a-b| ≤ tol · max |b|.
pub fn check_rel(name: &str, a: &[f32], b: &[f32], tol: f64) {
    let (d, m) = diff(a, b);
    eprintln!("{name}: max abs diff {d:.3e} = {:.3e} x max|ref| {m:.3e}", d / m.max(1e-30));
    assert!(m > 0.0, "{name}: reference is all zeros");
    assert!(d <= tol * m, "{name}: max abs diff {d:.3e} > {tol:.1e} x max|ref| {m:.3e}");
}

pub fn count_diff<T: PartialEq>(a: &[T], b: &[T]) -> usize {
    assert_eq!(a.len(), b.len(), "length");
    a.iter().zip(b).filter(|(x, y)| x != y).count()
}

/// Element-wise |a − b| ≤ atol + rtol·|b| for every entry (testkit's `allclose` rule); returns the failure.
pub fn close_report(name: &str, a: &[f32], b: &[f32], atol: f64, rtol: f64) -> Option<String> {
    let a: Vec<f64> = a.iter().map(|&x| x as f64).collect();
    let b: Vec<f64> = b.iter().map(|&x| x as f64).collect();
    mvsplat360_testkit::allclose_report(name, &a, &b, atol, rtol)
}

/// Assert [`close_report`] finds nothing.
pub fn check_close(name: &str, a: &[f32], b: &[f32], atol: f64, rtol: f64) {
    if let Some(m) = close_report(name, a, b, atol, rtol) {
        panic!("{m}");
    }
}

/// max |v|.
pub fn max_abs(v: &[f32]) -> f64 {
    v.iter().fold(0f64, |m, &x| m.max((x as f64).abs()))
}

/// Visible Gaussians whose view-space centre lies outside the 1.3·tan(fov) cone in x or y: the rasterizer
/// clamps t.x/t.z (t.y/t.z) in the EWA Jacobian there, and the fork's backward treats the clamped value as a
/// constant.
pub fn clamped_jacobian(means: &[f32], radii: &[i64], cam: &RasterCamera) -> Vec<usize> {
    let v = &cam.viewmatrix;
    let tf = cam.tanfov();
    (0..radii.len())
        .filter(|&i| {
            let p = &means[3 * i..3 * i + 3];
            let t: Vec<f32> = (0..3).map(|r| v[r][0] * p[0] + v[r][1] * p[1] + v[r][2] * p[2] + v[r][3]).collect();
            radii[i] > 0 && ((t[0] / t[2]).abs() > 1.3 * tf[0] || (t[1] / t[2]).abs() > 1.3 * tf[1])
        })
        .collect()
}

/// Rows `idx` of an (N, c) buffer.
pub fn rows(v: &[f32], c: usize, idx: &[usize]) -> Vec<f32> {
    idx.iter().flat_map(|&i| v[c * i..c * i + c].to_vec()).collect()
}
