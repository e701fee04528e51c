//! Gaussian export/import: the standard 3DGS `.ply` (graphdeco layout, read by SIBR, SuperSplat,
//! antimatter15/splat and most viewers) and antimatter15's 32-byte `.splat`.
//!
//! Our SH coefficients live in the fork's permuted basis; files use graphdeco's basis, so export maps
//! degrees 0..3 with [`crate::sh::fork_to_graphdeco_matrix`] (degree 4, ignored by the renderer, is dropped).

mod decompose;
mod ply;
mod splat;

use candle_core::{DType, Device, Tensor};

pub use decompose::{covariance_to_scale_rotation, scale_rotation_to_covariance};
pub use ply::{read_ply, write_ply};
pub use splat::{encode_splat, write_splat};

use crate::error::{input_err, Result};
use crate::gaussians::Gaussians;

/// Plain-data Gaussians in the file-format parameterisation (scale + rotation), SH in OUR basis.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportGaussians {
    pub means: Vec<[f32; 3]>,
    /// Linear scales (standard deviations).
    pub scales: Vec<[f32; 3]>,
    /// Unit quaternions (w, x, y, z).
    pub quats: Vec<[f32; 4]>,
    /// Opacity in [0, 1].
    pub opacities: Vec<f32>,
    /// (N, K, 3) coefficient-major, the renderer's (fork) basis.
    pub sh: Vec<f32>,
    pub sh_coeffs: usize,
}

impl ExportGaussians {
    pub fn len(&self) -> usize {
        self.means.len()
    }

    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// From the shared `Gaussians` (covariances decomposed; SH truncated to degree ≤ 3).
    pub fn from_gaussians(g: &Gaussians) -> Result<Self> {
        let n = g.means.dim(0)?;
        let means = g.means.to_dtype(DType::F32)?.to_device(&Device::Cpu)?.flatten_all()?.to_vec1::<f32>()?;
        let covs = g.covariances.to_dtype(DType::F32)?.to_device(&Device::Cpu)?.flatten_all()?.to_vec1::<f32>()?;
        let op = g.opacities.to_dtype(DType::F32)?.to_device(&Device::Cpu)?.flatten_all()?.to_vec1::<f32>()?;
        let (_, three, k) = g.harmonics.dims3()?;
        if three != 3 || covs.len() != 9 * n || means.len() != 3 * n || op.len() != n {
            return Err(input_err("gaussians", "expected means (N,3), covariances (N,3,3), opacities (N), harmonics (N,3,K)"));
        }
        let kk = k.min(16);
        let harm = g.harmonics.to_dtype(DType::F32)?.to_device(&Device::Cpu)?.flatten_all()?.to_vec1::<f32>()?;
        let mut out = ExportGaussians {
            means: Vec::with_capacity(n),
            scales: Vec::with_capacity(n),
            quats: Vec::with_capacity(n),
            opacities: op,
            sh: vec![0.0; n * kk * 3],
            sh_coeffs: kk,
        };
        for i in 0..n {
            out.means.push([means[3 * i], means[3 * i + 1], means[3 * i + 2]]);
            let c = &covs[9 * i..9 * i + 9];
            let m = [[c[0] as f64, c[1] as f64, c[2] as f64], [c[3] as f64, c[4] as f64, c[5] as f64], [c[6] as f64, c[7] as f64, c[8] as f64]];
            let (s, q) = covariance_to_scale_rotation(m);
            out.scales.push(s);
            out.quats.push(q);
            for ch in 0..3 {
                for j in 0..kk {
                    out.sh[(i * kk + j) * 3 + ch] = harm[(i * 3 + ch) * k + j];
                }
            }
        }
        Ok(out)
    }

    /// Back to the shared layout: covariances R S² Rᵀ, harmonics (N,3,25) zero-padded, `feature_channels`
    /// feature SH set to zero (files carry no latent features).
    pub fn to_gaussians(&self, feature_channels: usize, device: &Device) -> Result<Gaussians> {
        let n = self.len();
        let mut covs = Vec::with_capacity(9 * n);
        for i in 0..n {
            let c = scale_rotation_to_covariance(self.scales[i], self.quats[i]);
            covs.extend(c.iter().flatten().map(|&v| v as f32));
        }
        let k = self.sh_coeffs;
        let mut harm = vec![0f32; n * 3 * 25];
        for i in 0..n {
            for ch in 0..3 {
                for j in 0..k.min(25) {
                    harm[(i * 3 + ch) * 25 + j] = self.sh[(i * k + j) * 3 + ch];
                }
            }
        }
        let flat: Vec<f32> = self.means.iter().flatten().copied().collect();
        Ok(Gaussians {
            means: Tensor::from_vec(flat, (n, 3), device)?,
            covariances: Tensor::from_vec(covs, (n, 3, 3), device)?,
            opacities: Tensor::from_vec(self.opacities.clone(), n, device)?,
            harmonics: Tensor::from_vec(harm, (n, 3, 25), device)?,
            feature_harmonics: Tensor::zeros((n, feature_channels, 9), DType::F32, device)?,
        })
    }
}
