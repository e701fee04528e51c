//! The MVSplat360 refinement run (`SVDDiffusion.test_step`): CLIP context token, rendered-feature concat
//! condition, EDM sampling with linear guidance, chunked temporal-VAE decoding, ×0.5 resize and clamp.
//!
//! The VAE decoder and CLIP image embedder are reached through [`LatentDecoder`] / [`ImageEmbedder`] so the
//! sampler does not depend on how those modules are built (implemented for the `vae` / `clip` modules).

use candle_core::{DType, Device, Result, Tensor};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

use crate::sampling::{sample, SampleInputs, SamplerConfig, StepRecord};
use crate::unet::VideoUNet;

/// Temporal VAE decoder: latents already divided by the scale factor, (n, 4, h, w) holding `num_frames`
/// frames of one video chunk → images (n, 3, 8h, 8w) in [-1, 1] (unclamped).
pub trait LatentDecoder: Send + Sync {
    fn decode(&self, z: &Tensor, num_frames: usize) -> Result<Tensor>;
}

/// CLIP image embedder: views (n, 3, H, W) in [0, 1] → projected embeddings (n, D).
pub trait ImageEmbedder: Send + Sync {
    fn embed(&self, views: &Tensor) -> Result<Tensor>;
}

/// Refiner settings; defaults = MVSplat360 DL3DV evaluation.
#[derive(Debug, Clone, PartialEq)]
pub struct RefinerConfig {
    pub sampler: SamplerConfig,
    /// VAE latent scale (0.18215).
    pub scale_factor: f32,
    /// Rendered features → latent grid factor (×0.25: renders ×2 before a factor-8 VAE).
    pub feature_scale: f32,
    /// Frames per VAE decode call (`en_and_decode_n_samples_a_time`); None = all frames at once.
    pub decode_chunk: Option<usize>,
}

impl Default for RefinerConfig {
    fn default() -> Self {
        Self { sampler: SamplerConfig::default(), scale_factor: 0.18215, feature_scale: 0.25, decode_chunk: Some(1) }
    }
}

/// Bilinear resize with `align_corners=True` semantics on (N, C, H, W) (PyTorch `F.interpolate`).
pub fn resize_bilinear_align_corners(x: &Tensor, oh: usize, ow: usize) -> Result<Tensor> {
    let (n, c, h, w) = x.dims4()?;
    let src = x.to_dtype(DType::F32)?.contiguous()?.flatten_all()?.to_vec1::<f32>()?;
    let coord = |o: usize, out: usize, inp: usize| -> (usize, usize, f32) {
        if out <= 1 || inp <= 1 {
            return (0, 0, 0.0);
        }
        let s = o as f32 * ((inp - 1) as f32 / (out - 1) as f32);
        let i0 = (s.floor() as usize).min(inp - 1);
        let i1 = (i0 + 1).min(inp - 1);
        (i0, i1, s - i0 as f32)
    };
    let ys: Vec<_> = (0..oh).map(|o| coord(o, oh, h)).collect();
    let xs: Vec<_> = (0..ow).map(|o| coord(o, ow, w)).collect();
    let mut out = vec![0f32; n * c * oh * ow];
    for p in 0..n * c {
        let plane = &src[p * h * w..(p + 1) * h * w];
        let dst = &mut out[p * oh * ow..(p + 1) * oh * ow];
        for (oy, &(y0, y1, fy)) in ys.iter().enumerate() {
            for (ox, &(x0, x1, fx)) in xs.iter().enumerate() {
                let top = plane[y0 * w + x0] * (1.0 - fx) + plane[y0 * w + x1] * fx;
                let bot = plane[y1 * w + x0] * (1.0 - fx) + plane[y1 * w + x1] * fx;
                dst[oy * ow + ox] = top * (1.0 - fy) + bot * fy;
            }
        }
    }
    Tensor::from_vec(out, (n, c, oh, ow), x.device())
}

/// Output size of `F.interpolate(scale_factor=s)`: floor(in · s).
fn scaled(v: usize, s: f32) -> usize {
    ((v as f64) * (s as f64)).floor() as usize
}

/// Seeded standard-normal noise (ChaCha, platform independent): same seed → same tensor.
pub fn seeded_noise(seed: u64, shape: &[usize], device: &Device) -> Result<Tensor> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
    Tensor::from_vec(v, shape, device)
}

/// Inputs of one refinement chunk (B videos of F frames).
pub struct RefineInputs<'a> {
    /// (B, V, 3, H, W) context views in [0, 1].
    pub context_views: &'a Tensor,
    /// (B, F, 4, Hr, Wr) rendered 4-channel features.
    pub rendered_features: &'a Tensor,
    /// (B·F, 4, h, w) initial noise; reuse the same tensor for every chunk of a video (MVSplat360 does).
    pub noise: &'a Tensor,
}

pub struct Refiner {
    pub unet: VideoUNet,
    pub cfg: RefinerConfig,
}

impl Refiner {
    pub fn new(unet: VideoUNet, cfg: RefinerConfig) -> Self {
        Self { unet, cfg }
    }

    /// Cross-attention context: the per-view CLIP embeddings (B, V, D) averaged over views → (B, 1, D).
    pub fn context_embedding(per_view: &Tensor) -> Result<Tensor> {
        per_view.mean_keepdim(1)
    }

    /// Rendered features (B, F, 4, Hr, Wr) → concat condition (B·F, 4, h, w) at `feature_scale`.
    pub fn concat_features(&self, feats: &Tensor) -> Result<Tensor> {
        let (b, f, c, h, w) = feats.dims5()?;
        let x = feats.reshape((b * f, c, h, w))?;
        resize_bilinear_align_corners(&x, scaled(h, self.cfg.feature_scale), scaled(w, self.cfg.feature_scale))
    }

    /// Latent shape (B·F, 4, h, w) for the given rendered features, e.g. for [`seeded_noise`].
    pub fn noise_shape(&self, feats_dims: &[usize]) -> Vec<usize> {
        let s = self.cfg.feature_scale;
        vec![feats_dims[0] * feats_dims[1], 4, scaled(feats_dims[3], s), scaled(feats_dims[4], s)]
    }

    /// EDM sampling → latents (B·F, 4, h, w) (still multiplied by the VAE scale factor).
    pub fn sample_latents(
        &self,
        clip_embedding: &Tensor,
        concat: &Tensor,
        noise: &Tensor,
        num_frames: usize,
        on_step: Option<&mut dyn FnMut(&StepRecord)>,
    ) -> Result<Tensor> {
        sample(&self.unet, &self.cfg.sampler, &SampleInputs { noise, context: clip_embedding, concat, num_frames }, on_step)
    }

    /// Decode latents in chunks of `decode_chunk` frames, downscale by 1/(feature_scale·8) and map to [0, 1]:
    /// (B·F, 4, h, w) → (B, F, 3, H, W).
    pub fn decode(&self, decoder: &dyn LatentDecoder, latents: &Tensor, num_frames: usize) -> Result<Tensor> {
        let n = latents.dim(0)?;
        let z = (latents / self.cfg.scale_factor as f64)?;
        let chunk = self.cfg.decode_chunk.unwrap_or(n).max(1);
        let mut parts = Vec::new();
        let mut i = 0;
        while i < n {
            let m = chunk.min(n - i);
            parts.push(decoder.decode(&z.narrow(0, i, m)?, m)?);
            i += m;
        }
        let x = Tensor::cat(&parts, 0)?;
        self.postprocess(&x, num_frames)
    }

    /// Decoded images (B·F, 3, H', W') in [-1, 1] → frames (B, F, 3, H, W) in [0, 1].
    pub fn postprocess(&self, decoded: &Tensor, num_frames: usize) -> Result<Tensor> {
        let (n, c, h, w) = decoded.dims4()?;
        let up = self.cfg.feature_scale as f64 * 8.0;
        let x = if up > 1.0 {
            let s = (1.0 / up) as f32;
            resize_bilinear_align_corners(decoded, scaled(h, s), scaled(w, s))?
        } else {
            decoded.clone()
        };
        let (_, _, oh, ow) = x.dims4()?;
        ((x + 1.0)? / 2.0)?.clamp(0f32, 1f32)?.reshape((n / num_frames, num_frames, c, oh, ow))
    }

    /// Full run for one chunk of F target frames → refined frames (B, F, 3, H, W) in [0, 1].
    pub fn refine(&self, embedder: &dyn ImageEmbedder, decoder: &dyn LatentDecoder, inp: &RefineInputs) -> Result<Tensor> {
        let (b, v, c, h, w) = inp.context_views.dims5()?;
        let f = inp.rendered_features.dim(1)?;
        let per_view = embedder.embed(&inp.context_views.reshape((b * v, c, h, w))?)?;
        let d = per_view.dim(1)?;
        let ctx = Self::context_embedding(&per_view.reshape((b, v, d))?)?;
        let concat = self.concat_features(inp.rendered_features)?;
        let latents = self.sample_latents(&ctx, &concat, inp.noise, f, None)?;
        self.decode(decoder, &latents, f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn align_corners_resize_keeps_corners_and_is_linear() {
        // f(y, x) = 2y + 3x is reproduced exactly by bilinear interpolation; corners map to corners.
        let (h, w) = (5, 9);
        let v: Vec<f32> = (0..h * w).map(|i| (2 * (i / w) + 3 * (i % w)) as f32).collect();
        let x = Tensor::from_vec(v, (1, 1, h, w), &Device::Cpu).unwrap();
        let y = resize_bilinear_align_corners(&x, 3, 4).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for oy in 0..3 {
            for ox in 0..4 {
                let sy = oy as f32 * 4.0 / 2.0;
                let sx = ox as f32 * 8.0 / 3.0;
                assert!((y[oy * 4 + ox] - (2.0 * sy + 3.0 * sx)).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn seeded_noise_is_reproducible_and_standard() {
        let a = seeded_noise(7, &[2, 4, 8, 8], &Device::Cpu).unwrap();
        let b = seeded_noise(7, &[2, 4, 8, 8], &Device::Cpu).unwrap();
        let c = seeded_noise(8, &[2, 4, 8, 8], &Device::Cpu).unwrap();
        assert_eq!(a.to_vec3::<f32>().is_err(), true); // rank 4
        let d = (&a - &b).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert_eq!(d, 0.0);
        let e = (&a - &c).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(e > 0.1);
        let m = a.mean_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(m.abs() < 0.15, "mean {m}");
    }
}

impl LatentDecoder for crate::vae::AutoencoderKL {
    fn decode(&self, z: &Tensor, num_frames: usize) -> Result<Tensor> {
        crate::vae::AutoencoderKL::decode(self, z, num_frames).map_err(candle_core::Error::wrap)
    }
}

impl ImageEmbedder for crate::clip::ClipImageEmbedder {
    fn embed(&self, views: &Tensor) -> Result<Tensor> {
        crate::clip::ClipImageEmbedder::embed(self, views).map_err(candle_core::Error::wrap)
    }
}
