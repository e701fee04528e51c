//! Scene scale: the model expects scenes in the units it was trained with (its near/far planes are fixed
//! numbers). Benchmark data is already in those units; other inputs are scaled (see [`Normalize`]).

use mvsplat360_camera::Camera;
use serde::{Deserialize, Serialize};

use crate::model::DataConfig;

/// How a scene is brought to the model's units.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Normalize {
    /// Use the scene's own units.
    #[default]
    None,
}

/// Model space = scene space scaled by `scale` about the origin (rotations unchanged).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneTransform {
    pub scale: f64,
}

impl SceneTransform {
    pub fn identity() -> Self {
        Self { scale: 1.0 }
    }

    /// The camera in model space.
    pub fn apply(&self, c: &Camera) -> Camera {
        let mut out = c.clone();
        for r in 0..3 {
            out.c2w[r][3] *= self.scale;
        }
        out
    }

    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({ "scale": self.scale })
    }
}

/// The transform for a scene given its (preprocessed) context cameras.
pub fn scene_transform(data: &DataConfig, _context: &[Camera]) -> SceneTransform {
    match data.normalize {
        Normalize::None => SceneTransform::identity(),
    }
}
