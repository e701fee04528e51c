//! Training: losses, optimizer + one-cycle schedule, the official view sampler, data (chunks, procedural and
//! POV-Ray scenes), checkpoints and the loop behind `mvsplat360 train`.

pub mod bench;
pub mod blend;
pub mod checkpoint;
pub mod config;
pub mod data;
pub mod dist;
pub mod error;
pub mod init;
pub mod log;
pub mod loss;
pub mod optim;
pub mod refiner;
pub mod sampler;
pub mod scenes;
pub mod trainer;
pub mod vae_stage;

pub use config::TrainConfig;
pub use error::{Result, TrainError};
pub use log::StepRecord;
pub use trainer::{export_checkpoint, run, Monitor, Quiet, RunOptions, Summary};
