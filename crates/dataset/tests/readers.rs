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
            let mean = |d: &[f32]| d.iter().map(|&x| x as f64).sum::<f64>() / d.len() as f64;
            let m_full = mean(&full.image(v).unwrap().data);
            assert!((mean(&img.data) - m_full).abs() < 0.01, "view {v}: mean colour differs");
        }
    }
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
        (
            write(d, "t4.json", r#"{"fl_x": 5, "frames": [{"file_path": "a.png", "transform_matrix": [[1,0],[0,1]]}]}"#),
            "frames[0].transform_matrix",
        ),
        (write(d, "t5.json", &format!(r#"{{"frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}]}}"#)), "no focal length"),
        (
            write(d, "t6.json", &format!(r#"{{"fl_x": 5, "frames": [{{"file_path": "nope.png", "transform_matrix": {IDENT}}}]}}"#)),
            "nope.png does not exist",
        ),
        (
            write(d, "t7.json", &format!(r#"{{"fl_x": "big", "frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}]}}"#)),
            "fl_x: expected a finite number",
        ),
        (
            write(
                d,
                "t8.json",
                &format!(
                    r#"{{"fl_x": 5, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}, {{"file_path": "b.png", "transform_matrix": {IDENT}}}]}}"#
                ),
            ),
            "differs from the first view's 8x6",
        ),
        (
            write(d, "t9.json", &format!(r#"{{"fl_x": -5, "frames": [{{"file_path": "a.png", "transform_matrix": {IDENT}}}]}}"#)),
            "view a.png: focal length fx = -5",
        ),
        (
            write(
                d,
                "t10.json",
                r#"{"fl_x": 5, "frames": [{"file_path": "a.png", "transform_matrix": [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
            ),
            "not orthonormal",
        ),
        (write(d, "c.torch", "not a zip"), "not a torch zip archive"),
    ];
    for (p, needle) in &cases {
        let e = err_of(p);
        assert!(e.contains(needle), "{}: expected `{needle}` in `{e}`", p.display());
    }
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
    // Distorted model accepted (distortion ignored), so a valid scene reads.
    std::fs::write(m.join("cameras.txt"), "1 SIMPLE_RADIAL 8 6 5 4 3 0.01\n").unwrap();
    tiny_png(&tmp.path().join("images"), "a.png", 8, 6);
    let s: Scene = read_scene(tmp.path()).unwrap();
    assert_eq!((s.cameras[0].fx, s.cameras[0].fy, s.cameras[0].cx), (5.0, 5.0, 4.0));
}
