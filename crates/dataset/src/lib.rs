//! Scene readers: nerfstudio/instant-ngp `transforms.json`, COLMAP `sparse/0` (binary or text), the
//! pixelSplat/MVSplat `.torch` chunks, and the evaluation index. Every reader returns the same [`Scene`]
//! with cameras already in the project convention (c2w, OpenCV axes, pixel intrinsics). Images are decoded
//! to f32 ([`image`]) and resized as the official loader resizes them ([`resize`]).

pub mod atomic;
pub mod colmap;
pub mod error;
pub mod image;
pub mod index;
pub mod resize;
pub mod torch_chunk;
pub mod transforms;

use std::path::{Path, PathBuf};

use mvsplat360_camera::Camera;

pub use error::DatasetError;
pub use image::{ImageF32, ImageSource};
pub use index::{read_evaluation_index, EvaluationEntry};
pub use resize::resize_pil_lanczos;

/// One scene: per view a name, a camera and where its image comes from (decoded on demand).
#[derive(Debug, Clone)]
pub struct Scene {
    pub name: String,
    pub view_names: Vec<String>,
    pub cameras: Vec<Camera>,
    pub images: Vec<ImageSource>,
}

impl Scene {
    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// Decode view `i` as f32 CHW in [0,1]; checks it has the size its camera says.
    pub fn image(&self, i: usize) -> Result<ImageF32, DatasetError> {
        let img = self.images[i].decode()?;
        let cam = &self.cameras[i];
        if img.width != cam.width || img.height != cam.height {
            return Err(DatasetError::ImageSize { view: self.view_names[i].clone(), expected: (cam.width, cam.height), found: (img.width, img.height) });
        }
        Ok(img)
    }

    /// Validate every camera and that all views share one image size (the model needs a uniform batch).
    pub fn validate(&self) -> Result<(), DatasetError> {
        if self.cameras.is_empty() {
            return Err(DatasetError::EmptyScene { scene: self.name.clone() });
        }
        let (w0, h0) = (self.cameras[0].width, self.cameras[0].height);
        for (cam, name) in self.cameras.iter().zip(&self.view_names) {
            cam.validate(name)?;
            if (cam.width, cam.height) != (w0, h0) {
                return Err(DatasetError::InconsistentSize { view: name.clone(), first: (w0, h0), found: (cam.width, cam.height) });
            }
        }
        Ok(())
    }
}

/// Which reader a path calls for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneFormat {
    Transforms,
    Colmap,
    TorchChunk,
}

/// Detect the format: a `transforms*.json` file or a folder holding `transforms.json`; a COLMAP folder
/// (`sparse/0`, `sparse` or the model folder itself); a `.torch` chunk file.
pub fn detect_format(path: &Path) -> Result<(SceneFormat, PathBuf), DatasetError> {
    if !path.exists() {
        return Err(DatasetError::NotFound { path: path.to_path_buf() });
    }
    if path.is_file() {
        return match path.extension().and_then(|e| e.to_str()) {
            Some("json") => Ok((SceneFormat::Transforms, path.to_path_buf())),
            Some("torch") => Ok((SceneFormat::TorchChunk, path.to_path_buf())),
            _ => Err(DatasetError::UnknownFormat { path: path.to_path_buf() }),
        };
    }
    if path.join("transforms.json").is_file() {
        return Ok((SceneFormat::Transforms, path.join("transforms.json")));
    }
    if colmap::find_model_dir(path).is_some() {
        return Ok((SceneFormat::Colmap, path.to_path_buf()));
    }
    Err(DatasetError::UnknownFormat { path: path.to_path_buf() })
}

/// Read a scene in any supported format. For a `.torch` chunk, `scene_key` picks the scene (default: first).
pub fn read_scene_with(path: &Path, scene_key: Option<&str>) -> Result<Scene, DatasetError> {
    let (format, file) = detect_format(path)?;
    let scene = match format {
        SceneFormat::Transforms => transforms::read(&file)?,
        SceneFormat::Colmap => colmap::read(&file)?,
        SceneFormat::TorchChunk => torch_chunk::read_scene(&file, scene_key)?,
    };
    scene.validate()?;
    Ok(scene)
}

/// Read a scene in any supported format (first scene of a `.torch` chunk).
pub fn read_scene(path: &Path) -> Result<Scene, DatasetError> {
    read_scene_with(path, None)
}
