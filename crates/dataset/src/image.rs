//! Images: decoding (PNG/JPEG) to f32 CHW in [0,1], and the sources a scene's views come from.

use std::io::Read;
use std::path::PathBuf;
use std::sync::Arc;

use crate::DatasetError;

/// f32 image, layout (C=3, H, W), values in [0,1].
#[derive(Debug, Clone, PartialEq)]
pub struct ImageF32 {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

impl ImageF32 {
    /// Keep columns `x0..x0+w`, rows `y0..y0+h`.
    pub fn crop(&self, x0: u32, y0: u32, w: u32, h: u32) -> ImageF32 {
        let (sw, sh) = (self.width as usize, self.height as usize);
        let mut data = Vec::with_capacity(3 * (w * h) as usize);
        for c in 0..3 {
            for y in y0 as usize..(y0 + h) as usize {
                let row = c * sh * sw + y * sw;
                data.extend_from_slice(&self.data[row + x0 as usize..row + (x0 + w) as usize]);
            }
        }
        ImageF32 { width: w, height: h, data }
    }

    /// Bilinear resize with pixel centres aligned (PyTorch's `align_corners=False`, no antialiasing).
    pub fn resize_bilinear(&self, w: u32, h: u32) -> ImageF32 {
        let (sw, sh) = (self.width as usize, self.height as usize);
        let (w, h) = (w as usize, h as usize);
        let mut data = vec![0f32; 3 * w * h];
        let (rx, ry) = (sw as f32 / w as f32, sh as f32 / h as f32);
        for y in 0..h {
            let fy = ((y as f32 + 0.5) * ry - 0.5).clamp(0.0, (sh - 1) as f32);
            let (y0, ty) = (fy.floor() as usize, fy - fy.floor());
            let y1 = (y0 + 1).min(sh - 1);
            for x in 0..w {
                let fx = ((x as f32 + 0.5) * rx - 0.5).clamp(0.0, (sw - 1) as f32);
                let (x0, tx) = (fx.floor() as usize, fx - fx.floor());
                let x1 = (x0 + 1).min(sw - 1);
                for c in 0..3 {
                    let p = |yy: usize, xx: usize| self.data[(c * sh + yy) * sw + xx];
                    let top = p(y0, x0) * (1.0 - tx) + p(y0, x1) * tx;
                    let bot = p(y1, x0) * (1.0 - tx) + p(y1, x1) * tx;
                    data[(c * h + y) * w + x] = top * (1.0 - ty) + bot * ty;
                }
            }
        }
        ImageF32 { width: w as u32, height: h as u32, data }
    }

    /// To 8-bit RGB as the official code saves images (`(x.clip(0, 1) * 255).type(torch.uint8)`: f32 product,
    /// truncated toward zero), so that every PNG written here holds the levels the official scripts would score.
    /// Decoded 8-bit images come back unchanged (`p/255·255` truncates to `p` for every level in f32).
    pub fn to_rgb8(&self) -> ::image::RgbImage {
        let (w, h) = (self.width as usize, self.height as usize);
        ::image::RgbImage::from_fn(self.width, self.height, |x, y| {
            let i = y as usize * w + x as usize;
            let px = |c: usize| (self.data[c * w * h + i].clamp(0.0, 1.0) * 255.0) as u8;
            ::image::Rgb([px(0), px(1), px(2)])
        })
    }

    pub fn from_rgb8(img: &::image::RgbImage) -> ImageF32 {
        let (w, h) = (img.width() as usize, img.height() as usize);
        let mut data = vec![0f32; 3 * w * h];
        for (x, y, p) in img.enumerate_pixels() {
            let i = y as usize * w + x as usize;
            for c in 0..3 {
                data[c * w * h + i] = p[c] as f32 / 255.0;
            }
        }
        ImageF32 { width: w as u32, height: h as u32, data }
    }
}

/// Where a view's pixels live; decoding is deferred so large scenes cost no memory until used.
#[derive(Debug, Clone)]
pub enum ImageSource {
    File(PathBuf),
    /// Encoded PNG/JPEG bytes (from a `.torch` chunk), with a label for error messages.
    Encoded {
        label: String,
        bytes: Arc<Vec<u8>>,
    },
}

impl ImageSource {
    pub fn label(&self) -> String {
        match self {
            ImageSource::File(p) => p.display().to_string(),
            ImageSource::Encoded { label, .. } => label.clone(),
        }
    }

    /// Image size from the header only.
    pub fn dimensions(&self) -> Result<(u32, u32), DatasetError> {
        let err = |msg: String| DatasetError::Image { what: self.label(), msg };
        match self {
            ImageSource::File(p) => ::image::image_dimensions(p).map_err(|e| err(e.to_string())),
            ImageSource::Encoded { bytes, .. } => ::image::ImageReader::new(std::io::Cursor::new(bytes.as_slice()))
                .with_guessed_format()
                .map_err(|e| err(e.to_string()))?
                .into_dimensions()
                .map_err(|e| err(e.to_string())),
        }
    }

    pub fn decode(&self) -> Result<ImageF32, DatasetError> {
        let err = |msg: String| DatasetError::Image { what: self.label(), msg };
        let file_bytes;
        let bytes: &[u8] = match self {
            ImageSource::File(p) => {
                file_bytes = std::fs::read(p).map_err(|e| err(e.to_string()))?;
                &file_bytes
            }
            ImageSource::Encoded { bytes, .. } => bytes.as_slice(),
        };
        if bytes.is_empty() {
            return Err(err("the file is empty".into()));
        }
        let reader = ::image::ImageReader::new(std::io::Cursor::new(bytes)).with_guessed_format().map_err(|e| err(e.to_string()))?;
        if reader.format() == Some(::image::ImageFormat::Jpeg) && !jpeg_complete(bytes) {
            // The JPEG decoder fills a cut-off scan with grey instead of failing.
            return Err(err("the JPEG is truncated (no end-of-image marker after its last scan)".into()));
        }
        let dynimg = decode_limited(reader, bytes.len() as u64).map_err(err)?;
        // Alpha is dropped: scenes are composited photos, not masked objects.
        Ok(ImageF32::from_rgb8(&dynimg.to_rgb8()))
    }
}

/// The longest side a reader accepts (DL3DV's 4K frames and a 48 MP phone photo are well inside).
pub const MAX_SIDE: u32 = 16384;
/// Decoded bytes per byte of the file at most: deflate reaches 1032:1 and a 1-bit palette adds 32×, a progressive
/// JPEG's DC-only scans ≈ 4096:1. A file claiming more is truncated or crafted.
const MAX_RATIO: u64 = 1 << 15;

/// The decoders' limits, set explicitly (not `image`'s defaults, which may change): [`MAX_SIDE`] a side, 1 GiB of
/// decoded pixels.
pub fn decode_limits() -> ::image::Limits {
    let mut l = ::image::Limits::default();
    l.max_image_width = Some(MAX_SIDE);
    l.max_image_height = Some(MAX_SIDE);
    l.max_alloc = Some(1 << 30);
    l
}

/// A limited decoder for `reader`, refusing (before it allocates) an image whose claimed size a file of
/// `file_len` bytes could not hold.
pub fn limited_decoder<'a, R: std::io::BufRead + std::io::Seek + 'a>(
    mut reader: ::image::ImageReader<R>,
    file_len: u64,
) -> Result<impl ::image::ImageDecoder + 'a, String> {
    reader.limits(decode_limits());
    let dec = reader.into_decoder().map_err(limit_msg)?;
    let (w, h) = ::image::ImageDecoder::dimensions(&dec);
    let need = ::image::ImageDecoder::total_bytes(&dec);
    if need > MAX_RATIO.saturating_mul(file_len).saturating_add(1 << 20) {
        return Err(format!(
            "the header claims {w}x{h} pixels ({need} bytes decoded), more than a file of {file_len} bytes can hold: it is truncated or not a real image"
        ));
    }
    Ok(dec)
}

/// [`limited_decoder`], decoded.
pub fn decode_limited<R: std::io::BufRead + std::io::Seek>(reader: ::image::ImageReader<R>, file_len: u64) -> Result<::image::DynamicImage, String> {
    ::image::DynamicImage::from_decoder(limited_decoder(reader, file_len)?).map_err(limit_msg)
}

fn limit_msg(e: ::image::ImageError) -> String {
    match e {
        ::image::ImageError::Limits(l) => format!("{l}: this reader takes at most {MAX_SIDE} pixels a side and 1 GiB of pixels; scale the image down first"),
        e => e.to_string(),
    }
}

impl ImageSource {
    /// The EXIF orientation (1–8) of a JPEG, from its header only (the first 128 KiB of a file: the EXIF
    /// segment sits before the image data and holds at most 64 KiB). `None`: not a JPEG, no EXIF or no tag.
    pub fn exif_orientation(&self) -> Option<u16> {
        match self {
            ImageSource::File(p) => {
                let mut f = std::fs::File::open(p).ok()?.take(128 << 10);
                let mut head = vec![0u8; 2];
                f.read_exact(&mut head).ok()?;
                // Only a JPEG is read further (PNGs cost two bytes).
                if head != [0xFF, 0xD8] {
                    return None;
                }
                f.read_to_end(&mut head).ok()?;
                jpeg_exif_orientation(&head)
            }
            ImageSource::Encoded { bytes, .. } => jpeg_exif_orientation(bytes),
        }
    }
}

/// The orientation tag of a JPEG's EXIF segment (APP1 `Exif\0\0`), walking the marker segments up to the
/// first scan; the TIFF structure inside is parsed by `image`'s own EXIF reader.
pub fn jpeg_exif_orientation(b: &[u8]) -> Option<u16> {
    if !b.starts_with(&[0xFF, 0xD8]) {
        return None;
    }
    let mut i = 2;
    while i + 4 <= b.len() {
        if b[i] != 0xFF {
            return None;
        }
        let marker = b[i + 1];
        match marker {
            0xFF => i += 1,
            0x01 | 0xD0..=0xD8 => i += 2,
            0xD9 | 0xDA => return None,
            _ => {
                let len = u16::from_be_bytes([b[i + 2], b[i + 3]]) as usize;
                if len < 2 {
                    return None;
                }
                let seg = b.get(i + 4..i + 2 + len)?;
                if marker == 0xE1 && seg.starts_with(b"Exif\0\0") {
                    return ::image::metadata::Orientation::from_exif_chunk(&seg[6..]).map(|o| o.to_exif() as u16);
                }
                i += 2 + len;
            }
        }
    }
    None
}

/// Whether a JPEG stream ends its last scan with an end-of-image marker. Inside entropy-coded data 0xFF is
/// always followed by 0x00 or a restart marker, so the last SOS (FFDA) must be followed by an EOI (FFD9);
/// comparing the last of each also works when an EXIF thumbnail carries its own markers earlier on.
fn jpeg_complete(b: &[u8]) -> bool {
    let last = |m: u8| b.windows(2).rposition(|w| w[0] == 0xFF && w[1] == m);
    match (last(0xDA), last(0xD9)) {
        (Some(sos), Some(eoi)) => eoi > sos,
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rgb8_roundtrip_and_crop() {
        let img = ::image::RgbImage::from_fn(5, 4, |x, y| ::image::Rgb([(x * 50) as u8, (y * 60) as u8, 7]));
        let f = ImageF32::from_rgb8(&img);
        assert_eq!(f.data.len(), 60);
        assert_eq!(f.data[3], 150.0 / 255.0); // channel 0, row 0, x 3
        assert_eq!(f.to_rgb8(), img);
        let c = f.crop(1, 2, 3, 2);
        assert_eq!((c.width, c.height), (3, 2));
        assert_eq!(c.to_rgb8().get_pixel(0, 0), img.get_pixel(1, 2));
        assert_eq!(c.to_rgb8().get_pixel(2, 1), img.get_pixel(3, 3));
    }

    #[test]
    fn rgb8_truncates_as_the_official_save_image() {
        // Every 8-bit level survives decode → save; a fraction of a level is cut, never rounded up; outside
        // [0, 1] clamps.
        let levels: Vec<f32> = (0..=255).map(|p| p as f32 / 255.0).collect();
        let mut data = Vec::new();
        for c in 0..3 {
            data.extend(levels.iter().map(|&v| if c == 0 { v } else { (v + 0.7 / 255.0).min(1.0) }));
        }
        let img = ImageF32 { width: 256, height: 1, data }.to_rgb8();
        for p in 0..=255u32 {
            let px = img.get_pixel(p, 0);
            assert_eq!(px[0] as u32, p, "level {p}");
            assert_eq!(px[1] as u32, p, "level {p} + 0.7 truncates to {p}");
        }
        let edge = ImageF32 { width: 1, height: 1, data: vec![-0.2, 1.5, 0.999] }.to_rgb8();
        assert_eq!(edge.get_pixel(0, 0).0, [0, 255, 254]);
    }

    #[test]
    fn bilinear_resize_closed_form() {
        // A horizontal ramp v = x/7 on 8 columns halved to 4: output pixel x samples source x' = 2x + 0.5,
        // so the ramp value is (2x + 0.5)/7 exactly (interior, no clamping).
        let data: Vec<f32> = (0..3).flat_map(|_| (0..2).flat_map(|_| (0..8).map(|x| x as f32 / 7.0))).collect();
        let img = ImageF32 { width: 8, height: 2, data };
        let r = img.resize_bilinear(4, 1);
        for x in 0..4 {
            assert!((r.data[x] - (2.0 * x as f32 + 0.5) / 7.0).abs() < 1e-6);
        }
        assert_eq!(img.resize_bilinear(8, 2), img);
    }
}

#[cfg(test)]
mod jpeg_tests {
    use super::*;

    fn jpeg() -> Vec<u8> {
        let img = ::image::RgbImage::from_fn(32, 24, |x, y| ::image::Rgb([(x * 7) as u8, (y * 9) as u8, 100]));
        let mut buf = std::io::Cursor::new(Vec::new());
        img.write_to(&mut buf, ::image::ImageFormat::Jpeg).unwrap();
        buf.into_inner()
    }

    #[test]
    fn truncated_and_empty_jpegs_are_refused() {
        let full = jpeg();
        let src = |b: Vec<u8>| ImageSource::Encoded { label: "v".into(), bytes: Arc::new(b) };
        assert!(src(full.clone()).decode().is_ok());
        for cut in [full.len() - 2, full.len() * 2 / 3, full.len() / 3] {
            let e = src(full[..cut].to_vec()).decode().unwrap_err().to_string();
            assert!(e.contains("truncated") || e.contains("cannot decode"), "{cut}: {e}");
        }
        assert!(src(vec![]).decode().unwrap_err().to_string().contains("empty"));
        // Trailing bytes after the end marker are harmless.
        let mut padded = full.clone();
        padded.extend_from_slice(&[0, 0, 0]);
        assert!(src(padded).decode().is_ok());
    }
}
