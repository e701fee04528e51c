//! Shared encoder parts (`encoder/common/`): the Gaussian adapter and the SH rotation it uses.

pub mod gaussian_adapter;
pub mod sh_rotation;

pub use gaussian_adapter::{gaussians_from_prediction, gaussians_from_prediction_at_step, AdapterIntermediates, EncoderGaussians};
