//! mvsplat360 pipeline stage.
