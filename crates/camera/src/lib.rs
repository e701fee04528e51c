//! mvsplat360 camera stage.
