//! Helpers of the official `vggt/utils/`: pose encodings and rotations, image loading.

pub mod load_fn;
pub mod pose_enc;
pub mod rotation;
