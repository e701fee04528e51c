//! Key-name mapping tables, one per foreign layout, into the sgm/open_clip names the model code uses.

pub mod clip;
pub mod unet;
pub mod vae;
