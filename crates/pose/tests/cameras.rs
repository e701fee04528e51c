//! Photos become COLMAP cameras by device: two JPEGs of one size whose EXIF names two phone models go to two
//! subfolders of `images/`, which COLMAP's `--ImageReader.single_camera_per_folder 1` makes two cameras; one
//! model stays one camera (`--ImageReader.single_camera 1`, no subfolders). Seen through a stub `colmap` that
//! records the feature extractor's command and the images it was given, then fails (the run stops there).

use std::path::{Path, PathBuf};

use mvsplat360_pose::{pose, NoProgress, PoseError, PoseOptions};

/// Prints COLMAP's banner; `feature_extractor` records its arguments and the files under `--image_path`.
const COLMAP: &str = r#"#!/bin/sh
if [ "$1" = "-h" ]; then
  echo "COLMAP 3.8 -- Structure-from-Motion and Multi-View Stereo"
  echo "(Commit 43de802 on 2023-01-31 without CUDA)"
  exit 0
fi
dir=$(dirname "$0")
prev=""
for a in "$@"; do
  if [ "$prev" = "--image_path" ]; then images=$a; fi
  prev=$a
done
echo "$*" > "$dir/argv.txt"
(cd "$images" && find . -type f | sort) > "$dir/images.txt"
exit 1
"#;

fn stub(dir: &Path) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    let p = dir.join("colmap");
    std::fs::write(&p, COLMAP).unwrap();
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
    p
}

/// A 64×48 JPEG (a pattern of its own per `seed`) with an EXIF APP1 segment naming this make, model and focal.
fn jpeg_with_exif(path: &Path, seed: u32, make: &str, model: &str) {
    use exif::{Field, In, Rational, Tag, Value};
    let fields = [
        Field { tag: Tag::Make, ifd_num: In::PRIMARY, value: Value::Ascii(vec![make.as_bytes().to_vec()]) },
        Field { tag: Tag::Model, ifd_num: In::PRIMARY, value: Value::Ascii(vec![model.as_bytes().to_vec()]) },
        Field { tag: Tag::FocalLength, ifd_num: In::PRIMARY, value: Value::Rational(vec![Rational { num: 42, denom: 10 }]) },
    ];
    let mut w = exif::experimental::Writer::new();
    for f in &fields {
        w.push_field(f);
    }
    let mut tiff = std::io::Cursor::new(Vec::new());
    w.write(&mut tiff, false).unwrap();
    let tiff = tiff.into_inner();
    let img = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4 + seed * 60) as u8, (y * 5) as u8, ((x ^ y) * 3) as u8]));
    let mut jpeg = vec![];
    img.write_to(&mut std::io::Cursor::new(&mut jpeg), image::ImageFormat::Jpeg).unwrap();
    // APP1 right after SOI: FF E1, its length (these two bytes included), "Exif\0\0", the TIFF data.
    let mut out = jpeg[..2].to_vec();
    out.extend([0xFF, 0xE1]);
    out.extend(((2 + 6 + tiff.len()) as u16).to_be_bytes());
    out.extend(b"Exif\0\0");
    out.extend(&tiff);
    out.extend(&jpeg[2..]);
    std::fs::write(path, out).unwrap();
}

/// Poses two photos of these models; returns the extractor's arguments, the images it saw, and pose.json's
/// record of the cameras (from the work folder's frames.json).
fn extract(models: [&str; 2]) -> (String, Vec<String>, serde_json::Value) {
    let d = tempfile::tempdir().unwrap();
    let photos = d.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for (k, m) in models.iter().enumerate() {
        jpeg_with_exif(&photos.join(format!("{k}.jpg")), k as u32, "Acme", m);
    }
    let opts = PoseOptions { colmap: Some(stub(d.path())), min_views: 2, ..Default::default() };
    let e = pose(&photos, &d.path().join("scene"), &opts, &NoProgress).unwrap_err();
    assert!(matches!(e, PoseError::Engine { .. }), "{e}");
    assert!(e.to_string().contains("feature_extractor"), "{e}");
    let argv = std::fs::read_to_string(d.path().join("argv.txt")).unwrap();
    let images = std::fs::read_to_string(d.path().join("images.txt")).unwrap().lines().map(String::from).collect();
    let work = std::fs::read_dir(d.path()).unwrap().map(|e| e.unwrap().path()).find(|p| p.to_string_lossy().contains(".scene.pose-")).unwrap();
    let frames: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(work.join("frames.json")).unwrap()).unwrap();
    (argv, images, frames["detail"]["cameras"].clone())
}

#[test]
fn two_phone_models_of_one_size_are_two_cameras() {
    let (argv, images, cameras) = extract(["Phone 1", "Phone 2"]);
    assert!(argv.contains("--ImageReader.single_camera_per_folder 1"), "{argv}");
    assert_eq!(images, ["./64x48-1/0000_0.jpg", "./64x48-2/0001_1.jpg"]);
    let models: Vec<&str> = cameras.as_array().unwrap().iter().map(|c| c["model"].as_str().unwrap()).collect();
    assert_eq!(models, ["Phone 1", "Phone 2"]);
    assert_eq!(cameras[0]["make"], "Acme");
    assert_eq!(cameras[0]["focal_mm"], 4.2);

    let (argv, images, cameras) = extract(["Phone 1", "Phone 1"]);
    assert!(argv.contains("--ImageReader.single_camera 1"), "{argv}");
    assert_eq!(images, ["./0000_0.jpg", "./0001_1.jpg"]);
    assert_eq!(cameras.as_array().unwrap().len(), 1);
}
