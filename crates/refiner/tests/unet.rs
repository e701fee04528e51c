//! VideoUNet parity against the diffusers fixture (`svd/`), plus the sgm-layout, f16 and label_emb-slicing
//! load paths (the fixture re-saved under sgm names through the key table).
//!
//! Tolerance of a single UNet call: |Δ| ≤ CALL × max|ref| of the output (scale-relative: attention and convolution
//! outputs are sums that cancel, so entries near zero carry the tensor-scale noise). Measured on 7 fixtures (shared
//! + seeds 0–2 at two sizes): ≤ 2.2e-6 of max (3.3e-6 at max ~1.5); the fixture README's float32-vs-float64 run
//! of the reference is 1.05e-5 of max → CALL = 1e-5 (4.5× the measured f32-vs-f32 spread).

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use mvsplat360_refiner::unet::keymap::diffusers_to_sgm;
use mvsplat360_refiner::unet::util::timestep_embedding;
use mvsplat360_refiner::unet::{UNetError, UNetInputs, UNetLayout, VideoUNet, VideoUNetConfig};
use mvsplat360_testkit::{self as tk, assert_close, fixture, get, load, max_abs_diff, Tol};

const CALL: f64 = 1e-5;

struct Case {
    pipe: HashMap<String, Tensor>,
    cfg: VideoUNetConfig,
}

fn case() -> Case {
    let cfg = VideoUNetConfig::from_diffusers_json(&fixture("svd/svd_unet_config.json")).expect("config");
    Case { pipe: load("svd/svd_pipeline.safetensors"), cfg }
}

/// UNet outputs for step `i` of the fixture: (v_uncond, v_cond), each (B·F, 4, h, w).
fn run_step(unet: &VideoUNet, c: &Case, i: usize) -> (Tensor, Tensor) {
    let inp = get(&c.pipe, "step_unet_input").get(i).unwrap(); // (2B, F, 8, h, w)
    let (b2, f, ch, h, w) = inp.dims5().unwrap();
    let n = b2 * f;
    let x = inp.reshape((n, ch, h, w)).unwrap();
    let t = get(&c.pipe, "timesteps").to_vec1::<f32>().unwrap()[i];
    let emb = get(&c.pipe, "clip_embedding"); // (B, 1, D)
    let (b, lc, d) = emb.dims3().unwrap();
    let ctx = emb.unsqueeze(1).unwrap().broadcast_as((b, f, lc, d)).unwrap().reshape((b * f, lc, d)).unwrap();
    let ctx = Tensor::cat(&[&ctx.zeros_like().unwrap(), &ctx], 0).unwrap();
    let cond_aug = get(&c.pipe, "cond_aug").to_vec1::<f32>().unwrap()[0];
    let y = timestep_embedding(&vec![cond_aug; n], c.cfg.adm_in_channels.unwrap(), 10000.0, &Device::Cpu).unwrap();
    let out = unet.forward(&UNetInputs { x: &x, timesteps: &vec![t; n], context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None }).unwrap();
    (out.narrow(0, 0, n / 2).unwrap(), out.narrow(0, n / 2, n / 2).unwrap())
}

fn expected(c: &Case, name: &str, i: usize) -> Tensor {
    let t = get(&c.pipe, name).get(i).unwrap();
    let d = t.dims().to_vec();
    t.reshape((d[0] * d[1], d[2], d[3], d[4])).unwrap()
}

#[test]
fn unet_matches_diffusers_fixture_every_step() {
    let c = case();
    let unet = VideoUNet::load(&fixture("svd/svd_unet.safetensors"), None, &c.cfg, &Device::Cpu).expect("strict load");
    let steps = get(&c.pipe, "timesteps").dim(0).unwrap();
    for i in 0..steps {
        let (vu, vc) = run_step(&unet, &c, i);
        tk::assert_check(&format!("step_v_uncond[{i}]"), &vu, &expected(&c, "step_v_uncond", i), Tol::of_max(CALL));
        tk::assert_check(&format!("step_v_cond[{i}]"), &vc, &expected(&c, "step_v_cond", i), Tol::of_max(CALL));
    }
}

/// The fixture's UNet with `--dtype bf16` on the CPU (weights packed in bf16; `vdpbf16ps` with AVX512-BF16,
/// storage only without) against the official outputs at every step: relative L2 error ≤ 16u, u = 2⁻⁸, the
/// bound tests/half.rs derives (√P·ρ over the products on the longest path, with a 1.6× margin for gain). The
/// error must be non-zero: the bf16 path ran.
#[test]
fn unet_in_bf16_on_the_cpu_is_within_the_error_model_of_the_fixture() {
    let c = case();
    let unet = VideoUNet::load_as(&fixture("svd/svd_unet.safetensors"), None, &c.cfg, &Device::Cpu, candle_core::DType::BF16).expect("strict load");
    let rel = |a: &Tensor, b: &Tensor| {
        let d = (a - b).unwrap().sqr().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap() as f64;
        (d / b.sqr().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap() as f64).sqrt()
    };
    let u = 1.0 / 256.0;
    for i in 0..get(&c.pipe, "timesteps").dim(0).unwrap() {
        let (vu, vc) = run_step(&unet, &c, i);
        for (name, got, want) in [("uncond", vu, expected(&c, "step_v_uncond", i)), ("cond", vc, expected(&c, "step_v_cond", i))] {
            let e = rel(&got, &want);
            eprintln!("step {i} {name}: bf16 relative L2 error {e:.2e} ({:.2} u)", e / u);
            assert!(e > 0.0 && e <= 16.0 * u, "step {i} {name}: relative L2 error {e:.2e} (16u = {:.2e})", 16.0 * u);
        }
    }
}

/// Re-save the fixture under sgm names (`model.diffusion_model.` prefix, as in svd.safetensors), optionally
/// as f16 and with a widened label_emb input (768-style), and check the same outputs come back.
#[test]
fn sgm_layout_f16_and_wide_label_emb_load_the_same_model() {
    let c = case();
    let diff = load("svd/svd_unet.safetensors");
    let dir = tempfile::tempdir().unwrap();
    let mut sgm = HashMap::new();
    for (k, v) in &diff {
        let s = diffusers_to_sgm(k, &c.cfg).unwrap_or_else(|| panic!("fixture key {k} has no sgm name"));
        let v = if s == "label_emb.0.0.weight" {
            // Extra trailing columns must be dropped by the loader (fps / motion-bucket inputs).
            let extra = Tensor::ones((v.dim(0).unwrap(), 2 * v.dim(1).unwrap()), DType::F32, &Device::Cpu).unwrap();
            Tensor::cat(&[v, &extra], 1).unwrap()
        } else {
            v.clone()
        };
        sgm.insert(format!("model.diffusion_model.{s}"), v);
    }
    // A non-UNet key of a full checkpoint must be ignored.
    sgm.insert("first_stage_model.decoder.conv_in.weight".into(), Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap());
    let p32 = dir.path().join("sgm32.safetensors");
    candle_core::safetensors::save(&sgm, &p32).unwrap();
    let p16 = dir.path().join("sgm16.safetensors");
    let sgm16: HashMap<String, Tensor> = sgm.iter().map(|(k, v)| (k.clone(), v.to_dtype(DType::F16).unwrap())).collect();
    candle_core::safetensors::save(&sgm16, &p16).unwrap();

    let reference = VideoUNet::load(&fixture("svd/svd_unet.safetensors"), Some(UNetLayout::Diffusers), &c.cfg, &Device::Cpu).unwrap();
    let (ru, rc) = run_step(&reference, &c, 1);
    let m32 = VideoUNet::load(&p32, None, &c.cfg, &Device::Cpu).expect("sgm layout, auto-detected");
    let (u, v) = run_step(&m32, &c, 1);
    assert_close("sgm f32 uncond", &u, &ru, 0.0);
    assert_close("sgm f32 cond", &v, &rc, 0.0);
    let m16 = VideoUNet::load(&p16, None, &c.cfg, &Device::Cpu).expect("sgm layout f16");
    let (u, v) = run_step(&m16, &c, 1);
    // f16 weight rounding (rel 2^-11) through ~40 layers: a few 1e-3 on outputs of magnitude ~1.5.
    let (du, _) = max_abs_diff(&u, &ru);
    let (dv, _) = max_abs_diff(&v, &rc);
    eprintln!("f16 weights: max abs diff uncond {du:.2e}, cond {dv:.2e}");
    assert!(du < 2e-2 && dv < 2e-2 && du > 0.0, "f16 load: {du} {dv}");
}

#[test]
fn wrong_config_lists_missing_unexpected_and_misshaped_keys() {
    let c = case();
    let mut cfg = c.cfg.clone();
    cfg.num_res_blocks = 2; // fixture has 1 per level → missing resnets.1 etc.
    cfg.in_channels = 4; // → conv_in shape mismatch
    let err = VideoUNet::load(&fixture("svd/svd_unet.safetensors"), None, &cfg, &Device::Cpu).unwrap_err();
    match &err {
        UNetError::KeyMismatch { missing, mismatched, .. } => {
            assert!(!missing.is_empty());
            assert!(mismatched.iter().any(|m| m.starts_with("conv_in.weight")), "{mismatched:?}");
        }
        e => panic!("unexpected error {e}"),
    }
    let msg = err.to_string();
    assert!(msg.contains("missing") && msg.contains("svd_unet.safetensors"), "{msg}");
}
