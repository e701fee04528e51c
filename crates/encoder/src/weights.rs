//! Weight files by official key names: shared with every model crate (`mvsplat360_dataset::weights`).
pub use mvsplat360_dataset::weights::*;
