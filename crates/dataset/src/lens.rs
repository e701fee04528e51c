//! Lens distortion and its removal. Every reader hands the rest of the program pinhole cameras; a view whose
//! lens distorts keeps its [`Distortion`] beside the camera, and [`Scene::image`](crate::Scene::image) resamples
//! its photo onto that pinhole camera ([`undistort`]) before anyone sees the pixels.
//!
//! The models, on normalised coordinates `(x, y) = ((u − cx)/fx, (v − cy)/fy)` of the undistorted ray, with
//! `r² = x² + y²` (COLMAP `src/colmap/sensor/models.h`, `*CameraModel::Distortion`; nerfstudio
//! `nerfstudio/cameras/camera_utils.py`, `_compute_residual_and_jacobian`):
//!
//! ```text
//! x_d = x·radial(r²) + 2·p1·x·y + p2·(r² + 2x²)
//! y_d = y·radial(r²) + p1·(r² + 2y²) + 2·p2·x·y
//! SIMPLE_RADIAL  radial = 1 + k·r²                                  (no tangential terms)
//! RADIAL         radial = 1 + k1·r² + k2·r⁴                         (no tangential terms)
//! OPENCV         radial = 1 + k1·r² + k2·r⁴
//! FULL_OPENCV    radial = (1 + k1·r² + k2·r⁴ + k3·r⁶) / (1 + k4·r² + k5·r⁴ + k6·r⁶)
//! nerfstudio     radial = 1 + k1·r² + k2·r⁴ + k3·r⁶ + k4·r⁸         (camera_model OPENCV and the other perspective ones)
//! ```
//!
//! The distorted pixel is `(fx·x_d + cx, fy·y_d + cy)`. COLMAP and nerfstudio write the tangential terms the
//! way OpenCV does (`p1` pairs with `2xy` in `x_d` and with `r² + 2y²` in `y_d`).

use rayon::prelude::*;

use mvsplat360_camera::Camera;

use crate::ImageF32;

/// The distortion coefficients of one lens (the focal lengths and principal point are the view's [`Camera`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Distortion {
    /// COLMAP `SIMPLE_RADIAL` (`f, cx, cy, k`).
    SimpleRadial { k: f64 },
    /// COLMAP `RADIAL` (`f, cx, cy, k1, k2`).
    Radial { k1: f64, k2: f64 },
    /// COLMAP `OPENCV` (`fx, fy, cx, cy, k1, k2, p1, p2`).
    OpenCv { k1: f64, k2: f64, p1: f64, p2: f64 },
    /// COLMAP `FULL_OPENCV` (`fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`): OpenCV's rational model.
    FullOpenCv { k1: f64, k2: f64, p1: f64, p2: f64, k3: f64, k4: f64, k5: f64, k6: f64 },
    /// nerfstudio's perspective model (`transforms.json` keys `k1`…`k4`, `p1`, `p2`).
    Perspective { k1: f64, k2: f64, k3: f64, k4: f64, p1: f64, p2: f64 },
}

impl Distortion {
    /// The model's name as the scene file spells it.
    pub fn name(&self) -> &'static str {
        match self {
            Distortion::SimpleRadial { .. } => "SIMPLE_RADIAL",
            Distortion::Radial { .. } => "RADIAL",
            Distortion::OpenCv { .. } => "OPENCV",
            Distortion::FullOpenCv { .. } => "FULL_OPENCV",
            Distortion::Perspective { .. } => "nerfstudio perspective (k1-k4, p1, p2)",
        }
    }

    /// `None` when every coefficient is zero (the lens is a pinhole already).
    pub fn nonzero(self) -> Option<Distortion> {
        let c = self.coefficients();
        c.iter().any(|&v| v != 0.0).then_some(self)
    }

    fn coefficients(&self) -> Vec<f64> {
        match *self {
            Distortion::SimpleRadial { k } => vec![k],
            Distortion::Radial { k1, k2 } => vec![k1, k2],
            Distortion::OpenCv { k1, k2, p1, p2 } => vec![k1, k2, p1, p2],
            Distortion::FullOpenCv { k1, k2, p1, p2, k3, k4, k5, k6 } => vec![k1, k2, p1, p2, k3, k4, k5, k6],
            Distortion::Perspective { k1, k2, k3, k4, p1, p2 } => vec![k1, k2, k3, k4, p1, p2],
        }
    }

    /// The radial factor at `r2` = r².
    pub fn radial(&self, r2: f64) -> f64 {
        let (r4, r6) = (r2 * r2, r2 * r2 * r2);
        match *self {
            Distortion::SimpleRadial { k } => 1.0 + k * r2,
            Distortion::Radial { k1, k2 } | Distortion::OpenCv { k1, k2, .. } => 1.0 + k1 * r2 + k2 * r4,
            Distortion::FullOpenCv { k1, k2, k3, k4, k5, k6, .. } => (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6),
            Distortion::Perspective { k1, k2, k3, k4, .. } => 1.0 + k1 * r2 + k2 * r4 + k3 * r6 + k4 * r4 * r4,
        }
    }

    fn tangential(&self) -> (f64, f64) {
        match *self {
            Distortion::SimpleRadial { .. } | Distortion::Radial { .. } => (0.0, 0.0),
            Distortion::OpenCv { p1, p2, .. } | Distortion::FullOpenCv { p1, p2, .. } | Distortion::Perspective { p1, p2, .. } => (p1, p2),
        }
    }

    /// The distorted normalised coordinates of the undistorted ray `(x, y)` (see the module docs).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = self.radial(r2);
        let (p1, p2) = self.tangential();
        (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
    }

    /// The largest radius up to `r_max` over which `r ↦ r·radial(r²)` keeps increasing. Past it the polynomial
    /// folds back (a strong barrel term, or a pole of the rational model), and sampling there would paste a
    /// mirrored copy of the image centre into the corners.
    pub fn monotonic_radius(&self, r_max: f64) -> f64 {
        const STEPS: usize = 4096;
        let dr = r_max / STEPS as f64;
        let mut prev = 0.0;
        for i in 1..=STEPS {
            let r = i as f64 * dr;
            let g = r * self.radial(r * r);
            if !g.is_finite() || g <= prev {
                return (i - 1) as f64 * dr;
            }
            prev = g;
        }
        f64::INFINITY
    }
}

/// Resample a photo taken through `lens` onto the pinhole camera `cam` (same size, same `fx, fy, cx, cy`).
///
/// Each output pixel's centre `(i + 0.5, j + 0.5)` is lifted to its ray, distorted, and the photo is sampled
/// bilinearly at the distorted position (pixel centres at +0.5). A position inside the photo's rectangle
/// `[0, W] × [0, H]` reads the nearest pixels (edge pixels cover the outer half pixel); one outside it, or a ray
/// past the radius where the lens polynomial folds back ([`Distortion::monotonic_radius`]), is black.
pub fn undistort(img: &ImageF32, cam: &Camera, lens: &Distortion) -> ImageF32 {
    let (w, h) = (img.width as usize, img.height as usize);
    let (wf, hf) = (w as f64, h as f64);
    let corner = |u: f64, v: f64| ((u - cam.cx) / cam.fx).hypot((v - cam.cy) / cam.fy);
    let r_max = corner(0.0, 0.0).max(corner(wf, 0.0)).max(corner(0.0, hf)).max(corner(wf, hf));
    let r_ok = lens.monotonic_radius(r_max * 1.01);
    // Source position (continuous pixel index, centres at integers) of every output pixel; None = black.
    let map: Vec<Option<(f32, f32)>> = (0..w * h)
        .into_par_iter()
        .map(|k| {
            let x = ((k % w) as f64 + 0.5 - cam.cx) / cam.fx;
            let y = ((k / w) as f64 + 0.5 - cam.cy) / cam.fy;
            if x.hypot(y) > r_ok {
                return None;
            }
            let (xd, yd) = lens.distort(x, y);
            let (u, v) = (cam.fx * xd + cam.cx, cam.fy * yd + cam.cy);
            ((0.0..=wf).contains(&u) && (0.0..=hf).contains(&v)).then(|| ((u - 0.5).clamp(0.0, wf - 1.0) as f32, (v - 0.5).clamp(0.0, hf - 1.0) as f32))
        })
        .collect();
    let mut data = vec![0f32; 3 * w * h];
    for (c, out) in data.chunks_mut(w * h).enumerate() {
        let src = &img.data[c * w * h..(c + 1) * w * h];
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, px) in row.iter_mut().enumerate() {
                if let Some((u, v)) = map[y * w + x] {
                    *px = bilinear(src, w, h, u, v);
                }
            }
        });
    }
    ImageF32 { width: img.width, height: img.height, data }
}

/// Bilinear sample of one plane at a continuous index `(u, v)` already clamped to `[0, w−1] × [0, h−1]`.
fn bilinear(p: &[f32], w: usize, h: usize, u: f32, v: f32) -> f32 {
    let (x0, y0) = (u.floor() as usize, v.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (tx, ty) = (u - x0 as f32, v - y0 as f32);
    let top = p[y0 * w + x0] * (1.0 - tx) + p[y0 * w + x1] * tx;
    let bot = p[y1 * w + x0] * (1.0 - tx) + p[y1 * w + x1] * tx;
    top * (1.0 - ty) + bot * ty
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(w: u32, h: u32) -> Camera {
        let c2w = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
        Camera { fx: 20.0, fy: 20.0, cx: w as f64 / 2.0, cy: h as f64 / 2.0, width: w, height: h, c2w }
    }

    #[test]
    fn zero_coefficients_are_no_lens_and_identity_when_applied() {
        assert_eq!(Distortion::OpenCv { k1: 0.0, k2: 0.0, p1: 0.0, p2: 0.0 }.nonzero(), None);
        assert!(Distortion::Perspective { k1: 0.0, k2: 0.0, k3: 0.0, k4: 1e-9, p1: 0.0, p2: 0.0 }.nonzero().is_some());
        // Radial factor 1 everywhere (k4 = 0 on a zero numerator term): every pixel samples its own centre.
        let img = ImageF32 { width: 5, height: 4, data: (0..60).map(|v| v as f32 / 60.0).collect() };
        let lens = Distortion::FullOpenCv { k1: 0.0, k2: 0.0, p1: 0.0, p2: 0.0, k3: 0.0, k4: 0.0, k5: 0.0, k6: 0.0 };
        assert_eq!(undistort(&img, &cam(5, 4), &lens), img);
    }

    #[test]
    fn fold_back_is_black() {
        // k = −1: r·(1 − r²) peaks at r = 1/√3; with f = 20 px that is 11.5 px from the centre.
        let lens = Distortion::SimpleRadial { k: -1.0 };
        let r = lens.monotonic_radius(2.0);
        assert!((r - 1.0 / 3f64.sqrt()).abs() < 2.0 / 4096.0 + 1e-12, "{r}");
        let img = ImageF32 { width: 40, height: 40, data: vec![0.5; 3 * 1600] };
        let out = undistort(&img, &cam(40, 40), &lens);
        assert_eq!(out.data[20 * 40 + 20], 0.5, "centre");
        assert_eq!(out.data[0], 0.0, "corner (r = 1.41) is past the fold");
        assert_eq!(Distortion::OpenCv { k1: 0.1, k2: 0.0, p1: 0.0, p2: 0.0 }.monotonic_radius(3.0), f64::INFINITY);
    }
}
