//! Lens distortion through the product readers, against an independent warp.
//!
//! For each model a smooth analytic pinhole image `f` (a sum of low-frequency sines) is warped into the photo a
//! distorted lens would take: for every photo pixel the distortion is inverted by Newton's method (the model's
//! equations written out again here, from COLMAP `src/colmap/sensor/models.h` and nerfstudio
//! `nerfstudio/cameras/camera_utils.py`) and `f` is evaluated at the undistorted ray — no sampling of an image.
//! The photo is stored as an 8-bit PNG beside a scene file, read back through `read_scene` + `Scene::image`
//! (which undistorts), and compared with `f` at the pinhole pixel centres.
//!
//! Error model, per channel, on pixels whose source position lies ≥ 2 px inside the photo:
//! `|undistorted − f| ≤ 0.5/255 (8-bit rounding of the photo; bilinear weights are convex, so it passes
//! through unchanged) + (h²/8)·(max|g_xx| + max|g_yy|) (bilinear interpolation of the photo's continuous image
//! g = f∘undistort, h = 1 px; the maxima sampled on a ½-px grid with a 5 % margin) + 1e-5 (f32 arithmetic)`.
//! Each test prints the worst measured error / bound; it also checks that the comparison would catch a
//! missing correction (the raw photo is far outside the bound) and, for tangential models, swapped p1/p2.

use std::path::Path;

use mvsplat360_dataset::lens::{undistort, Distortion};
use mvsplat360_dataset::{read_scene, ImageF32};

// ---- the analytic pinhole image ----

/// (amplitude, ωx, ωy, phase) per channel: periods 20–45 px, so the bilinear error stays small but nonzero.
const WAVES: [[(f64, f64, f64, f64); 3]; 3] = [
    [(0.12, 0.21, 0.05, 0.3), (0.08, -0.07, 0.24, 1.1), (0.06, 0.15, 0.16, 2.0)],
    [(0.10, 0.05, 0.27, 0.7), (0.09, 0.23, -0.11, 2.4), (0.05, 0.18, 0.18, 0.1)],
    [(0.11, 0.25, 0.13, 1.9), (0.07, 0.02, -0.19, 0.5), (0.07, -0.2, 0.1, 2.9)],
];

/// Channel `c` of the pinhole image at pixel position `(u, v)` (pixel-edge coordinates).
fn f(c: usize, u: f64, v: f64) -> f64 {
    0.5 + WAVES[c].iter().map(|&(a, wx, wy, ph)| a * (wx * u + wy * v + ph).sin()).sum::<f64>()
}

// ---- the lens, written out independently of the product ----

/// Coefficients in the scene file's order, with the model they belong to.
#[derive(Clone, Copy, Debug)]
enum Lens {
    SimpleRadial([f64; 1]),
    Radial([f64; 2]),
    OpenCv([f64; 4]),
    FullOpenCv([f64; 8]),
    /// transforms.json k1, k2, k3, k4, p1, p2.
    Nerfstudio([f64; 6]),
}

impl Lens {
    /// COLMAP's `Distortion(u, v) → (du, dv)` plus the identity.
    fn forward(self, u: f64, v: f64) -> (f64, f64) {
        let (u2, v2, uv) = (u * u, v * v, u * v);
        let r2 = u2 + v2;
        let tangential = |p1: f64, p2: f64| (2.0 * p1 * uv + p2 * (r2 + 2.0 * u2), 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2));
        let (radial_minus_1, (tu, tv)) = match self {
            Lens::SimpleRadial([k]) => (k * r2, (0.0, 0.0)),
            Lens::Radial([k1, k2]) => (k1 * r2 + k2 * r2 * r2, (0.0, 0.0)),
            Lens::OpenCv([k1, k2, p1, p2]) => (k1 * r2 + k2 * r2 * r2, tangential(p1, p2)),
            Lens::FullOpenCv([k1, k2, p1, p2, k3, k4, k5, k6]) => {
                let (r4, r6) = (r2 * r2, r2 * r2 * r2);
                ((1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6) - 1.0, tangential(p1, p2))
            }
            // nerfstudio's d(r) = 1 + r·(k1 + r·(k2 + r·(k3 + r·k4))) with r = x² + y².
            Lens::Nerfstudio([k1, k2, k3, k4, p1, p2]) => (r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4))), tangential(p1, p2)),
        };
        (u + u * radial_minus_1 + tu, v + v * radial_minus_1 + tv)
    }

    /// The undistorted ray of a distorted one: Newton's method with a central-difference Jacobian.
    fn inverse(self, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..60 {
            let (fx, fy) = self.forward(x, y);
            let (rx, ry) = (fx - xd, fy - yd);
            if rx.abs().max(ry.abs()) < 1e-14 {
                return (x, y);
            }
            let h = 1e-6;
            let (ax, ay) = self.forward(x + h, y);
            let (bx, by) = self.forward(x - h, y);
            let (cx, cy) = self.forward(x, y + h);
            let (dx, dy) = self.forward(x, y - h);
            let (j00, j10, j01, j11) = ((ax - bx) / (2.0 * h), (ay - by) / (2.0 * h), (cx - dx) / (2.0 * h), (cy - dy) / (2.0 * h));
            let det = j00 * j11 - j01 * j10;
            x -= (j11 * rx - j01 * ry) / det;
            y -= (-j10 * rx + j00 * ry) / det;
        }
        panic!("Newton did not converge at ({xd}, {yd})");
    }

    fn colmap_line(self, id: u32, k: &Intr) -> String {
        let (model, p): (&str, Vec<f64>) = match self {
            Lens::SimpleRadial(c) => ("SIMPLE_RADIAL", [&[k.fx, k.cx, k.cy][..], &c[..]].concat()),
            Lens::Radial(c) => ("RADIAL", [&[k.fx, k.cx, k.cy][..], &c[..]].concat()),
            Lens::OpenCv(c) => ("OPENCV", [&[k.fx, k.fy, k.cx, k.cy][..], &c[..]].concat()),
            Lens::FullOpenCv(c) => ("FULL_OPENCV", [&[k.fx, k.fy, k.cx, k.cy][..], &c[..]].concat()),
            Lens::Nerfstudio(_) => unreachable!("not a COLMAP model"),
        };
        let p: Vec<String> = p.iter().map(|v| format!("{v:.17}")).collect();
        format!("{id} {model} {} {} {}\n", k.w, k.h, p.join(" "))
    }

    fn json_keys(self) -> String {
        let Lens::Nerfstudio([k1, k2, k3, k4, p1, p2]) = self else { unreachable!() };
        format!(r#""k1": {k1}, "k2": {k2}, "k3": {k3}, "k4": {k4}, "p1": {p1}, "p2": {p2}"#)
    }

    fn swapped_tangential(self) -> Option<Distortion> {
        match self {
            Lens::OpenCv([k1, k2, p1, p2]) => Some(Distortion::OpenCv { k1, k2, p1: p2, p2: p1 }),
            Lens::FullOpenCv([k1, k2, p1, p2, k3, k4, k5, k6]) => Some(Distortion::FullOpenCv { k1, k2, p1: p2, p2: p1, k3, k4, k5, k6 }),
            Lens::Nerfstudio([k1, k2, k3, k4, p1, p2]) => Some(Distortion::Perspective { k1, k2, k3, k4, p1: p2, p2: p1 }),
            _ => None,
        }
    }
}

/// A view's size and pinhole intrinsics (a single f for the one-focal COLMAP models).
#[derive(Clone, Copy, Debug)]
struct Intr {
    w: u32,
    h: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

/// Two sizes, landscape and portrait, principal points off centre; `single` = one focal length.
fn sizes(single: bool) -> [Intr; 2] {
    let fy = |f: f64, g: f64| if single { f } else { g };
    [Intr { w: 96, h: 64, fx: 72.0, fy: fy(72.0, 69.5), cx: 48.6, cy: 31.3 }, Intr { w: 72, h: 100, fx: 80.0, fy: fy(80.0, 83.0), cx: 35.2, cy: 50.9 }]
}

// ---- the independent warp and the comparison ----

/// The photo the lens takes of `f`: each pixel centre inverted through the lens, `f` evaluated at its pinhole
/// position. 8-bit, rounded.
fn distorted_photo(lens: Lens, k: &Intr) -> image::RgbImage {
    image::RgbImage::from_fn(k.w, k.h, |i, j| {
        let (x, y) = lens.inverse((i as f64 + 0.5 - k.cx) / k.fx, (j as f64 + 0.5 - k.cy) / k.fy);
        let (u, v) = (k.fx * x + k.cx, k.fy * y + k.cy);
        image::Rgb(std::array::from_fn(|c| (f(c, u, v) * 255.0).round().clamp(0.0, 255.0) as u8))
    })
}

/// The photo's continuous image (all channels) at photo position `(s, t)`.
fn g(lens: Lens, k: &Intr, s: f64, t: f64) -> [f64; 3] {
    let (x, y) = lens.inverse((s - k.cx) / k.fx, (t - k.cy) / k.fy);
    std::array::from_fn(|c| f(c, k.fx * x + k.cx, k.fy * y + k.cy))
}

/// The bound of the module docs per channel: max |g_ss|, |g_tt| on a ½-px grid over the photo's interior.
fn bounds(lens: Lens, k: &Intr) -> [f64; 3] {
    let d = 0.5;
    let (mut mss, mut mtt) = ([0f64; 3], [0f64; 3]);
    for a in 2..2 * k.w - 1 {
        for b in 2..2 * k.h - 1 {
            let (s, t) = (a as f64 * d, b as f64 * d);
            let (g0, gl, gr, gu, gd) = (g(lens, k, s, t), g(lens, k, s - d, t), g(lens, k, s + d, t), g(lens, k, s, t - d), g(lens, k, s, t + d));
            for c in 0..3 {
                mss[c] = mss[c].max(((gr[c] - 2.0 * g0[c] + gl[c]) / (d * d)).abs());
                mtt[c] = mtt[c].max(((gd[c] - 2.0 * g0[c] + gu[c]) / (d * d)).abs());
            }
        }
    }
    std::array::from_fn(|c| 0.5 / 255.0 + 1.05 * (mss[c] + mtt[c]) / 8.0 + 1e-5)
}

/// Worst |img − f| / bound over the pixels whose source lies ≥ 2 px inside the photo; also the pixel count.
fn worst_ratio(img: &ImageF32, lens: Lens, k: &Intr, bounds: &[f64; 3]) -> (f64, usize) {
    assert_eq!((img.width, img.height), (k.w, k.h), "the pinhole image keeps the photo's size");
    let (w, h) = (k.w as usize, k.h as usize);
    let (mut worst, mut n) = (0f64, 0);
    for j in 0..h {
        for i in 0..w {
            let (u, v) = (i as f64 + 0.5, j as f64 + 0.5);
            let (xd, yd) = lens.forward((u - k.cx) / k.fx, (v - k.cy) / k.fy);
            let (s, t) = (k.fx * xd + k.cx, k.fy * yd + k.cy);
            if s < 2.0 || t < 2.0 || s > k.w as f64 - 2.0 || t > k.h as f64 - 2.0 {
                continue;
            }
            n += 1;
            for (c, b) in bounds.iter().enumerate() {
                let err = (img.data[c * w * h + j * w + i] as f64 - f(c, u, v)).abs();
                worst = worst.max(err / b);
            }
        }
    }
    (worst, n)
}

/// Check one read-back view: within the bound, and the check is sharp (raw photo, swapped p1/p2 fail it).
fn check_view(what: &str, got: &ImageF32, photo: &image::RgbImage, lens: Lens, k: &Intr) -> f64 {
    let b = bounds(lens, k);
    let (ratio, n) = worst_ratio(got, lens, k, &b);
    assert!(n > (k.w * k.h) as usize / 2, "{what}: only {n} pixels compared");
    let raw = ImageF32::from_rgb8(photo);
    let (raw_ratio, _) = worst_ratio(&raw, lens, k, &b);
    eprintln!(
        "{what}: worst error / bound {ratio:.3} over {n} pixels, bound {:.4}..{:.4} (uncorrected photo: {raw_ratio:.1})",
        b.iter().fold(1f64, |m, &x| m.min(x)),
        b.iter().fold(0f64, |m, &x| m.max(x))
    );
    assert!(ratio <= 1.0, "{what}: error {ratio:.3}× the bound");
    assert!(raw_ratio > 5.0, "{what}: the uncorrected photo is only {raw_ratio:.2}× the bound; the test would not notice a missing correction");
    if let Some(swapped) = lens.swapped_tangential() {
        let cam = mvsplat360_camera::Camera { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy, width: k.w, height: k.h, c2w: IDENT4 };
        let (sw, _) = worst_ratio(&undistort(&raw, &cam, &swapped), lens, k, &b);
        eprintln!("  ...with p1 and p2 swapped: {sw:.2}");
        assert!(sw > 2.0, "{what}: swapping p1 and p2 stays within {sw:.2}× the bound; the test would not notice");
    }
    ratio
}

const IDENT4: [[f64; 4]; 4] = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
const IDENT: &str = "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";

/// A COLMAP text scene with one camera and one image per (coefficient set, size), read back and checked.
fn colmap_case(name: &str, sets: [Lens; 2], single_focal: bool) {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("sparse/0")).unwrap();
    std::fs::create_dir_all(root.join("images")).unwrap();
    let (mut cams, mut imgs, mut views) = (String::new(), String::new(), Vec::new());
    for (a, lens) in sets.iter().enumerate() {
        for (b, k) in sizes(single_focal).iter().enumerate() {
            let id = (a * 2 + b + 1) as u32;
            let file = format!("v{id}.png");
            let photo = distorted_photo(*lens, k);
            photo.save(root.join("images").join(&file)).unwrap();
            cams.push_str(&lens.colmap_line(id, k));
            imgs.push_str(&format!("{id} 1 0 0 0 0 0 0 {id} {file}\n\n"));
            views.push((file, photo, *lens, *k));
        }
    }
    std::fs::write(root.join("sparse/0/cameras.txt"), cams).unwrap();
    std::fs::write(root.join("sparse/0/images.txt"), imgs).unwrap();
    let scene = read_scene(root).unwrap();
    let mut worst = 0f64;
    for (file, photo, lens, k) in &views {
        let i = scene.view_names.iter().position(|n| n == file).unwrap();
        assert!(scene.lens(i).is_some(), "{name} {file}: distortion attached");
        worst = worst.max(check_view(&format!("{name} {file} {}x{}", k.w, k.h), &scene.image(i).unwrap(), photo, *lens, k));
    }
    eprintln!("{name}: worst error / bound {worst:.3}");
}

#[test]
fn colmap_simple_radial() {
    colmap_case("SIMPLE_RADIAL", [Lens::SimpleRadial([-0.12]), Lens::SimpleRadial([0.08])], true);
}

#[test]
fn colmap_radial() {
    colmap_case("RADIAL", [Lens::Radial([-0.10, 0.02]), Lens::Radial([0.06, -0.03])], true);
}

#[test]
fn colmap_opencv() {
    colmap_case("OPENCV", [Lens::OpenCv([-0.09, 0.015, 0.012, -0.008]), Lens::OpenCv([0.05, -0.02, -0.015, 0.01])], false);
}

#[test]
fn colmap_full_opencv() {
    colmap_case(
        "FULL_OPENCV",
        [Lens::FullOpenCv([-0.08, 0.02, 0.01, -0.006, 0.005, 0.05, -0.01, 0.004]), Lens::FullOpenCv([0.1, -0.03, -0.008, 0.012, 0.01, 0.12, 0.02, -0.005])],
        false,
    );
}

fn json_frame(file: &str, k: &Intr, keys: Option<String>) -> String {
    let extra = keys.map(|s| format!(", {s}")).unwrap_or_default();
    format!(
        r#"{{"file_path": "{file}", "transform_matrix": {IDENT}, "fl_x": {}, "fl_y": {}, "cx": {}, "cy": {}, "w": {}, "h": {}{extra}}}"#,
        k.fx, k.fy, k.cx, k.cy, k.w, k.h
    )
}

/// transforms.json, distortion top level (every frame, both sizes) and per frame (overriding a different top
/// level, beside a frame that inherits it).
#[test]
fn transforms_json_perspective_top_level_and_per_frame() {
    let a = Lens::Nerfstudio([-0.1, 0.03, -0.01, 0.004, 0.01, -0.012]);
    let b = Lens::Nerfstudio([0.07, -0.02, 0.008, -0.002, -0.009, 0.011]);
    let [k1, k2] = sizes(false);
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let mut worst = 0f64;
    let mut run = |json: &str, frames: Vec<(&str, Intr, Lens)>| {
        let mut photos = Vec::new();
        for (file, k, lens) in &frames {
            let p = distorted_photo(*lens, k);
            p.save(d.join(file)).unwrap();
            photos.push(p);
        }
        let scene = read_scene(&d.join(json)).unwrap();
        for (i, ((file, k, lens), photo)) in frames.iter().zip(&photos).enumerate() {
            assert_eq!(&scene.view_names[i], file);
            worst = worst.max(check_view(&format!("{json} {file} {}x{}", k.w, k.h), &scene.image(i).unwrap(), photo, *lens, k));
        }
    };
    // Top level: both sizes take the same coefficients; camera_model given explicitly.
    let frames = [json_frame("t1.png", &k1, None), json_frame("t2.png", &k2, None)].join(", ");
    std::fs::write(d.join("top.json"), format!(r#"{{"camera_model": "OPENCV", {}, "frames": [{frames}]}}"#, a.json_keys())).unwrap();
    run("top.json", vec![("t1.png", k1, a), ("t2.png", k2, a)]);
    // Top level b (no camera_model: the default perspective model); frames 0-1 override every key with a.
    let frames = [json_frame("p1.png", &k1, Some(a.json_keys())), json_frame("p2.png", &k2, Some(a.json_keys())), json_frame("p3.png", &k2, None)].join(", ");
    std::fs::write(d.join("frames.json"), format!(r#"{{{}, "frames": [{frames}]}}"#, b.json_keys())).unwrap();
    run("frames.json", vec![("p1.png", k1, a), ("p2.png", k2, a), ("p3.png", k2, b)]);
    eprintln!("nerfstudio perspective: worst error / bound {worst:.3}");
}

// ---- closed form, refusals, EXIF, sizes ----

/// distort() at (x, y) = (1/2, −1/4) against values worked out by hand with exact fractions: r² = 5/16,
/// 2xy = −1/4, r² + 2x² = 13/16, r² + 2y² = 7/16.
#[test]
fn distort_closed_form() {
    let (x, y) = (0.5, -0.25);
    let (k1, k2, p1, p2) = (0.1, -0.01, 0.001, 0.002);
    // radial 1 + k·r² = 1 + 1/32 = 33/32.
    let sr = Distortion::SimpleRadial { k: 0.1 };
    // radial 1 + 1/32 − 25/25600 = 1055/1024.
    let r = Distortion::Radial { k1, k2 };
    // tangential x: p1·(−1/4) + p2·13/16 = 0.001375; y: p1·7/16 + p2·(−1/4) = −0.0000625.
    let ocv = Distortion::OpenCv { k1, k2, p1, p2 };
    // radial (1055/1024 + 0.003·125/4096) / (1 + 0.05·5/16 − 0.02·25/256 + 0.005·125/4096).
    let full = Distortion::FullOpenCv { k1, k2, p1, p2, k3: 0.003, k4: 0.05, k5: -0.02, k6: 0.005 };
    // radial 1 − 0.1·5/16 + 0.02·25/256 − 0.003·125/4096 + 0.004·625/65536.
    let persp = Distortion::Perspective { k1: -0.1, k2: 0.02, k3: -0.003, k4: 0.004, p1, p2 };
    let cases = [
        (sr, (33.0 / 64.0, -33.0 / 128.0)),
        (r, (1055.0 / 2048.0, -1055.0 / 4096.0)),
        (ocv, (132227.0 / 256000.0, -131907.0 / 512000.0)),
        (full, (135417431.0 / 265768000.0, -135085221.0 / 531536000.0)),
        (persp, (15948181.0 / 32768000.0, -15907221.0 / 65536000.0)),
    ];
    for (d, (ex, ey)) in cases {
        let (gx, gy) = d.distort(x, y);
        assert!((gx - ex).abs() < 1e-15 && (gy - ey).abs() < 1e-15, "{}: ({gx}, {gy}) vs ({ex}, {ey})", d.name());
    }
    assert_eq!(ocv.distort(0.0, 0.0), (0.0, 0.0));
}

fn err_of(p: &Path) -> String {
    match read_scene(p) {
        Ok(_) => panic!("{} should be refused", p.display()),
        Err(e) => e.to_string(),
    }
}

fn assert_refusal(e: &str, file: &str, what: &str, model: &str) {
    for needle in [file, what, model, "mvsplat360 pose", "colmap image_undistorter"] {
        assert!(e.contains(needle), "expected `{needle}` in `{e}`");
    }
}

#[test]
fn transforms_json_fisheye_equirectangular_unknown_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    image::RgbImage::new(8, 6).save(d.join("a.png")).unwrap();
    let frame = |extra: &str| format!(r#"{{"file_path": "a.png", "transform_matrix": {IDENT}{extra}}}"#);
    let cases = [
        (
            "fisheye.json",
            format!(r#"{{"camera_model": "OPENCV_FISHEYE", "fl_x": 5, "k1": 0.1, "frames": [{}]}}"#, frame("")),
            "camera_model (frame 0, a.png)",
            "OPENCV_FISHEYE",
        ),
        (
            "equirect.json",
            format!(r#"{{"fl_x": 5, "frames": [{}]}}"#, frame(r#", "camera_model": "EQUIRECTANGULAR""#)),
            "frames[0].camera_model",
            "EQUIRECTANGULAR",
        ),
        ("unknown.json", format!(r#"{{"camera_model": "BANANA", "fl_x": 5, "frames": [{}]}}"#, frame("")), "camera_model", "BANANA"),
        // A frame's own model wins over a perspective top level.
        (
            "override.json",
            format!(r#"{{"camera_model": "PINHOLE", "fl_x": 5, "frames": [{}]}}"#, frame(r#", "camera_model": "OPENCV_FISHEYE""#)),
            "frames[0].camera_model",
            "OPENCV_FISHEYE",
        ),
    ];
    for (file, json, what, model) in cases {
        std::fs::write(d.join(file), json).unwrap();
        assert_refusal(&err_of(&d.join(file)), file, what, model);
    }
    // Perspective models read; all-zero coefficients mean no lens.
    std::fs::write(d.join("pinhole.json"), format!(r#"{{"camera_model": "SIMPLE_RADIAL", "k1": 0, "p2": 0.0, "fl_x": 5, "frames": [{}]}}"#, frame("")))
        .unwrap();
    let s = read_scene(&d.join("pinhole.json")).unwrap();
    assert!(s.lens(0).is_none());
    // A non-string model names its field.
    std::fs::write(d.join("num.json"), format!(r#"{{"camera_model": 3, "fl_x": 5, "frames": [{}]}}"#, frame(""))).unwrap();
    assert!(err_of(&d.join("num.json")).contains("camera_model: expected a string"));
}

/// instant-ngp's `"is_fisheye": true` (top level or per frame, the frame's value winning) is refused as a fisheye,
/// naming the file, the field and the fix, whatever `camera_model` says; `false` reads as before.
#[test]
fn transforms_json_instant_ngp_is_fisheye_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    image::RgbImage::new(8, 6).save(d.join("a.png")).unwrap();
    let frame = |extra: &str| format!(r#"{{"file_path": "a.png", "transform_matrix": {IDENT}{extra}}}"#);
    let cases = [
        ("top.json", format!(r#"{{"is_fisheye": true, "fl_x": 5, "k1": 0.1, "frames": [{}]}}"#, frame("")), "is_fisheye (frame 0, a.png)"),
        ("frame.json", format!(r#"{{"fl_x": 5, "frames": [{}, {}]}}"#, frame(""), frame(r#", "is_fisheye": true"#)), "frames[1].is_fisheye (frame 1, a.png)"),
        (
            "override.json",
            format!(r#"{{"is_fisheye": false, "camera_model": "PINHOLE", "fl_x": 5, "frames": [{}]}}"#, frame(r#", "is_fisheye": true"#)),
            "frames[0].is_fisheye",
        ),
    ];
    for (file, json, what) in cases {
        std::fs::write(d.join(file), json).unwrap();
        let e = err_of(&d.join(file));
        assert_refusal(&e, file, what, "is_fisheye");
        assert!(e.contains("fisheye lens"), "{e}");
    }
    // `false`, top level or per frame, is a perspective lens as before.
    std::fs::write(d.join("no.json"), format!(r#"{{"is_fisheye": false, "fl_x": 5, "frames": [{}]}}"#, frame(r#", "is_fisheye": false"#))).unwrap();
    assert!(read_scene(&d.join("no.json")).unwrap().lens(0).is_none());
    // A frame's `false` wins over a top-level `true`.
    std::fs::write(d.join("mixed.json"), format!(r#"{{"is_fisheye": true, "fl_x": 5, "frames": [{}]}}"#, frame(r#", "is_fisheye": false"#))).unwrap();
    assert_eq!(read_scene(&d.join("mixed.json")).unwrap().len(), 1);
    // Not a boolean: the field is named.
    std::fs::write(d.join("num.json"), format!(r#"{{"is_fisheye": 1, "fl_x": 5, "frames": [{}]}}"#, frame(""))).unwrap();
    let e = err_of(&d.join("num.json"));
    assert!(e.contains("is_fisheye") && e.contains("expected true or false"), "{e}");
}

/// COLMAP `cameras.bin` with one camera of `model_id` and `params`.
fn cameras_bin(model_id: i32, params: &[f64]) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(&1u64.to_le_bytes());
    b.extend_from_slice(&1i32.to_le_bytes());
    b.extend_from_slice(&model_id.to_le_bytes());
    b.extend_from_slice(&8u64.to_le_bytes());
    b.extend_from_slice(&6u64.to_le_bytes());
    for p in params {
        b.extend_from_slice(&p.to_le_bytes());
    }
    b
}

#[test]
fn colmap_fisheye_and_spherical_refused_text_and_binary() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tmp.path().join("sparse/0");
    std::fs::create_dir_all(&m).unwrap();
    std::fs::create_dir_all(tmp.path().join("images")).unwrap();
    image::RgbImage::new(8, 6).save(tmp.path().join("images/a.png")).unwrap();
    std::fs::write(m.join("images.txt"), "1 1 0 0 0 0 0 0 1 a.png\n\n").unwrap();
    for line in [
        "1 OPENCV_FISHEYE 8 6 5 5 4 3 0.1 0 0 0",
        "1 SIMPLE_RADIAL_FISHEYE 8 6 5 4 3 0.1",
        "1 RADIAL_FISHEYE 8 6 5 4 3 0.1 0.01",
        "1 THIN_PRISM_FISHEYE 8 6 5 5 4 3 0 0 0 0 0 0 0 0",
        "1 FOV 8 6 5 5 4 3 0.9",
        "1 EQUIRECTANGULAR 8 6 8 6",
    ] {
        std::fs::write(m.join("cameras.txt"), format!("{line}\n")).unwrap();
        let model = line.split(' ').nth(1).unwrap();
        assert_refusal(&err_of(tmp.path()), "cameras.txt", "camera 1", model);
    }
    std::fs::remove_file(m.join("cameras.txt")).unwrap();
    std::fs::remove_file(m.join("images.txt")).unwrap();
    // images.bin with one image (id 1, identity pose, camera 1, a.png, no points).
    let mut ib = Vec::new();
    ib.extend_from_slice(&1u64.to_le_bytes());
    ib.extend_from_slice(&1i32.to_le_bytes());
    for v in [1.0f64, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0] {
        ib.extend_from_slice(&v.to_le_bytes());
    }
    ib.extend_from_slice(&1i32.to_le_bytes());
    ib.extend_from_slice(b"a.png\0");
    ib.extend_from_slice(&0u64.to_le_bytes());
    std::fs::write(m.join("images.bin"), ib).unwrap();
    for (id, model, params) in [
        (5, "OPENCV_FISHEYE", vec![5.0, 5.0, 4.0, 3.0, 0.1, 0.0, 0.0, 0.0]),
        (7, "FOV", vec![5.0, 5.0, 4.0, 3.0, 0.9]),
        (17, "EQUIRECTANGULAR", vec![8.0, 6.0]),
    ] {
        std::fs::write(m.join("cameras.bin"), cameras_bin(id, &params)).unwrap();
        assert_refusal(&err_of(tmp.path()), "cameras.bin", "camera 1", model);
    }
    // The binary distorted models keep every parameter: RADIAL has 5, FULL_OPENCV 12.
    std::fs::write(m.join("cameras.bin"), cameras_bin(3, &[5.0, 4.0, 3.0, 0.01, -0.002])).unwrap();
    let s = read_scene(tmp.path()).unwrap();
    assert_eq!(s.lens(0), Some(&Distortion::Radial { k1: 0.01, k2: -0.002 }));
    let full: Vec<f64> = (0..12).map(|i| if i < 4 { [5.0, 5.5, 4.0, 3.0][i] } else { 0.001 * i as f64 }).collect();
    std::fs::write(m.join("cameras.bin"), cameras_bin(6, &full)).unwrap();
    let s = read_scene(tmp.path()).unwrap();
    assert_eq!((s.cameras[0].fx, s.cameras[0].fy, s.cameras[0].cx, s.cameras[0].cy), (5.0, 5.5, 4.0, 3.0));
    let p = &full[4..];
    assert_eq!(s.lens(0), Some(&Distortion::FullOpenCv { k1: p[0], k2: p[1], p1: p[2], p2: p[3], k3: p[4], k4: p[5], k5: p[6], k6: p[7] }));
    let cams = mvsplat360_dataset::colmap::read_cameras_bin(&m.join("cameras.bin")).unwrap();
    assert_eq!(cams[&1].params, full);
}

/// A JPEG with an APP1 EXIF segment holding only the orientation tag (little-endian TIFF, IFD0 with one entry).
fn jpeg_with_orientation(orientation: Option<u16>, w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 9) as u8, (y * 7) as u8, 50]));
    let mut jpg = std::io::Cursor::new(Vec::new());
    img.write_to(&mut jpg, image::ImageFormat::Jpeg).unwrap();
    let jpg = jpg.into_inner();
    let Some(o) = orientation else { return jpg };
    let mut tiff = b"II*\0".to_vec();
    tiff.extend_from_slice(&8u32.to_le_bytes());
    tiff.extend_from_slice(&1u16.to_le_bytes());
    for v in [0x0112u16, 3] {
        tiff.extend_from_slice(&v.to_le_bytes());
    }
    tiff.extend_from_slice(&1u32.to_le_bytes());
    tiff.extend_from_slice(&o.to_le_bytes());
    tiff.extend_from_slice(&[0, 0, 0, 0, 0, 0]);
    let mut app1 = vec![0xFF, 0xE1];
    app1.extend_from_slice(&((2 + 6 + tiff.len()) as u16).to_be_bytes());
    app1.extend_from_slice(b"Exif\0\0");
    app1.extend_from_slice(&tiff);
    [&jpg[..2], &app1, &jpg[2..]].concat()
}

#[test]
fn exif_orientation_is_reported_never_applied() {
    use image::ImageDecoder;
    for o in [1u16, 3, 6, 8] {
        let bytes = jpeg_with_orientation(Some(o), 12, 8);
        assert_eq!(mvsplat360_dataset::image::jpeg_exif_orientation(&bytes), Some(o));
        // image's own decoder reads the same tag from the same bytes.
        let mut dec = image::codecs::jpeg::JpegDecoder::new(std::io::Cursor::new(&bytes)).unwrap();
        assert_eq!(dec.orientation().unwrap().to_exif() as u16, o);
    }
    assert_eq!(mvsplat360_dataset::image::jpeg_exif_orientation(&jpeg_with_orientation(None, 12, 8)), None);
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    std::fs::write(d.join("a.jpg"), jpeg_with_orientation(Some(1), 12, 8)).unwrap();
    std::fs::write(d.join("b.jpg"), jpeg_with_orientation(None, 12, 8)).unwrap();
    std::fs::write(d.join("c.jpg"), jpeg_with_orientation(Some(6), 12, 8)).unwrap();
    std::fs::write(d.join("d.jpg"), jpeg_with_orientation(Some(8), 12, 8)).unwrap();
    let frames: Vec<String> = ["a", "b", "c", "d"].iter().map(|n| format!(r#"{{"file_path": "{n}.jpg", "transform_matrix": {IDENT}}}"#)).collect();
    std::fs::write(d.join("transforms.json"), format!(r#"{{"fl_x": 10, "frames": [{}]}}"#, frames.join(", "))).unwrap();
    let s = read_scene(d).unwrap();
    // The first tagged view (in view order) is the one the warning names.
    assert_eq!(s.exif_rotated_view(), Some((2, 6)));
    // Pixels as stored: a 90° tag does not swap the size.
    let img = s.image(2).unwrap();
    assert_eq!((img.width, img.height), (12, 8));
}

#[test]
fn mixed_sizes_are_read() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    image::RgbImage::new(8, 6).save(d.join("a.png")).unwrap();
    image::RgbImage::new(6, 10).save(d.join("b.png")).unwrap();
    let frames = [format!(r#"{{"file_path": "a.png", "transform_matrix": {IDENT}}}"#), format!(r#"{{"file_path": "b.png", "transform_matrix": {IDENT}}}"#)];
    std::fs::write(d.join("transforms.json"), format!(r#"{{"fl_x": 5, "frames": [{}]}}"#, frames.join(", "))).unwrap();
    let s = read_scene(d).unwrap();
    assert_eq!([(s.cameras[0].width, s.cameras[0].height), (s.cameras[1].width, s.cameras[1].height)], [(8, 6), (6, 10)]);
    assert_eq!((s.image(1).unwrap().width, s.image(1).unwrap().height), (6, 10));
}
