//! mvsplat360 metrics stage.
