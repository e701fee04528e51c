//! The kernels' differentiable mode: a tiny UNet and a tiny VAE encoder give the fast path's values
//! (≤ 1e-4 relative to the output's largest magnitude) and every input and weight (`Var`) gets a non-zero
//! gradient. Random weights (biases 0, norm scales 1, mix factors 0, matrices ±1/√fan_in).

use candle_core::{DType, Device, Tensor, Var};
use mvsplat360_refiner::kernels;
use mvsplat360_refiner::unet::util::timestep_embedding;
use mvsplat360_refiner::unet::{UNetInputs, VideoUNet, VideoUNetConfig};
use mvsplat360_refiner::vae::{AutoencoderConfig, AutoencoderKL};

fn max_abs(t: &Tensor) -> f32 {
    t.abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
}

fn rel_diff(a: &Tensor, b: &Tensor) -> f32 {
    max_abs(&(a - b).unwrap()) / max_abs(b).max(1e-12)
}

fn tiny_unet_cfg() -> VideoUNetConfig {
    VideoUNetConfig::tiny()
}

/// Moves every `Var` but those `keep` names (×1.25 + 0.01 + noise) by `Var::set`, and saves the new values
/// under `prefix` + name to `file` (what a model loaded after training would read).
fn move_vars_and_save(vars: &[(String, Var)], prefix: &str, keep: impl Fn(&str) -> bool, file: &std::path::Path) {
    let dev = Device::Cpu;
    let mut moved = std::collections::HashMap::new();
    for (k, v) in vars {
        let t = if keep(k) {
            v.as_tensor().copy().unwrap()
        } else {
            (v.as_tensor().affine(1.25, 0.01).unwrap() + Tensor::randn(0f32, 0.05, v.dims(), &dev).unwrap()).unwrap()
        };
        v.set(&t).unwrap();
        moved.insert(format!("{prefix}{k}"), t);
    }
    candle_core::safetensors::save(&moved, file).unwrap();
}

/// Inputs of the tiny UNet: 3 frames (the temporal convs see both borders and an interior frame) and two
/// context tokens (one token makes the cross-attention queries/keys inert).
fn tiny_unet_inputs() -> (usize, Tensor, Tensor, Tensor, [f32; 3]) {
    let dev = Device::Cpu;
    let f = 3;
    let x = Tensor::randn(0f32, 1.0, (f, 8, 4, 6), &dev).unwrap();
    let ctx = Tensor::randn(0f32, 1.0, (f, 2, 32), &dev).unwrap();
    let y = timestep_embedding(&[0.02; 3], 32, 10000.0, &dev).unwrap();
    (f, x, ctx, y, [0.3f32, -0.2, 0.7])
}

/// Every `Var` gets a gradient with a non-zero entry; returns how many were checked.
fn assert_all_grads_nonzero(grads: &candle_core::backprop::GradStore, vars: &[(String, Var)], filter: impl Fn(&str) -> bool) -> usize {
    let mut n = 0;
    let mut zero = Vec::new();
    for (name, v) in vars.iter().filter(|(n, _)| filter(n)) {
        match grads.get(v.as_tensor()) {
            Some(g) if max_abs(g) > 0.0 => {}
            Some(_) => zero.push(format!("{name} (zero)")),
            None => zero.push(format!("{name} (none)")),
        }
        n += 1;
    }
    assert!(zero.is_empty(), "{} of {n} weights without gradient: {zero:?}", zero.len());
    n
}

#[test]
fn tiny_unet_differentiable_mode_matches_fast_path_and_reaches_every_weight() {
    let dev = Device::Cpu;
    let cfg = tiny_unet_cfg();
    let (f, x, ctx, y, ts) = tiny_unet_inputs();

    assert!(!kernels::is_differentiable(), "the fast path must be the default");
    let fast_model = VideoUNet::random(&cfg, 11, &dev).unwrap();
    let fast = fast_model.forward(&UNetInputs { x: &x, timesteps: &ts, context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None }).unwrap();

    let (model, vars) = VideoUNet::random_trainable(&cfg, 11, &dev).unwrap();
    let xv = Var::from_tensor(&x).unwrap();
    let out = {
        let _g = kernels::differentiable();
        model.forward(&UNetInputs { x: xv.as_tensor(), timesteps: &ts, context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None }).unwrap()
    };
    assert!(!kernels::is_differentiable(), "the guard must restore the fast path");
    let d = rel_diff(&out, &fast);
    eprintln!("UNet differentiable vs fast: max rel diff {d:.2e}, {} weights", vars.len());
    assert!(d <= 1e-4, "UNet: differentiable path differs from the fast path by {d:.2e}");

    // Trainable weights in fast mode give the same model as plain random weights.
    let same = model.forward(&UNetInputs { x: &x, timesteps: &ts, context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None }).unwrap();
    assert_eq!(max_abs(&(&same - &fast).unwrap()), 0.0);

    let r = Tensor::randn(0f32, 1.0, out.dims(), &dev).unwrap();
    let loss = (&out * &r).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let gx = grads.get(xv.as_tensor()).expect("input gradient");
    assert!(max_abs(gx) > 0.0);
    // Both halves of the input (noisy latent and concat condition) reach the output.
    for (c0, name) in [(0, "latent"), (4, "concat")] {
        assert!(max_abs(&gx.narrow(1, c0, 4).unwrap()) > 0.0, "no gradient on the {name} channels");
    }
    let n = assert_all_grads_nonzero(&grads, &vars, |_| true);
    assert!(n > 100, "only {n} weights");
    assert!(vars.iter().any(|(k, _)| k.ends_with("time_mixer.mix_factor")));
}

#[test]
fn tiny_vae_encoder_differentiable_mode_matches_fast_path_and_reaches_every_weight() {
    let dev = Device::Cpu;
    let cfg = AutoencoderConfig { ch: 32, ch_mult: vec![1, 2], num_res_blocks: 1, ..AutoencoderConfig::default() };
    let img = Tensor::rand(-1f32, 1.0, (2, 3, 8, 10), &dev).unwrap();
    let fast_model = AutoencoderKL::random(&cfg, 5, &dev).unwrap();
    let (fm, fl) = fast_model.encode(&img).unwrap();

    let (model, vars) = AutoencoderKL::random_trainable(&cfg, 5, &dev).unwrap();
    let iv = Var::from_tensor(&img).unwrap();
    let (m, l) = {
        let _g = kernels::differentiable();
        model.encode(iv.as_tensor()).unwrap()
    };
    let (dm, dl) = (rel_diff(&m, &fm), rel_diff(&l, &fl));
    eprintln!("VAE encoder differentiable vs fast: mean {dm:.2e}, logvar {dl:.2e}");
    assert!(dm <= 1e-4 && dl <= 1e-4, "VAE encoder: mean {dm:.2e}, logvar {dl:.2e}");
    assert_eq!(m.dims(), &[2, 4, 4, 5]);

    let r1 = Tensor::randn(0f32, 1.0, m.dims(), &dev).unwrap();
    let r2 = Tensor::randn(0f32, 1.0, l.dims(), &dev).unwrap();
    let loss = ((&m * &r1).unwrap().sum_all().unwrap() + (&l * &r2).unwrap().sum_all().unwrap()).unwrap();
    let grads = loss.backward().unwrap();
    assert!(max_abs(grads.get(iv.as_tensor()).expect("input gradient")) > 0.0);
    let n = assert_all_grads_nonzero(&grads, &vars, |k| k.starts_with("encoder."));
    assert!(n > 20, "only {n} encoder weights");
    let _ = DType::F32;
}

/// The decoder (training a VAE from scratch): one frame per call, as MVSplat360 decodes.
#[test]
fn tiny_vae_decoder_differentiable_mode_matches_fast_path_and_reaches_every_weight() {
    let dev = Device::Cpu;
    let cfg = AutoencoderConfig { ch: 32, ch_mult: vec![1, 2], num_res_blocks: 1, ..AutoencoderConfig::default() };
    let z = Tensor::randn(0f32, 1.0, (2, 4, 4, 5), &dev).unwrap();
    let fast = AutoencoderKL::random(&cfg, 5, &dev).unwrap().decode(&z, 1).unwrap();
    let (model, vars) = AutoencoderKL::random_trainable(&cfg, 5, &dev).unwrap();
    let zv = Var::from_tensor(&z).unwrap();
    let x = {
        let _g = kernels::differentiable();
        model.decode(zv.as_tensor(), 1).unwrap()
    };
    let d = rel_diff(&x, &fast);
    eprintln!("VAE decoder differentiable vs fast: {d:.2e}");
    assert!(d <= 1e-4, "VAE decoder: {d:.2e}");
    assert_eq!(x.dims(), &[2, 3, 8, 10]);
    let r = Tensor::randn(0f32, 1.0, x.dims(), &dev).unwrap();
    let grads = (&x * &r).unwrap().sum_all().unwrap().backward().unwrap();
    assert!(max_abs(grads.get(zv.as_tensor()).expect("latent gradient")) > 0.0);
    // Every decoder weight gets one, the temporal convolutions and the mix factors included.
    let n = assert_all_grads_nonzero(&grads, &vars, |k| k.starts_with("decoder."));
    assert!(n > 20, "only {n} decoder weights");
    assert!(vars.iter().any(|(k, _)| k.starts_with("decoder.") && k.ends_with("mix_factor")));
}

/// Training changes a weight by `Var::set` (Adam): the model must then compute with the new values, exactly
/// as a model loaded from them does, in both modes. A weight rearranged once at load (a copy) would keep its
/// initial values in the forward while the saved `Var` drifts; so would a mix factor read as a number at load.
#[test]
fn vae_trainable_weights_follow_their_vars() {
    let dev = Device::Cpu;
    let cfg = AutoencoderConfig { ch: 32, ch_mult: vec![1, 2], num_res_blocks: 1, ..AutoencoderConfig::default() };
    let (model, vars) = AutoencoderKL::random_trainable(&cfg, 5, &dev).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("vae.safetensors");
    move_vars_and_save(&vars, "first_stage_model.", |_| false, &file);
    let loaded = AutoencoderKL::load(&file, None, &cfg, &dev).unwrap();
    let img = Tensor::rand(-1f32, 1.0, (2, 3, 32, 40), &dev).unwrap();
    let z = Tensor::randn(0f32, 1.0, (2, 4, 4, 5), &dev).unwrap();
    let want = (loaded.encode(&img).unwrap().0, loaded.decode(&z, 1).unwrap());
    for differentiable in [false, true] {
        let _g = differentiable.then(kernels::differentiable);
        let (m, x) = (model.encode(&img).unwrap().0, model.decode(&z, 1).unwrap());
        let (dm, dx) = (rel_diff(&m, &want.0), rel_diff(&x, &want.1));
        eprintln!("differentiable {differentiable}: encoder {dm:.2e}, decoder {dx:.2e}");
        assert!(dm <= 1e-5 && dx <= 1e-5, "differentiable {differentiable}: the model does not follow its Vars (encoder {dm:.2e}, decoder {dx:.2e})");
    }
}

/// The UNet twin of [`vae_trainable_weights_follow_their_vars`].
#[test]
fn unet_trainable_weights_follow_their_vars() {
    let dev = Device::Cpu;
    let cfg = tiny_unet_cfg();
    let (model, vars) = VideoUNet::random_trainable(&cfg, 11, &dev).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("unet.safetensors");
    move_vars_and_save(&vars, "model.diffusion_model.", |_| false, &file);
    let loaded = VideoUNet::load(&file, None, &cfg, &dev).unwrap();
    let (f, x, ctx, y, ts) = tiny_unet_inputs();
    let run = |m: &VideoUNet| m.forward(&UNetInputs { x: &x, timesteps: &ts, context: &ctx, y: Some(&y), num_video_frames: f, num_splits: None }).unwrap();
    let want = run(&loaded);
    for differentiable in [false, true] {
        let _g = differentiable.then(kernels::differentiable);
        let d = rel_diff(&run(&model), &want);
        assert!(d <= 1e-5, "differentiable {differentiable}: the UNet does not follow its Vars ({d:.2e})");
    }
}

#[test]
fn differentiable_switch_is_per_thread_and_restored() {
    assert!(!kernels::is_differentiable());
    let prev = kernels::set_differentiable(true);
    assert!(!prev && kernels::is_differentiable());
    std::thread::spawn(|| assert!(!kernels::is_differentiable())).join().unwrap();
    {
        let _g = kernels::differentiable();
        assert!(kernels::is_differentiable());
    }
    assert!(kernels::is_differentiable(), "a nested guard restores the previous setting");
    kernels::set_differentiable(false);
    assert!(!kernels::is_differentiable());
}
