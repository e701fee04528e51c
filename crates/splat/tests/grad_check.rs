//! Finite-difference check of the `Exact` backward on a tiny scene (independent of the fixtures), plus
//! properties of the `Official` backward (feature stop-grad).

use mvsplat360_splat::cpu::{self, CovInput, ForwardOutput, GradMode, PixelGrads, RasterInputs, RasterSettings};
use mvsplat360_splat::RasterCamera;

struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
    fn range(&mut self, a: f32, b: f32) -> f32 {
        a + (b - a) * self.next()
    }
}

const K: usize = 16;
const NF: usize = 2;

#[derive(Clone)]
struct Scene {
    means: Vec<f32>,
    cov: Vec<f32>,
    scales: Vec<f32>,
    quats: Vec<f32>,
    opac: Vec<f32>,
    sh: Vec<f32>,
    feat: Vec<f32>,
}

fn camera() -> RasterCamera {
    let mut v = [[0f32; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    RasterCamera { viewmatrix: v, fx: 20.0, fy: 20.0, cx: 10.0, cy: 9.0, width: 20, height: 18, near: 0.1, far: 100.0 }
}

fn scene() -> Scene {
    let mut r = Lcg(7);
    // Big Gaussians: every one reaches every pixel with alpha well above 1/255, so no discrete decision flips
    // under small perturbations. The last one lies outside the 1.3·tanfov cone (Jacobian clamp); the
    // fully opaque one exercises the 0.99 alpha clamp.
    let centres = [[0.0, 0.0, 3.0], [0.3, -0.2, 3.5], [-0.4, 0.3, 4.0], [0.0625, 0.1875, 2.5], [2.6, 0.1, 3.25]];
    let mut s = Scene { means: vec![], cov: vec![], scales: vec![], quats: vec![], opac: vec![], sh: vec![], feat: vec![] };
    for (i, c) in centres.iter().enumerate() {
        s.means.extend_from_slice(c);
        let sc = [r.range(1.6, 2.2), r.range(1.6, 2.2), r.range(1.6, 2.2)];
        let mut q = [r.range(-1.0, 1.0), r.range(-1.0, 1.0), r.range(-1.0, 1.0), r.range(-1.0, 1.0)];
        let qn = q.iter().map(|x| x * x).sum::<f32>().sqrt();
        q.iter_mut().for_each(|x| *x /= qn);
        s.scales.extend_from_slice(&sc);
        s.quats.extend_from_slice(&q);
        s.opac.push(if i == 3 { 0.9972 } else { r.range(0.3, 0.6) });
        for k in 0..K {
            for _ in 0..3 {
                s.sh.push(if k == 0 { r.range(0.8, 1.2) } else { r.range(-0.1, 0.1) });
            }
        }
        for _ in 0..NF {
            s.feat.push(r.range(-1.0, 1.0));
        }
    }
    // cov3d from scales/rotation (R S² Rᵀ) in f64.
    for i in 0..centres.len() {
        let [w, x, y, z] = [s.quats[4 * i] as f64, s.quats[4 * i + 1] as f64, s.quats[4 * i + 2] as f64, s.quats[4 * i + 3] as f64];
        let rm = [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
        ];
        let e = |a: usize, b: usize| (0..3).map(|k| rm[a][k] * rm[b][k] * (s.scales[3 * i + k] as f64).powi(2)).sum::<f64>() as f32;
        s.cov.extend_from_slice(&[e(0, 0), e(0, 1), e(0, 2), e(1, 1), e(1, 2), e(2, 2)]);
    }
    s
}

fn inputs<'a>(s: &'a Scene, scale_rot: bool) -> RasterInputs<'a> {
    RasterInputs {
        means: &s.means,
        cov: if scale_rot { CovInput::ScaleRot { scales: &s.scales, quats: &s.quats } } else { CovInput::Cov3d(&s.cov) },
        opacities: &s.opac,
        sh: &s.sh,
        sh_coeffs: K,
        sh_degree: 3,
        features: &s.feat,
        num_features: NF,
    }
}

struct Weights {
    rgb: Vec<f32>,
    feat: Vec<f32>,
    alpha: Vec<f32>,
    depth: Vec<f32>,
}

fn weights(hw: usize) -> Weights {
    let mut r = Lcg(99);
    let mut v = |n: usize| (0..n).map(|_| r.range(-1.0, 1.0)).collect::<Vec<f32>>();
    let mut w = Weights { rgb: v(3 * hw), feat: v(NF * hw), alpha: v(hw), depth: v(hw) };
    if let Ok(m) = std::env::var("FD_ONLY") {
        if !m.contains('r') {
            w.rgb.fill(0.0);
        }
        if !m.contains('f') {
            w.feat.fill(0.0);
        }
        if !m.contains('a') {
            w.alpha.fill(0.0);
        }
        if !m.contains('d') {
            w.depth.fill(0.0);
        }
    }
    w
}

fn loss(o: &ForwardOutput, w: &Weights) -> f64 {
    let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
    dot(&o.rgb, &w.rgb) + dot(&o.features, &w.feat) + dot(&o.alpha, &w.alpha) + dot(&o.depth, &w.depth)
}

fn settings() -> RasterSettings {
    RasterSettings { camera: camera(), background: [0.2, 0.5, 0.7] }
}

#[test]
fn scene_is_smooth_everywhere() {
    // Guard for the FD test's premise: every Gaussian is visible, touches all tiles and has alpha ≥ 2/255
    // at every pixel; no pixel stops early.
    let s = scene();
    let st = settings();
    let o = cpu::forward(&inputs(&s, false), &st).unwrap();
    let (w, h) = (st.camera.width, st.camera.height);
    let mut n_clamped = 0;
    for i in 0..s.opac.len() {
        assert!(o.radii[i] > 0);
        assert_eq!(o.tiles_touched[i] as usize, w.div_ceil(16) * h.div_ceil(16));
        for y in 0..h {
            for x in 0..w {
                let dx = o.means2d[2 * i] - x as f32;
                let dy = o.means2d[2 * i + 1] - y as f32;
                let c = &o.conic[3 * i..3 * i + 3];
                let p = -0.5 * (c[0] * dx * dx + c[2] * dy * dy) - c[1] * dx * dy;
                let a = s.opac[i] * p.exp();
                if std::env::var("FD_DEBUG").is_ok() && a > 0.97 {
                    eprintln!("g{i} ({x},{y}) {a}");
                }
                assert!(a > 2.0 / 255.0, "Gaussian {i} too faint at ({x},{y})");
                // Keep the 0.99 clamp away from any pixel (a kink finite differences cannot resolve).
                assert!((a - 0.99).abs() > 1.5e-3, "Gaussian {i} at ({x},{y}) has o*G = {a}, too close to 0.99");
                if a > 0.99 {
                    n_clamped += 1;
                }
            }
        }
    }
    assert!(n_clamped > 0, "no pixel exercises the 0.99 alpha clamp");
    assert!(o.final_t.iter().all(|&t| t > 1e-3));
    let nclamp = (0..s.opac.len()).filter(|&i| (s.means[3 * i] / s.means[3 * i + 2]).abs() > 1.3 * 0.5).count();
    assert_eq!(nclamp, 1);
}

fn max_rel_err(name: &str, an: &[f32], fd: &[f64]) -> f64 {
    let m = an.iter().fold(0f64, |a, b| a.max(b.abs() as f64));
    let d = an.iter().zip(fd).fold(0f64, |a, (x, y)| a.max((*x as f64 - y).abs()));
    if std::env::var("FD_DEBUG").is_ok() {
        for (x, y) in an.iter().zip(fd) {
            eprintln!("  an {x:12.5} fd {y:12.5}");
        }
    }
    eprintln!("{name}: max |an - fd| = {d:.3e} = {:.3e} x max|an| {m:.3e}", d / m);
    assert!(m > 0.0, "{name}: all-zero gradient");
    d / m
}

fn fd_check(scale_rot: bool) {
    let s0 = scene();
    let st = settings();
    let hw = st.camera.width * st.camera.height;
    let w = weights(hw);
    let fwd = cpu::forward(&inputs(&s0, scale_rot), &st).unwrap();
    let pg = PixelGrads { rgb: &w.rgb, features: &w.feat, alpha: Some(&w.alpha), depth: Some(&w.depth) };
    let g = cpu::backward(&inputs(&s0, scale_rot), &st, &fwd, &pg, GradMode::Exact).unwrap();
    let eps = 1e-3f32;
    let fd_of = |pick: &dyn Fn(&mut Scene) -> &mut Vec<f32>| -> Vec<f64> {
        let len = pick(&mut s0.clone()).len();
        (0..len)
            .map(|j| {
                let mut sp = s0.clone();
                pick(&mut sp)[j] += eps;
                let mut sm = s0.clone();
                pick(&mut sm)[j] -= eps;
                let lp = loss(&cpu::forward(&inputs(&sp, scale_rot), &st).unwrap(), &w);
                let lm = loss(&cpu::forward(&inputs(&sm, scale_rot), &st).unwrap(), &w);
                // Use the exactly representable step to avoid f32 rounding of x ± eps.
                let xp = pick(&mut sp)[j] as f64;
                let xm = pick(&mut sm)[j] as f64;
                (lp - lm) / (xp - xm)
            })
            .collect()
    };
    let tol = 5e-3;
    assert!(max_rel_err("means", &g.means, &fd_of(&|s| &mut s.means)) < tol);
    assert!(max_rel_err("opacities", &g.opacities, &fd_of(&|s| &mut s.opac)) < tol);
    assert!(max_rel_err("sh", &g.sh, &fd_of(&|s| &mut s.sh)) < tol);
    assert!(max_rel_err("features", &g.features, &fd_of(&|s| &mut s.feat)) < tol);
    if scale_rot {
        assert!(max_rel_err("scales", g.scales.as_ref().unwrap(), &fd_of(&|s| &mut s.scales)) < tol);
        assert!(max_rel_err("quats", g.quats.as_ref().unwrap(), &fd_of(&|s| &mut s.quats)) < tol);
    } else {
        assert!(max_rel_err("cov3d", &g.cov3d, &fd_of(&|s| &mut s.cov)) < tol);
    }
}

#[test]
fn exact_backward_matches_finite_differences_cov3d() {
    fd_check(false);
}

#[test]
fn exact_backward_matches_finite_differences_scale_rot() {
    fd_check(true);
}

#[test]
fn official_feature_pass_is_stop_grad_for_geometry() {
    let s = scene();
    let st = settings();
    let hw = st.camera.width * st.camera.height;
    let w = weights(hw);
    let inp = inputs(&s, false);
    let fwd = cpu::forward(&inp, &st).unwrap();
    let zeros = vec![0f32; NF * hw];
    let with = PixelGrads { rgb: &w.rgb, features: &w.feat, alpha: None, depth: None };
    let without = PixelGrads { rgb: &w.rgb, features: &zeros, alpha: None, depth: None };
    let a = cpu::backward(&inp, &st, &fwd, &with, GradMode::Official).unwrap();
    let b = cpu::backward(&inp, &st, &fwd, &without, GradMode::Official).unwrap();
    assert_eq!(a.means, b.means);
    assert_eq!(a.cov3d, b.cov3d);
    assert_eq!(a.opacities, b.opacities);
    assert!(a.features.iter().any(|&x| x != 0.0));
    // ...while the exact mode lets the feature image reach the geometry.
    let c = cpu::backward(&inp, &st, &fwd, &with, GradMode::Exact).unwrap();
    let d = cpu::backward(&inp, &st, &fwd, &without, GradMode::Exact).unwrap();
    assert!(c.means.iter().zip(&d.means).any(|(x, y)| (x - y).abs() > 1e-3));
}

/// The official backward's clamped-Jacobian gradient (the fork holds the clamped t.x = ±1.3·tanfov·t.z constant:
/// no gradient to t.x through J, and ∂J/∂t.z with t.x fixed) against finite differences of the forward, where the
/// two must agree: Gaussian 4 is outside the cone in x, and moving it along the view's x or y axis leaves t.z, hence
/// the clamped t.x and J, unchanged, so there the fork's gradient is the true derivative. Along z it is by design not
/// (the clamp's dependence on t.z is dropped): there the official gradient must differ from the central difference,
/// and the exact mode must match it. The other deliberate deviations are kept out: no feature image gradient (stop-
/// grad), SH coefficient 14 zeroed (its backward uses another basis function), and Gaussian 4 never reaches the
/// 0.99 alpha clamp. (The fixtures cannot serve as reference: their one visible clamped Gaussian has zero gradient.)
#[test]
fn official_clamped_jacobian_gradient_matches_finite_differences_where_it_is_a_derivative() {
    let mut s = scene();
    for i in 0..s.opac.len() {
        for c in 0..3 {
            s.sh[(i * K + 14) * 3 + c] = 0.0;
        }
    }
    let st = settings();
    let hw = st.camera.width * st.camera.height;
    let mut w = weights(hw);
    w.feat.fill(0.0);
    w.alpha.fill(0.0);
    w.depth.fill(0.0);
    let inp = inputs(&s, false);
    let fwd = cpu::forward(&inp, &st).unwrap();
    let pg = PixelGrads { rgb: &w.rgb, features: &w.feat, alpha: None, depth: None };
    let official = cpu::backward(&inp, &st, &fwd, &pg, GradMode::Official).unwrap();
    let exact = cpu::backward(&inp, &st, &fwd, &pg, GradMode::Exact).unwrap();
    let g = 4;
    let tf = st.camera.tanfov();
    assert!((s.means[3 * g] / s.means[3 * g + 2]).abs() > 1.3 * tf[0], "Gaussian {g} must be outside the cone in x");
    // The camera is the identity: view axes = world axes.
    // Step 3e-2: the f32 forward's rounding noise swamps smaller steps for one Gaussian's gradient (measured:
    // central differences settle to ≤ 0.5 % at 3e-2 from 1–9 % at 1e-3).
    let eps = 3e-2f32;
    let fd = |axis: usize| -> f64 {
        let mut sp = s.clone();
        sp.means[3 * g + axis] += eps;
        let mut sm = s.clone();
        sm.means[3 * g + axis] -= eps;
        let lp = loss(&cpu::forward(&inputs(&sp, false), &st).unwrap(), &w);
        let lm = loss(&cpu::forward(&inputs(&sm, false), &st).unwrap(), &w);
        (lp - lm) / (sp.means[3 * g + axis] as f64 - sm.means[3 * g + axis] as f64)
    };
    let fds: Vec<f64> = (0..3).map(fd).collect();
    let off: Vec<f64> = official.means[3 * g..3 * g + 3].iter().map(|&x| x as f64).collect();
    let ex: Vec<f64> = exact.means[3 * g..3 * g + 3].iter().map(|&x| x as f64).collect();
    eprintln!("Gaussian {g} means gradient: official {off:?}, exact {ex:?}, central differences {fds:?}");
    // Measured at this step: |an − fd| ≤ 1.4e-5 (x, y) and 2.2e-5 (z, exact) with components up to 0.0245; the
    // official z component differs from the central difference by 1.0e-2.
    let scale = fds.iter().fold(0f64, |m, x| m.max(x.abs()));
    let (atol, rtol) = (1e-3 * scale, 1e-2);
    mvsplat360_testkit::assert_allclose_slice("official d/dx, d/dy (clamped Gaussian)", &off[..2], &fds[..2], atol, rtol);
    mvsplat360_testkit::assert_allclose_slice("exact d/dx, d/dy, d/dz (clamped Gaussian)", &ex, &fds, atol, rtol);
    let dz = (off[2] - fds[2]).abs();
    assert!(dz > 10.0 * (atol + rtol * fds[2].abs()), "official d/dz {} should drop the clamp's t.z dependence (fd {})", off[2], fds[2]);
}
