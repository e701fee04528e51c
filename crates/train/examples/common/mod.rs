//! Helpers shared by the exploration examples (`tto`, `post`, `ibr`, `blend`).
#![allow(dead_code)]

use candle_core::Tensor;

/// Removes `flag VALUE` from `args` and returns VALUE, or `default` when the flag is absent.
pub fn take_flag(args: &mut Vec<String>, flag: &str, default: &str) -> String {
    match args.iter().position(|a| a == flag) {
        Some(i) => {
            let v = args.remove(i + 1);
            args.remove(i);
            v
        }
        None => default.to_string(),
    }
}

/// PSNR of a prediction (clamped to [0, 1]) against its photo.
pub fn psnr(a: &Tensor, b: &Tensor) -> anyhow::Result<f64> {
    let a: Vec<f32> = a.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
    let b: Vec<f32> = b.flatten_all()?.to_vec1()?;
    Ok(mvsplat360_metrics::psnr::psnr(&a, &b))
}

/// A context view for image-based rendering: camera, photo (3,H,W) and z-depth per pixel (infinite where unknown).
pub struct View {
    pub cam: mvsplat360_camera::Camera,
    pub img: Vec<f32>,
    pub z: Vec<f32>,
}

/// Bilinear sample of a (3,H,W) image at pixel coordinates (centres at +0.5), clamped at the border.
pub fn bilinear(img: &[f32], w: usize, h: usize, x: f64, y: f64, out: &mut [f32; 3]) {
    let (x, y) = ((x - 0.5).clamp(0.0, w as f64 - 1.0), (y - 0.5).clamp(0.0, h as f64 - 1.0));
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    for c in 0..3 {
        let p = &img[c * w * h..];
        let a = p[y0 * w + x0] * (1.0 - fx) + p[y0 * w + x1] * fx;
        let b = p[y1 * w + x0] * (1.0 - fx) + p[y1 * w + x1] * fx;
        out[c] = a * (1.0 - fy) + b * fy;
    }
}
