//! COLMAP sparse models (`cameras` + `images`, binary or text). Poses are world-to-camera (qvec wxyz, tvec) in
//! OpenCV axes already. Perspective models with distortion (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV) keep
//! every parameter; their views carry the [`Distortion`] and load undistorted ([`crate::lens`]). Fisheye,
//! division, EUCM and spherical models are refused.

use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use mvsplat360_camera::convert::{colmap_to_c2w, to_array};
use mvsplat360_camera::Camera;

use crate::error::io;
use crate::{DatasetError, Distortion, ImageSource, Scene};

/// The folder holding `cameras.{bin,txt}`: `<root>/sparse/0`, `<root>/sparse` or `<root>` itself.
pub fn find_model_dir(root: &Path) -> Option<PathBuf> {
    [root.join("sparse/0"), root.join("sparse"), root.to_path_buf()].into_iter().find(|d| d.join("cameras.bin").is_file() || d.join("cameras.txt").is_file())
}

#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    pub model: String,
    pub width: u32,
    pub height: u32,
    /// Every parameter, in COLMAP's order for the model.
    pub params: Vec<f64>,
    /// fx, fy, cx, cy.
    pub pinhole: [f64; 4],
    /// The model has distortion terms (zero or not).
    pub distorted: bool,
    /// The distortion, when some coefficient is not zero.
    pub distortion: Option<Distortion>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub camera_id: u32,
    pub name: String,
}

fn malformed(path: &Path, msg: impl Into<String>) -> DatasetError {
    DatasetError::Colmap { path: path.to_path_buf(), msg: msg.into() }
}

/// Model id → (name, parameter count), as `src/colmap/sensor/models.h` numbers them.
fn model_by_id(id: i32) -> Option<(&'static str, usize)> {
    Some(match id {
        0 => ("SIMPLE_PINHOLE", 3),
        1 => ("PINHOLE", 4),
        2 => ("SIMPLE_RADIAL", 4),
        3 => ("RADIAL", 5),
        4 => ("OPENCV", 8),
        5 => ("OPENCV_FISHEYE", 8),
        6 => ("FULL_OPENCV", 12),
        7 => ("FOV", 5),
        8 => ("SIMPLE_RADIAL_FISHEYE", 4),
        9 => ("RADIAL_FISHEYE", 5),
        10 => ("THIN_PRISM_FISHEYE", 12),
        11 => ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
        12 => ("SIMPLE_DIVISION", 4),
        13 => ("DIVISION", 5),
        14 => ("SIMPLE_FISHEYE", 3),
        15 => ("FISHEYE", 4),
        16 => ("EUCM", 6),
        17 => ("EQUIRECTANGULAR", 2),
        _ => return None,
    })
}

/// Why a model cannot be read as a pinhole camera (None: it can, possibly after undistortion).
fn refusal(model: &str) -> Option<&'static str> {
    Some(match model {
        "SIMPLE_PINHOLE" | "PINHOLE" | "SIMPLE_RADIAL" | "RADIAL" | "OPENCV" | "FULL_OPENCV" => return None,
        "OPENCV_FISHEYE"
        | "FOV"
        | "SIMPLE_RADIAL_FISHEYE"
        | "RADIAL_FISHEYE"
        | "THIN_PRISM_FISHEYE"
        | "RAD_TAN_THIN_PRISM_FISHEYE"
        | "SIMPLE_FISHEYE"
        | "FISHEYE" => "a fisheye lens, which this reader does not undistort (read as a pinhole, every ray would be wrong)",
        "EQUIRECTANGULAR" => "a 360° panorama, not a perspective image",
        "SIMPLE_DIVISION" | "DIVISION" | "EUCM" => "a lens model this reader does not undistort",
        _ => "which is not a COLMAP camera model this reader knows",
    })
}

fn make_camera(path: &Path, id: u32, model: &str, width: u32, height: u32, p: &[f64]) -> Result<ColmapCamera, DatasetError> {
    if let Some(why) = refusal(model) {
        return Err(DatasetError::UnsupportedLens { path: path.to_path_buf(), what: format!("camera {id}"), model: model.to_string(), why: why.to_string() });
    }
    let need = match model {
        "SIMPLE_PINHOLE" => 3,
        "PINHOLE" | "SIMPLE_RADIAL" => 4,
        "RADIAL" => 5,
        "OPENCV" => 8,
        _ => 12,
    };
    if p.len() != need {
        return Err(malformed(path, format!("camera {id}: model {model} has {need} parameters, found {}", p.len())));
    }
    if let Some(v) = p.iter().find(|v| !v.is_finite()) {
        return Err(malformed(path, format!("camera {id}: parameter {v} is not finite")));
    }
    let (pinhole, distortion) = match model {
        "SIMPLE_PINHOLE" => ([p[0], p[0], p[1], p[2]], None),
        "PINHOLE" => ([p[0], p[1], p[2], p[3]], None),
        "SIMPLE_RADIAL" => ([p[0], p[0], p[1], p[2]], Some(Distortion::SimpleRadial { k: p[3] })),
        "RADIAL" => ([p[0], p[0], p[1], p[2]], Some(Distortion::Radial { k1: p[3], k2: p[4] })),
        "OPENCV" => ([p[0], p[1], p[2], p[3]], Some(Distortion::OpenCv { k1: p[4], k2: p[5], p1: p[6], p2: p[7] })),
        _ => ([p[0], p[1], p[2], p[3]], Some(Distortion::FullOpenCv { k1: p[4], k2: p[5], p1: p[6], p2: p[7], k3: p[8], k4: p[9], k5: p[10], k6: p[11] })),
    };
    Ok(ColmapCamera {
        model: model.to_string(),
        width,
        height,
        params: p.to_vec(),
        pinhole,
        distorted: distortion.is_some(),
        distortion: distortion.and_then(Distortion::nonzero),
    })
}

struct Bin<'a> {
    path: &'a Path,
    data: &'a [u8],
    pos: usize,
}

impl Bin<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], DatasetError> {
        // `pos + n` could overflow on a crafted count; the remaining length cannot.
        if n > self.data.len() - self.pos {
            return Err(malformed(self.path, format!("file ends early at byte {} (truncated?)", self.data.len())));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u64(&mut self) -> Result<u64, DatasetError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap_or_default()))
    }
    fn i32(&mut self) -> Result<i32, DatasetError> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().unwrap_or_default()))
    }
    fn f64(&mut self) -> Result<f64, DatasetError> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().unwrap_or_default()))
    }
    fn cstr(&mut self) -> Result<String, DatasetError> {
        let rest = &self.data[self.pos..];
        let end = rest.iter().position(|&b| b == 0).ok_or_else(|| malformed(self.path, "unterminated image name"))?;
        let s = String::from_utf8_lossy(&rest[..end]).into_owned();
        self.pos += end + 1;
        Ok(s)
    }
}

fn read_bytes(path: &Path) -> Result<Vec<u8>, DatasetError> {
    let mut v = vec![];
    std::fs::File::open(path).and_then(|mut f| f.read_to_end(&mut v)).map_err(|e| io(path, e))?;
    Ok(v)
}

pub fn read_cameras_bin(path: &Path) -> Result<HashMap<u32, ColmapCamera>, DatasetError> {
    let data = read_bytes(path)?;
    let mut b = Bin { path, data: &data, pos: 0 };
    let n = b.u64()?;
    let mut out = HashMap::new();
    for _ in 0..n {
        let id = b.i32()?;
        let model_id = b.i32()?;
        let (model, np) = model_by_id(model_id).ok_or_else(|| malformed(path, format!("camera {id}: unknown model id {model_id}")))?;
        let (w, h) = (b.u64()?, b.u64()?);
        let params = (0..np).map(|_| b.f64()).collect::<Result<Vec<_>, _>>()?;
        out.insert(id as u32, make_camera(path, id as u32, model, w as u32, h as u32, &params)?);
    }
    Ok(out)
}

pub fn read_images_bin(path: &Path) -> Result<Vec<ColmapImage>, DatasetError> {
    let data = read_bytes(path)?;
    let mut b = Bin { path, data: &data, pos: 0 };
    let n = b.u64()?;
    let mut out = vec![];
    for _ in 0..n {
        let _id = b.i32()?;
        let qvec = [b.f64()?, b.f64()?, b.f64()?, b.f64()?];
        let tvec = [b.f64()?, b.f64()?, b.f64()?];
        let camera_id = b.i32()? as u32;
        let name = b.cstr()?;
        let npts = b.u64()? as usize;
        b.take(npts.checked_mul(24).ok_or_else(|| malformed(path, "absurd point count"))?)?;
        out.push(ColmapImage { qvec, tvec, camera_id, name });
    }
    Ok(out)
}

fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, l)| !l.starts_with('#'))
}

fn parse_nums<T: std::str::FromStr>(path: &Path, line: usize, toks: &[&str]) -> Result<Vec<T>, DatasetError> {
    toks.iter().map(|t| t.parse::<T>().map_err(|_| malformed(path, format!("line {line}: `{t}` is not a number")))).collect()
}

pub fn read_cameras_txt(path: &Path) -> Result<HashMap<u32, ColmapCamera>, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| io(path, e))?;
    let mut out = HashMap::new();
    for (ln, line) in data_lines(&text).filter(|(_, l)| !l.is_empty()) {
        let t: Vec<&str> = line.split_whitespace().collect();
        if t.len() < 5 {
            return Err(malformed(path, format!("line {ln}: expected `ID MODEL WIDTH HEIGHT PARAMS...`")));
        }
        let ids: Vec<u32> = parse_nums(path, ln, &[t[0], t[2], t[3]])?;
        let params: Vec<f64> = parse_nums(path, ln, &t[4..])?;
        out.insert(ids[0], make_camera(path, ids[0], t[1], ids[1], ids[2], &params)?);
    }
    Ok(out)
}

pub fn read_images_txt(path: &Path) -> Result<Vec<ColmapImage>, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| io(path, e))?;
    let mut out = vec![];
    // Two lines per image; the second (2D points) may be empty, so keep blank lines after a header line.
    let mut expect_points = false;
    for (ln, line) in data_lines(&text) {
        if expect_points {
            expect_points = false;
            continue;
        }
        if line.is_empty() {
            continue;
        }
        let t: Vec<&str> = line.split_whitespace().collect();
        if t.len() < 10 {
            return Err(malformed(path, format!("line {ln}: expected `ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`")));
        }
        let v: Vec<f64> = parse_nums(path, ln, &t[1..8])?;
        let cam: Vec<u32> = parse_nums(path, ln, &t[8..9])?;
        out.push(ColmapImage { qvec: [v[0], v[1], v[2], v[3]], tvec: [v[4], v[5], v[6]], camera_id: cam[0], name: t[9..].join(" ") });
        expect_points = true;
    }
    Ok(out)
}

/// Read a COLMAP scene rooted at `root` (images in `<root>/images`, sorted by name).
pub fn read(root: &Path) -> Result<Scene, DatasetError> {
    let model = find_model_dir(root).ok_or_else(|| DatasetError::UnknownFormat { path: root.to_path_buf() })?;
    let (cams, mut imgs) = if model.join("cameras.bin").is_file() {
        (read_cameras_bin(&model.join("cameras.bin"))?, read_images_bin(&model.join("images.bin"))?)
    } else {
        (read_cameras_txt(&model.join("cameras.txt"))?, read_images_txt(&model.join("images.txt"))?)
    };
    imgs.sort_by(|a, b| a.name.cmp(&b.name));
    let image_dir = root.join("images");
    let mut scene = Scene { name: root.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into()), ..Scene::default() };
    for im in imgs {
        let c = cams
            .get(&im.camera_id)
            .ok_or_else(|| malformed(&model, format!("image {} refers to camera {} which is not in the cameras file", im.name, im.camera_id)))?;
        let [fx, fy, cx, cy] = c.pinhole;
        scene.cameras.push(Camera { fx, fy, cx, cy, width: c.width, height: c.height, c2w: to_array(&colmap_to_c2w(im.qvec, im.tvec)) });
        let p = image_dir.join(&im.name);
        if !p.is_file() {
            return Err(DatasetError::Colmap { path: model.clone(), msg: format!("image {} not found at {}", im.name, p.display()) });
        }
        scene.images.push(ImageSource::File(p));
        scene.distortion.push(c.distortion);
        scene.view_names.push(im.name);
    }
    Ok(scene)
}
