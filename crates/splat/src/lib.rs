//! Gaussian splatting: the `Gaussians` type, the differentiable rasterizer (RGB + latent features) and
//! .ply/.splat I/O.
//!
//! The rasterizer reproduces MVSplat360's renderer (latentSplat's fork of graphdeco's
//! diff-gaussian-rasterization): [`cpu`] is the plain-slice core, [`render`] the candle wrapper with autograd,
//! and `cuda` (feature `cuda-raster`) the same kernels on a GPU (`cuda/rasterize.cu`, tested on CPU by emulation).

pub mod bench;
pub mod camera;
pub mod cpu;
#[cfg(feature = "cuda-raster")]
pub mod cuda;
pub mod error;
pub mod gaussians;
pub mod io;
pub mod op;
pub mod sh;
mod util;

pub use camera::RasterCamera;
pub use cpu::{CovInput, ForwardOutput, GradMode, Gradients, PixelGrads, RasterInputs, RasterSettings};
pub use error::{Result, SplatError};
pub use gaussians::Gaussians;
pub use op::{render, render_views, RenderOptions, RenderOutput};
