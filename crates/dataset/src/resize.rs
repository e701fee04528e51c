//! Image resizing exactly as the official loader does it (`rescale` in MVSplat360's
//! `src/dataset/shims/crop_shim.py`), bit for bit:
//!
//! ```python
//! image_new = (image * 255).clip(min=0, max=255).type(torch.uint8)   # 1. quantise
//! image_new = Image.fromarray(rearrange(image_new, "c h w -> h w c").numpy())
//! image_new = image_new.resize((w, h), Image.LANCZOS)                # 2. Pillow's 8-bit Lanczos
//! image_new = torch.tensor(np.array(image_new) / 255, dtype=image.dtype)   # 3. back to float32
//! ```
//!
//! 1. **Quantise** ([`quantize_like_torch`]): one float32 multiply by 255, clip to [0, 255], and C's float →
//!    `uint8` conversion, which *truncates* toward zero (it does not round). For an image decoded from 8 bits
//!    (`p / 255` in float32, as torchvision's `ToTensor` and [`ImageF32::from_rgb8`] compute it) this is
//!    lossless: `fl32(fl32(p / 255) · 255) == p` holds exactly for all 256 levels — no level falls a hair
//!    below `p` and truncates to `p − 1` (checked in `tests/pil_lanczos.rs`). It only bites on values off the
//!    1/255 grid (e.g. 0.999 → 254.745 → 254).
//! 2. **Resample** ([`resize_pil_lanczos_u8`]): Pillow's `ImagingResample` for 8-bit images
//!    (`src/libImaging/Resample.c`), reproduced at the integer level:
//!    - per axis, `scale = in / out`, `filterscale = max(scale, 1)`, `support = 3 · filterscale`; output pixel
//!      `i` is centred at `center = (i + 0.5) · scale` in input coordinates, its window is
//!      `xmin = max(0, (int)(center − support + 0.5))`, `xmax = min(in, (int)(center + support + 0.5))`
//!      (C casts: truncation toward zero), and its weights are
//!      `lanczos3((x − center + 0.5) / filterscale)` in `f64` (`sinc(x)·sinc(x/3)` on `[-3, 3)`), divided by
//!      their sum, then made integers with 22 fractional bits: `(int)(k · 2²² ± 0.5)` (rounding half away from
//!      zero);
//!    - each output sample is `clip8((1 << 21) + Σ src · k)`, `clip8(v) = clamp(v >> 22, 0, 255)`, in 32-bit
//!      integers — channels are independent, so planar processing gives the same numbers as Pillow's
//!      interleaved RGBX loop;
//!    - two passes through an 8-bit intermediate, each skipped when its size is unchanged (and no pass at
//!      all — a plain copy — when neither is). The order is Pillow 13's (`ImagingResampleInner`): vertical
//!      first when the height loses more than twice as many pixels as the width (`H − h > 0` and
//!      `H − h > 2·(W − w)`), horizontal first otherwise. Rounding to 8 bits between the passes makes the
//!      order visible (a level here and there). Older Pillows always ran horizontal first (12.2–12.3 made an
//!      exception only for images over 100× taller than wide), so results differ from those versions only
//!      where the rule picks vertical first: never for landscape photos scaled uniformly (`H − h = (1 − s)·H`
//!      is then below `2·(1 − s)·W`), only for portrait images over 2:1 or a much stronger height reduction.
//!      The fixture's Pillow version is in its metadata.
//! 3. **Back to float**: `q / 255` in `f64`, rounded to `f32` (for every level this equals the `f32` division).
//!
//! The same resampler serves VGGT's loader (`load_and_preprocess_images`, `Image.resize(..., BICUBIC)`):
//! [`resize_pil_u8`] takes the filter ([`PilFilter`]); only the kernel and its support differ, everything
//! above (windows, 22-bit weights, pass order, 8-bit intermediate) is shared, as it is in Pillow.
//!
//! Where the official code calls `rescale` with the image's own size (DL3DV's 480×270 frames at 480×270),
//! Pillow returns a copy, so only the (lossless) quantisation happens; callers may skip the call then.
//!
//! # Intrinsics: where our cameras and the official ones part
//! The pixels above are the official ones; the cameras are not. Ours follow the pixels exactly, with pixel
//! `(i, j)` centred at `(i + 0.5, j + 0.5)` (the convention Pillow's `center = (i + 0.5) · scale` also uses):
//! - [`Camera::rescaled`](mvsplat360_camera::Camera::rescaled) multiplies `fx, cx` by `W'/W` and `fy, cy` by
//!   `H'/H` (each axis its own factor, so the rounding of `W' = round(W·s)` is accounted for);
//! - [`Camera::cropped`](mvsplat360_camera::Camera::cropped) keeps `fx, fy` and moves the principal point
//!   with the origin: `cx' = cx − x0`, `cy' = cy − y0`.
//!
//! The official code keeps *normalised* intrinsics (`fx/W, fy/H, cx/W, cy/H`). Its resize leaves them
//! unchanged, which equals our `rescaled` exactly. Its `center_crop` (used for the crop to the target size and
//! again by the patch shim's crop to a multiple of 64) only multiplies the normalised `fx` by `w_in/w_out` and
//! `fy` by `h_in/h_out` and leaves the normalised `cx, cy` alone — right only for a principal point at the
//! image centre and an even crop margin. In pixels, with `col = (w_in − w_out) // 2`:
//! `ours − official = cx − col − cx·w_out/w_in = (cx − w_in/2)·(1 − w_out/w_in) + ((w_in − w_out)/2 − col)`:
//! an off-centre principal point moves by the first term, and an odd margin (the official comment's "odd input
//! dimensions induce half-pixel misalignments") adds half a pixel; the same holds for `cy` with rows.
//! (The patch shim asserts even sizes, so cropping in one step, as [`Camera::cropped`] after our single
//! plan does, lands on the same pixels as the official two steps.) Examples: DL3DV 480×270 → 448×256 has even
//! margins (32, 14), so only an off-centre principal point differs; 960×540 → 455×256 → 448×256 has margin 7
//! (`col = 3`), so a centred `cx = 227.5` becomes 224.5 here and 224 in the official code.
//!
//! [`Camera::cropped`]: mvsplat360_camera::Camera::cropped

use rayon::prelude::*;

use crate::ImageF32;

/// Pillow's `PRECISION_BITS` (`32 − 8 − 2`): fractional bits of the integer filter weights.
const PRECISION_BITS: u32 = 22;

/// A Pillow resampling filter (`Image.Resampling.*`) for [`resize_pil_u8`]: its kernel and support radius are
/// Pillow's (`src/libImaging/Resample.c`), evaluated in `f64` with the same operation order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PilFilter {
    /// `Image.LANCZOS`: `sinc(x)·sinc(x/3)` on `[-3, 3)`, support 3.
    Lanczos,
    /// `Image.BICUBIC`: Keys' cubic convolution with `a = −0.5`, support 2.
    Bicubic,
}

impl PilFilter {
    /// The kernel's support radius at scale 1 (Pillow's `filter.support`).
    pub fn support(self) -> f64 {
        match self {
            PilFilter::Lanczos => 3.0,
            PilFilter::Bicubic => 2.0,
        }
    }

    fn kernel(self, x: f64) -> f64 {
        match self {
            PilFilter::Lanczos => lanczos(x),
            PilFilter::Bicubic => bicubic(x),
        }
    }
}

/// `(v * 255).clip(0, 255).type(torch.uint8)` for one float32 value: float32 multiply, clamp, truncation
/// toward zero. (NaN, for which torch's cast is undefined, maps to 0.)
#[inline]
pub fn quantize_like_torch(v: f32) -> u8 {
    // `as u8` truncates toward zero (and saturates), as C's conversion does on the clipped value.
    (v * 255.0f32).clamp(0.0, 255.0) as u8
}

/// The official `rescale`: quantise to 8 bits as torch does, resize with Pillow's `Image.LANCZOS`, divide by
/// 255 (in `f64`, rounded to `f32`). Bit-exact against Pillow (see the module docs). Panics on an empty
/// input or output size (Pillow raises).
pub fn resize_pil_lanczos(img: &ImageF32, width: u32, height: u32) -> ImageF32 {
    let q: Vec<u8> = img.data.iter().map(|&v| quantize_like_torch(v)).collect();
    let out = resize_pil_lanczos_u8(&q, 3, img.width, img.height, width, height);
    let data = out.iter().map(|&p| (p as f64 / 255.0) as f32).collect();
    ImageF32 { width, height, data }
}

/// Pillow's `Image.resize((width, height), Image.LANCZOS)` of an 8-bit image held as `channels` planes of
/// `src_width`×`src_height` (layout C, H, W); returns the planes of the result. Bit-exact against Pillow 13
/// (earlier versions differ where [`vertical_pass_first`] holds, see the module docs). Panics on an empty size
/// or a buffer of the wrong length.
pub fn resize_pil_lanczos_u8(src: &[u8], channels: usize, src_width: u32, src_height: u32, width: u32, height: u32) -> Vec<u8> {
    resize_pil_u8(src, channels, src_width, src_height, width, height, PilFilter::Lanczos)
}

/// Pillow's `Image.resize((width, height), filter)` of an 8-bit image held as `channels` planes of
/// `src_width`×`src_height` (layout C, H, W); returns the planes of the result. Bit-exact against Pillow 13
/// (see the module docs for the pass order of earlier versions). Panics on an empty size or a buffer of the
/// wrong length.
pub fn resize_pil_u8(src: &[u8], channels: usize, src_width: u32, src_height: u32, width: u32, height: u32, filter: PilFilter) -> Vec<u8> {
    resize_pil_u8_rows(src, channels, src_width, src_height, width, height, 0..height, filter)
}

/// Rows `rows` of [`resize_pil_u8`]'s result (planes of `rows.len()`×`width`), computing only those: the
/// vertical pass's output rows are independent of each other, so this equals cropping the full result, bit
/// for bit, without its cost (a centre crop of a tall image). Panics as [`resize_pil_u8`] does, and on a row
/// range outside `0..height`.
#[allow(clippy::too_many_arguments)]
pub fn resize_pil_u8_rows(
    src: &[u8],
    channels: usize,
    src_width: u32,
    src_height: u32,
    width: u32,
    height: u32,
    rows: std::ops::Range<u32>,
    filter: PilFilter,
) -> Vec<u8> {
    let (w, h, ow, oh) = (src_width as usize, src_height as usize, width as usize, height as usize);
    assert!(w > 0 && h > 0 && ow > 0 && oh > 0, "resize {src_width}x{src_height} -> {width}x{height}: sizes must be positive");
    assert_eq!(src.len(), channels * w * h, "resize: buffer holds {} bytes, expected {channels}x{h}x{w}", src.len());
    assert!(rows.start <= rows.end && rows.end <= height, "resize: rows {rows:?} outside 0..{height}");
    let rows = rows.start as usize..rows.end as usize;
    let n = rows.len();
    match (ow != w, oh != h) {
        (false, false) => plane_rows(src, channels, w, h, rows).into_owned(),
        (true, false) => horizontal_pass(&plane_rows(src, channels, w, h, rows), channels * n, w, ow, filter),
        (false, true) => vertical_pass(src, channels, w, h, oh, rows, filter),
        (true, true) if vertical_pass_first(src_width, src_height, width, height) => {
            horizontal_pass(&vertical_pass(src, channels, w, h, oh, rows, filter), channels * n, w, ow, filter)
        }
        (true, true) => vertical_pass(&horizontal_pass(src, channels * h, w, ow, filter), channels, ow, h, oh, rows, filter),
    }
}

/// Rows `rows` of each of `channels` planes of `w`×`h` (borrowed when that is all of them).
fn plane_rows(src: &[u8], channels: usize, w: usize, h: usize, rows: std::ops::Range<usize>) -> std::borrow::Cow<'_, [u8]> {
    if rows == (0..h) {
        return src.into();
    }
    (0..channels).flat_map(|c| &src[(c * h + rows.start) * w..(c * h + rows.end) * w]).copied().collect::<Vec<u8>>().into()
}

/// Whether Pillow 13 runs the vertical pass first for a `src_width`×`src_height` → `width`×`height` resize:
/// "if height is being scaled down more than twice the amount the width is" (`H − h > 0 && H − h > (W − w)·2`,
/// in C `int`s). Pillow ≤ 12.1 always runs horizontal first.
pub fn vertical_pass_first(src_width: u32, src_height: u32, width: u32, height: u32) -> bool {
    let dh = src_height as i64 - height as i64;
    let dw = src_width as i64 - width as i64;
    dh > 0 && dh > dw * 2
}

/// Integer filter weights for one axis: output sample `i` reads `len[i]` inputs from `start[i]` with weights
/// `k[i * ksize ..][.. len[i]]` (Pillow's `precompute_coeffs` + `normalize_coeffs_8bpc`).
struct Coeffs {
    ksize: usize,
    start: Vec<usize>,
    len: Vec<usize>,
    k: Vec<i32>,
}

fn sinc(x: f64) -> f64 {
    if x == 0.0 {
        return 1.0;
    }
    let x = x * std::f64::consts::PI;
    x.sin() / x
}

fn lanczos(x: f64) -> f64 {
    if (-3.0..3.0).contains(&x) {
        sinc(x) * sinc(x / 3.0)
    } else {
        0.0
    }
}

/// Pillow's `bicubic_filter` (`a = −0.5`), with its expression order: `((a + 2)·x − (a + 3))·x·x + 1` inside
/// one pixel, `(((x − 5)·x + 8)·x − 4)·a` out to two.
fn bicubic(x: f64) -> f64 {
    const A: f64 = -0.5;
    let x = x.abs();
    if x < 1.0 {
        ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
    } else if x < 2.0 {
        (((x - 5.0) * x + 8.0) * x - 4.0) * A
    } else {
        0.0
    }
}

fn coeffs(in_size: usize, out_size: usize, filter: PilFilter) -> Coeffs {
    // Pillow passes the box as C floats; `in1 - in0` = `in_size` exactly (sizes < 2^24).
    let scale = in_size as f32 as f64 / out_size as f64;
    let filterscale = scale.max(1.0);
    let support = filter.support() * filterscale;
    let ksize = support.ceil() as usize * 2 + 1;
    let inv_filterscale = 1.0 / filterscale;
    let (mut start, mut len) = (Vec::with_capacity(out_size), Vec::with_capacity(out_size));
    let mut k = vec![0i32; out_size * ksize];
    let mut w = vec![0f64; ksize];
    for xx in 0..out_size {
        // `in0 + (xx + 0.5) * scale` with in0 = 0. C's `(int)` truncates toward zero; negative values are
        // clamped to 0 right after, as in Pillow.
        let center = (xx as f64 + 0.5) * scale;
        let xmin = ((center - support + 0.5) as i64).max(0);
        let xmax = ((center + support + 0.5) as i64).min(in_size as i64) - xmin;
        let n = xmax.max(0) as usize;
        let mut ww = 0.0;
        for (x, wx) in w[..n].iter_mut().enumerate() {
            *wx = filter.kernel(((x as i64 + xmin) as f64 - center + 0.5) * inv_filterscale);
            ww += *wx;
        }
        let row = &mut k[xx * ksize..xx * ksize + n];
        for (kx, &wx) in row.iter_mut().zip(&w[..n]) {
            let wx = if ww != 0.0 { wx / ww } else { wx };
            let f = wx * (1u32 << PRECISION_BITS) as f64;
            *kx = if wx < 0.0 { (-0.5 + f) as i32 } else { (0.5 + f) as i32 };
        }
        start.push(xmin as usize);
        len.push(n);
    }
    Coeffs { ksize, start, len, k }
}

/// Pillow's `clip8`: the accumulator's integer part, clamped to a byte.
#[inline]
fn clip8(acc: i32) -> u8 {
    (acc >> PRECISION_BITS).clamp(0, 255) as u8
}

/// The rounding offset every accumulator starts from.
const HALF: i32 = 1 << (PRECISION_BITS - 1);

/// Resample each of `rows` rows from `w` to `ow` samples.
fn horizontal_pass(src: &[u8], rows: usize, w: usize, ow: usize, filter: PilFilter) -> Vec<u8> {
    let c = coeffs(w, ow, filter);
    let mut out = vec![0u8; rows * ow];
    out.par_chunks_mut(ow).zip(src.par_chunks(w)).for_each(|(line_out, line_in)| {
        for (xx, o) in line_out.iter_mut().enumerate() {
            let (s, n) = (c.start[xx], c.len[xx]);
            let k = &c.k[xx * c.ksize..xx * c.ksize + n];
            // Integer sums are exact, so the order of terms does not matter; wrapping as C's `int` does in
            // practice (Pillow's two guard bits keep real sums far from overflow).
            let acc = line_in[s..s + n].iter().zip(k).fold(HALF, |a, (&p, &kx)| a.wrapping_add((p as i32).wrapping_mul(kx)));
            *o = clip8(acc);
        }
    });
    out
}

/// Resample each of `channels` planes of `w`×`h` to `w`×`oh`, keeping output rows `rows`.
fn vertical_pass(src: &[u8], channels: usize, w: usize, h: usize, oh: usize, rows: std::ops::Range<usize>, filter: PilFilter) -> Vec<u8> {
    let c = coeffs(h, oh, filter);
    let n = rows.len();
    let mut out = vec![0u8; channels * n * w];
    out.par_chunks_mut(w).enumerate().for_each_init(
        || vec![0i32; w],
        |acc, (i, line_out)| {
            let (plane, yy) = (i / n, rows.start + i % n);
            let (s, n) = (c.start[yy], c.len[yy]);
            let k = &c.k[yy * c.ksize..yy * c.ksize + n];
            acc.fill(HALF);
            for (y, &ky) in (s..s + n).zip(k) {
                let line_in = &src[(plane * h + y) * w..(plane * h + y + 1) * w];
                for (a, &p) in acc.iter_mut().zip(line_in) {
                    *a = a.wrapping_add((p as i32).wrapping_mul(ky));
                }
            }
            for (o, &a) in line_out.iter_mut().zip(acc.iter()) {
                *o = clip8(a);
            }
        },
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_sum_to_one_in_fixed_point() {
        // Normalised weights round to integers summing to 2^22 within a few units (one rounding each).
        for filter in [PilFilter::Lanczos, PilFilter::Bicubic] {
            for (i, o) in [(960, 455), (540, 256), (37, 80), (23, 1), (250, 31), (61, 518)] {
                let c = coeffs(i, o, filter);
                for xx in 0..o {
                    let s: i64 = c.k[xx * c.ksize..xx * c.ksize + c.len[xx]].iter().map(|&k| k as i64).sum();
                    assert!((s - (1 << PRECISION_BITS)).abs() <= c.len[xx] as i64, "{filter:?} {i}->{o} sample {xx}: {s}");
                    assert!(c.start[xx] + c.len[xx] <= i);
                }
            }
        }
    }

    #[test]
    fn pass_order_is_pillow_13s() {
        // Uniform downscales go vertical first only for images more than twice as tall as wide.
        assert!(!vertical_pass_first(960, 540, 455, 256));
        assert!(!vertical_pass_first(540, 960, 256, 455));
        assert!(vertical_pass_first(400, 1000, 200, 500));
        // The rule's tie (H − h = 2·(W − w)) stays horizontal first; upscaling the width with any height
        // reduction goes vertical first.
        assert!(!vertical_pass_first(37, 23, 28, 5) && vertical_pass_first(37, 23, 30, 5));
        assert!(vertical_pass_first(37, 23, 100, 22) && !vertical_pass_first(37, 23, 100, 23));
    }

    #[test]
    fn bicubic_kernel_is_keys_a_minus_half() {
        // Interpolating at the taps, a partition of unity, zero from 2 on.
        assert_eq!(bicubic(0.0), 1.0);
        assert_eq!(bicubic(1.0), 0.0);
        assert_eq!(bicubic(-2.0), 0.0);
        assert_eq!(bicubic(0.5), 0.5625);
        assert_eq!(bicubic(1.5), -0.0625);
        for t in [0.1, 0.25, 0.7] {
            let s: f64 = (-2..=2).map(|k| bicubic(t + k as f64)).sum();
            assert!((s - 1.0).abs() < 1e-12, "{t}: {s}");
        }
    }

    #[test]
    fn row_windows_equal_the_cropped_result() {
        let src: Vec<u8> = (0..3 * 23 * 9).map(|i| (i * 37 % 251) as u8).collect();
        // Vertical first, horizontal first, vertical only, horizontal only, copy.
        for (ow, oh) in [(40, 5), (40, 60), (9, 60), (40, 23), (9, 23)] {
            for filter in [PilFilter::Lanczos, PilFilter::Bicubic] {
                let full = resize_pil_u8(&src, 3, 9, 23, ow, oh, filter);
                let (a, b) = (oh as usize / 3, oh as usize - 1);
                let part = resize_pil_u8_rows(&src, 3, 9, 23, ow, oh, a as u32..b as u32, filter);
                let ow = ow as usize;
                let want: Vec<u8> = (0..3).flat_map(|c| &full[(c * oh as usize + a) * ow..(c * oh as usize + b) * ow]).copied().collect();
                assert_eq!(part, want, "{ow}x{oh} {filter:?}");
            }
        }
    }

    #[test]
    fn constant_and_identity() {
        let src = vec![77u8; 3 * 13 * 9];
        assert!(resize_pil_lanczos_u8(&src, 3, 13, 9, 5, 20).iter().all(|&p| p == 77));
        assert!(resize_pil_u8(&src, 3, 13, 9, 518, 294, PilFilter::Bicubic).iter().all(|&p| p == 77));
        let ramp: Vec<u8> = (0..3 * 13 * 9).map(|i| (i * 7 % 256) as u8).collect();
        assert_eq!(resize_pil_lanczos_u8(&ramp, 3, 13, 9, 13, 9), ramp);
        let img = ImageF32 { width: 13, height: 9, data: ramp.iter().map(|&p| p as f32 / 255.0).collect() };
        assert_eq!(resize_pil_lanczos(&img, 13, 9), img);
    }
}
