//! End-to-end refiner parity (`svd/`): feature resize, CLIP-token averaging, EDM sampling, chunked temporal
//! VAE decoding (part B's `vae`), ×0.5 resize and clamp → `frames_chunk1` / `frames_all`.
//!
//! Tolerances, relative to the reference's max |ref| (frames: max 1): glue (resize, view mean, post-processing)
//! GLUE = 1e-6 (≈ 16 u: interpolation / averaging / clamp rounding, measured ≤ 1.2e-7 of max); end to end through the
//! sampler and the VAE E2E = 2e-5: the sampler's per-step bound of tests/sampling.rs at its last step (4 steps:
//! 4e-5 of the latents) shrinks through the decoder to the frames; measured ≤ 3.8e-6 on 7 fixtures (shared + seeds
//! 0–2 at two sizes), 5.3×.

use std::sync::Mutex;

use candle_core::{Device, Tensor};
use mvsplat360_refiner::clip::{ClipImageEmbedder, ClipVisionConfig};
use mvsplat360_refiner::refiner::{ImageEmbedder, LatentDecoder, RefineInputs, Refiner, RefinerConfig};
use mvsplat360_refiner::sampling::SamplerConfig;
use mvsplat360_refiner::unet::{VideoUNet, VideoUNetConfig};
use mvsplat360_refiner::vae::{AutoencoderConfig, AutoencoderKL};
use mvsplat360_testkit::{self as tk, fixture, get, load, Tol};

const GLUE: f64 = 1e-6;
const E2E: f64 = 2e-5;

fn refiner(decode_chunk: Option<usize>, steps: usize) -> Refiner {
    let ucfg = VideoUNetConfig::from_diffusers_json(&fixture("svd/svd_unet_config.json")).unwrap();
    let unet = VideoUNet::load(&fixture("svd/svd_unet.safetensors"), None, &ucfg, &Device::Cpu).unwrap();
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(fixture("svd/svd_run_config.json")).unwrap()).unwrap();
    let sampler = SamplerConfig {
        num_steps: steps,
        min_scale: rc["min_g"].as_f64().unwrap() as f32,
        max_scale: rc["max_g"].as_f64().unwrap() as f32,
        cond_aug: rc["cond_aug"].as_f64().unwrap() as f32,
        ..SamplerConfig::default()
    };
    Refiner::new(unet, RefinerConfig { sampler, decode_chunk, ..RefinerConfig::default() })
}

/// Stands in for the CLIP tower: returns the fixture's per-view embeddings (checks the view averaging).
struct FixtureClip(Tensor);
impl ImageEmbedder for FixtureClip {
    fn embed(&self, views: &Tensor) -> candle_core::Result<Tensor> {
        assert_eq!(views.dim(0)?, self.0.dim(0)?);
        Ok(self.0.clone())
    }
}

/// Returns slices of a fixture decoded tensor and records the chunk sizes it was called with.
struct FixtureDecoder {
    decoded: Tensor,
    calls: Mutex<Vec<usize>>,
}
impl LatentDecoder for FixtureDecoder {
    fn decode(&self, z: &Tensor, num_frames: usize) -> candle_core::Result<Tensor> {
        let mut c = self.calls.lock().unwrap();
        let start: usize = c.iter().sum();
        c.push(num_frames);
        self.decoded.narrow(0, start, z.dim(0)?)
    }
}

#[test]
fn features_context_and_postprocess_match_fixture() {
    let pipe = load("svd/svd_pipeline.safetensors");
    let r = refiner(Some(1), 1);
    let cf = r.concat_features(get(&pipe, "gs_rendered_features")).unwrap();
    let want = get(&pipe, "concat_features");
    tk::assert_check("concat_features", &cf, &want.reshape(cf.dims()).unwrap(), Tol::of_max(GLUE));
    let e = get(&pipe, "clip_image_embeds");
    let (bv, d) = e.dims2().unwrap();
    let b = get(&pipe, "clip_embedding").dim(0).unwrap();
    let ctx = Refiner::context_embedding(&e.reshape((b, bv / b, d)).unwrap()).unwrap();
    tk::assert_check("clip_embedding", &ctx, get(&pipe, "clip_embedding"), Tol::of_max(GLUE));
    let f = get(&pipe, "frames_all").dim(1).unwrap();
    for (dec, frames) in [("decoded_chunk1", "frames_chunk1"), ("decoded_all", "frames_all")] {
        let out = r.postprocess(get(&pipe, dec), f).unwrap();
        tk::assert_check(frames, &out, get(&pipe, frames), Tol::of_max(GLUE));
    }
    // Chunked decoding calls the decoder with `decode_chunk` frames at a time and reassembles in order.
    let n = get(&pipe, "decoded_chunk1").dim(0).unwrap();
    let lat = Tensor::zeros((n, 4, 2, 2), candle_core::DType::F32, &Device::Cpu).unwrap();
    for (chunk, expect) in [(Some(1), vec![1; n]), (Some(4), vec![4, n - 4]), (None, vec![n])] {
        let r = Refiner::new(refiner(None, 1).unet, RefinerConfig { decode_chunk: chunk, ..RefinerConfig::default() });
        let dec = FixtureDecoder { decoded: get(&pipe, "decoded_chunk1").clone(), calls: Mutex::new(vec![]) };
        let out = r.decode(&dec, &lat, f).unwrap();
        assert_eq!(*dec.calls.lock().unwrap(), expect);
        tk::assert_check("frames via chunked decode", &out, get(&pipe, "frames_chunk1"), Tol::of_max(GLUE));
    }
}

#[test]
fn end_to_end_frames_match_fixture_with_temporal_vae() {
    let pipe = load("svd/svd_pipeline.safetensors");
    let steps = get(&pipe, "timesteps").dim(0).unwrap();
    let vcfg = AutoencoderConfig::from_diffusers_json(&fixture("svd/svd_vae_config.json")).unwrap();
    let vae = AutoencoderKL::load(&fixture("svd/svd_vae.safetensors"), None, &vcfg, &Device::Cpu).unwrap();
    let fixture_clip = FixtureClip(get(&pipe, "clip_image_embeds").clone());
    let ccfg = ClipVisionConfig::from_transformers_json(&fixture("svd/svd_clip_vision_config.json")).unwrap();
    let real_clip = ClipImageEmbedder::load(&fixture("svd/svd_clip_vision.safetensors"), None, &ccfg, &Device::Cpu).unwrap();
    let embedders: [(&str, &dyn ImageEmbedder); 2] = [("fixture embeds", &fixture_clip), ("CLIP tower", &real_clip)];
    for ((chunk, name), (which, clip)) in [(Some(1), "frames_chunk1"), (None, "frames_all"), (Some(1), "frames_chunk1"), (None, "frames_all")]
        .into_iter()
        .zip([embedders[0], embedders[0], embedders[1], embedders[1]])
    {
        let r = refiner(chunk, steps);
        let out = r
            .refine(
                clip,
                &vae,
                &RefineInputs { context_views: get(&pipe, "context_views"), rendered_features: get(&pipe, "gs_rendered_features"), noise: get(&pipe, "noise") },
            )
            .unwrap();
        tk::assert_check(&format!("{name} ({which})"), &out, get(&pipe, name), Tol::of_max(E2E));
    }
}
