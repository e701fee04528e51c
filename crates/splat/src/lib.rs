//! Gaussian splatting: the `Gaussians` type, the differentiable rasterizer (RGB + latent features) and
//! .ply/.splat I/O.
//!
//! The rasterizer reproduces MVSplat360's renderer (latentSplat's fork of graphdeco's
//! diff-gaussian-rasterization): [`cpu`] is the plain-slice core, [`render`] the candle wrapper with autograd.

pub mod bench;
pub mod camera;
pub mod cpu;
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
