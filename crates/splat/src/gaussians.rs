//! The Gaussians of one scene, in the layout every stage shares (see DESIGN.md, Conventions).

use candle_core::Tensor;

/// One scene's 3D Gaussians (no batch dimension; a batch is a `Vec<Gaussians>`).
#[derive(Debug, Clone)]
pub struct Gaussians {
    /// (N,3) world-space centres.
    pub means: Tensor,
    /// (N,3,3) world-space covariances.
    pub covariances: Tensor,
    /// (N,) opacities in [0,1].
    pub opacities: Tensor,
    /// (N,3,25) RGB spherical harmonics, world frame; coefficient k = l² + i (i = 0..2l), colour-major.
    pub harmonics: Tensor,
    /// (N,C,9) latent-feature SH of degree 2, world frame (C = 4 in the pipeline).
    pub feature_harmonics: Tensor,
}
