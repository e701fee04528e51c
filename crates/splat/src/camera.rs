//! The camera as the rasterizer sees it ([`RasterCamera::from_camera`] converts a `mvsplat360_camera::Camera`).

use crate::error::{input_err, Result};

/// A pinhole camera for rasterization: world-to-camera matrix (row-major, OpenCV axes) and pixel intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RasterCamera {
    /// World-to-camera 4×4, row-major: `p_view = V[:3,:3] p + V[:3,3]`.
    pub viewmatrix: [[f32; 4]; 4],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: usize,
    pub height: usize,
    /// Near/far only enter the projection matrix's clip z, which the rasterizer does not use.
    pub near: f32,
    pub far: f32,
}

impl RasterCamera {
    /// The rasterizer's camera for a project camera (intrinsics in pixels, OpenCV axes), with the model's
    /// near/far planes.
    pub fn from_camera(c: &mvsplat360_camera::Camera, near: f32, far: f32) -> Self {
        let w2c = c.w2c_matrix();
        let mut v = [[0f32; 4]; 4];
        for (r, row) in v.iter_mut().enumerate() {
            for (k, x) in row.iter_mut().enumerate() {
                *x = w2c[(r, k)] as f32;
            }
        }
        RasterCamera {
            viewmatrix: v,
            fx: c.fx as f32,
            fy: c.fy as f32,
            cx: c.cx as f32,
            cy: c.cy as f32,
            width: c.width as usize,
            height: c.height as usize,
            near,
            far,
        }
    }

    /// `tan(fov/2)` per axis, as the official wrapper derives it from the intrinsics.
    pub fn tanfov(&self) -> [f32; 2] {
        [self.width as f32 / (2.0 * self.fx), self.height as f32 / (2.0 * self.fy)]
    }

    /// Focal lengths as the CUDA kernel recomputes them from `tanfov` (float32).
    pub fn focal(&self) -> [f32; 2] {
        let t = self.tanfov();
        [self.width as f32 / (2.0 * t[0]), self.height as f32 / (2.0 * t[1])]
    }

    /// Projection matrix P (row-major), including an off-centre principal point.
    pub fn projmatrix(&self) -> [[f32; 4]; 4] {
        let (w, h) = (self.width as f32, self.height as f32);
        let mut p = [[0f32; 4]; 4];
        p[0][0] = 2.0 * self.fx / w;
        p[1][1] = 2.0 * self.fy / h;
        p[0][2] = 2.0 * self.cx / w - 1.0;
        p[1][2] = 2.0 * self.cy / h - 1.0;
        p[3][2] = 1.0;
        p[2][2] = self.far / (self.far - self.near);
        p[2][3] = -(self.far * self.near) / (self.far - self.near);
        p
    }

    /// `P @ viewmatrix` (row-major), float32 like the official wrapper.
    pub fn full_proj(&self) -> [[f32; 4]; 4] {
        let p = self.projmatrix();
        let v = &self.viewmatrix;
        let mut out = [[0f32; 4]; 4];
        for (i, row) in out.iter_mut().enumerate() {
            for (j, o) in row.iter_mut().enumerate() {
                *o = (0..4).map(|k| p[i][k] * v[k][j]).sum();
            }
        }
        out
    }

    /// Camera centre in world coordinates (`-R^T t`, computed in f64).
    pub fn campos(&self) -> [f32; 3] {
        let v = &self.viewmatrix;
        let mut c = [0f32; 3];
        for (j, cj) in c.iter_mut().enumerate() {
            let s: f64 = (0..3).map(|i| v[i][j] as f64 * v[i][3] as f64).sum();
            *cj = (-s) as f32;
        }
        c
    }

    /// Reject cameras the rasterizer cannot handle (zero-sized image, non-finite numbers).
    pub fn validate(&self) -> Result<()> {
        if self.width == 0 || self.height == 0 {
            return Err(input_err("camera", format!("image size {}x{} must be positive", self.width, self.height)));
        }
        // Tile rects are packed in 16-bit fields.
        const MAX_SIDE: usize = 16 * u16::MAX as usize;
        if self.width > MAX_SIDE || self.height > MAX_SIDE {
            return Err(input_err("camera", format!("image size {}x{} exceeds the rasterizer's {MAX_SIDE} px per side", self.width, self.height)));
        }
        let ok = [self.fx, self.fy, self.cx, self.cy].iter().all(|x| x.is_finite())
            && self.fx > 0.0
            && self.fy > 0.0
            && self.viewmatrix.iter().flatten().all(|x| x.is_finite());
        if !ok {
            return Err(input_err("camera", "fx, fy must be positive and all camera numbers finite"));
        }
        Ok(())
    }

    /// Build from a row-major 4×4 slice (e.g. a flattened tensor).
    pub fn viewmatrix_from_slice(v: &[f32]) -> Result<[[f32; 4]; 4]> {
        if v.len() != 16 {
            return Err(input_err("viewmatrix", format!("expected 16 values, got {}", v.len())));
        }
        let mut m = [[0f32; 4]; 4];
        for i in 0..4 {
            m[i].copy_from_slice(&v[4 * i..4 * i + 4]);
        }
        Ok(m)
    }
}
