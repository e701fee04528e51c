//! Depth maps of folder scenes (`depth/<view>.png` + `depth/depth.json`) on a real POV-Ray scene written by
//! `scripts/render-povray-scene --depth` (6 views of woodbox at 128×64, `tests/data/woodbox-depth`; the script's
//! self-test checks its depth pass against the closed-form distance to a sphere). Here: the maps, read through
//! the training loader, describe one surface seen from every camera, and bad folders are refused by name.

use std::path::{Path, PathBuf};

use mvsplat360_camera::Camera;
use mvsplat360_pipeline::preprocess::{InputSize, Preprocess};
use mvsplat360_train::scenes::read_folder_scene;
use nalgebra::Vector3;

fn scene_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/woodbox-depth")
}

fn pre(width: u32, height: u32) -> Preprocess {
    Preprocess { size: InputSize::Fixed { width, height }, multiple: 16 }
}

/// The world point at ray distance `d` through pixel (x, y)'s centre.
fn unproject(cam: &Camera, x: usize, y: usize, d: f64) -> Vector3<f64> {
    let dc = Vector3::new((x as f64 + 0.5 - cam.cx) / cam.fx, (y as f64 + 0.5 - cam.cy) / cam.fy, 1.0).normalize();
    let r = |i: usize| Vector3::new(cam.c2w[i][0], cam.c2w[i][1], cam.c2w[i][2]).dot(&dc);
    cam.center() + d * Vector3::new(r(0), r(1), r(2))
}

#[test]
fn povray_depth_maps_agree_across_views() {
    let s = read_folder_scene(&scene_dir(), &pre(128, 64)).unwrap();
    let depths = s.depths.as_ref().expect("the folder has depth/depth.json");
    assert_eq!(depths.len(), 6);
    // 0 in the PNG = unknown (sky, clipped colours) = infinite here; the rest is value × unit.
    let unit: f64 =
        serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(scene_dir().join("depth/depth.json")).unwrap()).unwrap()["unit"].as_f64().unwrap();
    let raw = image::open(scene_dir().join("depth/002.png")).unwrap().to_luma16().into_raw();
    for (v, d) in raw.iter().zip(&depths[2]) {
        if *v == 0 {
            assert!(d.is_infinite());
        } else {
            assert!(((*d as f64) - *v as f64 * unit).abs() <= 1e-6 * (*d as f64), "{d} vs {v} × {unit}");
        }
    }
    // Each known pixel of view a, moved to its 3D point and seen from view b, lands where b's map has the same
    // distance — unless b sees something nearer there (occlusion) or the pixel is on an edge (nearest-pixel
    // lookup; the 6 views are 60° apart). Measured: median relative error 0.33–0.66 %, 67–76 % of the pixels
    // within 2 %. (The value check above catches a wrong unit: a factor 1.02 fails it.)
    for (a, b) in [(0, 1), (1, 2), (3, 4), (5, 0)] {
        let (ca, cb) = (&s.cameras[a], &s.cameras[b]);
        let (w, h) = (ca.width as usize, ca.height as usize);
        let mut rel = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let d = depths[a][y * w + x] as f64;
                if !d.is_finite() {
                    continue;
                }
                let p = unproject(ca, x, y, d);
                let (u, v, z) = cb.project(&p);
                if z <= 0.0 || u < 0.0 || v < 0.0 || u >= w as f64 || v >= h as f64 {
                    continue;
                }
                let db = depths[b][v as usize * w + u as usize] as f64;
                if db.is_finite() {
                    let dist = (p - cb.center()).norm();
                    rel.push((db - dist).abs() / dist);
                }
            }
        }
        assert!(rel.len() > w * h / 4, "views {a}→{b}: only {} pixels compared", rel.len());
        rel.sort_by(f64::total_cmp);
        let median = rel[rel.len() / 2];
        let within = rel.iter().filter(|&&r| r < 0.02).count() as f64 / rel.len() as f64;
        eprintln!("views {a}→{b}: {} px, median {median:.4}, within 2 %: {within:.3}", rel.len());
        assert!(median < 0.01 && within > 0.5, "views {a}→{b}: median relative error {median}, {within} within 2 %");
    }
}

fn copy_scene(to: &Path) {
    for sub in ["", "images", "depth"] {
        std::fs::create_dir_all(to.join(sub)).unwrap();
        for e in std::fs::read_dir(scene_dir().join(sub)).unwrap() {
            let e = e.unwrap();
            if e.file_type().unwrap().is_file() {
                std::fs::copy(e.path(), to.join(sub).join(e.file_name())).unwrap();
            }
        }
    }
}

fn error_of(dir: &Path, p: &Preprocess) -> String {
    read_folder_scene(dir, p).map(|_| ()).unwrap_err().to_string()
}

#[test]
fn bad_depth_folders_are_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("scene");
    copy_scene(&dir);
    assert!(read_folder_scene(&dir, &pre(128, 64)).unwrap().depths.is_some());

    // Photos resampled to another training size: the maps cannot follow.
    let e = error_of(&dir, &pre(64, 32));
    assert!(e.contains("training size"), "{e}");

    // A missing map.
    std::fs::rename(dir.join("depth/003.png"), tmp.path().join("003.png")).unwrap();
    let e = error_of(&dir, &pre(128, 64));
    assert!(e.contains("depth/003.png"), "{e}");

    // An 8-bit map.
    image::GrayImage::new(128, 64).save(dir.join("depth/003.png")).unwrap();
    let e = error_of(&dir, &pre(128, 64));
    assert!(e.contains("depth/003.png") && e.contains("16-bit"), "{e}");

    // A map of another size.
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::new(64, 64).save(dir.join("depth/003.png")).unwrap();
    let e = error_of(&dir, &pre(128, 64));
    assert!(e.contains("depth/003.png") && e.contains("64×64"), "{e}");

    // A unit that is not a positive number.
    std::fs::rename(tmp.path().join("003.png"), dir.join("depth/003.png")).unwrap();
    std::fs::write(dir.join("depth/depth.json"), r#"{"unit": -1}"#).unwrap();
    let e = error_of(&dir, &pre(128, 64));
    assert!(e.contains("depth.json") && e.contains("unit"), "{e}");

    // Without depth/depth.json the folder trains photometrically.
    std::fs::remove_file(dir.join("depth/depth.json")).unwrap();
    assert!(read_folder_scene(&dir, &pre(128, 64)).unwrap().depths.is_none());
}
