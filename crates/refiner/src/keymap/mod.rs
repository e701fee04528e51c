//! Key-name mapping tables, one per foreign layout, into the sgm/open_clip names the model code uses (the UNet's,
//! built from its config, is [`crate::unet::keymap`]).

pub mod clip;
pub mod vae;
