use nalgebra::{Matrix3, Matrix4, Vector3};
use serde::{Deserialize, Serialize};

/// A pinhole camera: intrinsics in pixels for a `width`×`height` image, extrinsics camera-to-world (OpenCV axes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
    /// Camera-to-world, row-major, last row 0 0 0 1.
    pub c2w: [[f64; 4]; 4],
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("view {view}: {field} is not finite ({value}); check the pose/intrinsics in the scene file")]
    NotFinite { view: String, field: &'static str, value: f64 },
    #[error("view {view}: focal length {field} = {value} must be positive")]
    BadFocal { view: String, field: &'static str, value: f64 },
    #[error("view {view}: principal point ({cx}, {cy}) lies outside the {width}x{height} image")]
    PrincipalPointOutside { view: String, cx: f64, cy: f64, width: u32, height: u32 },
    #[error("view {view}: image size {width}x{height} is empty")]
    EmptyImage { view: String, width: u32, height: u32 },
    #[error("view {view}: rotation is not orthonormal (|RᵀR − I| = {err:.2e} > 1e-3); the pose may be scaled or corrupt")]
    NotOrthonormal { view: String, err: f64 },
    #[error("view {view}: rotation has determinant {det:.4} (must be +1; a reflection means a wrong axis convention)")]
    NotRightHanded { view: String, det: f64 },
    #[error("view {view}: last row of the 4x4 pose must be 0 0 0 1, got {row:?}")]
    BadLastRow { view: String, row: [f64; 4] },
    #[error("cannot crop a {width}x{height} image to a multiple of {multiple}: the result would be empty")]
    CropTooSmall { width: u32, height: u32, multiple: u32 },
}

/// Pixel rectangle kept by a crop: columns `x0..x0+width`, rows `y0..y0+height`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CropRect {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    pub fn c2w_matrix(&self) -> Matrix4<f64> {
        Matrix4::from_fn(|r, c| self.c2w[r][c])
    }

    pub fn w2c_matrix(&self) -> Matrix4<f64> {
        crate::convert::invert_rigid(&self.c2w_matrix())
    }

    pub fn rotation(&self) -> Matrix3<f64> {
        Matrix3::from_fn(|r, c| self.c2w[r][c])
    }

    pub fn center(&self) -> Vector3<f64> {
        Vector3::new(self.c2w[0][3], self.c2w[1][3], self.c2w[2][3])
    }

    /// Viewing direction (+z of the camera) in world coordinates.
    pub fn forward(&self) -> Vector3<f64> {
        Vector3::new(self.c2w[0][2], self.c2w[1][2], self.c2w[2][2])
    }

    /// Pixel intrinsics matrix K.
    pub fn k(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// Normalised intrinsics (fx/W, fy/H, cx/W, cy/H) as the official model expects them.
    pub fn normalized_intrinsics(&self) -> [f64; 4] {
        let (w, h) = (self.width as f64, self.height as f64);
        [self.fx / w, self.fy / h, self.cx / w, self.cy / h]
    }

    /// Inverse of [`Camera::normalized_intrinsics`].
    pub fn from_normalized(k: [f64; 4], width: u32, height: u32, c2w: [[f64; 4]; 4]) -> Self {
        let (w, h) = (width as f64, height as f64);
        Camera { fx: k[0] * w, fy: k[1] * h, cx: k[2] * w, cy: k[3] * h, width, height, c2w }
    }

    pub fn with_c2w(mut self, m: &Matrix4<f64>) -> Self {
        for r in 0..4 {
            for c in 0..4 {
                self.c2w[r][c] = m[(r, c)];
            }
        }
        self
    }

    /// Project a world point to pixel coordinates (pixel centres at +0.5) and its z-depth.
    pub fn project(&self, p_world: &Vector3<f64>) -> (f64, f64, f64) {
        let p = self.w2c_matrix().transform_point(&(*p_world).into());
        (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy, p.z)
    }

    /// Checks that every value is usable; `view` names the view in the error.
    pub fn validate(&self, view: &str) -> Result<(), CameraError> {
        let v = || view.to_string();
        for (field, value) in [("fx", self.fx), ("fy", self.fy), ("cx", self.cx), ("cy", self.cy)] {
            if !value.is_finite() {
                return Err(CameraError::NotFinite { view: v(), field, value });
            }
        }
        for (field, value) in [("fx", self.fx), ("fy", self.fy)] {
            if value <= 0.0 {
                return Err(CameraError::BadFocal { view: v(), field, value });
            }
        }
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::EmptyImage { view: v(), width: self.width, height: self.height });
        }
        if self.cx < 0.0 || self.cy < 0.0 || self.cx > self.width as f64 || self.cy > self.height as f64 {
            return Err(CameraError::PrincipalPointOutside { view: v(), cx: self.cx, cy: self.cy, width: self.width, height: self.height });
        }
        for row in &self.c2w {
            for &value in row {
                if !value.is_finite() {
                    return Err(CameraError::NotFinite { view: v(), field: "c2w", value });
                }
            }
        }
        if self.c2w[3] != [0.0, 0.0, 0.0, 1.0] {
            let row = self.c2w[3];
            if (row[0].abs() + row[1].abs() + row[2].abs() + (row[3] - 1.0).abs()) > 1e-6 {
                return Err(CameraError::BadLastRow { view: v(), row });
            }
        }
        let r = self.rotation();
        let err = (r.transpose() * r - Matrix3::identity()).norm();
        if err > 1e-3 {
            return Err(CameraError::NotOrthonormal { view: v(), err });
        }
        let det = r.determinant();
        if det <= 0.0 {
            return Err(CameraError::NotRightHanded { view: v(), det });
        }
        Ok(())
    }

    /// Scale the image by `(sx, sy)` (new size = round(old·s)); intrinsics follow the pixel grid.
    pub fn rescaled(&self, new_width: u32, new_height: u32) -> Camera {
        let sx = new_width as f64 / self.width as f64;
        let sy = new_height as f64 / self.height as f64;
        Camera { fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy, width: new_width, height: new_height, c2w: self.c2w }
    }

    /// Crop to `rect`; focal lengths are unchanged, the principal point moves with the origin.
    pub fn cropped(&self, rect: CropRect) -> Camera {
        Camera { cx: self.cx - rect.x0 as f64, cy: self.cy - rect.y0 as f64, width: rect.width, height: rect.height, ..self.clone() }
    }

    /// The official "patch shim": centre-crop H and W down to a multiple of `multiple` (64 for the encoder).
    pub fn center_crop_rect(&self, multiple: u32) -> Result<CropRect, CameraError> {
        let w = self.width / multiple * multiple;
        let h = self.height / multiple * multiple;
        if w == 0 || h == 0 {
            return Err(CameraError::CropTooSmall { width: self.width, height: self.height, multiple });
        }
        Ok(CropRect { x0: (self.width - w) / 2, y0: (self.height - h) / 2, width: w, height: h })
    }
}

#[cfg(test)]
pub(crate) fn test_camera() -> Camera {
    Camera {
        fx: 300.0,
        fy: 310.0,
        cx: 224.0,
        cy: 128.0,
        width: 448,
        height: 256,
        c2w: [[1.0, 0.0, 0.0, 0.5], [0.0, 1.0, 0.0, -0.25], [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalized_roundtrip_closed_form() {
        let c = test_camera();
        let k = c.normalized_intrinsics();
        assert_eq!(k, [300.0 / 448.0, 310.0 / 256.0, 0.5, 0.5]);
        let back = Camera::from_normalized(k, c.width, c.height, c.c2w);
        assert!((back.fx - c.fx).abs() < 1e-12 && (back.cy - c.cy).abs() < 1e-12);
    }

    #[test]
    fn projection_of_point_on_axis_hits_principal_point() {
        let c = test_camera();
        // A point 3 units in front of the camera centre along +z projects to (cx, cy) at depth 3.
        let p = c.center() + Vector3::new(0.0, 0.0, 3.0);
        let (u, v, z) = c.project(&p);
        assert!((u - 224.0).abs() < 1e-12 && (v - 128.0).abs() < 1e-12 && (z - 3.0).abs() < 1e-12);
        // Offset by one unit in x at depth 3 moves fx/3 pixels right.
        let (u2, _, _) = c.project(&(p + Vector3::new(1.0, 0.0, 0.0)));
        assert!((u2 - (224.0 + 100.0)).abs() < 1e-9);
    }

    #[test]
    fn center_crop_matches_shim() {
        let mut c = test_camera();
        c.width = 450;
        c.height = 300;
        c.cx = 225.0;
        c.cy = 150.0;
        let rect = c.center_crop_rect(64).unwrap();
        assert_eq!(rect, CropRect { x0: 1, y0: 22, width: 448, height: 256 });
        let cc = c.cropped(rect);
        assert_eq!((cc.cx, cc.cy, cc.fx), (224.0, 128.0, 300.0));
        // The normalised focal scales by W/W_new, as in the official shim.
        let k0 = c.normalized_intrinsics();
        let k1 = cc.normalized_intrinsics();
        assert!((k1[0] - k0[0] * 450.0 / 448.0).abs() < 1e-12);
        assert!((k1[1] - k0[1] * 300.0 / 256.0).abs() < 1e-12);
        assert!(matches!(c.center_crop_rect(512), Err(CameraError::CropTooSmall { .. })));
    }

    #[test]
    fn rescale_keeps_projection_consistent() {
        let c = test_camera();
        let r = c.rescaled(224, 128);
        let p = Vector3::new(0.3, -0.2, 5.0);
        let (u, v, _) = c.project(&p);
        let (u2, v2, _) = r.project(&p);
        assert!((u2 - u * 0.5).abs() < 1e-9 && (v2 - v * 0.5).abs() < 1e-9);
    }

    #[test]
    fn validation_names_the_problem() {
        let ok = test_camera();
        ok.validate("v0").unwrap();
        let mut c = ok.clone();
        c.fx = -1.0;
        assert!(c.validate("v3").unwrap_err().to_string().contains("view v3: focal length fx"));
        let mut c = ok.clone();
        c.cy = f64::NAN;
        assert!(c.validate("v1").unwrap_err().to_string().contains("cy is not finite"));
        let mut c = ok.clone();
        c.cx = 1000.0;
        assert!(c.validate("a").unwrap_err().to_string().contains("principal point"));
        let mut c = ok.clone();
        c.c2w[0][0] = 2.0;
        assert!(c.validate("a").unwrap_err().to_string().contains("not orthonormal"));
        let mut c = ok.clone();
        c.c2w[2][2] = -1.0;
        assert!(c.validate("a").unwrap_err().to_string().contains("determinant"));
        let mut c = ok.clone();
        c.c2w[3] = [0.0, 0.0, 1.0, 1.0];
        assert!(c.validate("a").unwrap_err().to_string().contains("last row"));
        let mut c = ok;
        c.width = 0;
        assert!(c.validate("a").unwrap_err().to_string().contains("empty"));
    }
}
