//! Smooth camera paths for rendering: interpolation through keyframes, a 360° orbit, and pose stabilisation.

use nalgebra::{Matrix3, Matrix4, Rotation3, UnitQuaternion, Vector3};

use crate::convert::orthonormalize;
use crate::Camera;

fn pose(r: &Matrix3<f64>, t: &Vector3<f64>) -> Matrix4<f64> {
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(r);
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(t);
    m
}

fn quat_of(c: &Camera) -> UnitQuaternion<f64> {
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(orthonormalize(&c.rotation())))
}

/// Catmull-Rom point on segment p1→p2 at s ∈ [0,1] (uniform parameterisation).
fn catmull_rom(p0: &Vector3<f64>, p1: &Vector3<f64>, p2: &Vector3<f64>, p3: &Vector3<f64>, s: f64) -> Vector3<f64> {
    let s2 = s * s;
    let s3 = s2 * s;
    (p1 * 2.0 + (p2 - p0) * s + (p0 * 2.0 - p1 * 5.0 + p2 * 4.0 - p3) * s2 + (p1 * 3.0 - p0 - p2 * 3.0 + p3) * s3) * 0.5
}

/// `frames` cameras along a smooth path through `keys` (spline positions, slerped rotations).
/// With `closed`, the path returns to the first key (a loop); otherwise it ends exactly on the last key.
/// Intrinsics are taken from the first key.
pub fn interpolate(keys: &[Camera], frames: usize, closed: bool) -> Vec<Camera> {
    if keys.is_empty() || frames == 0 {
        return vec![];
    }
    if keys.len() == 1 {
        return vec![keys[0].clone(); frames];
    }
    let n = keys.len();
    let segments = if closed { n } else { n - 1 };
    let centres: Vec<_> = keys.iter().map(|c| c.center()).collect();
    let quats: Vec<_> = keys.iter().map(quat_of).collect();
    let idx = |i: isize| -> usize {
        if closed {
            i.rem_euclid(n as isize) as usize
        } else {
            i.clamp(0, n as isize - 1) as usize
        }
    };
    (0..frames)
        .map(|f| {
            let t = if closed {
                f as f64 / frames as f64 * segments as f64
            } else if frames == 1 {
                0.0
            } else {
                f as f64 / (frames - 1) as f64 * segments as f64
            };
            let seg = (t.floor() as usize).min(segments - 1);
            let s = t - seg as f64;
            let i = seg as isize;
            let p = catmull_rom(&centres[idx(i - 1)], &centres[idx(i)], &centres[idx(i + 1)], &centres[idx(i + 2)], s);
            let (qa, mut qb) = (quats[idx(i)], quats[idx(i + 1)]);
            if qa.coords.dot(&qb.coords) < 0.0 {
                qb = UnitQuaternion::new_unchecked(-qb.into_inner());
            }
            let q = qa.slerp(&qb, s);
            keys[0].clone().with_c2w(&pose(q.to_rotation_matrix().matrix(), &p))
        })
        .collect()
}

/// Least-squares point closest to all optical axes (where the cameras look).
pub fn look_at_point(cameras: &[Camera]) -> Vector3<f64> {
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for c in cameras {
        let d = c.forward().normalize();
        let p = Matrix3::identity() - d * d.transpose();
        a += p;
        b += p * c.center();
    }
    a.try_inverse().map(|ai| ai * b).unwrap_or_else(|| cameras.iter().map(|c| c.center()).sum::<Vector3<f64>>() / cameras.len().max(1) as f64)
}

/// A camera at `eye` looking at `target`, with `up` the world up direction (OpenCV: image y points down-world).
pub fn look_at(template: &Camera, eye: &Vector3<f64>, target: &Vector3<f64>, up: &Vector3<f64>) -> Camera {
    let z = (target - eye).normalize();
    let mut x = (-up).cross(&z);
    if x.norm() < 1e-9 {
        x = z.cross(&Vector3::new(1.0, 0.0, 0.0));
    }
    let x = x.normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_columns(&[x, y, z]);
    template.clone().with_c2w(&pose(&r, eye))
}

/// A full 360° orbit of `frames` cameras around the point the input cameras look at, in the plane fitted to
/// their centres (up = mean of the cameras' −y axes), at their mean radius and height, starting at the first
/// camera's azimuth. Intrinsics from the first camera.
pub fn orbit(cameras: &[Camera], frames: usize) -> Vec<Camera> {
    if cameras.is_empty() {
        return vec![];
    }
    let target = look_at_point(cameras);
    let mut up: Vector3<f64> = cameras.iter().map(|c| -Vector3::new(c.c2w[0][1], c.c2w[1][1], c.c2w[2][1])).sum();
    if up.norm() < 1e-9 {
        up = Vector3::new(0.0, -1.0, 0.0);
    }
    let up = up.normalize();
    let rel: Vec<_> = cameras.iter().map(|c| c.center() - target).collect();
    let height = rel.iter().map(|r| r.dot(&up)).sum::<f64>() / rel.len() as f64;
    let radius = rel.iter().map(|r| (r - up * r.dot(&up)).norm()).sum::<f64>() / rel.len() as f64;
    let mut e1 = rel[0] - up * rel[0].dot(&up);
    if e1.norm() < 1e-9 {
        e1 = up.cross(&Vector3::new(1.0, 0.0, 0.0));
    }
    let e1 = e1.normalize();
    let e2 = up.cross(&e1);
    (0..frames)
        .map(|f| {
            let a = std::f64::consts::TAU * f as f64 / frames as f64;
            let eye = target + up * height + (e1 * a.cos() + e2 * a.sin()) * radius;
            look_at(&cameras[0], &eye, &target, &up)
        })
        .collect()
}

/// Smooth a pose sequence with a Gaussian filter of std `sigma` frames over positions and rotation matrices
/// (edges replicated), then re-orthonormalise each rotation (the filtered average is not a rotation).
pub fn stabilize(cameras: &[Camera], sigma: f64) -> Vec<Camera> {
    if sigma <= 0.0 || cameras.len() < 2 {
        return cameras.to_vec();
    }
    let radius = (3.0 * sigma).ceil() as isize;
    let weights: Vec<f64> = (-radius..=radius).map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let wsum: f64 = weights.iter().sum();
    let n = cameras.len() as isize;
    (0..n)
        .map(|i| {
            let mut r = Matrix3::zeros();
            let mut t = Vector3::zeros();
            for (k, w) in (-radius..=radius).zip(&weights) {
                let c = &cameras[(i + k).clamp(0, n - 1) as usize];
                r += c.rotation() * (*w / wsum);
                t += c.center() * (*w / wsum);
            }
            cameras[i as usize].clone().with_c2w(&pose(&orthonormalize(&r), &t))
        })
        .collect()
}

/// Weights of OpenCV's `getGaussianKernel(ksize, sigma <= 0)`: σ = 0.3·((ksize − 1)/2 − 1) + 0.8, normalised.
pub fn opencv_gaussian_kernel(ksize: usize) -> Vec<f64> {
    let sigma = 0.3 * ((ksize as f64 - 1.0) * 0.5 - 1.0) + 0.8;
    let c = (ksize as f64 - 1.0) / 2.0;
    let w: Vec<f64> = (0..ksize).map(|i| (-((i as f64 - c).powi(2)) / (2.0 * sigma * sigma)).exp()).collect();
    let s: f64 = w.iter().sum();
    w.into_iter().map(|x| x / s).collect()
}

/// The official `render_stabilization_path` (`stable_k_size` 15): each of rotation column 0, rotation column 1
/// and the position is filtered along the sequence with OpenCV's Gaussian kernel and reflect-101 borders
/// (`cv2.filter2D`); columns 0 and 1 are renormalised and column 2 is their cross product (not re-orthogonalised,
/// as the official code does). Frame count unchanged.
pub fn stabilize_official(cameras: &[Camera], ksize: usize) -> Vec<Camera> {
    let n = cameras.len() as isize;
    if n < 2 || ksize < 2 {
        return cameras.to_vec();
    }
    let k = opencv_gaussian_kernel(ksize);
    let r = (ksize / 2) as isize;
    // Reflect-101: …, 2, 1 | 0, 1, …, n−1 | n−2, n−3, … (repeated for kernels longer than the sequence).
    let reflect = |mut i: isize| -> usize {
        loop {
            if i < 0 {
                i = -i;
            } else if i >= n {
                i = 2 * (n - 1) - i;
            } else {
                return i as usize;
            }
        }
    };
    let col = |c: &Camera, j: usize| Vector3::new(c.c2w[0][j], c.c2w[1][j], c.c2w[2][j]);
    (0..n)
        .map(|i| {
            let (mut a, mut b, mut t) = (Vector3::zeros(), Vector3::zeros(), Vector3::zeros());
            for (o, w) in (-r..=r).zip(&k) {
                let c = &cameras[reflect(i + o)];
                a += col(c, 0) * *w;
                b += col(c, 1) * *w;
                t += col(c, 3) * *w;
            }
            let (a, b) = (a.normalize(), b.normalize());
            let z = a.cross(&b);
            let m = Matrix3::from_columns(&[a, b, z]);
            cameras[i as usize].clone().with_c2w(&pose(&m, &t))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ring(n: usize, radius: f64) -> Vec<Camera> {
        let base = crate::camera::test_camera();
        let up = Vector3::new(0.0, -1.0, 0.0);
        (0..n)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                let eye = Vector3::new(radius * a.cos(), -0.5, radius * a.sin());
                look_at(&base, &eye, &Vector3::zeros(), &up)
            })
            .collect()
    }

    #[test]
    fn look_at_points_at_target_and_is_rotation() {
        let c = &ring(4, 2.0)[1];
        c.validate("ring").unwrap();
        let (u, v, z) = c.project(&Vector3::zeros());
        assert!((u - c.cx).abs() < 1e-9 && (v - c.cy).abs() < 1e-9 && z > 0.0);
        // World up (−y) projects upward in the image (smaller v).
        let (_, v_up, _) = c.project(&Vector3::new(0.0, -0.3, 0.0));
        assert!(v_up < c.cy);
    }

    #[test]
    fn interpolation_passes_through_keys() {
        let keys = ring(6, 3.0);
        let path = interpolate(&keys, 12, true);
        assert_eq!(path.len(), 12);
        for (f, key) in [(0, 0), (2, 1), (4, 2), (10, 5)] {
            assert!((path[f].center() - keys[key].center()).norm() < 1e-9);
            assert!((path[f].rotation() - keys[key].rotation()).norm() < 1e-9);
        }
        let open = interpolate(&keys, 11, false);
        assert!((open[10].center() - keys[5].center()).norm() < 1e-9);
        for c in &path {
            c.validate("path").unwrap();
        }
    }

    #[test]
    fn orbit_closed_form_on_a_ring() {
        let keys = ring(5, 2.5);
        assert!(look_at_point(&keys).norm() < 1e-9);
        let o = orbit(&keys, 8);
        assert_eq!(o.len(), 8);
        assert!((o[0].center() - keys[0].center()).norm() < 1e-9);
        for c in &o {
            let rel = c.center();
            assert!(((rel.x * rel.x + rel.z * rel.z).sqrt() - 2.5).abs() < 1e-9);
            assert!((rel.y + 0.5).abs() < 1e-9);
            let (u, v, _) = c.project(&Vector3::zeros());
            assert!((u - c.cx).abs() < 1e-9 && (v - c.cy).abs() < 1e-9);
        }
        // Consecutive frames are 45° apart on the circle.
        let chord = (o[1].center() - o[0].center()).norm();
        assert!((chord - 2.0 * 2.5 * (std::f64::consts::PI / 8.0).sin()).abs() < 1e-9);
    }

    #[test]
    fn stabilize_smooths_and_stays_orthonormal() {
        let keys = ring(40, 2.0);
        // Constant sequence is a fixed point.
        let same = vec![keys[0].clone(); 7];
        for c in stabilize(&same, 2.0) {
            assert!((c.c2w_matrix() - keys[0].c2w_matrix()).norm() < 1e-9);
        }
        // Jittered positions: smoothing reduces the jitter and keeps rotations valid.
        let jitter: Vec<_> = keys
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let mut c = c.clone();
                c.c2w[1][3] += if i % 2 == 0 { 0.05 } else { -0.05 };
                c
            })
            .collect();
        let s = stabilize(&jitter, 2.0);
        for c in &s[3..37] {
            assert!((c.center().y + 0.5).abs() < 0.01);
            let r = c.rotation();
            assert!((r.transpose() * r - Matrix3::identity()).norm() < 1e-9);
            assert!((r.determinant() - 1.0).abs() < 1e-9);
        }
    }

    #[test]
    fn opencv_kernel_matches_its_closed_form() {
        // cv2.getGaussianKernel(15, -1): σ = 0.3·(7 − 1) + 0.8 = 2.6; centre weight 1/Σ exp(−i²/(2·2.6²)).
        let k = opencv_gaussian_kernel(15);
        assert_eq!(k.len(), 15);
        assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        let z: f64 = (-7..=7).map(|i| (-(i * i) as f64 / (2.0 * 2.6 * 2.6)).exp()).sum();
        assert!((k[7] - 1.0 / z).abs() < 1e-12);
        assert!((k[0] - (-49.0f64 / (2.0 * 2.6 * 2.6)).exp() / z).abs() < 1e-12);
    }

    #[test]
    fn official_stabilisation_closed_forms() {
        // Constant poses are a fixed point; a straight-line path with constant rotation stays on its line
        // (interior frames exactly, by symmetry of the kernel; edges reflect).
        let base = crate::camera::test_camera();
        let path: Vec<Camera> = (0..30)
            .map(|i| {
                let mut c = base.clone();
                c.c2w[0][3] = 0.1 * i as f64;
                c
            })
            .collect();
        let s = stabilize_official(&path, 15);
        for i in 7..23 {
            assert!((s[i].c2w[0][3] - 0.1 * i as f64).abs() < 1e-12, "frame {i}");
            for r in 0..3 {
                for c in 0..3 {
                    assert!((s[i].c2w[r][c] - base.c2w[r][c]).abs() < 1e-12);
                }
            }
        }
        // Reflect-101 at the start: frame 0 averages frames |o| → 0.1·Σ w_o |o| (not clamped to frame 0).
        let k = opencv_gaussian_kernel(15);
        let want: f64 = (-7i32..=7).zip(&k).map(|(o, w)| 0.1 * o.abs() as f64 * w).sum();
        assert!((s[0].c2w[0][3] - want).abs() < 1e-12);
        // Rotations: columns 0/1 unit length, column 2 their cross product.
        let ring = ring(20, 2.0);
        for c in stabilize_official(&ring, 15) {
            let r = c.rotation();
            let (a, b, z) = (r.column(0).into_owned(), r.column(1).into_owned(), r.column(2).into_owned());
            assert!((a.norm() - 1.0).abs() < 1e-12 && (b.norm() - 1.0).abs() < 1e-12);
            assert!((z - a.cross(&b)).norm() < 1e-12);
        }
    }
}
