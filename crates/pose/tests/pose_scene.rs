//! `pose` with the real engines (Debian's `colmap` and `ffmpeg`, which `scripts/test` installs) on the test
//! scene the project renders itself (`assets/pose-test/orbit24`: 24 views of a textured POV-Ray scene, 480×270,
//! true cameras known), as a video and as photos; and every way it must refuse.
//!
//! Bounds: the acceptance bounds (centre ≤ 2 % of the scene radius, rotation ≤ 1.5°, focal ≤ 2 %) for both.
//! 10 runs of this file measured, worst view of each run: video (H.264, libx264 defaults) centre 0.43–0.69 %,
//! rotation 0.15–0.22°, focal 0.11–0.91 %; photos 0.27–0.66 %, 0.08–0.15°, 0.02–0.41 %.

use std::path::{Path, PathBuf};
use std::process::Command;

use mvsplat360_camera::align::camera_errors;
use mvsplat360_camera::Camera;
use mvsplat360_pose::{pose, NoProgress, PoseError, PoseOptions};

const PHOTOS: [f64; 3] = [2.0, 1.5, 2.0];
const VIDEO: [f64; 3] = [2.0, 1.5, 2.0];

fn scene_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/pose-test/orbit24")
}

fn need(program: &str) {
    let ok = Command::new(program).arg("-h").output().is_ok();
    assert!(ok, "`{program}` is not installed: these tests need Debian's colmap and ffmpeg (scripts/test installs them: apt-get install -y colmap ffmpeg)");
}

/// An H.264 video (libx264's defaults, B-frames included) of the given frames, in order.
fn encode(frames: &[PathBuf], out: &Path) {
    let list = out.with_extension("txt");
    let text: String = frames.iter().map(|f| format!("file '{}'\nduration 0.125\n", f.display())).collect();
    std::fs::write(&list, text).unwrap();
    let st = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-f", "concat", "-safe", "0", "-i"])
        .arg(&list)
        .args(["-c:v", "libx264", "-pix_fmt", "yuv420p", "-r", "8"])
        .arg(out)
        .status()
        .unwrap();
    assert!(st.success());
}

fn true_frames() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(scene_dir().join("images")).unwrap().map(|e| e.unwrap().path()).collect();
    v.sort();
    v
}

/// The trailing number of a file stem: `frame_000012.jpg`, `0012_012.jpg` and `012.jpg` are frame 12.
fn frame_number(name: &str) -> Option<usize> {
    let stem = Path::new(name).file_stem()?.to_str()?;
    let digits: String = stem.chars().rev().take_while(char::is_ascii_digit).collect::<Vec<_>>().into_iter().rev().collect();
    digits.parse().ok()
}

fn check_cameras(posed: &Path, expect_views: usize, [centre_pct, rotation_deg, focal_pct]: [f64; 3]) {
    let truth = mvsplat360_dataset::read_scene(&scene_dir()).unwrap();
    let est = mvsplat360_dataset::read_scene(posed).unwrap();
    assert_eq!(est.len(), expect_views, "registered views");
    let mut e: Vec<Camera> = vec![];
    let mut t: Vec<Camera> = vec![];
    for (name, cam) in est.view_names.iter().zip(&est.cameras) {
        let k = frame_number(name).unwrap_or_else(|| panic!("{name}: no frame number"));
        let j = truth.view_names.iter().position(|n| frame_number(n) == Some(k)).unwrap_or_else(|| panic!("frame {k} not in the true scene"));
        e.push(cam.clone());
        t.push(truth.cameras[j].clone());
    }
    let err = camera_errors(&e, &t).unwrap();
    let (c, r, f) = (100.0 * err.centre_stats.max, err.rotation_stats.max, 100.0 * err.focal_stats.max);
    eprintln!("{}: centre max {c:.3} % of radius, rotation max {r:.3}°, focal max {f:.3} %", posed.display());
    assert!(c <= centre_pct, "centre error {c:.3} % > {centre_pct} %");
    assert!(r <= rotation_deg, "rotation error {r:.3}° > {rotation_deg}°");
    assert!(f.abs() <= focal_pct, "focal error {f:.3} % > {focal_pct} %");
}

#[test]
fn a_video_is_posed() {
    need("colmap");
    need("ffmpeg");
    let d = tempfile::tempdir().unwrap();
    let video = d.path().join("orbit.mp4");
    encode(&true_frames(), &video);
    let out = d.path().join("scene");
    let r = pose(&video, &out, &PoseOptions { frames: 24, ..Default::default() }, &NoProgress).unwrap();
    assert_eq!((r.registered, r.images_total, r.input_frames), (24, 24, 24));
    assert_eq!(r.sub_models.len(), 1);
    for f in ["images", "sparse/0/cameras.bin", "sparse/0/images.bin", "pose.json", "logs/mapper.log"] {
        assert!(out.join(f).exists(), "{f}");
    }
    // No work folder is left beside the scene.
    let left: Vec<_> = std::fs::read_dir(d.path()).unwrap().map(|e| e.unwrap().file_name()).filter(|n| n.to_string_lossy().starts_with('.')).collect();
    assert!(left.is_empty(), "{left:?}");
    let stages: Vec<&str> = r.seconds.stages.iter().map(|s| s.0.as_str()).collect();
    assert_eq!(stages, ["frames", "features", "matches", "mapper", "undistort"]);
    for cmd in ["sequential_matcher", "matches_importer"] {
        assert!(r.commands.iter().any(|c| c.argv.iter().any(|a| a == cmd)), "{cmd} not run");
    }
    check_cameras(&out, 24, VIDEO);
    // The same input again: the scene is reused, not posed again.
    let again = pose(&video, &out, &PoseOptions { frames: 24, ..Default::default() }, &NoProgress).unwrap();
    assert_eq!((again.fingerprint, again.registered, again.seconds.total), (r.fingerprint.clone(), r.registered, r.seconds.total));
}

#[test]
fn photos_are_posed() {
    need("colmap");
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("scene");
    let r = pose(&scene_dir().join("images"), &out, &PoseOptions::default(), &NoProgress).unwrap();
    assert_eq!((r.registered, r.images_total), (24, 24));
    assert!(r.commands.iter().any(|c| c.argv.iter().any(|a| a == "exhaustive_matcher")));
    check_cameras(&out, 24, PHOTOS);
    // The posed folder is a scene every reader takes.
    let s = mvsplat360_dataset::read_scene(&out).unwrap();
    assert!(s.cameras.iter().all(|c| (c.width, c.height) == (s.cameras[0].width, s.cameras[0].height)));
}

fn not_posed(input: &Path, out: &Path, opts: &PoseOptions) -> String {
    let e = pose(input, out, opts, &NoProgress).unwrap_err();
    assert!(!out.exists(), "{} was written", out.display());
    let parent = out.parent().unwrap();
    let left: Vec<_> =
        std::fs::read_dir(parent).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).filter(|n| n.starts_with('.')).collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    e.to_string()
}

#[test]
fn five_views_far_apart_are_refused_with_nothing_written() {
    need("colmap");
    let d = tempfile::tempdir().unwrap();
    let photos = d.path().join("five");
    std::fs::create_dir(&photos).unwrap();
    let truth = mvsplat360_dataset::read_scene(&scene_dir()).unwrap();
    let pick = mvsplat360_camera::select::farthest_views(&truth.cameras, 5, mvsplat360_camera::select::FpsStart::FarthestFromCentroid);
    for &i in &pick {
        let src = true_frames()[i].clone();
        std::fs::copy(&src, photos.join(src.file_name().unwrap())).unwrap();
    }
    let e = not_posed(&photos, &d.path().join("scene"), &PoseOptions::default());
    assert!(e.contains("of 10 image pairs matched"), "{e}");
    assert!(e.contains("could not pose") && e.contains("video"), "{e}");
    // Every unregistered file is named (here: all five, or all but a wrong two-view model's pair).
    let named = pick.iter().filter(|&&i| e.contains(&format!("{:03}.jpg", i))).count();
    assert!(named >= 3, "{e}");
}

#[test]
fn bad_inputs_each_give_one_clear_error() {
    need("colmap");
    need("ffmpeg");
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("scene");
    let opts = PoseOptions::default();
    let mk = |name: &str| {
        let p = d.path().join(name);
        std::fs::create_dir(&p).unwrap();
        p
    };
    let empty = mk("empty");
    let e = not_posed(&empty, &out, &opts);
    assert!(e.contains("holds no photos"), "{e}");

    let one = mk("one");
    std::fs::copy(&true_frames()[0], one.join("a.jpg")).unwrap();
    let e = not_posed(&one, &out, &opts);
    assert!(e.contains("holds 1 photo") && e.contains("video"), "{e}");

    // A file named as a photo that is not one: named, with the fix.
    let junk = mk("junk");
    for f in &true_frames()[..6] {
        std::fs::copy(f, junk.join(f.file_name().unwrap())).unwrap();
    }
    std::fs::write(junk.join("broken.jpg"), b"not a jpeg at all").unwrap();
    let e = not_posed(&junk, &out, &opts);
    assert!(e.contains("broken.jpg") && e.contains("cannot decode"), "{e}");

    let video = d.path().join("video.mp4");
    std::fs::write(&video, b"\x00\x00\x00\x18ftypmp42 this is not a video").unwrap();
    let e = not_posed(&video, &out, &opts);
    assert!(e.contains("video.mp4") && e.contains("cannot read it as a video"), "{e}");

    // A video of one frame repeated: nothing to triangulate.
    let still = d.path().join("still.mp4");
    encode(&vec![true_frames()[3].clone(); 24], &still);
    let e = not_posed(&still, &out, &PoseOptions { frames: 24, ..Default::default() });
    assert!(e.contains("identical"), "{e}");

    let e = pose(&empty, &out, &PoseOptions { camera_model: "OPENCV_FISHEYE".into(), ..Default::default() }, &NoProgress).unwrap_err();
    assert!(matches!(e, PoseError::Input { .. }) && e.to_string().contains("SIMPLE_RADIAL"), "{e}");

    let e = pose(&empty, &out, &PoseOptions { colmap: Some("/nonexistent/colmap".into()), ..Default::default() }, &NoProgress).unwrap_err();
    assert!(e.to_string().contains("apt-get install -y colmap"), "{e}");
    assert!(!out.exists());
}
