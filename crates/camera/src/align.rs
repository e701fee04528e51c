//! Similarity alignment of point sets (Umeyama 1991) and the pose errors of estimated cameras against true ones.
//!
//! An estimated reconstruction (COLMAP's) lives in its own frame and scale; [`camera_errors`] maps its camera
//! centres onto the true ones with the least-squares similarity and measures what is left.

use nalgebra::{Matrix3, Vector3};

use crate::Camera;

/// `p ↦ scale · rotation · p + translation`, with `rotation` proper (det +1).
#[derive(Debug, Clone, PartialEq)]
pub struct Similarity {
    pub scale: f64,
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
}

impl Similarity {
    pub fn apply(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.scale * (self.rotation * p) + self.translation
    }

    /// The camera moved into the target frame: centre mapped, orientation rotated, intrinsics kept.
    pub fn apply_camera(&self, camera: &Camera) -> Camera {
        let mut out = camera.clone();
        let r = self.rotation * camera.rotation();
        let c = self.apply(&camera.center());
        for i in 0..3 {
            for j in 0..3 {
                out.c2w[i][j] = r[(i, j)];
            }
            out.c2w[i][3] = c[i];
        }
        out
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AlignError {
    #[error("alignment needs as many source as target points: got {src} and {dst}")]
    LengthMismatch { src: usize, dst: usize },
    #[error("alignment needs at least 3 point pairs, got {n}")]
    TooFewPoints { n: usize },
    #[error("point {index} of the {set} set is not finite")]
    NotFinite { set: &'static str, index: usize },
    #[error(
        "the {set} points are {shape} (second spread {ratio:.1e} of the first): a similarity is not determined; \
         use cameras that do not lie on one line"
    )]
    Degenerate { set: &'static str, shape: &'static str, ratio: f64 },
}

/// Relative size of the second principal spread below which a point set counts as a line (or a point).
const DEGENERATE_RATIO: f64 = 1e-10;

/// The similarity minimising Σ |dst_i − (s R src_i + t)|² (Umeyama 1991, with its fix that keeps det R = +1 when
/// the best orthogonal map would be a reflection).
pub fn umeyama(src: &[Vector3<f64>], dst: &[Vector3<f64>]) -> Result<Similarity, AlignError> {
    if src.len() != dst.len() {
        return Err(AlignError::LengthMismatch { src: src.len(), dst: dst.len() });
    }
    let n = src.len();
    if n < 3 {
        return Err(AlignError::TooFewPoints { n });
    }
    for (set, pts) in [("source", src), ("target", dst)] {
        if let Some(index) = pts.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(AlignError::NotFinite { set, index });
        }
    }
    let mean = |pts: &[Vector3<f64>]| pts.iter().sum::<Vector3<f64>>() / n as f64;
    let (mu_src, mu_dst) = (mean(src), mean(dst));
    let mut cov_src = Matrix3::zeros();
    let mut cov_dst = Matrix3::zeros();
    let mut cross = Matrix3::zeros();
    for (x, y) in src.iter().zip(dst) {
        let (a, b) = (x - mu_src, y - mu_dst);
        cov_src += a * a.transpose();
        cov_dst += b * b.transpose();
        cross += b * a.transpose();
    }
    let inv_n = 1.0 / n as f64;
    let (cov_src, cov_dst, cross) = (cov_src * inv_n, cov_dst * inv_n, cross * inv_n);
    check_spread("source", &cov_src)?;
    check_spread("target", &cov_dst)?;

    let svd = cross.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else { unreachable!("SVD computed with U and Vᵀ requested") };
    // Singular values come sorted in descending order, so the sign flip lands on the smallest one.
    let mut s = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s[2] = -1.0;
    }
    let rotation = u * Matrix3::from_diagonal(&s) * v_t;
    let var_src = cov_src.trace();
    let scale = svd.singular_values.dot(&s) / var_src;
    let translation = mu_dst - scale * (rotation * mu_src);
    Ok(Similarity { scale, rotation, translation })
}

/// Refuses a point set whose covariance has rank < 2 (all points on one line, or all equal).
fn check_spread(set: &'static str, cov: &Matrix3<f64>) -> Result<(), AlignError> {
    let ev = cov.symmetric_eigenvalues();
    let mut ev: Vec<f64> = ev.iter().map(|v| v.max(0.0)).collect();
    ev.sort_by(|a, b| b.total_cmp(a));
    if ev[0] <= 0.0 {
        return Err(AlignError::Degenerate { set, shape: "all at one point", ratio: 0.0 });
    }
    let ratio = ev[1] / ev[0];
    if ratio < DEGENERATE_RATIO {
        return Err(AlignError::Degenerate { set, shape: "collinear", ratio });
    }
    Ok(())
}

/// Mean and maximum of a list of non-negative errors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    pub mean: f64,
    pub max: f64,
}

impl ErrorStats {
    fn of(values: impl Iterator<Item = f64>) -> Self {
        let (mut sum, mut max, mut n) = (0.0, 0.0f64, 0usize);
        for v in values {
            sum += v;
            max = max.max(v);
            n += 1;
        }
        ErrorStats { mean: if n == 0 { 0.0 } else { sum / n as f64 }, max }
    }
}

/// Errors of estimated cameras against true ones, after aligning the estimated centres onto the true centres.
#[derive(Debug, Clone)]
pub struct PoseErrors {
    /// Estimated frame → true frame.
    pub similarity: Similarity,
    /// Largest distance of a true centre from the true centres' centroid; centre errors are fractions of it.
    pub scene_radius: f64,
    /// Per camera: |aligned estimated centre − true centre| / `scene_radius`.
    pub centre: Vec<f64>,
    /// Per camera: angle of R_true⁻¹ · R · R_est in degrees (c2w rotations, R the alignment's rotation).
    pub rotation_deg: Vec<f64>,
    /// Per camera, signed: fx_est / fx_true − 1. Both must be on one pixel grid: an undistorted model is cropped,
    /// not scaled, so normalising by the widths would be wrong there; rescale the estimate first if its images were.
    pub focal: Vec<f64>,
    pub centre_stats: ErrorStats,
    pub rotation_stats: ErrorStats,
    /// Of |focal|.
    pub focal_stats: ErrorStats,
}

/// Aligns `estimated[i]` onto `truth[i]` (same order, same views) by their centres and measures centre,
/// rotation and focal errors per camera.
pub fn camera_errors(estimated: &[Camera], truth: &[Camera]) -> Result<PoseErrors, AlignError> {
    if estimated.len() != truth.len() {
        return Err(AlignError::LengthMismatch { src: estimated.len(), dst: truth.len() });
    }
    let src: Vec<_> = estimated.iter().map(Camera::center).collect();
    let dst: Vec<_> = truth.iter().map(Camera::center).collect();
    let similarity = umeyama(&src, &dst)?;
    let centroid = dst.iter().sum::<Vector3<f64>>() / dst.len() as f64;
    let scene_radius = dst.iter().map(|c| (c - centroid).norm()).fold(0.0, f64::max);
    let centre: Vec<f64> = src.iter().zip(&dst).map(|(e, t)| (similarity.apply(e) - t).norm() / scene_radius).collect();
    let rotation_deg: Vec<f64> =
        estimated.iter().zip(truth).map(|(e, t)| rotation_angle(&(t.rotation().transpose() * similarity.rotation * e.rotation())).to_degrees()).collect();
    let focal: Vec<f64> = estimated.iter().zip(truth).map(|(e, t)| e.fx / t.fx - 1.0).collect();
    Ok(PoseErrors {
        centre_stats: ErrorStats::of(centre.iter().copied()),
        rotation_stats: ErrorStats::of(rotation_deg.iter().copied()),
        focal_stats: ErrorStats::of(focal.iter().map(|f| f.abs())),
        similarity,
        scene_radius,
        centre,
        rotation_deg,
        focal,
    })
}

/// Rotation angle in radians; atan2 of the skew and symmetric parts stays accurate near 0 and π, where acos of
/// the trace loses digits.
pub fn rotation_angle(r: &Matrix3<f64>) -> f64 {
    let skew = Vector3::new(r[(2, 1)] - r[(1, 2)], r[(0, 2)] - r[(2, 0)], r[(1, 0)] - r[(0, 1)]);
    (0.5 * skew.norm()).atan2(0.5 * (r.trace() - 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Quaternion, Rotation3, UnitQuaternion};

    /// SplitMix64: a tiny seeded generator, so the tests need no dependency.
    struct Rng(u64);

    impl Rng {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        fn uniform(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        fn normal(&mut self) -> f64 {
            let u = self.uniform().max(1e-300);
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * self.uniform()).cos()
        }
        fn vector(&mut self) -> Vector3<f64> {
            Vector3::new(self.normal(), self.normal(), self.normal())
        }
        fn rotation(&mut self) -> Matrix3<f64> {
            let q = Quaternion::new(self.normal(), self.normal(), self.normal(), self.normal());
            UnitQuaternion::from_quaternion(q).to_rotation_matrix().into_inner()
        }
        fn similarity(&mut self, scale: f64) -> Similarity {
            Similarity { scale, rotation: self.rotation(), translation: self.vector() * 5.0 * scale }
        }
    }

    fn residual(sim: &Similarity, src: &[Vector3<f64>], dst: &[Vector3<f64>]) -> f64 {
        src.iter().zip(dst).map(|(x, y)| (y - sim.apply(x)).norm_squared()).sum()
    }

    const SCALES: [f64; 6] = [0.01, 0.2, 1.0, 3.7, 25.0, 100.0];

    #[test]
    fn exact_transforms_are_recovered() {
        for seed in 1..=5u64 {
            for &scale in &SCALES {
                let mut rng = Rng(seed * 1000 + (scale * 100.0) as u64);
                let truth = rng.similarity(scale);
                let n = 3 + (rng.next_u64() % 40) as usize;
                let src: Vec<_> = (0..n).map(|_| rng.vector() * 2.0 + Vector3::new(1.0, -3.0, 0.5)).collect();
                let dst: Vec<_> = src.iter().map(|p| truth.apply(p)).collect();
                let got = umeyama(&src, &dst).unwrap();
                let ctx = format!("seed {seed}, scale {scale}, n {n}");
                assert!((got.scale / scale - 1.0).abs() < 1e-9, "{ctx}: scale {} vs {scale}", got.scale);
                assert!((got.rotation - truth.rotation).norm() < 1e-9, "{ctx}: rotation off");
                assert!((got.rotation.determinant() - 1.0).abs() < 1e-12, "{ctx}");
                let t_err = (got.translation - truth.translation).norm() / scale;
                assert!(t_err < 1e-9, "{ctx}: translation off by {t_err:e} (relative to the scale)");
            }
        }
    }

    /// With isotropic noise of σ per coordinate the least-squares residual has the closed-form expectation
    /// σ²(3n − 7) (7 parameters fitted), the fit is never worse than the true transform, and its rotation error
    /// is of order σ / (s · spread · √n).
    #[test]
    fn noisy_fit_matches_least_squares_expectations() {
        for seed in 1..=4u64 {
            for &scale in &SCALES {
                let mut rng = Rng(seed.wrapping_mul(7919) + (scale * 1000.0) as u64);
                let truth = rng.similarity(scale);
                let n = 2000;
                let sigma = 0.01 * scale;
                let src: Vec<_> = (0..n).map(|_| rng.vector()).collect();
                let dst: Vec<_> = src.iter().map(|p| truth.apply(p) + rng.vector() * sigma).collect();
                let got = umeyama(&src, &dst).unwrap();
                let ctx = format!("seed {seed}, scale {scale}");
                let (fit, true_fit) = (residual(&got, &src, &dst), residual(&truth, &src, &dst));
                assert!(fit <= true_fit * (1.0 + 1e-12), "{ctx}: fit {fit:e} worse than the truth {true_fit:e}");
                let expect = sigma * sigma * (3 * n - 7) as f64;
                // The residual is σ² χ²(3n − 7): its relative spread is √(2 / (3n − 7)) ≈ 1.8 %.
                assert!((fit / expect - 1.0).abs() < 0.1, "{ctx}: residual {fit:e} vs expected {expect:e}");
                let angle = rotation_angle(&(truth.rotation.transpose() * got.rotation));
                let typical = sigma / (scale * (n as f64).sqrt());
                assert!(angle < 6.0 * typical, "{ctx}: rotation error {angle:e} rad, typical {typical:e}");
                assert!((got.scale / scale - 1.0).abs() < 6.0 * typical, "{ctx}: scale {}", got.scale);
            }
        }
    }

    #[test]
    fn fit_is_a_local_minimum() {
        let mut rng = Rng(42);
        let truth = rng.similarity(2.0);
        let src: Vec<_> = (0..50).map(|_| rng.vector()).collect();
        let dst: Vec<_> = src.iter().map(|p| truth.apply(p) + rng.vector() * 0.3).collect();
        let got = umeyama(&src, &dst).unwrap();
        let best = residual(&got, &src, &dst);
        for _ in 0..200 {
            let d = rng.vector() * 1e-4;
            let nudged = Similarity {
                scale: got.scale * (1.0 + 1e-4 * rng.normal()),
                rotation: Rotation3::new(d).into_inner() * got.rotation,
                translation: got.translation + rng.vector() * 1e-4,
            };
            assert!(residual(&nudged, &src, &dst) >= best);
        }
    }

    /// Mirrored targets: the best orthogonal map is a reflection; the fit must stay a rotation.
    #[test]
    fn reflections_give_proper_rotations() {
        let mirror = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, 1.0));
        for seed in 1..=4u64 {
            let mut rng = Rng(seed + 99);
            let (r, scale, t) = (rng.rotation(), 0.5 + rng.uniform() * 4.0, rng.vector());
            // Points in the plane z = 0: mirroring y equals a half turn about x, so an exact proper fit exists.
            let flat: Vec<_> = (0..12).map(|_| Vector3::new(rng.normal(), rng.normal(), 0.0)).collect();
            let dst: Vec<_> = flat.iter().map(|p| scale * (r * mirror * p) + t).collect();
            let got = umeyama(&flat, &dst).unwrap();
            assert!((got.rotation.determinant() - 1.0).abs() < 1e-12, "seed {seed}: det {}", got.rotation.determinant());
            assert!(residual(&got, &flat, &dst) < 1e-18 * dst.len() as f64, "seed {seed}: not exact");
            assert!((got.scale / scale - 1.0).abs() < 1e-9);
            // A full 3D set mirrored: no exact fit, but a proper rotation that is locally optimal.
            let solid: Vec<_> = (0..20).map(|_| rng.vector()).collect();
            let dst: Vec<_> = solid.iter().map(|p| scale * (r * mirror * p) + t).collect();
            let got = umeyama(&solid, &dst).unwrap();
            assert!((got.rotation.determinant() - 1.0).abs() < 1e-12);
            let best = residual(&got, &solid, &dst);
            for _ in 0..100 {
                let nudged = Similarity { rotation: Rotation3::new(rng.vector() * 1e-3).into_inner() * got.rotation, ..got.clone() };
                assert!(residual(&nudged, &solid, &dst) >= best, "seed {seed}");
            }
        }
    }

    #[test]
    fn degenerate_input_is_refused() {
        let p = |x: f64, y: f64, z: f64| Vector3::new(x, y, z);
        let three = [p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(0.0, 1.0, 0.0)];
        assert_eq!(umeyama(&three[..2], &three[..2]), Err(AlignError::TooFewPoints { n: 2 }));
        assert_eq!(umeyama(&three, &three[..2]), Err(AlignError::LengthMismatch { src: 3, dst: 2 }));
        let line: Vec<_> = (0..6).map(|i| p(1.0, 2.0, 3.0) + p(0.3, -0.2, 0.9) * i as f64).collect();
        let e = umeyama(&line, &line).unwrap_err();
        assert!(matches!(e, AlignError::Degenerate { set: "source", shape: "collinear", .. }), "{e:?}");
        assert!(e.to_string().contains("collinear"));
        let same = vec![p(1.0, 1.0, 1.0); 5];
        let good: Vec<_> = (0..5).map(|i| p(i as f64, (i * i) as f64, 1.0)).collect();
        let e = umeyama(&good, &same).unwrap_err();
        assert!(matches!(e, AlignError::Degenerate { set: "target", shape: "all at one point", .. }), "{e:?}");
        let mut bad = good.clone();
        bad[3].y = f64::NAN;
        assert_eq!(umeyama(&good, &bad), Err(AlignError::NotFinite { set: "target", index: 3 }));
        // Nearly but not exactly collinear sets are accepted.
        let mut bent = line.clone();
        bent[2].x += 1e-3;
        umeyama(&bent, &bent).unwrap();
    }

    fn orbit(n: usize, radius: f64) -> Vec<Camera> {
        (0..n)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                let eye = Vector3::new(radius * a.sin(), -0.3 * radius, -radius * a.cos());
                let z = (-eye).normalize();
                let x = Vector3::new(0.0, -1.0, 0.0).cross(&z).normalize();
                let y = z.cross(&x);
                let mut c2w = [[0.0; 4]; 4];
                for r in 0..3 {
                    c2w[r] = [x[r], y[r], z[r], eye[r]];
                }
                c2w[3][3] = 1.0;
                Camera { fx: 280.0, fy: 280.0, cx: 160.0, cy: 90.0, width: 320, height: 180, c2w }
            })
            .collect()
    }

    #[test]
    fn camera_errors_of_a_moved_copy_are_zero_and_perturbations_show() {
        let truth = orbit(12, 4.0);
        let mut rng = Rng(7);
        let to_est = rng.similarity(0.37);
        // The estimate lives in another frame, on the same pixel grid.
        let mut est: Vec<Camera> = truth.iter().map(|c| to_est.apply_camera(c)).collect();
        let e = camera_errors(&est, &truth).unwrap();
        assert!(e.centre_stats.max < 1e-12 && e.rotation_stats.max < 1e-9 && e.focal_stats.max < 1e-12, "{e:?}");
        assert!((e.scene_radius - 4.0).abs() < 1e-12, "{}", e.scene_radius);
        assert!((e.similarity.scale - 1.0 / 0.37).abs() < 1e-9);

        // Turn camera 3 by 2° about its own axis and make camera 5's focal 1 % long: the centres, which drive the
        // alignment, are untouched, so exactly those show up.
        let turn = Rotation3::new(Vector3::new(0.0, 0.0, 2f64.to_radians())).into_inner();
        est[3] = est[3].clone().with_c2w(&{
            let mut m = est[3].c2w_matrix();
            let r = est[3].rotation() * turn;
            m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
            m
        });
        est[5].fx *= 1.01;
        let e = camera_errors(&est, &truth).unwrap();
        assert!((e.rotation_deg[3] - 2.0).abs() < 1e-9, "{:?}", e.rotation_deg);
        assert!((e.rotation_stats.max - 2.0).abs() < 1e-9 && (e.rotation_stats.mean - 2.0 / 12.0).abs() < 1e-9);
        assert!((e.focal[5] - 0.01).abs() < 1e-12 && (e.focal_stats.max - 0.01).abs() < 1e-12);
        assert!(e.centre_stats.max < 1e-12);

        // Move one estimated centre by 10 % of the radius (in the true frame's units): the fit spreads it, never
        // leaving more than the unmoved alignment would (Σ err² ≤ 0.1²), and that camera keeps most of it.
        let shift = to_est.scale * 0.1 * e.scene_radius;
        est[0].c2w[0][3] += shift;
        let e = camera_errors(&est, &truth).unwrap();
        let sum_sq: f64 = e.centre.iter().map(|c| c * c).sum();
        assert!(sum_sq <= 0.01 + 1e-12 && e.centre[0] > 0.07, "{:?}", e.centre);
        assert_eq!(e.centre_stats.max, e.centre[0]);
    }

    #[test]
    fn camera_errors_refuse_too_few_or_collinear_cameras() {
        let truth = orbit(6, 2.0);
        assert_eq!(camera_errors(&truth[..2], &truth[..2]).unwrap_err(), AlignError::TooFewPoints { n: 2 });
        assert_eq!(camera_errors(&truth[..4], &truth).unwrap_err(), AlignError::LengthMismatch { src: 4, dst: 6 });
        let mut line = truth.clone();
        for (i, c) in line.iter_mut().enumerate() {
            c.c2w[0][3] = i as f64;
            c.c2w[1][3] = 0.0;
            c.c2w[2][3] = 0.0;
        }
        assert!(matches!(camera_errors(&line, &truth), Err(AlignError::Degenerate { .. })));
    }

    #[test]
    fn rotation_angle_is_accurate_small_and_large() {
        for deg in [1e-7, 0.01, 1.0, 45.0, 179.0, 180.0] {
            let r = Rotation3::new(Vector3::new(1.0, 2.0, -0.5).normalize() * f64::to_radians(deg)).into_inner();
            let got = rotation_angle(&r).to_degrees();
            assert!((got - deg).abs() < 1e-9 * deg.max(1.0), "{deg}° read as {got}°");
        }
    }
}
