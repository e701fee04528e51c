//! Scene readers: nerfstudio/instant-ngp `transforms.json`, COLMAP `sparse/0` (binary or text), the
//! pixelSplat/MVSplat `.torch` chunks, and the evaluation index. Every reader returns the same [`Scene`]
//! with cameras already in the project convention (c2w, OpenCV axes, pixel intrinsics, pinhole: a lens that
//! distorts is removed from the pixels as they are decoded, [`lens`]). Images are decoded to f32 ([`image`])
//! and resized as the official loader resizes them ([`resize`]).

pub mod atomic;
pub mod colmap;
pub mod error;
pub mod guard;
pub mod image;
pub mod index;
pub mod lens;
pub mod owner;
pub mod resize;
pub mod torch_chunk;
pub mod transforms;
pub mod weights;

use std::path::{Path, PathBuf};

use mvsplat360_camera::Camera;

pub use error::DatasetError;
pub use image::{ImageF32, ImageSource};
pub use index::{read_evaluation_index, EvaluationEntry};
pub use lens::Distortion;
pub use resize::resize_pil_lanczos;

/// One scene: per view a name, a pinhole camera, where its image comes from (decoded on demand) and the lens
/// distortion its photo still has (`None`: a pinhole photo; a missing entry counts as `None`). Views may differ
/// in size: preprocessing brings each to the model's size on its own.
#[derive(Debug, Clone, Default)]
pub struct Scene {
    pub name: String,
    pub view_names: Vec<String>,
    pub cameras: Vec<Camera>,
    pub images: Vec<ImageSource>,
    pub distortion: Vec<Option<Distortion>>,
}

impl Scene {
    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// The lens distortion of view `i`'s photo, if any.
    pub fn lens(&self, i: usize) -> Option<&Distortion> {
        self.distortion.get(i).and_then(Option::as_ref)
    }

    /// Decode view `i` as f32 CHW in [0,1], the pixels its pinhole camera sees: checks the photo has the size
    /// its camera says and removes its lens distortion ([`lens::undistort`]). Every reader of pixels comes here.
    pub fn image(&self, i: usize) -> Result<ImageF32, DatasetError> {
        let img = self.decode_checked(i)?;
        Ok(match self.lens(i) {
            Some(d) => lens::undistort(&img, &self.cameras[i], d),
            None => img,
        })
    }

    /// Whether view `i` decodes and has the size its camera says (the pixels are not kept, so the
    /// undistortion is skipped).
    pub fn check_image(&self, i: usize) -> Result<(), DatasetError> {
        self.decode_checked(i).map(|_| ())
    }

    fn decode_checked(&self, i: usize) -> Result<ImageF32, DatasetError> {
        let img = self.images[i].decode()?;
        let cam = &self.cameras[i];
        if img.width != cam.width || img.height != cam.height {
            return Err(DatasetError::ImageSize { view: self.view_names[i].clone(), expected: (cam.width, cam.height), found: (img.width, img.height) });
        }
        Ok(img)
    }

    /// Validate every camera. Views of different sizes are fine (each is preprocessed on its own).
    pub fn validate(&self) -> Result<(), DatasetError> {
        if self.cameras.is_empty() {
            return Err(DatasetError::EmptyScene { scene: self.name.clone() });
        }
        for (cam, name) in self.cameras.iter().zip(&self.view_names) {
            cam.validate(name)?;
        }
        Ok(())
    }

    /// The first view (in view order) whose JPEG carries an EXIF orientation other than 1, with that value.
    /// Readers never rotate: poses are estimated on the stored pixel grid, which is what the model gets.
    pub fn exif_rotated_view(&self) -> Option<(usize, u16)> {
        self.images.iter().enumerate().find_map(|(i, s)| s.exif_orientation().filter(|&o| o != 1).map(|o| (i, o)))
    }

    /// The load-time warnings, once per scene: which views get undistorted with which model, and the first photo
    /// whose EXIF orientation asks viewers to rotate it.
    fn warn_on_load(&self, path: &Path) {
        let lensed: Vec<usize> = (0..self.len()).filter(|&i| self.lens(i).is_some()).collect();
        if let Some(&first) = lensed.first() {
            let mut models: Vec<&str> = lensed.iter().filter_map(|&i| self.lens(i).map(Distortion::name)).collect();
            models.sort_unstable();
            models.dedup();
            tracing::warn!(
                "{}: {} of {} views have lens distortion ({}, first: {}); their photos are undistorted to the pinhole camera as they load (same size and intrinsics, see docs/cameras.md)",
                path.display(),
                lensed.len(),
                self.len(),
                models.join(", "),
                self.view_names[first]
            );
        }
        if let Some((i, o)) = self.exif_rotated_view() {
            tracing::warn!(
                "{}: {} has EXIF orientation {o} (viewers show it rotated); photos are read as stored, never rotated, so the poses must refer to the stored pixels (if they were estimated on rotated photos, rotate the files themselves and estimate again)",
                path.display(),
                self.images[i].label()
            );
        }
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
    scene.warn_on_load(path);
    Ok(scene)
}

/// Read a scene in any supported format (first scene of a `.torch` chunk).
pub fn read_scene(path: &Path) -> Result<Scene, DatasetError> {
    read_scene_with(path, None)
}
