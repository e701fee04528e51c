//! Every reader on real small files: the bundled POV-Ray scene (transforms.json, COLMAP binary and text written
//! independently by scripts/render-povray-scene) and a `.torch` chunk written by `torch.save`
//! (scripts/make-torch-chunk). The three formats describe the same cameras, so they must agree.

use std::path::{Path, PathBuf};

use mvsplat360_camera::Camera;
use mvsplat360_dataset::{colmap, read_scene, read_scene_with, torch_chunk, transforms, Scene};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn woodbox() -> PathBuf {
    root().join("assets/woodbox")
}

fn assert_same_camera(a: &Camera, b: &Camera, tol: f64, what: &str) {
    assert_eq!((a.width, a.height), (b.width, b.height), "{what}: size");
    for (x, y) in [(a.fx, b.fx), (a.fy, b.fy), (a.cx, b.cx), (a.cy, b.cy)] {
        assert!((x - y).abs() <= tol * x.abs().max(1.0), "{what}: intrinsics {x} vs {y}");
    }
    for r in 0..4 {
        for c in 0..4 {
            assert!((a.c2w[r][c] - b.c2w[r][c]).abs() <= tol, "{what}: c2w[{r}][{c}] {} vs {}", a.c2w[r][c], b.c2w[r][c]);
        }
    }
}

#[test]
fn transforms_json_bundled_scene() {
    let s = read_scene(&woodbox()).unwrap();
    assert_eq!(s.len(), 24);
    let c = &s.cameras[0];
    assert_eq!((c.width, c.height), (448, 256));
    // 60° horizontal field of view: fx = W / (2 tan 30°).
    assert!((c.fx - 448.0 / (2.0 * (30f64).to_radians().tan())).abs() < 1e-9);
    assert_eq!((c.cx, c.cy), (224.0, 128.0));
    // Cameras look at the box centre (0, -1, 0) in our y-down world.
    let target = nalgebra::Vector3::new(0.0, -1.0, 0.0);
    for cam in &s.cameras {
        let (u, v, z) = cam.project(&target);
        assert!((u - cam.cx).abs() < 1e-6 && (v - cam.cy).abs() < 1e-6 && z > 0.0);
    }
    let img = s.image(3).unwrap();
    assert_eq!((img.width, img.height, img.data.len()), (448, 256, 3 * 448 * 256));
    assert!(img.data.iter().all(|v| (0.0..=1.0).contains(v)));
}

#[test]
fn colmap_binary_and_text_match_transforms() {
    let t = transforms::read(&woodbox().join("transforms.json")).unwrap();
    let b = colmap::read(&woodbox()).unwrap();
    // Text model: a temporary COLMAP root with sparse/0 = the text files and images/ = the bundled images.
    let tmp = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(tmp.path().join("sparse/0")).unwrap();
    for f in ["cameras.txt", "images.txt"] {
        std::fs::copy(woodbox().join("sparse_txt/0").join(f), tmp.path().join("sparse/0").join(f)).unwrap();
    }
    std::os::unix::fs::symlink(woodbox().join("images"), tmp.path().join("images")).unwrap();
    let x = read_scene(tmp.path()).unwrap();
    assert_eq!(b.len(), 24);
    assert_eq!(x.len(), 24);
    for i in 0..24 {
        assert_eq!(b.view_names[i], format!("{i:03}.jpg"));
        assert_same_camera(&t.cameras[i], &b.cameras[i], 1e-9, "binary");
        assert_same_camera(&t.cameras[i], &x.cameras[i], 1e-9, "text");
    }
}

#[test]
fn torch_chunk_written_by_torch_save() {
    let dir = root().join("crates/dataset/tests/data/chunk");
    let chunk = dir.join("000000.torch");
    let scenes = torch_chunk::read_chunk(&chunk).unwrap();
    assert_eq!(scenes.iter().map(|s| s.key.as_str()).collect::<Vec<_>>(), ["woodbox_a", "woodbox_b"]);
    assert_eq!(scenes[0].timestamps, vec![0, 8, 16]);
    assert_eq!(scenes[1].timestamps, vec![4, 12]);
    let index = torch_chunk::read_chunk_index(&dir.join("index.json")).unwrap();
    assert_eq!(index["woodbox_b"], "000000.torch");

    let full = read_scene(&woodbox()).unwrap();
    let stored = stored_images(&chunk);
    assert_eq!(stored.len(), 5, "the chunk stores 3 + 2 encoded images");
    let mut used: Vec<usize> = Vec::new();
    let a = read_scene(&chunk).unwrap();
    let b = read_scene_with(&chunk, Some("woodbox_b")).unwrap();
    assert_eq!(a.name, "woodbox_a");
    for (scene, views) in [(&a, vec![0usize, 8, 16]), (&b, vec![4, 12])] {
        assert_eq!(scene.len(), views.len());
        for (k, &v) in views.iter().enumerate() {
            // Half-size images: pixel intrinsics halve; float32 storage limits the pose precision.
            let expect = full.cameras[v].rescaled(224, 128);
            assert_same_camera(&scene.cameras[k], &expect, 1e-5, "chunk");
            let img = scene.image(k).unwrap();
            assert_eq!((img.width, img.height), (224, 128));
            // Pixels, exactly: the image the reader returns is the one stored for this view, decoded unchanged
            // (no channel swap, transpose, flip, crop or rescale).
            let hits: Vec<usize> = stored.iter().enumerate().filter(|(_, s)| s.data == img.data).map(|(i, _)| i).collect();
            assert_eq!(hits.len(), 1, "{} view {v}: matches {} of the stored images exactly", scene.name, hits.len());
            assert!(!used.contains(&hits[0]), "{} view {v}: stored image {} returned twice", scene.name, hits[0]);
            used.push(hits[0]);
            // ...and it shows this view: per pixel against the original photo shrunk the way the chunk writer
            // did (PIL bicubic, see scripts/make-torch-chunk).
            let want = pil_bicubic_half(&full.image(v).unwrap());
            let d: Vec<f64> = img.data.iter().zip(&want).map(|(a, b)| (*a as f64 - b).abs() * 255.0).collect();
            let max = d.iter().fold(0f64, |m, &x| m.max(x));
            let mut sorted = d.clone();
            sorted.sort_by(f64::total_cmp);
            let p99 = sorted[sorted.len() * 99 / 100];
            let lossless = scene.name == "woodbox_b";
            eprintln!("{} view {v}: |reader - PIL bicubic of the original| max {max:.1}/255, p99 {p99:.1}/255", scene.name);
            let (max_tol, p99_tol) = if lossless { PNG_TOL } else { JPEG_TOL };
            assert!(max <= max_tol && p99 <= p99_tol, "{} view {v}: pixels differ from the original view (max {max:.1}, p99 {p99:.1} levels)", scene.name);
            // The same test with the view's neighbour in the scene must fail (the check tells views apart).
            let other = pil_bicubic_half(&full.image((v + 1) % full.len()).unwrap());
            let p99_other = {
                let mut d: Vec<f64> = img.data.iter().zip(&other).map(|(a, b)| (*a as f64 - b).abs() * 255.0).collect();
                d.sort_by(f64::total_cmp);
                d[d.len() * 99 / 100]
            };
            eprintln!("  ...against view {}: p99 {p99_other:.1}/255", (v + 1) % full.len());
            assert!(p99_other > 3.0 * p99.max(1.0), "view {v} is not told apart from view {}", (v + 1) % full.len());
        }
    }
    assert_eq!(used.len(), stored.len(), "every stored image is some view's");
}

/// Per-pixel tolerance (max, 99th percentile), in 8-bit levels, of a chunk image against [`pil_bicubic_half`] of
/// the original photo: the PNG views (lossless) only see PIL's fixed-point rounding and the two JPEG decoders of the
/// original (measured max 3, p99 1); the JPEG views (quality 85) add their own compression error (measured max
/// 28, p99 11). A neighbouring view differs by p99 81–122 levels.
const PNG_TOL: (f64, f64) = (6.0, 3.0);
const JPEG_TOL: (f64, f64) = (56.0, 22.0);

/// The encoded images stored in a `.torch` chunk, found without the torch reader: every zip member holding a
/// PNG or JPEG stream (the uint8 storages), decoded by the `image` crate into planar f32 like the reader's.
fn stored_images(chunk: &Path) -> Vec<mvsplat360_dataset::image::ImageF32> {
    use std::io::Read;
    let mut zip = zip::ZipArchive::new(std::fs::File::open(chunk).unwrap()).unwrap();
    let mut out = Vec::new();
    for i in 0..zip.len() {
        let mut f = zip.by_index(i).unwrap();
        let mut bytes = Vec::new();
        f.read_to_end(&mut bytes).unwrap();
        let is_png = bytes.starts_with(&[0x89, b'P', b'N', b'G']);
        let is_jpeg = bytes.starts_with(&[0xFF, 0xD8, 0xFF]);
        if !(is_png || is_jpeg) {
            continue;
        }
        let rgb = image::load_from_memory(&bytes).unwrap().to_rgb8();
        let (w, h) = rgb.dimensions();
        let mut data = vec![0f32; 3 * (w * h) as usize];
        for (x, y, p) in rgb.enumerate_pixels() {
            for c in 0..3 {
                data[c * (w * h) as usize + (y * w + x) as usize] = p[c] as f32 / 255.0;
            }
        }
        out.push(mvsplat360_dataset::image::ImageF32 { width: w, height: h, data });
    }
    out
}

/// PIL's `Image.resize((W/2, H/2), BICUBIC)` (a = −0.5, support scaled by 2 for the 2× reduction, horizontal
/// pass then vertical, 8-bit rounding after each) in f64; planar RGB in [0, 1].
fn pil_bicubic_half(src: &mvsplat360_dataset::image::ImageF32) -> Vec<f64> {
    let (w, h) = (src.width as usize, src.height as usize);
    let (ow, oh) = (w / 2, h / 2);
    let cubic = |x: f64| {
        let a = -0.5;
        let x = x.abs();
        if x < 1.0 {
            ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
        } else if x < 2.0 {
            (((x - 5.0) * x + 8.0) * x - 4.0) * a
        } else {
            0.0
        }
    };
    // Taps of output index `o` over an input axis of length n (PIL's precompute_coeffs).
    let taps = |o: usize, n: usize| -> Vec<(usize, f64)> {
        let scale = 2.0;
        let support = 2.0 * scale;
        let center = (o as f64 + 0.5) * scale;
        let lo = ((center - support + 0.5).floor().max(0.0)) as usize;
        let hi = ((center + support + 0.5).floor() as usize).min(n);
        let ws: Vec<(usize, f64)> = (lo..hi).map(|x| (x, cubic((x as f64 - center + 0.5) / scale))).collect();
        let sum: f64 = ws.iter().map(|t| t.1).sum();
        ws.into_iter().map(|(x, wt)| (x, wt / sum)).collect()
    };
    let round8 = |v: f64| (v * 255.0).round().clamp(0.0, 255.0) / 255.0;
    let mut out = vec![0f64; 3 * ow * oh];
    for c in 0..3 {
        let plane = &src.data[c * w * h..(c + 1) * w * h];
        let mut horiz = vec![0f64; ow * h];
        for y in 0..h {
            for x in 0..ow {
                horiz[y * ow + x] = round8(taps(x, w).iter().map(|&(i, wt)| wt * plane[y * w + i] as f64).sum());
            }
        }
        for y in 0..oh {
            let ty = taps(y, h);
            for x in 0..ow {
                out[c * ow * oh + y * ow + x] = round8(ty.iter().map(|&(i, wt)| wt * horiz[i * ow + x]).sum());
            }
        }
    }
    out
}

#[test]
fn evaluation_index() {
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("evaluation_index.json");
    std::fs::write(
        &p,
        r#"{"s1": {"context": [0, 8, 16], "target": [1, 2, 3]}, "s2": null,
            "s3": {"context": [1], "target": [2], "target_quantify": [2]}}"#,
    )
    .unwrap();
    let idx = mvsplat360_dataset::read_evaluation_index(&p).unwrap();
    assert_eq!(idx.len(), 3);
    assert_eq!(idx["s1"].as_ref().unwrap().context, vec![0, 8, 16]);
    assert!(idx["s2"].is_none());
    assert_eq!(idx["s3"].as_ref().unwrap().target_quantify, Some(vec![2]));
    let e = idx["s1"].as_ref().unwrap();
    mvsplat360_dataset::index::check_entry(&p, "s1", e, 24).unwrap();
    let err = mvsplat360_dataset::index::check_entry(&p, "s1", e, 10).unwrap_err().to_string();
    assert!(err.contains("s1.context") && err.contains("16 is out of range"), "{err}");
}

// ---- bad inputs: every error names the file and the problem ----

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn err_of(p: &Path) -> String {
    match read_scene(p) {
        Ok(_) => panic!("{} should fail", p.display()),
        Err(e) => e.to_string(),
    }
}

fn tiny_png(dir: &Path, name: &str, w: u32, h: u32) {
    image::RgbImage::from_pixel(w, h, image::Rgb([10, 20, 30])).save(dir.join(name)).unwrap();
}

const IDENT: &str = "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";

#[test]
fn bad_inputs_name_the_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    tiny_png(d, "a.png", 8, 6);
    tiny_png(d, "b.png", 10, 6);
    let cases: Vec<(PathBuf, &str)> = vec![
        (d.join("missing.json"), "no such file"),
        (write(d, "x.txt", "hello"), "not a recognised scene"),
        (write(d, "t1.json", "{ not json"), "invalid JSON"),
        (write(d, "t2.json", r#"{"fl_x": 5}"#), "frames: missing"),
        (write(d, "t3.json", r#"{"fl_x": 5, "frames": []}"#), "frames: the list is empty"),
        (write(d, "t4.json", r#"{"fl_x": 5, "frames": [{"file_path": "a.png", "transform_matrix": [[1,0],[0,1]]}]}"#), "frames[0].transform_matrix"),
        (write(d, "t5.json", &format!(r#"{{"frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}]}}"#)), "no focal length"),
        (write(d, "t6.json", &format!(r#"{{"fl_x": 5, "frames": [{{"file_path": "nope.png", "transform_matrix": {IDENT}}}]}}"#)), "nope.png does not exist"),
        (
            write(d, "t7.json", &format!(r#"{{"fl_x": "big", "frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}]}}"#)),
            "fl_x: expected a finite number",
        ),
        (
            write(d, "t9.json", &format!(r#"{{"fl_x": -5, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}]}}"#)),
            "view a.png: focal length fx = -5",
        ),
        (
            write(d, "t10.json", r#"{"fl_x": 5, "frames": [{"file_path": "a.png", "transform_matrix": [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#),
            "not orthonormal",
        ),
        (write(d, "c.torch", "not a zip"), "not a torch zip archive"),
    ];
    for (p, needle) in &cases {
        let e = err_of(p);
        assert!(e.contains(needle), "{}: expected `{needle}` in `{e}`", p.display());
    }
    // Views of different sizes are read (each is preprocessed to the model's size on its own).
    let p = write(
        d,
        "t8.json",
        &format!(r#"{{"fl_x": 5, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}, {{"file_path": "b.png", "transform_matrix": {IDENT}}}]}}"#),
    );
    let s = read_scene(&p).unwrap();
    assert_eq!([(s.cameras[0].width, s.cameras[0].height), (s.cameras[1].width, s.cameras[1].height)], [(8, 6), (10, 6)]);
    // Image whose real size disagrees with the declared w/h.
    let p = write(d, "t11.json", &format!(r#"{{"fl_x": 5, "w": 16, "h": 6, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}]}}"#));
    let s = read_scene(&p).unwrap();
    let e = s.image(0).unwrap_err().to_string();
    assert!(e.contains("image is 8x6 but its camera says 16x6"), "{e}");
    // Undecodable image.
    write(d, "bad.png", "garbage");
    let p = write(d, "t12.json", &format!(r#"{{"fl_x": 5, "w": 8, "h": 6, "frames": [{{"file_path": "bad.png", "transform_matrix": {IDENT}}}]}}"#));
    let e = read_scene(&p).unwrap().image(0).unwrap_err().to_string();
    assert!(e.contains("bad.png") && e.contains("cannot decode"), "{e}");
    // Unknown chunk scene key lists what exists.
    let chunk = root().join("crates/dataset/tests/data/chunk/000000.torch");
    let e = read_scene_with(&chunk, Some("nope")).unwrap_err().to_string();
    assert!(e.contains("no scene `nope`") && e.contains("woodbox_a"), "{e}");
}

#[test]
fn bad_colmap_models_name_the_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tmp.path().join("sparse/0");
    std::fs::create_dir_all(&m).unwrap();
    std::fs::create_dir_all(tmp.path().join("images")).unwrap();
    let check = |needle: &str| {
        let e = err_of(tmp.path());
        assert!(e.contains(needle), "expected `{needle}` in `{e}`");
    };
    // Truncated binary cameras file.
    let full = std::fs::read(woodbox().join("sparse/0/cameras.bin")).unwrap();
    std::fs::write(m.join("cameras.bin"), &full[..20]).unwrap();
    std::fs::copy(woodbox().join("sparse/0/images.bin"), m.join("images.bin")).unwrap();
    check("file ends early");
    std::fs::remove_file(m.join("cameras.bin")).unwrap();
    std::fs::remove_file(m.join("images.bin")).unwrap();
    // Text: fisheye model is refused with a fix.
    std::fs::write(m.join("cameras.txt"), "1 OPENCV_FISHEYE 8 6 5 5 4 3 0 0 0 0\n").unwrap();
    std::fs::write(m.join("images.txt"), "").unwrap();
    check("image_undistorter");
    // Text: non-numeric parameter.
    std::fs::write(m.join("cameras.txt"), "1 PINHOLE 8 6 5 five 4 3\n").unwrap();
    check("line 1: `five` is not a number");
    // Image that refers to a camera that does not exist.
    std::fs::write(m.join("cameras.txt"), "1 PINHOLE 8 6 5 5 4 3\n").unwrap();
    std::fs::write(m.join("images.txt"), "1 1 0 0 0 0 0 0 7 a.png\n\n").unwrap();
    check("refers to camera 7");
    // Missing image file.
    std::fs::write(m.join("images.txt"), "1 1 0 0 0 0 0 0 1 a.png\n\n").unwrap();
    check("image a.png not found");
    // A distorted perspective model reads: the pinhole part is the camera, the distortion rides along (its
    // removal is checked in tests/lens.rs).
    std::fs::write(m.join("cameras.txt"), "1 SIMPLE_RADIAL 8 6 5 4 3 0.01\n").unwrap();
    tiny_png(&tmp.path().join("images"), "a.png", 8, 6);
    let s: Scene = read_scene(tmp.path()).unwrap();
    assert_eq!((s.cameras[0].fx, s.cameras[0].fy, s.cameras[0].cx), (5.0, 5.0, 4.0));
    assert_eq!(s.lens(0), Some(&mvsplat360_dataset::Distortion::SimpleRadial { k: 0.01 }));
    // A parameter count that does not fit the model.
    std::fs::write(m.join("cameras.txt"), "1 RADIAL 8 6 5 4 3 0.01\n").unwrap();
    check("model RADIAL has 5 parameters, found 4");
}
