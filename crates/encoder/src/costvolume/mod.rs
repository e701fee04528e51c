//! Depth predictor (`costvolume/depth_predictor_multiview.py`): plane-sweep cost volume against the nearest
//! views, cost-volume UNet refinement, coarse disparity, depth-refinement UNet and the Gaussian head.

pub mod depth_predictor_multiview;
pub mod ldm_unet;

pub use depth_predictor_multiview::{DepthIntermediates, DepthPredictorInput, DepthPredictorMultiView, DepthPredictorOutput};
