//! `pose_encoding_to_extri_intri` for `absT_quaR_FoV`: camera-from-world `[R | t]` (OpenCV axes) and pinhole
//! intrinsics with the principal point at the image centre, in the pixels of the `H × W` the model saw.

use super::rotation::quat_to_mat;

/// One camera as VGGT predicts it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VggtCamera {
    /// World → camera, OpenCV axes (x right, y down, z forward), row-major 3 × 4.
    pub extrinsic: [[f64; 4]; 3],
    /// `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` in the model's pixels.
    pub intrinsic: [[f64; 3]; 3],
}

/// The 9 numbers `(tx, ty, tz, qx, qy, qz, qw, fov_h, fov_w)` → the camera, for images of `h × w` pixels:
/// `fy = (h/2) / tan(fov_h/2)`, `fx = (w/2) / tan(fov_w/2)`, `(cx, cy) = (w/2, h/2)`.
pub fn pose_encoding_to_extri_intri(enc: &[f32; 9], h: usize, w: usize) -> VggtCamera {
    let e: Vec<f64> = enc.iter().map(|&v| v as f64).collect();
    let r = quat_to_mat([e[3], e[4], e[5], e[6]]);
    let mut extrinsic = [[0.0; 4]; 3];
    for i in 0..3 {
        extrinsic[i][..3].copy_from_slice(&r[i]);
        extrinsic[i][3] = e[i];
    }
    let fy = (h as f64 / 2.0) / (e[7] / 2.0).tan();
    let fx = (w as f64 / 2.0) / (e[8] / 2.0).tan();
    VggtCamera { extrinsic, intrinsic: [[fx, 0.0, w as f64 / 2.0], [0.0, fy, h as f64 / 2.0], [0.0, 0.0, 1.0]] }
}

impl VggtCamera {
    /// Camera → world 4 × 4 (the project's convention), the exact inverse of the rigid `[R | t]`.
    pub fn cam_to_world(&self) -> [[f64; 4]; 4] {
        let e = &self.extrinsic;
        let mut m = [[0.0; 4]; 4];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = e[j][i];
            }
            m[i][3] = -(0..3).map(|j| e[j][i] * e[j][3]).sum::<f64>();
        }
        m[3][3] = 1.0;
        m
    }
}
