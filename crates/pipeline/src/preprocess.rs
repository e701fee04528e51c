//! Image preprocessing shared by `render`, `export` and `eval`: the official data path's `rescale_and_crop`
//! (scale so the image covers the model's input size, centre-crop to it) followed by the encoder's patch shim
//! (centre-crop to a multiple of 64). Intrinsics follow every step, so a photo and its camera stay consistent.
//! Each view is planned from its own size, so a scene may mix sizes: with a fixed input size every view comes
//! out the same, and only then are views batched. `native` keeps each size, so it needs views of one size
//! ([`Preprocess::check_sizes`]).

use mvsplat360_camera::Camera;
use mvsplat360_dataset::{ImageF32, Scene};

use crate::error::{flag, PipelineError, Result};

/// The input size the model sees.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum InputSize {
    /// Keep the photos' size (only the crop to a multiple of 64).
    Native,
    /// Scale to cover `width`×`height` (aspect kept), then centre-crop to it.
    Fixed { width: u32, height: u32 },
}

impl std::str::FromStr for InputSize {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        if s == "native" {
            return Ok(Self::Native);
        }
        let (w, h) = s.split_once('x').ok_or_else(|| format!("expected WIDTHxHEIGHT (e.g. 448x256) or `native`, got `{s}`"))?;
        let parse = |v: &str| v.trim().parse::<u32>().ok().filter(|&v| v > 0);
        match (parse(w), parse(h)) {
            (Some(width), Some(height)) => Ok(Self::Fixed { width, height }),
            _ => Err(format!("expected positive WIDTHxHEIGHT (e.g. 448x256), got `{s}`")),
        }
    }
}

/// Preprocessing settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Preprocess {
    pub size: InputSize,
    /// The encoder's size multiple (`shim_patch_size · downscale_factor`, 64).
    pub multiple: u32,
}

/// Where a camera's pixels go: scale to `scaled`, then keep the crop `(x0, y0, width, height)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plan {
    pub scaled: (u32, u32),
    pub crop: mvsplat360_camera::CropRect,
}

impl Preprocess {
    /// The resize and crop for a `width`×`height` photo. Errors when the result would be empty.
    pub fn plan(&self, cam: &Camera) -> Result<Plan> {
        let (w, h) = (cam.width, cam.height);
        let (scaled, target) = match self.size {
            InputSize::Native => ((w, h), (w, h)),
            InputSize::Fixed { width, height } => {
                // pixelSplat/MVSplat `rescale_and_crop`: one factor so the scaled image covers the target.
                let s = (height as f64 / h as f64).max(width as f64 / w as f64);
                let sw = ((w as f64 * s).round() as u32).max(width);
                let sh = ((h as f64 * s).round() as u32).max(height);
                ((sw, sh), (width, height))
            }
        };
        let m = self.multiple.max(1);
        let (cw, ch) = (target.0 / m * m, target.1 / m * m);
        if cw == 0 || ch == 0 {
            return Err(PipelineError::Camera(mvsplat360_camera::CameraError::CropTooSmall { width: target.0, height: target.1, multiple: m }));
        }
        let crop = mvsplat360_camera::CropRect { x0: (scaled.0 - cw) / 2, y0: (scaled.1 - ch) / 2, width: cw, height: ch };
        Ok(Plan { scaled, crop })
    }

    /// `--size native` keeps every photo's size, and the model batches views: refuse views of mixed sizes,
    /// naming each size with its first view. A fixed size accepts any mix.
    pub fn check_sizes(&self, scene: &Scene, views: &[usize]) -> Result<()> {
        if self.size != InputSize::Native {
            return Ok(());
        }
        let mut sizes: Vec<((u32, u32), usize, usize)> = Vec::new();
        for &i in views {
            let Some(c) = scene.cameras.get(i) else { continue };
            match sizes.iter_mut().find(|s| s.0 == (c.width, c.height)) {
                Some(s) => s.2 += 1,
                None => sizes.push(((c.width, c.height), i, 1)),
            }
        }
        if sizes.len() < 2 {
            return Ok(());
        }
        let list: Vec<String> = sizes
            .iter()
            .map(|((w, h), i, n)| format!("{} is {w}x{h}{}", scene.view_names[*i], if *n > 1 { format!(" (and {} more)", n - 1) } else { String::new() }))
            .collect();
        Err(flag(
            "--size",
            format!("`native` keeps each photo's size, but the views used differ: {}; give --size WIDTHxHEIGHT (or leave it out for the model's size) to bring them to one size", list.join(", ")),
        ))
    }

    /// The camera after preprocessing.
    pub fn camera(&self, cam: &Camera) -> Result<Camera> {
        let p = self.plan(cam)?;
        Ok(cam.rescaled(p.scaled.0, p.scaled.1).cropped(p.crop))
    }

    /// The photo and its camera after preprocessing.
    pub fn view(&self, image: &ImageF32, cam: &Camera) -> Result<(ImageF32, Camera)> {
        let p = self.plan(cam)?;
        let img = if p.scaled == (image.width, image.height) { image.clone() } else { resize(image, p.scaled.0, p.scaled.1) };
        let img = img.crop(p.crop.x0, p.crop.y0, p.crop.width, p.crop.height);
        Ok((img, cam.rescaled(p.scaled.0, p.scaled.1).cropped(p.crop)))
    }
}

/// Resize exactly as the official loader does (`rescale` in `crop_shim.py`): quantise to 8 bits as torch does,
/// Pillow's `Image.LANCZOS`, back to f32 — bit-exact against Pillow; see [`mvsplat360_dataset::resize`], which
/// also says where our intrinsics (exact rescale and crop) differ from the official ones. [`Preprocess::view`]
/// skips the call when the size is unchanged: the official call is then a copy after a quantisation that is
/// lossless for decoded 8-bit photos.
pub fn resize(img: &ImageF32, width: u32, height: u32) -> ImageF32 {
    mvsplat360_dataset::resize_pil_lanczos(img, width, height)
}

/// One preprocessed view of a scene.
#[derive(Debug, Clone)]
pub struct PreparedView {
    pub index: usize,
    pub name: String,
    pub image: ImageF32,
    pub camera: Camera,
}

/// Decode and preprocess view `i` of `scene`.
pub fn prepare_view(scene: &Scene, i: usize, pre: &Preprocess) -> Result<PreparedView> {
    let img = scene.image(i)?;
    let (image, camera) = pre.view(&img, &scene.cameras[i])?;
    Ok(PreparedView { index: i, name: scene.view_names[i].clone(), image, camera })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(w: u32, h: u32) -> Camera {
        Camera {
            fx: 400.0,
            fy: 410.0,
            cx: w as f64 / 2.0 + 3.0,
            cy: h as f64 / 2.0 - 2.0,
            width: w,
            height: h,
            c2w: [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        }
    }

    #[test]
    fn dl3dv_frame_to_448x256() {
        // 960x540 → factor max(256/540, 448/960) = 0.474 → 455x256 → crop 448x256 (x0 = 3).
        let pre = Preprocess { size: InputSize::Fixed { width: 448, height: 256 }, multiple: 64 };
        let p = pre.plan(&cam(960, 540)).unwrap();
        assert_eq!(p.scaled, (455, 256));
        assert_eq!((p.crop.x0, p.crop.y0, p.crop.width, p.crop.height), (3, 0, 448, 256));
        let c = pre.camera(&cam(960, 540)).unwrap();
        let s = 455.0 / 960.0;
        assert!((c.fx - 400.0 * s).abs() < 1e-9);
        assert!((c.fy - 410.0 * 256.0 / 540.0).abs() < 1e-9);
        assert!((c.cx - ((480.0 + 3.0) * s - 3.0)).abs() < 1e-9);
        assert_eq!((c.width, c.height), (448, 256));
    }

    #[test]
    fn official_dl3dv_framing() {
        // DL3DV 480P frames (480×270) are not resized; the patch shim crops row 7, column 16 → 448×256.
        let pre = Preprocess { size: InputSize::Fixed { width: 480, height: 270 }, multiple: 64 };
        let p = pre.plan(&cam(480, 270)).unwrap();
        assert_eq!(p.scaled, (480, 270));
        assert_eq!((p.crop.x0, p.crop.y0, p.crop.width, p.crop.height), (16, 7, 448, 256));
        // RE10K: 360×640 → 180×320 → multiple 16 → 320×176 (row 2).
        let pre = Preprocess { size: InputSize::Fixed { width: 320, height: 180 }, multiple: 16 };
        let p = pre.plan(&cam(640, 360)).unwrap();
        assert_eq!(p.scaled, (320, 180));
        assert_eq!((p.crop.x0, p.crop.y0, p.crop.width, p.crop.height), (0, 2, 320, 176));
    }

    #[test]
    fn native_only_crops_to_multiple() {
        let pre = Preprocess { size: InputSize::Native, multiple: 64 };
        let p = pre.plan(&cam(300, 200)).unwrap();
        assert_eq!(p.scaled, (300, 200));
        assert_eq!((p.crop.x0, p.crop.y0, p.crop.width, p.crop.height), (22, 4, 256, 192));
        assert!(pre.plan(&cam(60, 200)).is_err());
    }

    #[test]
    fn mixed_sizes_fixed_accepted_native_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let mut scene = Scene { name: "mixed".into(), ..Scene::default() };
        for (name, w, h) in [("a.png", 300u32, 200u32), ("b.png", 200, 300), ("c.png", 300, 200)] {
            let p = tmp.path().join(name);
            image::RgbImage::from_pixel(w, h, image::Rgb([90, 120, 150])).save(&p).unwrap();
            scene.view_names.push(name.into());
            scene.cameras.push(cam(w, h));
            scene.images.push(mvsplat360_dataset::ImageSource::File(p));
        }
        let fixed = Preprocess { size: InputSize::Fixed { width: 128, height: 128 }, multiple: 64 };
        fixed.check_sizes(&scene, &[0, 1, 2]).unwrap();
        for i in 0..3 {
            let v = prepare_view(&scene, i, &fixed).unwrap();
            assert_eq!((v.image.width, v.image.height, v.camera.width, v.camera.height), (128, 128, 128, 128), "view {i}");
        }
        let native = Preprocess { size: InputSize::Native, multiple: 64 };
        native.check_sizes(&scene, &[0, 2]).unwrap();
        let e = native.check_sizes(&scene, &[0, 1, 2]).unwrap_err().to_string();
        for needle in ["--size", "a.png is 300x200 (and 1 more)", "b.png is 200x300"] {
            assert!(e.contains(needle), "expected `{needle}` in `{e}`");
        }
    }

    #[test]
    fn size_parsing() {
        assert_eq!("448x256".parse::<InputSize>().unwrap(), InputSize::Fixed { width: 448, height: 256 });
        assert_eq!("native".parse::<InputSize>().unwrap(), InputSize::Native);
        assert!("448".parse::<InputSize>().is_err());
        assert!("0x5".parse::<InputSize>().is_err());
    }

    #[test]
    fn resize_keeps_constant_image_and_view_matches_plan() {
        // A decoded photo's level survives exactly; an off-grid value is truncated to 8 bits first, as the
        // official `(image * 255).type(torch.uint8)` does (0.25 · 255 = 63.75 → 63).
        let img = ImageF32 { width: 40, height: 30, data: vec![64.0 / 255.0; 3 * 40 * 30] };
        let r = resize(&img, 17, 13);
        assert!(r.data.iter().all(|&v| v == 64.0 / 255.0));
        let off_grid = ImageF32 { width: 40, height: 30, data: vec![0.25; 3 * 40 * 30] };
        assert!(resize(&off_grid, 17, 13).data.iter().all(|&v| v == 63.0 / 255.0));
        let pre = Preprocess { size: InputSize::Fixed { width: 16, height: 16 }, multiple: 16 };
        let (out, c) = pre.view(&img, &cam(40, 30)).unwrap();
        assert_eq!((out.width, out.height, c.width, c.height), (16, 16, 16, 16));
    }
}
