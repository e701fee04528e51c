//! mvsplat360 dataset stage.
