//! Pose conversions into the project convention (camera-to-world, OpenCV axes).

use nalgebra::{Matrix3, Matrix4, Quaternion, UnitQuaternion, Vector3};

/// Inverse of a rigid transform [R t; 0 1] as [Rᵀ −Rᵀt; 0 1] (exact, no general inversion).
pub fn invert_rigid(m: &Matrix4<f64>) -> Matrix4<f64> {
    let r = m.fixed_view::<3, 3>(0, 0).transpose();
    let t = -(r * m.fixed_view::<3, 1>(0, 3));
    let mut out = Matrix4::identity();
    out.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    out.fixed_view_mut::<3, 1>(0, 3).copy_from(&t);
    out
}

pub fn w2c_to_c2w(w2c: &Matrix4<f64>) -> Matrix4<f64> {
    invert_rigid(w2c)
}

pub fn c2w_to_w2c(c2w: &Matrix4<f64>) -> Matrix4<f64> {
    invert_rigid(c2w)
}

/// OpenGL / Blender / nerfstudio camera axes (+x right, +y up, +z backward) → OpenCV: flip the y and z axes.
pub fn opengl_to_opencv(c2w_gl: &Matrix4<f64>) -> Matrix4<f64> {
    c2w_gl * Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0))
}

/// Inverse of [`opengl_to_opencv`] (the same flip).
pub fn opencv_to_opengl(c2w_cv: &Matrix4<f64>) -> Matrix4<f64> {
    opengl_to_opencv(c2w_cv)
}

/// Rotation matrix of a quaternion given as (w, x, y, z); normalised first.
pub fn quat_wxyz_to_rotation(q: [f64; 4]) -> Matrix3<f64> {
    let uq = UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
    *uq.to_rotation_matrix().matrix()
}

/// COLMAP image pose (qvec wxyz and tvec of the world-to-camera transform, OpenCV axes) → c2w.
pub fn colmap_to_c2w(qvec: [f64; 4], tvec: [f64; 3]) -> Matrix4<f64> {
    let r = quat_wxyz_to_rotation(qvec);
    let mut w2c = Matrix4::identity();
    w2c.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    w2c.fixed_view_mut::<3, 1>(0, 3).copy_from(&Vector3::new(tvec[0], tvec[1], tvec[2]));
    invert_rigid(&w2c)
}

/// Row-major 3×4 world-to-camera (the .torch chunk layout) → c2w.
pub fn w2c_3x4_to_c2w(w: &[f64; 12]) -> Matrix4<f64> {
    let mut w2c = Matrix4::identity();
    for r in 0..3 {
        for c in 0..4 {
            w2c[(r, c)] = w[r * 4 + c];
        }
    }
    invert_rigid(&w2c)
}

pub fn to_array(m: &Matrix4<f64>) -> [[f64; 4]; 4] {
    let mut a = [[0.0; 4]; 4];
    for (r, row) in a.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = m[(r, c)];
        }
    }
    a
}

/// Nearest rotation matrix (polar decomposition via SVD), forced right-handed.
pub fn orthonormalize(m: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u.unwrap_or_else(Matrix3::identity), svd.v_t.unwrap_or_else(Matrix3::identity));
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        let mut u2 = u;
        u2.column_mut(2).scale_mut(-1.0);
        r = u2 * vt;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rot_y(a: f64) -> Matrix3<f64> {
        Matrix3::new(a.cos(), 0.0, a.sin(), 0.0, 1.0, 0.0, -a.sin(), 0.0, a.cos())
    }

    #[test]
    fn invert_rigid_is_inverse() {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&rot_y(0.7));
        m[(0, 3)] = 1.0;
        m[(1, 3)] = -2.0;
        m[(2, 3)] = 0.5;
        let p = invert_rigid(&m) * m;
        assert!((p - Matrix4::identity()).norm() < 1e-12);
        assert!((c2w_to_w2c(&w2c_to_c2w(&m)) - m).norm() < 1e-12);
    }

    #[test]
    fn opengl_flip_closed_form() {
        // A GL camera at the origin looking down −z (identity pose) is an OpenCV camera looking down −z world
        // with y pointing down-world: the closed form is diag(1,−1,−1,1).
        let cv = opengl_to_opencv(&Matrix4::identity());
        assert_eq!(cv, Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0)));
        // Its forward (+z OpenCV) is world −z, as the GL camera's view direction.
        assert_eq!(cv.fixed_view::<3, 1>(0, 2).into_owned(), Vector3::new(0.0, 0.0, -1.0));
        let m = opengl_to_opencv(&cv);
        assert_eq!(m, Matrix4::identity());
        assert_eq!(opencv_to_opengl(&cv), Matrix4::identity());
    }

    #[test]
    fn quaternion_closed_form() {
        // 90° about z: (w,x,y,z) = (cos45°, 0, 0, sin45°) maps x → y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let r = quat_wxyz_to_rotation([h, 0.0, 0.0, h]);
        let expect = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        assert!((r - expect).norm() < 1e-12);
        // Unnormalised input is normalised.
        assert!((quat_wxyz_to_rotation([2.0, 0.0, 0.0, 2.0]) - expect).norm() < 1e-12);
    }

    #[test]
    fn colmap_pose_closed_form() {
        // Identity rotation, tvec t: camera centre is −t.
        let c2w = colmap_to_c2w([1.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0]);
        assert_eq!(c2w.fixed_view::<3, 1>(0, 3).into_owned(), Vector3::new(-1.0, -2.0, -3.0));
        // 90° about z: centre = −Rᵀ t.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let c2w = colmap_to_c2w([h, 0.0, 0.0, h], [1.0, 0.0, 0.0]);
        let centre = c2w.fixed_view::<3, 1>(0, 3).into_owned();
        assert!((centre - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn w2c_3x4_layout() {
        let w = [1.0, 0.0, 0.0, 4.0, 0.0, 1.0, 0.0, 5.0, 0.0, 0.0, 1.0, 6.0];
        let c2w = w2c_3x4_to_c2w(&w);
        assert_eq!(c2w.fixed_view::<3, 1>(0, 3).into_owned(), Vector3::new(-4.0, -5.0, -6.0));
    }

    #[test]
    fn orthonormalize_recovers_rotation() {
        let r = rot_y(0.3);
        let noisy = r + Matrix3::new(1e-3, -2e-3, 0.0, 0.0, 1e-3, 1e-3, 2e-3, 0.0, -1e-3);
        let o = orthonormalize(&noisy);
        assert!((o.transpose() * o - Matrix3::identity()).norm() < 1e-12);
        assert!((o.determinant() - 1.0).abs() < 1e-12);
        assert!((o - r).norm() < 5e-3);
        // A reflection is turned into a proper rotation.
        let refl = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0));
        assert!((orthonormalize(&refl).determinant() - 1.0).abs() < 1e-12);
    }
}
