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

impl Gaussians {
    /// The same values, cut from the autograd graph.
    pub fn detach(&self) -> Self {
        Self {
            means: self.means.detach(),
            covariances: self.covariances.detach(),
            opacities: self.opacities.detach(),
            harmonics: self.harmonics.detach(),
            feature_harmonics: self.feature_harmonics.detach(),
        }
    }

    /// The Gaussians at indices `idx` (u32, along the first axis), gradients flowing back to these.
    pub fn select(&self, idx: &Tensor) -> candle_core::Result<Self> {
        Ok(Self {
            means: self.means.index_select(idx, 0)?,
            covariances: self.covariances.index_select(idx, 0)?,
            opacities: self.opacities.index_select(idx, 0)?,
            harmonics: self.harmonics.index_select(idx, 0)?,
            feature_harmonics: self.feature_harmonics.index_select(idx, 0)?,
        })
    }
}
