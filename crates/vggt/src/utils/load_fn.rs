//! The official `vggt/utils/load_fn.py::load_and_preprocess_images(image_path_list, mode)`, bit for bit:
//! the `f32` values we return equal torchvision's for every PNG (checked in `tests/preprocess.rs` against the
//! official function's output, written by `scripts/fixtures/official_vggt_preprocess.py`).
//!
//! Per image, as upstream does it:
//! 1. **Open** with Pillow, *without* applying the EXIF orientation (upstream never calls
//!    `ImageOps.exif_transpose`, so a phone photo stored sideways stays sideways here too).
//! 2. **Alpha**: only an image Pillow opens in mode `"RGBA"` is composited, with `Image.alpha_composite`, over
//!    opaque white; every other mode goes straight to `convert("RGB")`, which *drops* alpha. Which PNGs that is
//!    follows Pillow's PNG modes, not the file's alpha ([`decode_like_pil`]): RGBA (8 and 16 bits) and — a
//!    Pillow quirk — 16-bit gray+alpha, which Pillow opens as `"RGBA"`; *not* 8-bit gray+alpha (`"LA"`), nor
//!    palette or gray/RGB images whose `tRNS` chunk makes them transparent (`"P"`, `"L"`, `"RGB"`: the
//!    transparency is ignored, transparent pixels keep their colour). The composite is Pillow's integer
//!    formula (`src/libImaging/AlphaComposite.c`); over opaque white it reduces to
//!    `u = c·a + 255·(255 − a) + 128`, `out = (u + (u >> 8)) >> 8` ([`composite_over_white`]; checked against
//!    Pillow for all 65 536 `(c, a)`).
//! 3. **`convert("RGB")`**: gray is replicated; 16 bits become 8 as Pillow's PNG reader does it: RGB(A) and
//!    gray+alpha keep the high byte, but 16-bit *gray* opens as mode `"I;16"` and its conversion **saturates**
//!    (`min(v, 255)`), so a 16-bit grayscale photo comes out almost entirely white — upstream's behaviour,
//!    reproduced on purpose (and logged as a warning).
//! 4. **Size** (`round` is Python's, half to even; the arithmetic is `f64` in upstream's order):
//!    `crop`: width 518, height `round(h·(518/w)/14)·14`; `pad`: the longer side 518 (width when `w ≥ h`), the
//!    other `round(short·(518/long)/14)·14`. A size of 0 (an image over ~74:1) is an error, as in Pillow.
//! 5. **Resize** with `Image.resize(..., BICUBIC)`: Pillow's 8-bit resampler
//!    ([`mvsplat360_dataset::resize::resize_pil_u8`], `a = −0.5`, the pass order of Pillow 13).
//! 6. **`ToTensor`**: `level / 255` in `f32`.
//! 7. `crop`: rows `(new_h − 518)/2 ..` + 518 are kept when `new_h > 518` (only those are computed);
//!    `pad`: white (1.0) padding to 518×518, `top = (518 − new_h)/2` (floor), the rest below, same for columns.
//!
//! When the images' shapes differ (crop mode, different aspect ratios), each is padded with 1.0 to the largest
//! height and width, the floor half on the top/left (upstream prints a warning; we log one).
//!
//! **Decoders.** PNG decoding is lossless, so PNG inputs match exactly. A JPEG is decoded by the `image` crate
//! (zune-jpeg), Pillow uses libjpeg-turbo: their IDCT and chroma upsampling differ by a level here and there,
//! and those differences go through the same (exact) steps above — `tests/preprocess.rs` states the measured
//! bound. Only PNG and JPEG are read (the workspace's `image` build has no other codecs).
//!
//! # Where a model pixel came from
//! Each view's [`ViewGeometry`] records the original size, the resized size and where the resized image's
//! corner lands in the model's frame. Coordinates are continuous with the origin at the *corner* of pixel
//! (0, 0) (pixel `(i, j)` covers `[i, i+1) × [j, j+1)`, centre `(i + ½, j + ½)`) — the convention in which
//! Pillow's resampler maps output pixel centre `i + ½` to input `(i + ½)·in/out`, i.e. a pure scale, and in
//! which VGGT's principal point sits at `(W/2, H/2)`. Then `x_orig = (x_model − offset.x)·orig_w/resized_w`
//! (and the same for `y` with heights): see [`ViewGeometry::point_to_original`] and
//! [`ViewGeometry::intrinsics_to_original`]. The two axes have their own factors: rounding the size to a
//! multiple of 14 changes the aspect ratio slightly.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use image::{DynamicImage, RgbaImage};
use mvsplat360_dataset::image::decode_limited;
use mvsplat360_dataset::resize::{resize_pil_u8_rows, PilFilter};
use mvsplat360_dataset::ImageSource;

/// Upstream's `target_size`: the width in crop mode, the longer side in pad mode.
pub const TARGET_SIZE: u32 = 518;
/// Both sides are rounded to a multiple of the patch size.
pub const PATCH_SIZE: u32 = 14;

/// Upstream's `mode` argument.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PreprocessMode {
    /// `"crop"` (upstream's default): width 518, the height centre-cropped to 518 when taller.
    #[default]
    Crop,
    /// `"pad"`: the longer side 518, padded with white to 518×518; keeps every pixel.
    Pad,
}

impl PreprocessMode {
    /// Upstream's name for the mode.
    pub fn as_str(self) -> &'static str {
        match self {
            PreprocessMode::Crop => "crop",
            PreprocessMode::Pad => "pad",
        }
    }
}

impl std::fmt::Display for PreprocessMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Where one view's pixels went (see the module docs for the coordinate convention).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ViewGeometry {
    /// The decoded photo's (width, height).
    pub original: (u32, u32),
    /// The size it was resized to, before any crop or padding: (width, height).
    pub resized: (u32, u32),
    /// Where the resized image's (0, 0) corner lands in the model's frame: negative for a crop (`y = −start`),
    /// positive for padding (the view's own and the batch's together).
    pub offset: (i64, i64),
}

impl ViewGeometry {
    /// Factors from the resized grid to the original one: `(orig_w / resized_w, orig_h / resized_h)`.
    pub fn scale_to_original(&self) -> (f64, f64) {
        (self.original.0 as f64 / self.resized.0 as f64, self.original.1 as f64 / self.resized.1 as f64)
    }

    /// A point of the model's frame in the original photo (corner-origin pixel coordinates).
    pub fn point_to_original(&self, x: f64, y: f64) -> (f64, f64) {
        let (sx, sy) = self.scale_to_original();
        ((x - self.offset.0 as f64) * sx, (y - self.offset.1 as f64) * sy)
    }

    /// Pixel intrinsics `K` of the model's frame (e.g. from VGGT's pose encoding, principal point near
    /// `(W/2, H/2)`) → the same camera on the original photo's grid: `K' = A·K` with
    /// `A = [[sx, 0, −off_x·sx], [0, sy, −off_y·sy], [0, 0, 1]]`, so `fx' = fx·sx`, `cx' = (cx − off_x)·sx`,
    /// `fy' = fy·sy`, `cy' = (cy − off_y)·sy` (a skew scales with `sx`). Both in corner-origin pixels; for the
    /// pixel-centre-origin convention (`cx = (W−1)/2` for a centred camera) add ½ before and subtract ½ after.
    pub fn intrinsics_to_original(&self, k: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
        let (sx, sy) = self.scale_to_original();
        let (ox, oy) = (self.offset.0 as f64, self.offset.1 as f64);
        let row = |r: usize, s: f64, o: f64| [0, 1, 2].map(|c| (k[r][c] - o * k[2][c]) * s);
        [row(0, sx, ox), row(1, sy, oy), k[2]]
    }
}

/// The batch the model takes, in upstream's layout.
#[derive(Debug, Clone, PartialEq)]
pub struct Preprocessed {
    /// `frames × 3 × height × width`, values in `[0, 1]` (`level / 255`; padding 1.0).
    pub images: Vec<f32>,
    pub frames: usize,
    pub height: usize,
    pub width: usize,
    /// One per frame, in input order.
    pub views: Vec<ViewGeometry>,
}

impl Preprocessed {
    /// Frame `i` (`3 × height × width`).
    pub fn frame(&self, i: usize) -> &[f32] {
        let n = 3 * self.height * self.width;
        &self.images[i * n..(i + 1) * n]
    }

    /// The batch as a `(frames, 3, height, width)` tensor.
    pub fn to_tensor(&self, device: &candle_core::Device) -> candle_core::Result<candle_core::Tensor> {
        candle_core::Tensor::from_slice(&self.images, (self.frames, 3, self.height, self.width), device)
    }
}

/// Why images could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("no images given: VGGT needs at least one photo")]
    NoImages,
    #[error("cannot read {}: {source}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} is not an image this loader can decode ({msg}); give PNG or JPEG photos", path.display())]
    Decode { path: PathBuf, msg: String },
    #[error("{what} is {width}x{height}: in {mode} mode it would be resized to {new_width}x{new_height}; an image this thin cannot be used, crop it to a less extreme aspect ratio (at most about 74:1)")]
    TooThin { what: String, width: u32, height: u32, mode: PreprocessMode, new_width: u32, new_height: u32 },
}

/// Upstream's `load_and_preprocess_images(paths, mode)`: decode each file as Pillow opens it, then
/// [`preprocess_rgba8`]. Errors name the file.
pub fn load_and_preprocess_images<P: AsRef<Path>>(paths: &[P], mode: PreprocessMode) -> Result<Preprocessed, LoadError> {
    if paths.is_empty() {
        return Err(LoadError::NoImages);
    }
    let views = paths
        .iter()
        .map(|p| {
            let p = p.as_ref();
            let img = load_image_like_pil(p)?;
            resize_view(&img, mode, || p.display().to_string())
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(assemble(views))
}

/// The same from decoded pixels: each image as Pillow would hold it after `Image.open` — alpha only where
/// Pillow's mode is `"RGBA"` (elsewhere alpha must be 255; see [`decode_like_pil`]). Errors name the image by
/// its index.
pub fn preprocess_rgba8(images: &[RgbaImage], mode: PreprocessMode) -> Result<Preprocessed, LoadError> {
    if images.is_empty() {
        return Err(LoadError::NoImages);
    }
    let views = images.iter().enumerate().map(|(i, img)| resize_view(img, mode, || format!("image {i}"))).collect::<Result<Vec<_>, _>>()?;
    Ok(assemble(views))
}

/// Read and decode one file as [`decode_like_pil`] does.
pub fn load_image_like_pil(path: &Path) -> Result<RgbaImage, LoadError> {
    let bytes = std::fs::read(path).map_err(|source| LoadError::Read { path: path.to_path_buf(), source })?;
    decode_like_pil(bytes, &path.display().to_string()).map_err(|msg| LoadError::Decode { path: path.to_path_buf(), msg })
}

/// Decode an encoded image to what upstream's code holds before `alpha_composite` / `convert("RGB")`: RGBA
/// with the alpha Pillow would composite, and 255 wherever Pillow's mode has no alpha or `convert("RGB")`
/// would drop it. PNGs follow Pillow's PNG modes (module docs, steps 2–3); other files go through
/// [`ImageSource::decode`] (limits, truncated-JPEG check) and are opaque (a JPEG has no alpha).
pub fn decode_like_pil(bytes: Vec<u8>, label: &str) -> Result<RgbaImage, String> {
    match png_header(&bytes) {
        Some((bit_depth, color_type)) => decode_png_like_pil(&bytes, bit_depth, color_type, label),
        None => {
            let img = ImageSource::Encoded { label: label.to_string(), bytes: Arc::new(bytes) }.decode().map_err(|e| e.to_string())?;
            Ok(DynamicImage::ImageRgb8(img.to_rgb8()).to_rgba8())
        }
    }
}

/// `(bit depth, colour type)` from a PNG's IHDR (which the format requires to come first).
fn png_header(b: &[u8]) -> Option<(u8, u8)> {
    (b.len() >= 26 && b.starts_with(b"\x89PNG\r\n\x1a\n") && &b[12..16] == b"IHDR").then(|| (b[24], b[25]))
}

fn decode_png_like_pil(bytes: &[u8], bit_depth: u8, color_type: u8, label: &str) -> Result<RgbaImage, String> {
    let reader = image::ImageReader::with_format(std::io::Cursor::new(bytes), image::ImageFormat::Png);
    let img = decode_limited(reader, bytes.len() as u64)?;
    // Pillow's mode is "RGBA" for colour type 6 and, at 16 bits, for 4 (gray + alpha): only those composite.
    let rgba_mode = color_type == 6 || (color_type == 4 && bit_depth == 16);
    let alpha = |a: u8| if rgba_mode { a } else { 255 };
    let (w, h) = (img.width(), img.height());
    let out = match img {
        DynamicImage::ImageLuma8(g) => RgbaImage::from_fn(w, h, |x, y| gray(g.get_pixel(x, y)[0], 255)),
        DynamicImage::ImageLumaA8(g) => RgbaImage::from_fn(w, h, |x, y| {
            let p = g.get_pixel(x, y);
            gray(p[0], alpha(p[1]))
        }),
        DynamicImage::ImageRgb8(c) => RgbaImage::from_fn(w, h, |x, y| {
            let p = c.get_pixel(x, y);
            image::Rgba([p[0], p[1], p[2], 255])
        }),
        DynamicImage::ImageRgba8(c) => RgbaImage::from_fn(w, h, |x, y| {
            let p = c.get_pixel(x, y);
            image::Rgba([p[0], p[1], p[2], alpha(p[3])])
        }),
        // 16-bit gray (with or without tRNS) is Pillow's "I;16": `convert("RGB")` saturates at 255.
        DynamicImage::ImageLuma16(g) if color_type == 0 => {
            tracing::warn!(
                "{label} is a 16-bit grayscale PNG: like upstream (Pillow's \"I;16\" → RGB) its values saturate at 255, so it comes out mostly white"
            );
            RgbaImage::from_fn(w, h, |x, y| gray(g.get_pixel(x, y)[0].min(255) as u8, 255))
        }
        DynamicImage::ImageLumaA16(g) if color_type == 0 => {
            tracing::warn!(
                "{label} is a 16-bit grayscale PNG: like upstream (Pillow's \"I;16\" → RGB) its values saturate at 255, so it comes out mostly white"
            );
            RgbaImage::from_fn(w, h, |x, y| gray(g.get_pixel(x, y)[0].min(255) as u8, 255))
        }
        // Every other 16-bit PNG: Pillow's raw modes ("RGB;16B", "RGBA;16B", "LA;16B") keep the high byte.
        DynamicImage::ImageLumaA16(g) => RgbaImage::from_fn(w, h, |x, y| {
            let p = g.get_pixel(x, y);
            gray(hi(p[0]), alpha(hi(p[1])))
        }),
        DynamicImage::ImageRgb16(c) => RgbaImage::from_fn(w, h, |x, y| {
            let p = c.get_pixel(x, y);
            image::Rgba([hi(p[0]), hi(p[1]), hi(p[2]), 255])
        }),
        DynamicImage::ImageRgba16(c) => RgbaImage::from_fn(w, h, |x, y| {
            let p = c.get_pixel(x, y);
            image::Rgba([hi(p[0]), hi(p[1]), hi(p[2]), alpha(hi(p[3]))])
        }),
        other => return Err(format!("unexpected PNG pixel format {:?} (bit depth {bit_depth}, colour type {color_type})", other.color())),
    };
    Ok(out)
}

fn gray(v: u8, a: u8) -> image::Rgba<u8> {
    image::Rgba([v, v, v, a])
}

fn hi(v: u16) -> u8 {
    (v >> 8) as u8
}

/// Pillow's `Image.alpha_composite(white, src)` for one colour channel `c` with alpha `a`, the background
/// opaque white: its integer path (`AlphaComposite.c`, 7 extra bits of precision, `SHIFTFORDIV255` rounding)
/// reduces to this closed form, equal to Pillow for every `(c, a)` (the fixture holds Pillow's full table).
/// `a = 255` returns `c`, `a = 0` returns 255.
#[inline]
pub fn composite_over_white(c: u8, a: u8) -> u8 {
    let (c, a) = (c as u32, a as u32);
    let u = c * a + 255 * (255 - a) + 128;
    ((u + (u >> 8)) >> 8) as u8
}

/// Upstream's new size for a `width`×`height` image: `round(short·(518/long)/14)·14` with Python's `round`
/// (half to even), computed in `f64` in upstream's order. Returns (width, height); a side of 0 means the image
/// is too thin (Pillow refuses to resize to it). Sizes must be positive.
pub fn target_size(width: u32, height: u32, mode: PreprocessMode) -> (u32, u32) {
    // Saturating (`as` and `min`): only absurd aspect ratios (millions to one) come near the limit.
    let side = |other: u32, fixed: u32| {
        let patches = ((other as f64 * (TARGET_SIZE as f64 / fixed as f64)) / PATCH_SIZE as f64).round_ties_even() as u64;
        (patches * PATCH_SIZE as u64).min(u32::MAX as u64) as u32
    };
    match mode {
        PreprocessMode::Pad if width < height => (side(width, height), TARGET_SIZE),
        _ => (TARGET_SIZE, side(height, width)),
    }
}

/// One view after resize and its own crop/padding, as 8-bit levels (padding 255 ↔ 1.0).
struct View {
    planes: Vec<u8>,
    width: usize,
    height: usize,
    geometry: ViewGeometry,
}

fn resize_view(img: &RgbaImage, mode: PreprocessMode, what: impl Fn() -> String) -> Result<View, LoadError> {
    let (w, h) = img.dimensions();
    let (nw, nh) = if w == 0 || h == 0 { (0, 0) } else { target_size(w, h, mode) };
    if nw == 0 || nh == 0 {
        return Err(LoadError::TooThin { what: what(), width: w, height: h, mode, new_width: nw, new_height: nh });
    }
    // alpha_composite over white, then convert("RGB"), to planes.
    let n = (w * h) as usize;
    let mut src = vec![0u8; 3 * n];
    for (i, p) in img.pixels().enumerate() {
        for c in 0..3 {
            src[c * n + i] = if p[3] == 255 { p[c] } else { composite_over_white(p[c], p[3]) };
        }
    }
    let rows = match mode {
        PreprocessMode::Crop if nh > TARGET_SIZE => {
            let start = (nh - TARGET_SIZE) / 2;
            start..start + TARGET_SIZE
        }
        _ => 0..nh,
    };
    let resized = resize_pil_u8_rows(&src, 3, w, h, nw, nh, rows.clone(), PilFilter::Bicubic);
    let (rw, rh) = (nw as usize, rows.len());
    let geometry = ViewGeometry { original: (w, h), resized: (nw, nh), offset: (0, -(rows.start as i64)) };
    let view = View { planes: resized, width: rw, height: rh, geometry };
    Ok(match mode {
        PreprocessMode::Crop => view,
        PreprocessMode::Pad => pad_view(view, TARGET_SIZE as usize, TARGET_SIZE as usize),
    })
}

/// Upstream's `F.pad(img, (left, right, top, bottom), value=1.0)` with the floor half on top/left.
fn pad_view(v: View, height: usize, width: usize) -> View {
    if (v.height, v.width) == (height, width) {
        return v;
    }
    let (top, left) = ((height - v.height) / 2, (width - v.width) / 2);
    let mut planes = vec![255u8; 3 * height * width];
    for c in 0..3 {
        for y in 0..v.height {
            let src = &v.planes[(c * v.height + y) * v.width..][..v.width];
            planes[(c * height + top + y) * width + left..][..v.width].copy_from_slice(src);
        }
    }
    let (ox, oy) = v.geometry.offset;
    let geometry = ViewGeometry { offset: (ox + left as i64, oy + top as i64), ..v.geometry };
    View { planes, width, height, geometry }
}

fn assemble(views: Vec<View>) -> Preprocessed {
    let height = views.iter().map(|v| v.height).max().unwrap_or(0);
    let width = views.iter().map(|v| v.width).max().unwrap_or(0);
    if views.iter().any(|v| (v.height, v.width) != (height, width)) {
        let shapes: Vec<String> = views.iter().map(|v| format!("{}x{}", v.width, v.height)).collect();
        tracing::warn!("images of different shapes ({}): each is padded with white to {width}x{height}, as upstream does", shapes.join(", "));
    }
    let frames = views.len();
    let mut images = Vec::with_capacity(frames * 3 * height * width);
    let mut geometry = Vec::with_capacity(frames);
    for v in views {
        let v = pad_view(v, height, width);
        images.extend(v.planes.iter().map(|&p| p as f32 / 255.0));
        geometry.push(v.geometry);
    }
    Preprocessed { images, frames, height, width, views: geometry }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_round_half_to_even() {
        // 41·(518/74)/14 = 20.5 → 20; 43·7/14 = 21.5 → 22.
        assert_eq!(target_size(74, 41, PreprocessMode::Crop), (518, 280));
        assert_eq!(target_size(74, 43, PreprocessMode::Crop), (518, 308));
        assert_eq!(target_size(37, 90, PreprocessMode::Crop), (518, 1260));
        assert_eq!(target_size(37, 90, PreprocessMode::Pad), (210, 518));
        assert_eq!(target_size(50, 50, PreprocessMode::Pad), (518, 518));
        assert_eq!(target_size(1000, 10, PreprocessMode::Crop), (518, 0));
    }

    #[test]
    fn composite_ends() {
        for c in 0..=255u8 {
            assert_eq!(composite_over_white(c, 255), c);
            assert_eq!(composite_over_white(c, 0), 255);
        }
        assert_eq!(composite_over_white(0, 128), 127);
    }

    #[test]
    fn too_thin_is_an_error() {
        let img = RgbaImage::from_pixel(1000, 10, image::Rgba([0, 0, 0, 255]));
        let e = preprocess_rgba8(&[img], PreprocessMode::Crop).unwrap_err().to_string();
        assert!(e.contains("image 0") && e.contains("1000x10") && e.contains("518x0"), "{e}");
    }
}
