//! `load_and_preprocess_images` against the official function: `tests/fixtures/preprocess/` (written by
//! `scripts/fixtures/official_vggt_preprocess.py`, see its README) holds small PNG/JPEG inputs and the official
//! outputs of several lists in both modes. The bound is **exact equality** of every `f32` for every PNG case;
//! the JPEG case is exact given Pillow's decoded pixels and within a stated bound from the file (the decoders
//! differ).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use mvsplat360_vggt::utils::load_fn::{
    composite_over_white, load_and_preprocess_images, preprocess_rgba8, LoadError, PreprocessMode, Preprocessed, ViewGeometry,
};
use serde_json::Value;

fn dir() -> PathBuf {
    let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/preprocess");
    assert!(d.join("official.safetensors").is_file(), "fixture missing: {} (run scripts/fixtures/official_vggt_preprocess.py)", d.display());
    d
}

/// A safetensors file's metadata and its U8 tensors (shape, bytes); read by hand (the header is JSON).
struct Fixture {
    meta: HashMap<String, String>,
    tensors: HashMap<String, (Vec<usize>, Vec<u8>)>,
}

fn fixture() -> Fixture {
    let bytes = std::fs::read(dir().join("official.safetensors")).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Map<String, Value> = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let data = &bytes[8 + n..];
    let mut meta = HashMap::new();
    let mut tensors = HashMap::new();
    for (k, v) in header {
        if k == "__metadata__" {
            meta = v.as_object().unwrap().iter().map(|(k, v)| (k.clone(), v.as_str().unwrap().to_string())).collect();
            continue;
        }
        assert_eq!(v["dtype"], "U8", "{k}");
        let shape = v["shape"].as_array().unwrap().iter().map(|d| d.as_u64().unwrap() as usize).collect();
        let off = v["data_offsets"].as_array().unwrap();
        let (a, b) = (off[0].as_u64().unwrap() as usize, off[1].as_u64().unwrap() as usize);
        tensors.insert(k, (shape, data[a..b].to_vec()));
    }
    Fixture { meta, tensors }
}

struct Case {
    name: String,
    mode: PreprocessMode,
    inputs: Vec<String>,
    shape: [usize; 4],
    /// The official output as 8-bit levels (S × 3 × H × W).
    levels: Vec<u8>,
}

fn cases(fx: &Fixture) -> Vec<Case> {
    let cases: Vec<Value> = serde_json::from_str(&fx.meta["cases"]).unwrap();
    cases
        .iter()
        .map(|c| {
            let shape: Vec<usize> = c["shape"].as_array().unwrap().iter().map(|d| d.as_u64().unwrap() as usize).collect();
            let [s, ch, h, w] = shape[..] else { panic!("shape {shape:?}") };
            assert_eq!(ch, 3);
            let mut levels = vec![255u8; s * 3 * h * w];
            for (i, f) in c["frames"].as_array().unwrap().iter().enumerate() {
                let f = f.as_array().unwrap();
                let [top, bottom, left, right] = [1, 2, 3, 4].map(|k| f[k].as_u64().unwrap() as usize);
                let (ch_, cw) = (h - top - bottom, w - left - right);
                if ch_ == 0 || cw == 0 {
                    continue;
                }
                let core = image::open(dir().join("official").join(f[0].as_str().unwrap())).unwrap().to_rgb8();
                assert_eq!(core.dimensions(), (cw as u32, ch_ as u32));
                for (x, y, p) in core.enumerate_pixels() {
                    for k in 0..3 {
                        levels[((i * 3 + k) * h + top + y as usize) * w + left + x as usize] = p[k];
                    }
                }
            }
            let mode = match c["mode"].as_str().unwrap() {
                "crop" => PreprocessMode::Crop,
                "pad" => PreprocessMode::Pad,
                m => panic!("mode {m}"),
            };
            let inputs = c["inputs"].as_array().unwrap().iter().map(|p| p.as_str().unwrap().to_string()).collect();
            Case { name: c["name"].as_str().unwrap().to_string(), mode, inputs, shape: [s, 3, h, w], levels }
        })
        .collect()
}

/// `None` when every value equals `level / 255` bit for bit; otherwise a description of the differences.
fn compare(ours: &Preprocessed, case: &Case) -> Option<String> {
    let [s, _, h, w] = case.shape;
    if [ours.frames, 3, ours.height, ours.width] != case.shape {
        return Some(format!("shape {:?}, official {:?}", [ours.frames, 3, ours.height, ours.width], case.shape));
    }
    let want = |i: usize| case.levels[i] as f32 / 255.0;
    let bad: Vec<usize> = (0..ours.images.len()).filter(|&i| ours.images[i].to_bits() != want(i).to_bits()).collect();
    if bad.is_empty() {
        return None;
    }
    let level = |v: f32| (v * 255.0).round() as i32;
    let max = bad.iter().map(|&i| (level(ours.images[i]) - case.levels[i] as i32).abs()).max().unwrap();
    let first: Vec<String> = bad
        .iter()
        .take(6)
        .map(|&i| format!("(f{} c{} y{} x{}: ours {} official {})", i / (3 * h * w), i / (h * w) % 3, i / w % h, i % w, level(ours.images[i]), case.levels[i]))
        .collect();
    Some(format!("{} of {} values differ (max {max} levels; S={s}): {}", bad.len(), ours.images.len(), first.join(" ")))
}

fn paths(case: &Case) -> Vec<PathBuf> {
    case.inputs.iter().map(|f| dir().join("inputs").join(f)).collect()
}

#[test]
fn png_cases_equal_the_official_output_bit_for_bit() {
    let fx = fixture();
    let cases = cases(&fx);
    assert!(cases.len() >= 10);
    let mut failures = Vec::new();
    let mut checked = 0;
    for case in cases.iter().filter(|c| c.inputs.iter().all(|f| f.ends_with(".png"))) {
        let ours = load_and_preprocess_images(&paths(case), case.mode).unwrap_or_else(|e| panic!("{}: {e}", case.name));
        if let Some(d) = compare(&ours, case) {
            failures.push(format!("{} ({}, {:?}): {d}", case.name, case.mode, case.inputs));
        }
        checked += 1;
    }
    assert!(checked >= 10);
    assert!(failures.is_empty(), "Pillow {} / torch {} disagree:\n{}", fx.meta["pillow"], fx.meta["torch"], failures.join("\n"));
}

#[test]
fn jpeg_is_exact_from_pillows_pixels_and_close_from_the_file() {
    let fx = fixture();
    let cases = cases(&fx);
    let case = cases.iter().find(|c| c.name == "jpeg_crop").expect("jpeg_crop case");
    // Everything after the decoder is exact: Pillow's decoded pixels give the official output.
    let (shape, rgb) = &fx.tensors["jpeg.pil_rgb"];
    let pil = image::RgbImage::from_raw(shape[1] as u32, shape[0] as u32, rgb.clone()).unwrap();
    let ours = preprocess_rgba8(&[image::DynamicImage::ImageRgb8(pil.clone()).to_rgba8()], case.mode).unwrap();
    assert_eq!(compare(&ours, case), None, "from Pillow's decoded pixels");
    // From the file, the `image` crate's decoder (zune-jpeg) and Pillow's libjpeg-turbo differ by a few levels
    // (measured here: ≤ 3 in the decoded pixels, ≤ 4 after the bicubic upscale, whose negative lobes amplify a
    // little); the bound is that measurement, so a decoder change shows up here.
    let ours_decoded = image::open(&paths(case)[0]).unwrap().to_rgb8();
    let decode: Vec<i32> = ours_decoded.as_raw().iter().zip(pil.as_raw()).map(|(&a, &b)| (a as i32 - b as i32).abs()).collect();
    let ours = load_and_preprocess_images(&paths(case), case.mode).unwrap();
    let out: Vec<i32> = ours.images.iter().zip(&case.levels).map(|(&v, &l)| ((v * 255.0).round() as i32 - l as i32).abs()).collect();
    let summary = |d: &[i32]| {
        let n = d.iter().filter(|&&x| x > 0).count();
        let mean = d.iter().map(|&x| x as f64).sum::<f64>() / d.len() as f64;
        (*d.iter().max().unwrap(), format!("{n} of {} values differ, by at most {} levels (mean {mean:.3})", d.len(), d.iter().max().unwrap()))
    };
    let ((dmax, dmsg), (omax, omsg)) = (summary(&decode), summary(&out));
    eprintln!("JPEG decoded pixels: {dmsg}; preprocessed: {omsg}");
    assert!(dmax <= 3 && omax <= 4, "the JPEG decoders differ more than measured before: decoded {dmsg}; preprocessed {omsg}");
}

#[test]
fn alpha_composite_equals_pillow_for_every_level_and_alpha() {
    let fx = fixture();
    let (shape, table) = &fx.tensors["alpha_composite"];
    assert_eq!(shape, &vec![256, 256]);
    for c in 0..=255u8 {
        for a in 0..=255u8 {
            assert_eq!(composite_over_white(c, a), table[c as usize * 256 + a as usize], "c {c} a {a}");
        }
    }
}

#[test]
fn geometry_of_crop_pad_and_batch_padding() {
    let d = dir().join("inputs");
    let p = |f: &str| d.join(f);
    // Crop: the portrait is resized to 518x1260 and rows 371.. kept; the landscape (308 rows) is padded to the
    // batch's 518 with 105 white rows on top.
    let out = load_and_preprocess_images(&[p("rgb_61x37.png"), p("rgb_37x90.png")], PreprocessMode::Crop).unwrap();
    assert_eq!((out.frames, out.height, out.width), (2, 518, 518));
    assert_eq!(out.views[0], ViewGeometry { original: (61, 37), resized: (518, 308), offset: (0, 105) });
    assert_eq!(out.views[1], ViewGeometry { original: (37, 90), resized: (518, 1260), offset: (0, -371) });
    assert!(out.frame(0)[..105 * 518].iter().all(|&v| v == 1.0));
    // Pad: the portrait becomes 210x518 with 154 white columns each side.
    let out = load_and_preprocess_images(&[p("rgb_37x90.png")], PreprocessMode::Pad).unwrap();
    assert_eq!(out.views[0], ViewGeometry { original: (37, 90), resized: (210, 518), offset: (154, 0) });
    assert_eq!(out.to_tensor(&candle_core::Device::Cpu).unwrap().dims(), &[1, 3, 518, 518]);
}

#[test]
fn intrinsics_map_back_to_the_original_photo() {
    // 37x90 in crop mode: 518x1260 (both axes ×14), rows 371..889 kept. A centred camera in the model's frame
    // (principal point (259, 259)) is the centred camera of the photo: ((259 − 0)/14, (259 + 371)/14) =
    // (18.5, 45) = (37/2, 90/2); focal lengths scale by 1/14.
    let g = ViewGeometry { original: (37, 90), resized: (518, 1260), offset: (0, -371) };
    let k = [[700.0, 0.0, 259.0], [0.0, 700.0, 259.0], [0.0, 0.0, 1.0]];
    let ko = g.intrinsics_to_original(&k);
    assert_eq!(ko, [[50.0, 0.0, 18.5], [0.0, 50.0, 45.0], [0.0, 0.0, 1.0]]);
    // 61x37 in pad mode: 518x308 (×518/61 across, ×308/37 down), 105 white rows above. The model frame's
    // corners of the picture map to the photo's corners, its centre to the photo's centre.
    let g = ViewGeometry { original: (61, 37), resized: (518, 308), offset: (0, 105) };
    assert_eq!(g.point_to_original(0.0, 105.0), (0.0, 0.0));
    assert_eq!(g.point_to_original(518.0, 413.0), (61.0, 37.0));
    let ko = g.intrinsics_to_original(&[[400.0, 2.0, 259.0], [0.0, 300.0, 259.0], [0.0, 0.0, 1.0]]);
    let (sx, sy) = (61.0 / 518.0, 37.0 / 308.0);
    let want = [[400.0 * sx, 2.0 * sx, 30.5], [0.0, 300.0 * sy, 18.5], [0.0, 0.0, 1.0]];
    for r in 0..3 {
        for c in 0..3 {
            assert!((ko[r][c] - want[r][c]).abs() < 1e-12, "K[{r}][{c}] = {} want {}", ko[r][c], want[r][c]);
        }
    }
}

#[test]
fn errors_name_the_problem_and_the_file() {
    let none: [PathBuf; 0] = [];
    assert!(matches!(load_and_preprocess_images(&none, PreprocessMode::Crop), Err(LoadError::NoImages)));
    assert!(matches!(preprocess_rgba8(&[], PreprocessMode::Pad), Err(LoadError::NoImages)));

    let tmp = tempfile::tempdir().unwrap();
    let notes = tmp.path().join("notes.png");
    std::fs::write(&notes, "these are not pixels\n").unwrap();
    let good = dir().join("inputs/rgb_61x37.png");
    let e = load_and_preprocess_images(&[good.clone(), notes.clone()], PreprocessMode::Crop).unwrap_err();
    assert!(matches!(e, LoadError::Decode { .. }), "{e:?}");
    let msg = e.to_string();
    assert!(msg.contains(&notes.display().to_string()) && msg.contains("PNG or JPEG"), "{msg}");

    // A PNG cut short, and a file that is not there.
    let cut = tmp.path().join("cut.png");
    let bytes = std::fs::read(&good).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let msg = load_and_preprocess_images(std::slice::from_ref(&cut), PreprocessMode::Pad).unwrap_err().to_string();
    assert!(msg.contains(&cut.display().to_string()), "{msg}");
    let missing = tmp.path().join("missing.jpg");
    let e = load_and_preprocess_images(std::slice::from_ref(&missing), PreprocessMode::Crop).unwrap_err();
    assert!(matches!(e, LoadError::Read { .. }) && e.to_string().contains(&missing.display().to_string()), "{e}");
}
