//! nerfstudio / instant-ngp `transforms.json`: c2w in OpenGL axes, intrinsics shared at the top level or per
//! frame (`fl_x`/`fl_y`/`cx`/`cy`/`w`/`h`, or `camera_angle_x`/`camera_angle_y`), image paths relative to the file.
//! `camera_model` (default `OPENCV`) must be one of nerfstudio's perspective models; their distortion `k1`…`k4`,
//! `p1`, `p2` (top level or per frame, per key the frame's value wins) is removed as the photos load
//! ([`crate::lens`]). Fisheye (nerfstudio's models, and instant-ngp's `"is_fisheye": true`), equirectangular and
//! unknown models are refused.

use std::path::{Path, PathBuf};

use mvsplat360_camera::convert::{opengl_to_opencv, to_array};
use mvsplat360_camera::Camera;
use nalgebra::Matrix4;
use serde_json::Value;

use crate::error::{field, io};
use crate::{DatasetError, Distortion, ImageSource, Scene};

fn num(path: &Path, obj: &Value, top: &Value, key: &str, frame: usize) -> Result<Option<f64>, DatasetError> {
    for (v, loc) in [(obj.get(key), format!("frames[{frame}].{key}")), (top.get(key), key.to_string())] {
        if let Some(v) = v {
            return match v.as_f64() {
                Some(x) if x.is_finite() => Ok(Some(x)),
                _ => Err(field(path, loc, format!("expected a finite number, got {v}"))),
            };
        }
    }
    Ok(None)
}

/// A frame's `camera_model` (per frame, else top level, else nerfstudio's default `OPENCV`), refused unless it is
/// one of nerfstudio's perspective models (`CAMERA_MODEL_TO_TYPE` in `nerfstudio/cameras/cameras.py`), which all
/// share the k1–k4, p1, p2 distortion.
fn check_camera_model(path: &Path, obj: &Value, top: &Value, frame: usize, rel: &str) -> Result<(), DatasetError> {
    let (v, loc) = match (obj.get("camera_model"), top.get("camera_model")) {
        (Some(v), _) => (v, format!("frames[{frame}].camera_model")),
        (None, Some(v)) => (v, "camera_model".to_string()),
        (None, None) => return Ok(()),
    };
    let model = v.as_str().ok_or_else(|| field(path, &loc, format!("expected a string such as \"OPENCV\", got {v}")))?;
    let why = match model {
        "SIMPLE_PINHOLE" | "PINHOLE" | "SIMPLE_RADIAL" | "RADIAL" | "OPENCV" => return Ok(()),
        "OPENCV_FISHEYE" | "FISHEYE624" => "a fisheye lens, which this reader does not undistort (read as a pinhole, every ray would be wrong)",
        "EQUIRECTANGULAR" | "OMNIDIRECTIONALSTEREO_L" | "OMNIDIRECTIONALSTEREO_R" | "VR180_L" | "VR180_R" => "a panorama, not a perspective image",
        "ORTHOPHOTO" => "an orthographic image, not a perspective one",
        _ => "which is not a camera model this reader knows (perspective ones: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV)",
    };
    Err(DatasetError::UnsupportedLens {
        path: path.to_path_buf(),
        what: format!("{loc} (frame {frame}, {rel})"),
        model: model.to_string(),
        why: why.to_string(),
    })
}

/// instant-ngp's `is_fisheye` (per frame, else top level): `true` makes its k1–k4 the terms of an OpenCV fisheye
/// lens (instant-ngp's `OpenCVFisheye` mode), which read as a perspective lens would put every ray in the wrong
/// place, so it is refused as nerfstudio's `OPENCV_FISHEYE` is.
fn check_is_fisheye(path: &Path, obj: &Value, top: &Value, frame: usize, rel: &str) -> Result<(), DatasetError> {
    let (v, loc) = match (obj.get("is_fisheye"), top.get("is_fisheye")) {
        (Some(v), _) => (v, format!("frames[{frame}].is_fisheye")),
        (None, Some(v)) => (v, "is_fisheye".to_string()),
        (None, None) => return Ok(()),
    };
    match v.as_bool() {
        Some(false) => Ok(()),
        Some(true) => Err(DatasetError::UnsupportedLens {
            path: path.to_path_buf(),
            what: format!("{loc} (frame {frame}, {rel})"),
            model: "OPENCV_FISHEYE (instant-ngp's `\"is_fisheye\": true`)".to_string(),
            why: "a fisheye lens, which this reader does not undistort (read as a pinhole, every ray would be wrong)".to_string(),
        }),
        None => Err(field(path, loc, format!("expected true or false, got {v}"))),
    }
}

/// nerfstudio's perspective distortion of a frame; `None` when every coefficient is zero or absent.
fn distortion(path: &Path, obj: &Value, top: &Value, frame: usize) -> Result<Option<Distortion>, DatasetError> {
    let k = |key: &str| num(path, obj, top, key, frame).map(|v| v.unwrap_or(0.0));
    let d = Distortion::Perspective { k1: k("k1")?, k2: k("k2")?, k3: k("k3")?, k4: k("k4")?, p1: k("p1")?, p2: k("p2")? };
    Ok(d.nonzero())
}

/// Resolve a frame's image path: relative to the JSON's folder; instant-ngp files may omit the extension.
fn resolve_image(path: &Path, base: &Path, rel: &str, frame: usize) -> Result<PathBuf, DatasetError> {
    let p = base.join(rel);
    if p.is_file() {
        return Ok(p);
    }
    if p.extension().is_none() {
        for ext in ["png", "jpg", "jpeg", "PNG", "JPG"] {
            let q = p.with_extension(ext);
            if q.is_file() {
                return Ok(q);
            }
        }
    }
    Err(field(path, format!("frames[{frame}].file_path"), format!("image {} does not exist", p.display())))
}

pub fn read(path: &Path) -> Result<Scene, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| io(path, e))?;
    let top: Value = serde_json::from_str(&text).map_err(|source| DatasetError::Json { path: path.into(), source })?;
    let frames = top.get("frames").and_then(Value::as_array).ok_or_else(|| field(path, "frames", "missing or not a list of frames"))?;
    if frames.is_empty() {
        return Err(field(path, "frames", "the list is empty; a scene needs at least one view"));
    }
    let base = path.parent().unwrap_or(Path::new("."));
    let mut scene = Scene { name: base.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into()), ..Scene::default() };
    for (i, f) in frames.iter().enumerate() {
        let rel = f.get("file_path").and_then(Value::as_str).ok_or_else(|| field(path, format!("frames[{i}].file_path"), "missing or not a string"))?;
        check_is_fisheye(path, f, &top, i, rel)?;
        check_camera_model(path, f, &top, i, rel)?;
        let img_path = resolve_image(path, base, rel, i)?;
        let m = f
            .get("transform_matrix")
            .and_then(Value::as_array)
            .ok_or_else(|| field(path, format!("frames[{i}].transform_matrix"), "missing; expected a 4x4 list"))?;
        let bad = || field(path, format!("frames[{i}].transform_matrix"), "expected 4 rows of 4 numbers (3x4 allowed)");
        if m.len() != 4 && m.len() != 3 {
            return Err(bad());
        }
        let mut gl = Matrix4::identity();
        for (r, row) in m.iter().enumerate() {
            let row = row.as_array().filter(|row| row.len() == 4).ok_or_else(bad)?;
            for (c, v) in row.iter().enumerate() {
                gl[(r, c)] = v.as_f64().ok_or_else(bad)?;
            }
        }
        let source = ImageSource::File(img_path);
        let (w, h) = match (num(path, f, &top, "w", i)?, num(path, f, &top, "h", i)?) {
            (Some(w), Some(h)) if w >= 1.0 && h >= 1.0 => (w as u32, h as u32),
            (Some(_), Some(_)) => return Err(field(path, "w/h", "image size must be at least 1x1")),
            _ => source.dimensions()?,
        };
        let (wf, hf) = (w as f64, h as f64);
        let fx = match (num(path, f, &top, "fl_x", i)?, num(path, f, &top, "camera_angle_x", i)?) {
            (Some(fx), _) => fx,
            (None, Some(a)) => 0.5 * wf / (0.5 * a).tan(),
            (None, None) => return Err(field(path, format!("frames[{i}]"), "no focal length: give fl_x or camera_angle_x")),
        };
        let fy = match (num(path, f, &top, "fl_y", i)?, num(path, f, &top, "camera_angle_y", i)?) {
            (Some(fy), _) => fy,
            (None, Some(a)) => 0.5 * hf / (0.5 * a).tan(),
            (None, None) => fx,
        };
        let cx = num(path, f, &top, "cx", i)?.unwrap_or(wf / 2.0);
        let cy = num(path, f, &top, "cy", i)?.unwrap_or(hf / 2.0);
        scene.cameras.push(Camera { fx, fy, cx, cy, width: w, height: h, c2w: to_array(&opengl_to_opencv(&gl)) });
        scene.distortion.push(distortion(path, f, &top, i)?);
        scene.view_names.push(rel.to_string());
        scene.images.push(source);
    }
    Ok(scene)
}
