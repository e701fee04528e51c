//! The COLMAP binary writer against the two readers that matter: the project's own (`mvsplat360_dataset::colmap`,
//! files and whole scene folder) and COLMAP itself (`colmap model_converter` to text, which `scripts/test`
//! installs: Debian's `colmap`). Poses include half turns and near half turns, where a quaternion taken from the
//! trace alone loses its digits.

use std::collections::HashMap;
use std::f64::consts::PI;
use std::path::{Path, PathBuf};
use std::process::Command;

use mvsplat360_camera::convert::colmap_to_c2w;
use mvsplat360_dataset::colmap::{read, read_cameras_bin, read_images_bin};
use mvsplat360_pose::colmap_writer::{write_binary, PinholeCamera, Point2D, Point3D, PosedImage, TrackElement, NO_POINT3D, UNKNOWN_ERROR};
use mvsplat360_pose::PoseError;
use nalgebra::{Matrix4, Rotation3, Unit, UnitQuaternion, Vector3};

/// splitmix64: a fixed, dependency-free sequence.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
    fn axis(&mut self) -> Unit<Vector3<f64>> {
        loop {
            let v = Vector3::new(self.range(-1.0, 1.0), self.range(-1.0, 1.0), self.range(-1.0, 1.0));
            if v.norm() > 0.1 && v.norm() < 1.0 {
                return Unit::new_normalize(v);
            }
        }
    }
}

fn c2w_of(r: &Rotation3<f64>, centre: Vector3<f64>) -> [[f64; 4]; 4] {
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(r.matrix());
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&centre);
    let mut a = [[0.0; 4]; 4];
    for (i, row) in a.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = m[(i, j)];
        }
    }
    a
}

/// Camera rotations (camera-to-world): random, exact half turns about an axis and a coordinate axis, a half turn
/// minus 1e-7 rad, and the identity.
fn rotations(rng: &mut Rng) -> Vec<Rotation3<f64>> {
    let random =
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)));
    vec![
        random.to_rotation_matrix(),
        Rotation3::from_axis_angle(&rng.axis(), PI),
        Rotation3::from_axis_angle(&Vector3::y_axis(), PI),
        Rotation3::from_axis_angle(&rng.axis(), PI - 1e-7),
        Rotation3::identity(),
    ]
}

struct Model {
    cameras: Vec<PinholeCamera>,
    images: Vec<PosedImage>,
    points: Vec<Point3D>,
    c2w: HashMap<String, [[f64; 4]; 4]>,
}

fn model(seed: u64) -> Model {
    let mut rng = Rng(seed);
    let cameras = vec![
        PinholeCamera { id: 1, width: 64, height: 48, fx: 70.25, fy: 71.5, cx: 31.75, cy: 24.125 },
        PinholeCamera { id: 2, width: 40, height: 72, fx: 55.0 + 1.0 / 3.0, fy: 54.9, cx: 20.2, cy: 35.8 },
        PinholeCamera { id: 7, width: 96, height: 30, fx: 1e3 * PI, fy: 1e3 * std::f64::consts::E, cx: 47.9, cy: 15.1 },
    ];
    let names = ["b.png", "a.png", "sub/c.png", "e.png", "d.png"];
    let cam_of = [1, 2, 7, 1, 2];
    let mut images = vec![];
    let mut c2w = HashMap::new();
    for (k, r) in rotations(&mut rng).iter().enumerate() {
        let centre = Vector3::new(rng.range(-5.0, 5.0), rng.range(-5.0, 5.0), rng.range(-5.0, 5.0));
        let m = c2w_of(r, centre);
        // Ids out of name order, as a real model's are.
        let id = [4, 9, 2, 3, 10][k];
        images.push(PosedImage::from_c2w(id, cam_of[k], names[k], &m).unwrap());
        c2w.insert(names[k].to_string(), m);
    }
    images[0].points2d = vec![
        Point2D { x: 1.5, y: 2.25, point3d_id: Some(1) },
        Point2D { x: 10.0, y: 20.0, point3d_id: None },
        Point2D { x: 33.125, y: 40.5, point3d_id: Some(2) },
    ];
    images[1].points2d = vec![Point2D { x: 0.5, y: 0.75, point3d_id: None }, Point2D { x: 5.0, y: 6.0, point3d_id: Some(1) }];
    let points = vec![
        Point3D {
            id: 1,
            xyz: [0.1, -2.5, 3.0 + 1e-12],
            rgb: [255, 0, 17],
            error: 0.625,
            track: vec![TrackElement { image_id: 4, point2d_idx: 0 }, TrackElement { image_id: 9, point2d_idx: 1 }],
        },
        Point3D { id: 2, xyz: [1e6, -1e-6, 0.0], rgb: [1, 2, 3], error: 1.0 / 3.0, track: vec![TrackElement { image_id: 4, point2d_idx: 2 }] },
        Point3D { id: 77, xyz: [-4.0, 5.5, 6.25], rgb: [128, 128, 128], error: UNKNOWN_ERROR, track: vec![] },
    ];
    Model { cameras, images, points, c2w }
}

fn max_diff(a: &[[f64; 4]; 4], b: &[[f64; 4]; 4]) -> f64 {
    a.iter().flatten().zip(b.iter().flatten()).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}

fn c2w_array(m: &Matrix4<f64>) -> [[f64; 4]; 4] {
    let mut a = [[0.0; 4]; 4];
    for (i, row) in a.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = m[(i, j)];
        }
    }
    a
}

#[test]
fn quaternions_are_unit_with_nonnegative_w_and_keep_the_pose() {
    for seed in 0..200 {
        let m = model(seed);
        for im in &m.images {
            let n = im.qvec.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!((n - 1.0).abs() < 1e-15 && im.qvec[0] >= 0.0, "seed {seed} {}: {:?}", im.name, im.qvec);
            let back = c2w_array(&colmap_to_c2w(im.qvec, im.tvec));
            let d = max_diff(&back, &m.c2w[&im.name]);
            assert!(d < 1e-9, "seed {seed} {}: c2w differs by {d:e}", im.name);
            assert!(max_diff(&im.c2w(), &m.c2w[&im.name]) < 1e-9);
        }
    }
}

#[test]
fn project_reader_round_trip() {
    let tmp = tempfile::tempdir().unwrap();
    for seed in [1, 2, 3] {
        let m = model(seed);
        let root = tmp.path().join(format!("scene{seed}"));
        let dir = root.join("sparse/0");
        write_binary(&dir, &m.cameras, &m.images, &m.points).unwrap();

        let cams = read_cameras_bin(&dir.join("cameras.bin")).unwrap();
        assert_eq!(cams.len(), m.cameras.len());
        for c in &m.cameras {
            let r = &cams[&c.id];
            assert_eq!((r.model.as_str(), r.width, r.height), ("PINHOLE", c.width, c.height));
            assert_eq!(r.params, c.params().to_vec(), "camera {}", c.id);
            assert_eq!(r.pinhole, c.params());
            assert!(!r.distorted);
        }
        let imgs = read_images_bin(&dir.join("images.bin")).unwrap();
        assert_eq!(imgs.len(), m.images.len());
        // Written sorted by id.
        let ids: Vec<u32> = {
            let mut v: Vec<&PosedImage> = m.images.iter().collect();
            v.sort_by_key(|i| i.id);
            v.iter().map(|i| i.camera_id).collect()
        };
        assert_eq!(imgs.iter().map(|i| i.camera_id).collect::<Vec<_>>(), ids);
        for r in &imgs {
            let w = m.images.iter().find(|i| i.name == r.name).unwrap();
            assert_eq!((r.qvec, r.tvec, r.camera_id), (w.qvec, w.tvec, w.camera_id));
            let d = max_diff(&c2w_array(&colmap_to_c2w(r.qvec, r.tvec)), &m.c2w[&r.name]);
            assert!(d < 1e-9, "{}: c2w differs by {d:e}", r.name);
        }

        // The whole scene folder: images/ with PNGs of each camera's size.
        for im in &m.images {
            let c = m.cameras.iter().find(|c| c.id == im.camera_id).unwrap();
            let p = root.join("images").join(&im.name);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            image::RgbImage::from_pixel(c.width, c.height, image::Rgb([10, 20, 30])).save(&p).unwrap();
        }
        let scene = read(&root).unwrap();
        let mut names: Vec<&str> = m.images.iter().map(|i| i.name.as_str()).collect();
        names.sort();
        assert_eq!(scene.view_names, names);
        for (name, cam) in scene.view_names.iter().zip(&scene.cameras) {
            let im = m.images.iter().find(|i| &i.name == name).unwrap();
            let c = m.cameras.iter().find(|c| c.id == im.camera_id).unwrap();
            assert_eq!([cam.fx, cam.fy, cam.cx, cam.cy], c.params(), "{name}");
            assert_eq!((cam.width, cam.height), (c.width, c.height));
            let d = max_diff(&cam.c2w, &m.c2w[name]);
            assert!(d < 1e-9, "{name}: c2w differs by {d:e}");
        }
        assert!(scene.distortion.iter().all(Option::is_none));
    }
}

#[test]
fn byte_layout() {
    let tmp = tempfile::tempdir().unwrap();
    let m = model(5);
    write_binary(tmp.path(), &m.cameras, &m.images, &m.points).unwrap();
    let cams = std::fs::read(tmp.path().join("cameras.bin")).unwrap();
    assert_eq!(cams.len(), 8 + 3 * (4 + 4 + 8 + 8 + 4 * 8));
    assert_eq!(u64::from_le_bytes(cams[0..8].try_into().unwrap()), 3);
    assert_eq!(u32::from_le_bytes(cams[8..12].try_into().unwrap()), 1);
    assert_eq!(i32::from_le_bytes(cams[12..16].try_into().unwrap()), 1, "PINHOLE");
    assert_eq!(u64::from_le_bytes(cams[16..24].try_into().unwrap()), 64);
    assert_eq!(u64::from_le_bytes(cams[24..32].try_into().unwrap()), 48);
    assert_eq!(f64::from_le_bytes(cams[32..40].try_into().unwrap()), 70.25);

    let imgs = std::fs::read(tmp.path().join("images.bin")).unwrap();
    let expect: usize = 8 + m.images.iter().map(|i| 4 + 7 * 8 + 4 + i.name.len() + 1 + 8 + 24 * i.points2d.len()).sum::<usize>();
    assert_eq!(imgs.len(), expect);
    // The first record is image 2 (sorted by id): "sub/c.png", no 2D points.
    assert_eq!(u32::from_le_bytes(imgs[8..12].try_into().unwrap()), 2);
    assert_eq!(&imgs[8 + 4 + 56 + 4..8 + 4 + 56 + 4 + 10], b"sub/c.png\0");
    // Image 4 (third, after 2 "sub/c.png" and 3 "e.png", both without 2D points): its second 2D point observes
    // nothing, written as u64::MAX (−1 as i64).
    let rec3 = 8 + (4 + 56 + 4 + 10 + 8) + (4 + 56 + 4 + 6 + 8);
    assert_eq!(u32::from_le_bytes(imgs[rec3..rec3 + 4].try_into().unwrap()), 4);
    let pts = rec3 + 4 + 56 + 4 + "b.png".len() + 1;
    assert_eq!(u64::from_le_bytes(imgs[pts..pts + 8].try_into().unwrap()), 3);
    let second = pts + 8 + 24;
    assert_eq!(i64::from_le_bytes(imgs[second + 16..second + 24].try_into().unwrap()), -1);
    assert_eq!(u64::from_le_bytes(imgs[second + 16..second + 24].try_into().unwrap()), NO_POINT3D);

    let p3 = std::fs::read(tmp.path().join("points3D.bin")).unwrap();
    let expect: usize = 8 + m.points.iter().map(|p| 8 + 24 + 3 + 8 + 8 + 8 * p.track.len()).sum::<usize>();
    assert_eq!(p3.len(), expect);
    assert_eq!(&p3[8 + 8 + 24..8 + 8 + 24 + 3], &[255, 0, 17]);
    // Nothing temporary is left.
    let mut left: Vec<String> = std::fs::read_dir(tmp.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    left.sort();
    assert_eq!(left, ["cameras.bin", "images.bin", "points3D.bin"]);
}

#[test]
fn same_bytes_whatever_the_input_order() {
    let tmp = tempfile::tempdir().unwrap();
    let mut m = model(9);
    write_binary(&tmp.path().join("a"), &m.cameras, &m.images, &m.points).unwrap();
    m.cameras.reverse();
    m.images.reverse();
    m.points.reverse();
    write_binary(&tmp.path().join("b"), &m.cameras, &m.images, &m.points).unwrap();
    for f in ["cameras.bin", "images.bin", "points3D.bin"] {
        assert_eq!(std::fs::read(tmp.path().join("a").join(f)).unwrap(), std::fs::read(tmp.path().join("b").join(f)).unwrap(), "{f}");
    }
}

fn refused(m: &Model, file: &str, words: &[&str]) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("model");
    let e = write_binary(&dir, &m.cameras, &m.images, &m.points).unwrap_err();
    assert!(matches!(e, PoseError::Input { .. }), "{e:?}");
    let s = e.to_string();
    assert!(s.contains(&dir.join(file).display().to_string()), "names the file: {s}");
    for w in words {
        assert!(s.contains(w), "`{w}` in: {s}");
    }
    assert!(!dir.exists(), "nothing is written for a refused model");
}

#[test]
fn inconsistent_models_are_refused_before_writing() {
    let mut m = model(4);
    m.images[2].camera_id = 5;
    refused(&m, "images.bin", &["image 2", "camera 5"]);

    let mut m = model(4);
    m.images[3].id = m.images[0].id;
    refused(&m, "images.bin", &["id used twice"]);

    let mut m = model(4);
    m.images[1].name = "b.png".into();
    refused(&m, "images.bin", &["name used by two images"]);

    let mut m = model(4);
    m.images[1].name = "a\0.png".into();
    refused(&m, "images.bin", &["NUL"]);

    let mut m = model(4);
    m.images[0].qvec[1] += 0.01;
    refused(&m, "images.bin", &["unit quaternion"]);

    let mut m = model(4);
    m.images[0].points2d[0].point3d_id = Some(5);
    refused(&m, "images.bin", &["3D point 5"]);

    let mut m = model(4);
    m.points[0].track[1].point2d_idx = 7;
    refused(&m, "points3D.bin", &["3D point 1", "image 9"]);

    let mut m = model(4);
    m.points[1].track.push(TrackElement { image_id: 11, point2d_idx: 0 });
    refused(&m, "points3D.bin", &["image 11"]);

    // A 2D point naming a 3D point whose track leaves it out.
    let mut m = model(4);
    m.points[1].track.clear();
    refused(&m, "images.bin", &["track does not list them"]);

    let mut m = model(4);
    m.points[2].xyz[0] = f64::NAN;
    refused(&m, "points3D.bin", &["3D point 77", "NaN"]);

    let mut m = model(4);
    m.cameras[1].fx = 0.0;
    refused(&m, "cameras.bin", &["camera 2", "positive"]);
}

#[test]
fn bad_poses_are_refused() {
    let mut c2w = c2w_of(&Rotation3::from_axis_angle(&Vector3::x_axis(), 0.3), Vector3::new(1.0, 2.0, 3.0));
    c2w[0][0] *= 1.5;
    let e = PosedImage::from_c2w(1, 1, "x.png", &c2w).unwrap_err().to_string();
    assert!(e.contains("x.png") && e.contains("not orthonormal"), "{e}");
    let mut c2w = c2w_of(&Rotation3::identity(), Vector3::zeros());
    c2w[3][2] = 0.5;
    let e = PosedImage::from_c2w(1, 1, "x.png", &c2w).unwrap_err().to_string();
    assert!(e.contains("last row"), "{e}");
    c2w[3][2] = f64::INFINITY;
    assert!(PosedImage::from_c2w(1, 1, "x.png", &c2w).unwrap_err().to_string().contains("not finite"));
    // A pose from an f32 network (orthonormal to ~1e-7) is accepted.
    let r = Rotation3::from_axis_angle(&Vector3::z_axis(), 1.0);
    let mut c2w = c2w_of(&r, Vector3::new(0.5, 0.25, -1.0));
    for row in c2w.iter_mut().take(3) {
        for v in row.iter_mut() {
            *v = *v as f32 as f64;
        }
    }
    let im = PosedImage::from_c2w(1, 1, "x.png", &c2w).unwrap();
    assert!(max_diff(&im.c2w(), &c2w) < 1e-6);
    // The centre is kept exactly (to rounding) even then.
    let back = im.c2w();
    assert!((0..3).all(|i| (back[i][3] - c2w[i][3]).abs() < 1e-15));
}

#[test]
fn rewrite_replaces_the_model_and_drops_stale_rig_files() {
    let tmp = tempfile::tempdir().unwrap();
    let m = model(6);
    write_binary(tmp.path(), &m.cameras, &m.images, &m.points).unwrap();
    std::fs::write(tmp.path().join("rigs.bin"), b"old").unwrap();
    std::fs::write(tmp.path().join("frames.bin"), b"old").unwrap();
    let m2 = model(7);
    write_binary(tmp.path(), &m2.cameras[..1], &[], &[]).unwrap();
    assert!(!tmp.path().join("rigs.bin").exists() && !tmp.path().join("frames.bin").exists());
    assert_eq!(read_cameras_bin(&tmp.path().join("cameras.bin")).unwrap().len(), 1);
    assert!(read_images_bin(&tmp.path().join("images.bin")).unwrap().is_empty());
    assert_eq!(std::fs::read(tmp.path().join("points3D.bin")).unwrap(), 0u64.to_le_bytes());
}

/// `colmap`, or a failure that says how to install it (this test must not pass without it).
fn colmap() -> PathBuf {
    let ok = Command::new("colmap").arg("-h").env("QT_QPA_PLATFORM", "offscreen").output().is_ok();
    assert!(
        ok,
        "`colmap` is not on PATH: this test checks that COLMAP itself reads the written model; install it (scripts/test does): apt-get install -y colmap"
    );
    PathBuf::from("colmap")
}

fn data_lines(path: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    text.lines().filter(|l| !l.starts_with('#')).map(str::to_string).collect()
}

fn num(s: &str) -> f64 {
    s.parse().unwrap_or_else(|_| panic!("`{s}` is not a number"))
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-15 * a.abs().max(b.abs()).max(1.0)
}

#[test]
fn colmap_reads_the_model() {
    let colmap = colmap();
    let tmp = tempfile::tempdir().unwrap();
    let m = model(11);
    let (bin, txt) = (tmp.path().join("bin"), tmp.path().join("txt"));
    write_binary(&bin, &m.cameras, &m.images, &m.points).unwrap();
    std::fs::create_dir_all(&txt).unwrap();
    let out = Command::new(&colmap)
        .args(["model_converter", "--input_path"])
        .arg(&bin)
        .arg("--output_path")
        .arg(&txt)
        .args(["--output_type", "TXT"])
        .env("QT_QPA_PLATFORM", "offscreen")
        .output()
        .unwrap();
    assert!(out.status.success(), "colmap model_converter failed: {}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));

    // cameras.txt: ID MODEL WIDTH HEIGHT PARAMS...
    let lines: Vec<String> = data_lines(&txt.join("cameras.txt")).into_iter().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), m.cameras.len());
    for l in &lines {
        let t: Vec<&str> = l.split_whitespace().collect();
        let c = m.cameras.iter().find(|c| c.id.to_string() == t[0]).unwrap_or_else(|| panic!("unknown camera in {l}"));
        assert_eq!(&t[1..4], ["PINHOLE", &c.width.to_string(), &c.height.to_string()], "{l}");
        let p: Vec<f64> = t[4..].iter().map(|s| num(s)).collect();
        assert_eq!(p.len(), 4, "{l}");
        assert!(p.iter().zip(c.params()).all(|(a, b)| close(*a, b)), "{l} vs {:?}", c.params());
    }

    // images.txt: two lines each: ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then (X Y POINT3D_ID)* (−1: none).
    let lines = data_lines(&txt.join("images.txt"));
    let lines: Vec<&String> = lines.iter().take(2 * m.images.len()).collect();
    assert_eq!(lines.len(), 2 * m.images.len());
    let mut seen = 0;
    for pair in lines.chunks(2) {
        let t: Vec<&str> = pair[0].split_whitespace().collect();
        assert_eq!(t.len(), 10, "{}", pair[0]);
        let im = m.images.iter().find(|i| i.id.to_string() == t[0]).unwrap_or_else(|| panic!("unknown image in {}", pair[0]));
        let v: Vec<f64> = t[1..8].iter().map(|s| num(s)).collect();
        assert!(v.iter().zip(im.qvec.iter().chain(&im.tvec)).all(|(a, b)| close(*a, *b)), "{} vs {:?} {:?}", pair[0], im.qvec, im.tvec);
        assert_eq!((t[8], t[9]), (im.camera_id.to_string().as_str(), im.name.as_str()));
        let p: Vec<&str> = pair[1].split_whitespace().collect();
        assert_eq!(p.len(), 3 * im.points2d.len(), "2D points of {}: {}", im.name, pair[1]);
        for (q, w) in p.chunks(3).zip(&im.points2d) {
            assert!(close(num(q[0]), w.x) && close(num(q[1]), w.y), "{}", pair[1]);
            let id: i64 = q[2].parse().unwrap();
            assert_eq!(id, w.point3d_id.map_or(-1, |i| i as i64), "{}", pair[1]);
        }
        seen += 1;
    }
    assert_eq!(seen, m.images.len());

    // points3D.txt: ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)*
    let lines: Vec<String> = data_lines(&txt.join("points3D.txt")).into_iter().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), m.points.len());
    for l in &lines {
        let t: Vec<&str> = l.split_whitespace().collect();
        let p = m.points.iter().find(|p| p.id.to_string() == t[0]).unwrap_or_else(|| panic!("unknown point in {l}"));
        assert!((1..4).all(|k| close(num(t[k]), p.xyz[k - 1])), "{l} vs {:?}", p.xyz);
        assert_eq!(&t[4..7], p.rgb.map(|c| c.to_string()), "{l}");
        assert!(close(num(t[7]), p.error), "{l}");
        let track: Vec<(u32, u32)> = t[8..].chunks(2).map(|c| (c[0].parse().unwrap(), c[1].parse().unwrap())).collect();
        assert_eq!(track, p.track.iter().map(|e| (e.image_id, e.point2d_idx)).collect::<Vec<_>>(), "{l}");
    }
}
