//! CPU rasterizer core on plain slices: preprocess (projection, EWA covariance, SH colour), per-tile binning
//! and depth sort, front-to-back compositing, and the reverse-traversal backward.

mod backward;
mod binning;
mod composite;
mod preprocess;
mod simd;

use crate::camera::RasterCamera;
use crate::error::{input_err, Result};
use crate::util::Pooled;

pub use backward::backward;
pub use composite::forward;

/// Tile edge in pixels (the CUDA kernel's BLOCK_X = BLOCK_Y).
pub const TILE: usize = 16;

/// Per-Gaussian 3D shape: precomputed covariance or scale + rotation.
#[derive(Debug, Clone, Copy)]
pub enum CovInput<'a> {
    /// (N,6) upper triangle 00, 01, 02, 11, 12, 22.
    Cov3d(&'a [f32]),
    /// (N,3) linear scales and (N,4) quaternions (w, x, y, z), not normalised.
    ScaleRot { scales: &'a [f32], quats: &'a [f32] },
}

/// Gradient flavour of the backward pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GradMode {
    /// What the official CUDA backward returns (five deliberate deviations; see the fixture README).
    #[default]
    Official,
    /// The true derivative of the forward, including the feature, alpha and depth images.
    Exact,
}

/// Rasterizer inputs for one scene (all row-major, no batch dim).
#[derive(Debug, Clone, Copy)]
pub struct RasterInputs<'a> {
    /// (N,3) world positions.
    pub means: &'a [f32],
    pub cov: CovInput<'a>,
    /// (N,) opacities.
    pub opacities: &'a [f32],
    /// (N,K,3) SH coefficients, coefficient-major (RGB last).
    pub sh: &'a [f32],
    /// K, coefficients per channel stored in `sh` (e.g. 25).
    pub sh_coeffs: usize,
    /// Active SH degree passed to the kernel; only degrees ≤ 3 are evaluated, as in the fork.
    pub sh_degree: usize,
    /// (N,C) precomputed feature channels (no background).
    pub features: &'a [f32],
    pub num_features: usize,
}

impl RasterInputs<'_> {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    /// Degree actually evaluated.
    pub fn eval_degree(&self) -> usize {
        let mut d = self.sh_degree.min(3);
        while (d + 1) * (d + 1) > self.sh_coeffs && d > 0 {
            d -= 1;
        }
        d
    }

    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        let chk = |name: &'static str, got: usize, want: usize| {
            if got != want {
                Err(input_err(name, format!("expected {want} values for {n} Gaussians, got {got}")))
            } else {
                Ok(())
            }
        };
        chk("means", self.means.len(), n * 3)?;
        match self.cov {
            CovInput::Cov3d(c) => chk("cov3d", c.len(), n * 6)?,
            CovInput::ScaleRot { scales, quats } => {
                chk("scales", scales.len(), n * 3)?;
                chk("quats", quats.len(), n * 4)?;
            }
        }
        if self.sh_coeffs == 0 {
            return Err(input_err("sh", "need at least one SH coefficient (the DC term)"));
        }
        chk("sh", self.sh.len(), n * self.sh_coeffs * 3)?;
        chk("features", self.features.len(), n * self.num_features)?;
        Ok(())
    }
}

/// Render settings for one view.
#[derive(Debug, Clone, Copy)]
pub struct RasterSettings {
    pub camera: RasterCamera,
    /// Background colour (RGB only; features get none).
    pub background: [f32; 3],
}

/// Everything the forward pass produces; images are planar (C,H,W) / (H,W), per-Gaussian arrays row-major.
#[derive(Debug, Clone)]
pub struct ForwardOutput {
    pub width: usize,
    pub height: usize,
    pub num_features: usize,
    /// (3,H,W)
    pub rgb: Vec<f32>,
    /// (C,H,W)
    pub features: Vec<f32>,
    /// (H,W) accumulated alpha = 1 - final_T.
    pub alpha: Vec<f32>,
    /// (H,W) expected view depth Σ w z (not normalised by alpha).
    pub depth: Vec<f32>,
    /// (H,W)
    pub final_t: Vec<f32>,
    /// (H,W) 1-based position in the tile list of the last blended Gaussian.
    pub n_contrib: Vec<u32>,
    /// (N,) pixel radius, 0 = culled.
    pub radii: Vec<i32>,
    /// (N,)
    pub tiles_touched: Vec<u32>,
    /// (N,2) pixel position.
    pub means2d: Vec<f32>,
    /// (N,3) 2D covariance (a, b, c) incl. the +0.3 low-pass.
    pub cov2d: Vec<f32>,
    /// (N,3) conic (A, B, C).
    pub conic: Vec<f32>,
    /// (N,) view-space z.
    pub depths: Vec<f32>,
    /// (N,3) SH colour after +0.5 and clamp.
    pub colors: Vec<f32>,
    pub(crate) clamped: Vec<u8>,
    /// Per-tile ranges into `point_list` (len tiles + 1).
    pub(crate) tile_start: Pooled<u32>,
    /// Gaussian index per (tile, depth)-sorted pair.
    pub(crate) point_list: Pooled<u32>,
    /// Packed kernel records (mx, my, conic, opacity, alpha-box half-extents) per Gaussian.
    pub(crate) geo: Pooled<[f32; preprocess::GEO_LEN]>,
    /// (N, 4+C) composited values: r, g, b, depth, features.
    pub(crate) vals: Pooled<f32>,
    /// Visible Gaussians in depth order.
    pub(crate) order: Pooled<u32>,
    /// (M+1) first Gaussian-major pair slot of each `order` entry.
    pub(crate) pstart: Pooled<u32>,
    /// Gaussian-major slot of each pair of `point_list` (where the backward writes its partial gradients).
    pub(crate) slot_of: Pooled<u32>,
}

impl ForwardOutput {
    /// Number of (tile, Gaussian) pairs.
    pub fn num_pairs(&self) -> usize {
        self.point_list.len()
    }
}

/// Pixel-space gradients of the loss (planar, same layout as [`ForwardOutput`]).
#[derive(Debug, Clone, Copy)]
pub struct PixelGrads<'a> {
    /// (3,H,W)
    pub rgb: &'a [f32],
    /// (C,H,W)
    pub features: &'a [f32],
    /// (H,W); used only by [`GradMode::Exact`] (the official backward ignores it).
    pub alpha: Option<&'a [f32]>,
    /// (H,W); used only by [`GradMode::Exact`].
    pub depth: Option<&'a [f32]>,
}

/// Gradients w.r.t. the rasterizer inputs (row-major, same shapes as the inputs).
#[derive(Debug, Clone)]
pub struct Gradients {
    pub means: Vec<f32>,
    /// (N,6) w.r.t. the upper-triangular covariance (off-diagonals count both symmetric positions).
    pub cov3d: Vec<f32>,
    /// (N,3), present for [`CovInput::ScaleRot`].
    pub scales: Option<Vec<f32>>,
    /// (N,4) (w,x,y,z), present for [`CovInput::ScaleRot`].
    pub quats: Option<Vec<f32>>,
    pub opacities: Vec<f32>,
    /// (N,K,3)
    pub sh: Vec<f32>,
    /// (N,C)
    pub features: Vec<f32>,
    /// (N,2) dL/d ndc of the projected centres (the fork's `means2D` gradient).
    pub means2d_ndc: Vec<f32>,
}

/// Camera constants shared by every stage.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Frame {
    pub v: [[f32; 4]; 4],
    pub fp: [[f32; 4]; 4],
    pub campos: [f32; 3],
    pub focal: [f32; 2],
    pub tanfov: [f32; 2],
    pub w: usize,
    pub h: usize,
    pub grid: [usize; 2],
}

impl Frame {
    pub fn new(cam: &RasterCamera) -> Self {
        Frame {
            v: cam.viewmatrix,
            fp: cam.full_proj(),
            campos: cam.campos(),
            focal: cam.focal(),
            tanfov: cam.tanfov(),
            w: cam.width,
            h: cam.height,
            grid: [cam.width.div_ceil(TILE), cam.height.div_ceil(TILE)],
        }
    }

    pub fn num_tiles(&self) -> usize {
        self.grid[0] * self.grid[1]
    }
}

/// Tile rectangle [xmin, ymin, xmax, ymax) touched by a Gaussian, with the CUDA kernel's truncation rules.
#[inline]
pub(crate) fn tile_rect(p: [f32; 2], radius: i32, grid: [usize; 2]) -> [usize; 4] {
    let r = radius as f32;
    let b = TILE as f32;
    let cl = |v: f32, g: usize| -> usize { (v as i32).clamp(0, g as i32) as usize };
    [cl((p[0] - r) / b, grid[0]), cl((p[1] - r) / b, grid[1]), cl((p[0] + r + b - 1.0) / b, grid[0]), cl((p[1] + r + b - 1.0) / b, grid[1])]
}
