//! VGGT (Wang et al., CVPR 2025, facebookresearch/vggt at 44b3afb): for a few unposed photos, in one forward
//! pass, each photo's camera (`absT_quaR_FoV`), depth with confidence and world points. Module files mirror the
//! official tree (`models/aggregator.py` → `models/aggregator.rs`, …), so a weight key such as
//! `aggregator.frame_blocks.3.attn.qkv.weight` leads to the file that owns it. Knows nothing of scenes: `pose`
//! turns the predictions into a scene folder.

pub mod bench;
pub mod config;
pub mod heads;
pub mod layers;
pub mod models;
pub mod utils;
pub mod weights;

pub use config::VggtConfig;
pub use models::vggt::{Predictions, Vggt};
