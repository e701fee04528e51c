//! Gaussian splatting: the `Gaussians` type, the differentiable rasterizer (RGB + latent features) and
//! .ply/.splat I/O.

pub mod gaussians;

pub use gaussians::Gaussians;
