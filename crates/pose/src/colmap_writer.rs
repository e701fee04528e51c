//! COLMAP sparse models written in COLMAP's binary format (`cameras.bin`, `images.bin`, `points3D.bin`), for scene
//! folders posed without COLMAP (the vggt model). The layout is the one of `WriteCamerasBinary`,
//! `WriteImagesBinary` and `WritePoints3DBinary` (`src/colmap/scene/reconstruction_io_binary.cc`), all
//! little-endian:
//!
//! - `cameras.bin`: u64 count; each: u32 camera_id, i32 model_id (PINHOLE = 1), u64 width, u64 height,
//!   f64 params (fx, fy, cx, cy).
//! - `images.bin`: u64 count; each: u32 image_id, f64 qw qx qy qz, f64 tx ty tz (world-to-camera), u32 camera_id,
//!   the name's bytes + NUL, u64 num_points2D, then per point f64 x, f64 y, u64 point3D_id (`u64::MAX`, i.e. −1
//!   as a signed number, for none).
//! - `points3D.bin`: u64 count; each: u64 point3D_id, f64 x y z, u8 r g b, f64 error, u64 track_length, then per
//!   element u32 image_id, u32 point2D_idx.
//!
//! COLMAP ≥ 3.12 also writes `rigs.bin` and `frames.bin`, and reads them when present; without them it reads a
//! model as one rig per camera and one frame per image (its backward-compatible path), which is what these files
//! describe. Records are written sorted by id, as COLMAP writes them, so the bytes do not depend on input order.

use std::collections::{HashMap, HashSet};
use std::io::{BufWriter, Write};
use std::path::Path;

use mvsplat360_camera::Camera;
use mvsplat360_dataset::atomic::write_atomic;

use crate::error::PoseError;

/// COLMAP's model id of PINHOLE (`src/colmap/sensor/models.h`).
pub const PINHOLE_MODEL_ID: i32 = 1;

/// The `point3D_id` of a 2D point that observes no 3D point (COLMAP's `kInvalidPoint3DId`).
pub const NO_POINT3D: u64 = u64::MAX;

/// The error COLMAP stores for a 3D point whose reprojection error is unknown.
pub const UNKNOWN_ERROR: f64 = -1.0;

/// A rotation is accepted as one when `RᵀR` is within this of the identity (each entry) and det R > 0: a pose
/// from a network in f32 passes, a scaled or sheared matrix does not.
pub const ROTATION_TOLERANCE: f64 = 1e-4;

/// A PINHOLE camera (COLMAP model id 1): focal lengths and principal point in pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct PinholeCamera {
    pub id: u32,
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl PinholeCamera {
    /// The intrinsics of one of our cameras (its pose goes to [`PosedImage::from_c2w`]).
    pub fn from_camera(id: u32, c: &Camera) -> PinholeCamera {
        PinholeCamera { id, width: c.width, height: c.height, fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy }
    }

    /// COLMAP's parameter order for PINHOLE.
    pub fn params(&self) -> [f64; 4] {
        [self.fx, self.fy, self.cx, self.cy]
    }
}

/// A 2D point of an image and the 3D point it observes, if any.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point2D {
    pub x: f64,
    pub y: f64,
    pub point3d_id: Option<u64>,
}

/// An image with its pose as COLMAP stores it: the world-to-camera rotation as a unit quaternion
/// `qvec = [qw, qx, qy, qz]` and translation `tvec`, OpenCV axes.
#[derive(Debug, Clone, PartialEq)]
pub struct PosedImage {
    pub id: u32,
    pub camera_id: u32,
    /// The file's path relative to the scene's `images/` folder.
    pub name: String,
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub points2d: Vec<Point2D>,
}

/// One observation of a 3D point: image `image_id`'s 2D point number `point2d_idx`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct TrackElement {
    pub image_id: u32,
    pub point2d_idx: u32,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Point3D {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    /// Mean reprojection error in pixels; [`UNKNOWN_ERROR`] when not known.
    pub error: f64,
    pub track: Vec<TrackElement>,
}

impl PosedImage {
    /// The image of a camera-to-world 4×4 (OpenCV axes, the project's convention), without 2D points: the exact
    /// inverse of what the COLMAP reader does (`mvsplat360_camera::convert::colmap_to_c2w`). The quaternion is
    /// normalised with `qw ≥ 0`; the translation is computed from the rotation the quaternion stores, so the
    /// camera centre is kept exactly.
    pub fn from_c2w(id: u32, camera_id: u32, name: impl Into<String>, c2w: &[[f64; 4]; 4]) -> Result<PosedImage, PoseError> {
        let name = name.into();
        let bad = |msg: String| PoseError::Input { path: name.clone().into(), msg: format!("image {id}: camera-to-world matrix {msg}") };
        if let Some(v) = c2w.iter().flatten().find(|v| !v.is_finite()) {
            return Err(bad(format!("holds {v}, which is not finite")));
        }
        if c2w[3] != [0.0, 0.0, 0.0, 1.0] {
            return Err(bad(format!("has last row {:?}; a rigid transform's is [0, 0, 0, 1]", c2w[3])));
        }
        let r_c2w = [[c2w[0][0], c2w[0][1], c2w[0][2]], [c2w[1][0], c2w[1][1], c2w[1][2]], [c2w[2][0], c2w[2][1], c2w[2][2]]];
        check_rotation(&r_c2w).map_err(|m| bad(format!("has rotation part {r_c2w:?}, which {m}")))?;
        let r_w2c = transpose(&r_c2w);
        let qvec = rotation_to_quaternion(&r_w2c);
        let r = quaternion_to_rotation(qvec);
        let centre = [c2w[0][3], c2w[1][3], c2w[2][3]];
        let rc = mul_vec(&r, &centre);
        Ok(PosedImage { id, camera_id, name, qvec, tvec: [-rc[0], -rc[1], -rc[2]], points2d: vec![] })
    }

    /// The camera-to-world 4×4 this image's pose describes.
    pub fn c2w(&self) -> [[f64; 4]; 4] {
        let rt = transpose(&quaternion_to_rotation(self.qvec));
        let c = mul_vec(&rt, &self.tvec);
        let mut m = [[0.0; 4]; 4];
        for i in 0..3 {
            m[i][..3].copy_from_slice(&rt[i]);
            m[i][3] = -c[i];
        }
        m[3][3] = 1.0;
        m
    }
}

type M3 = [[f64; 3]; 3];

fn transpose(m: &M3) -> M3 {
    let mut t = [[0.0; 3]; 3];
    for (i, row) in m.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            t[j][i] = *v;
        }
    }
    t
}

fn mul_vec(m: &M3, v: &[f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2])
}

/// Err(why) when `r` is not a rotation within [`ROTATION_TOLERANCE`].
fn check_rotation(r: &M3) -> Result<(), String> {
    let mut worst = 0.0f64;
    for i in 0..3 {
        for j in 0..3 {
            let dot: f64 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
            worst = worst.max((dot - if i == j { 1.0 } else { 0.0 }).abs());
        }
    }
    if worst > ROTATION_TOLERANCE {
        return Err(format!("is not orthonormal (RᵀR differs from the identity by {worst:.3e}, more than {ROTATION_TOLERANCE:e})"));
    }
    let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
    if det <= 0.0 {
        return Err(format!("is a reflection (determinant {det:.6}), not a rotation; are the camera axes flipped (OpenGL vs OpenCV)?"));
    }
    Ok(())
}

/// Unit quaternion `[w, x, y, z]` of a rotation matrix by Shepperd's method: the square root is taken of the
/// largest of the four `4q_i² − 1` candidates (trace or a diagonal entry), so no division by a small number
/// happens even near 180°, where the trace-only formula (`w = √(1 + tr)/2`) loses every digit. Sign: `w ≥ 0`;
/// at exactly 180° (`w = 0`), the first non-zero of x, y, z is positive.
pub fn rotation_to_quaternion(r: &[[f64; 3]; 3]) -> [f64; 4] {
    let tr = r[0][0] + r[1][1] + r[2][2];
    let q = if tr >= r[0][0] && tr >= r[1][1] && tr >= r[2][2] {
        let s = 2.0 * (1.0 + tr).sqrt();
        [s / 4.0, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s]
    } else if r[0][0] >= r[1][1] && r[0][0] >= r[2][2] {
        let s = 2.0 * (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt();
        [(r[2][1] - r[1][2]) / s, s / 4.0, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s]
    } else if r[1][1] >= r[2][2] {
        let s = 2.0 * (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt();
        [(r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, s / 4.0, (r[1][2] + r[2][1]) / s]
    } else {
        let s = 2.0 * (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt();
        [(r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, s / 4.0]
    };
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let q = q.map(|v| v / n);
    let flip = q[0] < 0.0 || (q[0] == 0.0 && q[1..].iter().find(|v| **v != 0.0).is_some_and(|v| *v < 0.0));
    if flip {
        q.map(|v| -v)
    } else {
        q
    }
}

/// Rotation matrix of a unit quaternion `[w, x, y, z]` (Hamilton convention, as COLMAP's Eigen quaternions).
pub fn quaternion_to_rotation(q: [f64; 4]) -> [[f64; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// Checks the model as a whole (ids unique and valid, references resolve, observations agree both ways, values
/// finite); the error names the file the offending record belongs to.
fn validate(dir: &Path, cameras: &[PinholeCamera], images: &[PosedImage], points: &[Point3D]) -> Result<(), PoseError> {
    let (cam_file, img_file, pts_file) = (dir.join("cameras.bin"), dir.join("images.bin"), dir.join("points3D.bin"));
    let bad = |file: &Path, msg: String| PoseError::Input { path: file.to_path_buf(), msg };

    let mut cam_ids = HashSet::new();
    for c in cameras {
        let what = format!("camera {}", c.id);
        if c.id == u32::MAX {
            return Err(bad(&cam_file, format!("{what}: id {} is COLMAP's invalid camera id", u32::MAX)));
        }
        if !cam_ids.insert(c.id) {
            return Err(bad(&cam_file, format!("{what}: id used twice")));
        }
        if c.width == 0 || c.height == 0 {
            return Err(bad(&cam_file, format!("{what}: size {}×{} is empty", c.width, c.height)));
        }
        if let Some(v) = c.params().iter().find(|v| !v.is_finite()) {
            return Err(bad(&cam_file, format!("{what}: parameter {v} is not finite")));
        }
        if c.fx <= 0.0 || c.fy <= 0.0 {
            return Err(bad(&cam_file, format!("{what}: focal lengths fx = {}, fy = {} must be positive", c.fx, c.fy)));
        }
    }

    let point_ids: HashSet<u64> = points.iter().map(|p| p.id).collect();
    let mut image_points: HashMap<u32, usize> = HashMap::new();
    let mut names = HashSet::new();
    // (point, image, index) of every 2D point that names a 3D point, to match against the tracks.
    let mut observations: HashSet<(u64, u32, u32)> = HashSet::new();
    for im in images {
        let what = format!("image {} ({})", im.id, im.name);
        if im.id == u32::MAX {
            return Err(bad(&img_file, format!("{what}: id {} is COLMAP's invalid image id", u32::MAX)));
        }
        if image_points.insert(im.id, im.points2d.len()).is_some() {
            return Err(bad(&img_file, format!("{what}: id used twice")));
        }
        if im.name.is_empty() || im.name.contains('\0') {
            return Err(bad(&img_file, format!("image {}: name {:?} must be non-empty and hold no NUL (COLMAP ends names with one)", im.id, im.name)));
        }
        if !names.insert(im.name.as_str()) {
            return Err(bad(&img_file, format!("{what}: name used by two images")));
        }
        if !cam_ids.contains(&im.camera_id) {
            return Err(bad(&img_file, format!("{what}: camera {} is not among the cameras written", im.camera_id)));
        }
        if let Some(v) = im.qvec.iter().chain(&im.tvec).find(|v| !v.is_finite()) {
            return Err(bad(&img_file, format!("{what}: pose value {v} is not finite")));
        }
        let norm = im.qvec.iter().map(|v| v * v).sum::<f64>().sqrt();
        if (norm - 1.0).abs() > 1e-9 {
            return Err(bad(&img_file, format!("{what}: quaternion {:?} has norm {norm}; COLMAP expects a unit quaternion", im.qvec)));
        }
        if u32::try_from(im.points2d.len()).is_err() {
            return Err(bad(&img_file, format!("{what}: {} 2D points is more than COLMAP indexes (u32)", im.points2d.len())));
        }
        for (k, p) in im.points2d.iter().enumerate() {
            if !p.x.is_finite() || !p.y.is_finite() {
                return Err(bad(&img_file, format!("{what}: 2D point {k} ({}, {}) is not finite", p.x, p.y)));
            }
            if let Some(pid) = p.point3d_id {
                if !point_ids.contains(&pid) {
                    return Err(bad(&img_file, format!("{what}: 2D point {k} observes 3D point {pid}, which is not among the points written")));
                }
                observations.insert((pid, im.id, k as u32));
            }
        }
    }

    let mut seen = HashSet::new();
    let mut tracked = 0usize;
    for p in points {
        let what = format!("3D point {}", p.id);
        if p.id == NO_POINT3D {
            return Err(bad(&pts_file, format!("{what}: id {NO_POINT3D} is COLMAP's invalid point id")));
        }
        if !seen.insert(p.id) {
            return Err(bad(&pts_file, format!("{what}: id used twice")));
        }
        if let Some(v) = p.xyz.iter().chain([&p.error]).find(|v| !v.is_finite()) {
            return Err(bad(&pts_file, format!("{what}: value {v} is not finite")));
        }
        let mut own = HashSet::new();
        for t in &p.track {
            let n = image_points
                .get(&t.image_id)
                .ok_or_else(|| bad(&pts_file, format!("{what}: track names image {}, which is not among the images written", t.image_id)))?;
            if t.point2d_idx as usize >= *n {
                return Err(bad(&pts_file, format!("{what}: track names 2D point {} of image {}, which has {n}", t.point2d_idx, t.image_id)));
            }
            if !observations.contains(&(p.id, t.image_id, t.point2d_idx)) || !own.insert(*t) {
                return Err(bad(
                    &pts_file,
                    format!(
                        "{what}: track element (image {}, 2D point {}) is listed twice or that 2D point does not name this 3D point",
                        t.image_id, t.point2d_idx
                    ),
                ));
            }
        }
        tracked += own.len();
    }
    if tracked != observations.len() {
        return Err(bad(&img_file, format!("{} 2D point(s) name a 3D point whose track does not list them", observations.len() - tracked)));
    }
    Ok(())
}

fn sorted_by<T, K: Ord>(items: &[T], key: impl Fn(&T) -> K) -> Vec<&T> {
    let mut v: Vec<&T> = items.iter().collect();
    v.sort_by_key(|t| key(t));
    v
}

fn encode_cameras(w: &mut impl Write, cameras: &[PinholeCamera]) -> std::io::Result<()> {
    w.write_all(&(cameras.len() as u64).to_le_bytes())?;
    for c in sorted_by(cameras, |c| c.id) {
        w.write_all(&c.id.to_le_bytes())?;
        w.write_all(&PINHOLE_MODEL_ID.to_le_bytes())?;
        w.write_all(&u64::from(c.width).to_le_bytes())?;
        w.write_all(&u64::from(c.height).to_le_bytes())?;
        for p in c.params() {
            w.write_all(&p.to_le_bytes())?;
        }
    }
    Ok(())
}

fn encode_images(w: &mut impl Write, images: &[PosedImage]) -> std::io::Result<()> {
    w.write_all(&(images.len() as u64).to_le_bytes())?;
    for im in sorted_by(images, |i| i.id) {
        w.write_all(&im.id.to_le_bytes())?;
        for v in im.qvec.iter().chain(&im.tvec) {
            w.write_all(&v.to_le_bytes())?;
        }
        w.write_all(&im.camera_id.to_le_bytes())?;
        w.write_all(im.name.as_bytes())?;
        w.write_all(&[0])?;
        w.write_all(&(im.points2d.len() as u64).to_le_bytes())?;
        for p in &im.points2d {
            w.write_all(&p.x.to_le_bytes())?;
            w.write_all(&p.y.to_le_bytes())?;
            w.write_all(&p.point3d_id.unwrap_or(NO_POINT3D).to_le_bytes())?;
        }
    }
    Ok(())
}

fn encode_points(w: &mut impl Write, points: &[Point3D]) -> std::io::Result<()> {
    w.write_all(&(points.len() as u64).to_le_bytes())?;
    for p in sorted_by(points, |p| p.id) {
        w.write_all(&p.id.to_le_bytes())?;
        for v in p.xyz {
            w.write_all(&v.to_le_bytes())?;
        }
        w.write_all(&p.rgb)?;
        w.write_all(&p.error.to_le_bytes())?;
        w.write_all(&(p.track.len() as u64).to_le_bytes())?;
        for t in &p.track {
            w.write_all(&t.image_id.to_le_bytes())?;
            w.write_all(&t.point2d_idx.to_le_bytes())?;
        }
    }
    Ok(())
}

fn write_file(path: &Path, encode: impl FnOnce(&mut BufWriter<std::fs::File>) -> std::io::Result<()>) -> Result<(), PoseError> {
    write_atomic(path, |tmp| {
        let mut w = BufWriter::new(std::fs::File::create(tmp)?);
        encode(&mut w)?;
        w.into_inner().map_err(|e| e.into_error())?.sync_all()
    })
    .map_err(|e| PoseError::io(path, e))
}

/// Writes the model into `dir` (created if missing) as `cameras.bin`, `images.bin` and `points3D.bin`, each to a
/// temporary name first and then renamed into place. The whole model is checked before anything is written:
/// unique ids, every camera an image uses and every image and 2D point a track names present, and each 2D
/// point that names a 3D point listed in that point's track (and the reverse), as COLMAP's tools assume.
/// A `rigs.bin` or `frames.bin` already in `dir` is removed: COLMAP ≥ 3.12 would read it alongside the new
/// images and fail on images it does not list. The three files are replaced one by one; for a folder that
/// appears whole, write into a fresh folder and rename it.
pub fn write_binary(dir: &Path, cameras: &[PinholeCamera], images: &[PosedImage], points: &[Point3D]) -> Result<(), PoseError> {
    validate(dir, cameras, images, points)?;
    std::fs::create_dir_all(dir).map_err(|e| PoseError::io(dir, e))?;
    for stale in ["rigs.bin", "frames.bin"] {
        let p = dir.join(stale);
        match std::fs::remove_file(&p) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(PoseError::io(&p, e)),
            _ => {}
        }
    }
    write_file(&dir.join("cameras.bin"), |w| encode_cameras(w, cameras))?;
    write_file(&dir.join("images.bin"), |w| encode_images(w, images))?;
    write_file(&dir.join("points3D.bin"), |w| encode_points(w, points))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn max_diff(a: &M3, b: &M3) -> f64 {
        a.iter().flatten().zip(b.iter().flatten()).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
    }

    #[test]
    fn half_turns_round_trip() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        // 180° about x, y, z and about (1, 1, 0)/√2: the trace is −1, so w = 0.
        let cases: [M3; 4] = [
            [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]],
            [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]],
            [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]],
            [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],
        ];
        let expect = [[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.0, h, h, 0.0]];
        for (r, e) in cases.iter().zip(expect) {
            let q = rotation_to_quaternion(r);
            assert!(q.iter().zip(e).all(|(a, b)| (a - b).abs() < 1e-15), "{q:?} vs {e:?}");
            assert!(max_diff(&quaternion_to_rotation(q), r) < 1e-15);
        }
    }

    #[test]
    fn sign_is_canonical() {
        // −q and q are one rotation: the result has w ≥ 0 whichever branch ran.
        for q in [[-0.5, 0.5, -0.5, 0.5], [0.1, -0.7, 0.7, 0.1], [-0.9, 0.1, 0.3, -0.3]] {
            let n = q.iter().map(|v: &f64| v * v).sum::<f64>().sqrt();
            let q = q.map(|v| v / n);
            let back = rotation_to_quaternion(&quaternion_to_rotation(q));
            assert!(back[0] >= 0.0);
            let s = if q[0] < 0.0 { -1.0 } else { 1.0 };
            assert!(back.iter().zip(q).all(|(a, b)| (a - s * b).abs() < 1e-14), "{back:?} vs {q:?}");
        }
    }

    #[test]
    fn reflection_and_scale_refused() {
        let mut m = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
        let e = PosedImage::from_c2w(3, 1, "a.png", &m).unwrap_err().to_string();
        assert!(e.contains("a.png") && e.contains("image 3") && e.contains("reflection"), "{e}");
        m[2][2] = 1.01;
        let e = PosedImage::from_c2w(3, 1, "a.png", &m).unwrap_err().to_string();
        assert!(e.contains("not orthonormal"), "{e}");
    }
}
