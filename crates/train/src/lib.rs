//! mvsplat360 train stage.
