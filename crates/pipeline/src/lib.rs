//! The product's path from posed photos to novel views: preprocessing, context/target choice, model loading,
//! encoder → test-time fit → rasterizer (→ learned blender) → refiner → histogram matching, and the output writers.
//!
//! Output folder of a render: `gaussians.ply` (+ `gaussians.splat`), `frames/{gsplat,blended,refined,final,gt}/NNNN.png`,
//! `video.mp4`, `compare.mp4` (gsplat | final | GT), `cameras.json`, `run.json`. A render is written to a stage
//! and swapped in when complete ([`txn`]), so the folder holds one whole run, and `--resume` continues one.

pub mod bench;
pub mod blend;
pub mod compute;
pub mod error;
pub mod eval;
pub mod eval_scenes;
pub mod fit;
pub mod launch;
pub mod model;
pub mod output;
pub mod preprocess;
pub mod progress;
pub mod render;
pub mod scale;
pub mod setup;
pub mod txn;
pub mod video;
pub mod views;

pub use error::{PipelineError, Result};
