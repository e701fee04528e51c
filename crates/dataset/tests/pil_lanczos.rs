//! `resize_pil_lanczos` against Pillow itself: `tests/fixtures/pil_lanczos.safetensors` holds small images
//! resized by Pillow's `Image.resize(..., Image.LANCZOS)` and the official `rescale` of a float32 image
//! (written by `scripts/fixtures/pil_lanczos.py`; its metadata names the Pillow version). The bound is
//! **exact equality**: every 8-bit level, and every f32 bit of the official path's output.

use mvsplat360_dataset::resize::{quantize_like_torch, resize_pil_lanczos, resize_pil_lanczos_u8};
use mvsplat360_dataset::ImageF32;
use safetensors::{Dtype, SafeTensors};

fn fixture() -> Vec<u8> {
    std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/pil_lanczos.safetensors")).unwrap()
}

/// (H, W, 3) u8 tensor → planar (3, H, W) and its (width, height).
fn planes(st: &SafeTensors, name: &str) -> (Vec<u8>, u32, u32) {
    let t = st.tensor(name).unwrap();
    assert_eq!(t.dtype(), Dtype::U8, "{name}");
    let (h, w) = (t.shape()[0], t.shape()[1]);
    assert_eq!(t.shape()[2], 3);
    let d = t.data();
    let mut p = vec![0u8; 3 * h * w];
    for i in 0..h * w {
        for c in 0..3 {
            p[c * h * w + i] = d[i * 3 + c];
        }
    }
    (p, w as u32, h as u32)
}

fn f32s(st: &SafeTensors, name: &str) -> (Vec<f32>, Vec<usize>) {
    let t = st.tensor(name).unwrap();
    assert_eq!(t.dtype(), Dtype::F32, "{name}");
    (t.data().chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect(), t.shape().to_vec())
}

/// Describe the differences between two planar images (for the failure message).
fn diff_report(ours: &[u8], pil: &[u8], w: usize, h: usize) -> String {
    let bad: Vec<usize> = (0..ours.len()).filter(|&i| ours[i] != pil[i]).collect();
    let max = bad.iter().map(|&i| (ours[i] as i32 - pil[i] as i32).abs()).max().unwrap_or(0);
    let first: Vec<String> =
        bad.iter().take(8).map(|&i| format!("(c{} y{} x{}: ours {} pil {})", i / (w * h), i % (w * h) / w, i % w, ours[i], pil[i])).collect();
    format!("{} of {} samples differ (max {} levels): {}", bad.len(), ours.len(), max, first.join(" "))
}

#[test]
fn u8_levels_equal_pillow() {
    let bytes = fixture();
    let (_, meta) = SafeTensors::read_metadata(&bytes).unwrap();
    let meta = meta.metadata().clone().unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let cases: Vec<(String, u32, u32)> = serde_json::from_str(&meta["cases"]).unwrap();
    assert!(cases.len() >= 20);
    let mut failures = Vec::new();
    for (name, ow, oh) in &cases {
        let (src, w, h) = planes(&st, &format!("{name}.src"));
        let (pil, pw, ph) = planes(&st, &format!("{name}.{ow}x{oh}"));
        assert_eq!((pw, ph), (*ow, *oh));
        let ours = resize_pil_lanczos_u8(&src, 3, w, h, *ow, *oh);
        if ours != pil {
            failures.push(format!("{name} {w}x{h} -> {ow}x{oh}: {}", diff_report(&ours, &pil, *ow as usize, *oh as usize)));
        }
        // The f32 entry point (image decoded as u8 / 255, as torchvision and `ImageF32::from_rgb8` do) gives
        // exactly the levels / 255.
        let img = ImageF32 { width: w, height: h, data: src.iter().map(|&p| p as f32 / 255.0).collect() };
        let out = resize_pil_lanczos(&img, *ow, *oh);
        assert_eq!((out.width, out.height), (*ow, *oh));
        let want: Vec<f32> = pil.iter().map(|&p| (p as f64 / 255.0) as f32).collect();
        if out.data != want {
            failures.push(format!("{name} -> {ow}x{oh}: the f32 path differs from the u8 path"));
        }
    }
    assert!(failures.is_empty(), "Pillow {} disagrees:\n{}", meta["pillow"], failures.join("\n"));
}

#[test]
fn official_rescale_of_off_grid_floats_is_bit_exact() {
    let bytes = fixture();
    let (_, meta) = SafeTensors::read_metadata(&bytes).unwrap();
    let meta = meta.metadata().clone().unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (src, shape) = f32s(&st, "f32.src");
    assert_eq!(shape[0], 3);
    // The fixture holds values the quantisation must truncate (254.99/255 → 254) and clip.
    assert!(src.iter().any(|&v| v < 0.0) && src.iter().any(|&v| v > 1.0));
    let img = ImageF32 { width: shape[2] as u32, height: shape[1] as u32, data: src };
    let targets: Vec<(u32, u32)> = serde_json::from_str(&meta["f32_cases"]).unwrap();
    assert!(targets.contains(&(img.width, img.height)), "the identity (quantise-only) case is covered");
    for (w, h) in targets {
        let (want, wshape) = f32s(&st, &format!("f32.{w}x{h}"));
        assert_eq!(wshape, [3, h as usize, w as usize]);
        let out = resize_pil_lanczos(&img, w, h);
        let bad = out.data.iter().zip(&want).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        assert_eq!(bad, 0, "{w}x{h}: {bad} of {} values differ from the official rescale", want.len());
    }
}

#[test]
fn quantisation_matches_torch_truncation_on_all_levels() {
    for p in 0u8..=255 {
        // Decoded as float32 p / 255 (torchvision's ToTensor), times 255 in float32: no level lands below p,
        // so truncation never loses one (fl32(fl32(p/255)·255) == p exactly, for every p).
        let v = p as f32 / 255.0;
        assert_eq!(v * 255.0, p as f32, "level {p}: fl32(fl32(p/255)*255) = {}", v * 255.0);
        assert_eq!(quantize_like_torch(v), p);
        // The way back (`np.array(...) / 255` in float64, then float32) is the same number as the f32 division.
        assert_eq!((p as f64 / 255.0) as f32, v);
        // One ulp below the level truncates to the level below: the rule is truncation, not rounding.
        if p > 0 {
            let below = f32::from_bits((p as f32).to_bits() - 1) / 255.0;
            assert_eq!(quantize_like_torch(below), if below * 255.0 < p as f32 { p - 1 } else { p });
        }
    }
    assert_eq!(quantize_like_torch(0.5), 127); // 127.5 truncates
    assert_eq!(quantize_like_torch(254.99 / 255.0), 254);
    assert_eq!(quantize_like_torch(0.999_999), 254);
    assert_eq!(quantize_like_torch(-0.1), 0);
    assert_eq!(quantize_like_torch(1.2), 255);
    assert_eq!(quantize_like_torch(f32::NAN), 0);
}
