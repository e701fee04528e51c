//! Parity of the SVD VAE (sgm layout model, loaded from the diffusers-layout fixture through
//! `keymap::vae`, and from the same weights re-keyed into the official sgm layout) against
//! `svd/svd_pipeline.safetensors` (see svd/README.md). Tolerances, relative to each output's max |ref| (sums that
//! cancel: entries near zero carry the tensor-scale noise): single model calls CALL = 1e-5 (measured on 7 fixtures —
//! shared + seeds 0–2 at two sizes — ≤ 2.8e-6 of max: encoder mean/logvar, decoder, frames); resize glue 2e-5
//! (measured 4.6e-6 at max ~1: bilinear weights rounded differently; README float32 vs float64 4.6e-6).

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use mvsplat360_refiner::keymap::vae::diffusers_to_sgm;
use mvsplat360_refiner::vae::{frames_from_decoded, prepare_encoder_input, AutoencoderConfig, AutoencoderKL, VaeError, VaeLayout};
use mvsplat360_refiner::weights::Piece;
use mvsplat360_testkit::{self as tk, fixture, get, load, max_abs_diff, Tol};

const CALL: f64 = 1e-5;
const GLUE: f64 = 2e-5;

fn cfg() -> AutoencoderConfig {
    AutoencoderConfig::from_diffusers_json(&fixture("svd/svd_vae_config.json")).expect("vae config")
}

fn vae() -> AutoencoderKL {
    AutoencoderKL::load(&fixture("svd/svd_vae.safetensors"), None, &cfg(), &Device::Cpu).expect("load diffusers-layout vae")
}

/// (B·F, 4, h, w) unscaled final latents, and F.
fn final_latents(p: &HashMap<String, Tensor>, scale: f64) -> (Tensor, usize) {
    let steps = get(p, "step_latents");
    let &[s, b, f, c, h, w] = steps.dims() else { panic!("step_latents must be 6-D") };
    let z = steps.narrow(0, s - 1, 1).unwrap().reshape((b * f, c, h, w)).unwrap();
    ((z / scale).unwrap(), f)
}

fn flat_frames(t: &Tensor) -> Tensor {
    let (b, f, c, h, w) = t.dims5().unwrap();
    t.reshape((b * f, c, h, w)).unwrap()
}

#[test]
fn encoder_input_and_posterior_match_fixture() {
    let p = load("svd/svd_pipeline.safetensors");
    let x = prepare_encoder_input(&flat_frames(get(&p, "target_views")), 2).unwrap();
    tk::assert_check("vae_encode_input", &x, get(&p, "vae_encode_input"), Tol::of_max(GLUE));

    let (mean, logvar) = vae().encode(get(&p, "vae_encode_input")).unwrap();
    for (n, a) in [("vae_encode_mean", &mean), ("vae_encode_logvar", &logvar)] {
        tk::assert_check(n, a, get(&p, n), Tol::of_max(CALL));
    }
}

#[test]
fn decoder_all_frames_and_one_per_call_match_fixture() {
    let p = load("svd/svd_pipeline.safetensors");
    let vae = vae();
    let (z, f) = final_latents(&p, vae.cfg.scale_factor);
    let all = vae.decode(&z, f).unwrap();
    let chunk1 = vae.decode_chunked(&z, Some(1)).unwrap();
    for (n, a) in [("decoded_all", &all), ("decoded_chunk1", &chunk1)] {
        tk::assert_check(n, a, get(&p, n), Tol::of_max(CALL));
    }
    // Chunks of 2 differ from both (temporal mixing sees other neighbours): guards the chunking.
    if f > 2 {
        let c2 = vae.decode_chunked(&z, Some(2)).unwrap();
        assert!(max_abs_diff(&c2, &all).0 > 1e-4 && max_abs_diff(&c2, &chunk1).0 > 1e-4);
    }
    for (n, a) in [("frames_all", &all), ("frames_chunk1", &chunk1)] {
        let fr = frames_from_decoded(a, 2).unwrap();
        let expected = flat_frames(get(&p, n));
        tk::assert_check(n, &fr, &expected, Tol::of_max(CALL));
    }
}

/// The same weights re-keyed into the official checkpoint layout (`refiner.first_stage_model.*`, 1×1 conv
/// attention weights) plus a key of another component: detected, loaded, identical outputs.
#[test]
fn sgm_layout_checkpoint_loads_to_the_same_model() {
    let src = load("svd/svd_vae.safetensors");
    let levels = cfg().ch_mult.len();
    let mut out: HashMap<String, Tensor> = HashMap::new();
    for (k, t) in &src {
        let (name, piece) = diffusers_to_sgm(k, levels).unwrap_or_else(|| panic!("unmapped fixture key {k}"));
        let t = match piece {
            Piece::Reshape => t.reshape((t.dim(0).unwrap(), t.dim(1).unwrap(), 1, 1)).unwrap(),
            _ => t.clone(),
        };
        out.insert(format!("refiner.first_stage_model.{name}"), t);
    }
    out.insert("refiner.model.diffusion_model.out.2.bias".into(), Tensor::zeros(4, DType::F32, &Device::Cpu).unwrap());
    let dir = std::env::temp_dir().join(format!("mvsplat360_vae_sgm_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("ckpt.safetensors");
    candle_core::safetensors::save(&out, &path).unwrap();

    let keys: Vec<String> = out.keys().cloned().collect();
    assert_eq!(VaeLayout::detect(&keys), Some(VaeLayout::Sgm { prefix: "refiner.first_stage_model.".into() }));
    let sgm = AutoencoderKL::load(&path, None, &cfg(), &Device::Cpu).expect("load sgm layout");
    let p = load("svd/svd_pipeline.safetensors");
    let (z, f) = final_latents(&p, sgm.cfg.scale_factor);
    let z = z.narrow(0, 0, f.min(2)).unwrap();
    let a = sgm.decode(&z, z.dim(0).unwrap()).unwrap();
    let b = vae().decode(&z, z.dim(0).unwrap()).unwrap();
    let (d, _) = max_abs_diff(&a, &b);
    assert!(d <= 1e-6, "sgm-layout vs diffusers-layout decode: {d:.3e}");
    let x = get(&p, "vae_encode_input").narrow(0, 0, 1).unwrap();
    let (d, _) = max_abs_diff(&sgm.encode(&x).unwrap().0, &vae().encode(&x).unwrap().0);
    assert!(d <= 1e-6, "sgm-layout vs diffusers-layout encode: {d:.3e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn strict_loading_lists_missing_and_unexpected_keys() {
    let mut src = load("svd/svd_vae.safetensors");
    src.remove("decoder.mid_block.resnets.0.time_mixer.mix_factor").unwrap();
    src.insert("decoder.extra_thing.weight".into(), Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap());
    let w = src.get("encoder.conv_in.bias").unwrap().clone();
    src.insert("encoder.conv_in.bias".into(), Tensor::cat(&[&w, &w], 0).unwrap());
    let dir = std::env::temp_dir().join(format!("mvsplat360_vae_strict_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("bad.safetensors");
    candle_core::safetensors::save(&src, &path).unwrap();
    let err = AutoencoderKL::load(&path, None, &cfg(), &Device::Cpu).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, VaeError::Weights(_)), "{msg}");
    assert!(msg.contains("decoder.mid.block_1.mix_factor"), "{msg}");
    assert!(msg.contains("decoder.extra_thing.weight"), "{msg}");
    assert!(msg.contains("encoder.conv_in.bias"), "{msg}");
    assert!(msg.contains("bad.safetensors"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}
