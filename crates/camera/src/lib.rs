//! Cameras and conventions: the one place that knows about axis conventions.
//!
//! Extrinsics are camera-to-world 4×4 with OpenCV camera axes (+x right, +y down, +z forward);
//! intrinsics are in pixels. Readers convert at their boundary with the functions here.

pub mod align;
pub mod camera;
pub mod convert;
pub mod select;
pub mod trajectory;

pub use align::{camera_errors, umeyama, AlignError, PoseErrors, Similarity};
pub use camera::{Camera, CameraError, CropRect};
