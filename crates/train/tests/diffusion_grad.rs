//! Refiner losses (`loss::diffusion`): closed forms of the σ schedule, scalings and loss value, exact zeros,
//! and backward gradients against central finite differences on a tiny random UNet / VAE.
//!
//! Finite differences: f32 forward, step h = 2e-2 on features / weights (loss changes ≫ f32 rounding), pass if
//! |g − fd| ≤ 2e-2·max(|g|, |fd|) + 1e-3·(largest |g| checked) — a wrong sign, factor or missing path fails.

use candle_core::{Device, Tensor, Var};
use mvsplat360_refiner::kernels;
use mvsplat360_refiner::refiner::resize_bilinear_align_corners as resize_reference;
use mvsplat360_refiner::refiner::seeded_noise;
use mvsplat360_refiner::unet::{VideoUNet, VideoUNetConfig};
use mvsplat360_refiner::vae::{AutoencoderConfig, AutoencoderKL};
use mvsplat360_train::loss::diffusion::*;
use rand::SeedableRng;

fn tiny_unet_cfg() -> VideoUNetConfig {
    VideoUNetConfig::tiny()
}

fn tiny_vae() -> AutoencoderKL {
    // 4 levels: the real factor-8 latent grid.
    let cfg = AutoencoderConfig { ch: 32, ch_mult: vec![1, 1, 2, 2], num_res_blocks: 1, ..AutoencoderConfig::default() };
    AutoencoderKL::random(&cfg, 9, &Device::Cpu).unwrap()
}

fn scalar(t: &Tensor) -> f64 {
    t.to_scalar::<f32>().unwrap() as f64
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn var_named<'a>(vars: &'a [(String, Var)], name: &str) -> &'a Var {
    &vars.iter().find(|(k, _)| k == name).unwrap_or_else(|| panic!("no weight {name}")).1
}

/// Set element `i` of `v` to `x`, returning the old value.
fn set_elem(v: &Var, i: usize, x: f32) -> f32 {
    let mut d = flat(v.as_tensor());
    let old = d[i];
    d[i] = x;
    v.set(&Tensor::from_vec(d, v.as_tensor().dims(), &Device::Cpu).unwrap()).unwrap();
    old
}

/// Central difference of `loss()` in element `i` of `v` (restored afterwards).
fn central_diff(v: &Var, i: usize, h: f32, loss: &dyn Fn() -> f64) -> f64 {
    let x0 = set_elem(v, i, 0.0);
    set_elem(v, i, x0 + h);
    let lp = loss();
    set_elem(v, i, x0 - h);
    let lm = loss();
    set_elem(v, i, x0);
    (lp - lm) / (2.0 * h as f64)
}

fn check_fd(what: &str, pairs: &[(f64, f64)]) {
    let scale = pairs.iter().map(|p| p.0.abs()).fold(0.0, f64::max);
    assert!(scale > 0.0, "{what}: all gradients are zero");
    for (k, &(g, fd)) in pairs.iter().enumerate() {
        let tol = 2e-2 * g.abs().max(fd.abs()) + 1e-3 * scale;
        eprintln!("{what}[{k}]: backward {g:+.6e}, central difference {fd:+.6e}");
        assert!((g - fd).abs() <= tol, "{what}[{k}]: backward {g:e} vs finite difference {fd:e}");
    }
}

struct Case {
    unet: VideoUNet,
    vars: Vec<(String, Var)>,
    latents: Tensor,
    features: Var,
    ctx: Tensor,
    sigmas: Vec<f32>,
    noise: Tensor,
    frames: usize,
}

fn case() -> Case {
    let dev = Device::Cpu;
    let (unet, vars) = VideoUNet::random_trainable(&tiny_unet_cfg(), 3, &dev).unwrap();
    let (n, frames) = (3, 3);
    Case {
        unet,
        vars,
        // Seeded: with unseeded draws about one in ten put a checked weight where the loss curves enough for
        // the central difference's O(h²) error to exceed the tolerance.
        latents: seeded_noise(21, &[n, 4, 4, 4], &dev).unwrap(),
        features: Var::from_tensor(&seeded_noise(22, &[n, 4, 4, 4], &dev).unwrap()).unwrap(),
        ctx: seeded_noise(23, &[1, 1, 32], &dev).unwrap(),
        sigmas: vec![0.6, 1.3, 3.1],
        noise: seeded_noise(24, &[n, 4, 4, 4], &dev).unwrap(),
        frames,
    }
}

impl Case {
    fn loss(&self) -> Tensor {
        diffusion_loss(&self.unet, &self.latents, self.features.as_tensor(), &self.ctx, &self.sigmas, &self.noise, self.frames).unwrap()
    }
}

#[test]
fn ddpm_sigmas_closed_form() {
    let s = DdpmSigmas::official();
    assert_eq!(s.len(), 1000);
    let v = s.as_slice();
    assert!(v.windows(2).all(|w| w[0] < w[1]), "ascending (DiscreteSampling flips the discretization)");
    // Independent closed form in f64: β_j = (√a + j(√b − √a)/999)², σ = √((1 − Π(1−β))/Π(1−β)).
    let (a, b) = (0.00085f64.sqrt(), 0.012f64.sqrt());
    let beta = |j: usize| (a + j as f64 * (b - a) / 999.0).powi(2);
    let first = (beta(0) / (1.0 - beta(0))).sqrt();
    let prod: f64 = (0..1000).map(|j| 1.0 - beta(j)).product();
    let last = ((1.0 - prod) / prod).sqrt();
    eprintln!("sigma_min {} (closed form {first}), sigma_max {} (closed form {last})", v[0], v[999]);
    assert!((v[0] as f64 / first - 1.0).abs() < 1e-6);
    assert!((v[999] as f64 / last - 1.0).abs() < 1e-5);
    assert!((first - 0.029_167).abs() < 1e-5 && (last - 14.6146).abs() < 1e-3);
    // Uniform index per frame: draws are schedule values, independent, and reach both ends.
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    let d = s.sample(&mut rng, 20_000);
    assert!(d.iter().all(|x| v.contains(x)));
    assert!(d.windows(2).any(|w| w[0] != w[1]));
    assert!(d.contains(&v[0]) && d.contains(&v[999]));
    let below_median = d.iter().filter(|&&x| x <= v[499]).count() as f64 / d.len() as f64;
    assert!((below_median - 0.5).abs() < 0.02, "{below_median}");
}

#[test]
fn scalings_and_weighting_closed_form() {
    for sigma in [0.029_167f32, 0.5, 1.0, 2.5, 14.6] {
        let s = scalings(sigma);
        let q = (sigma as f64).powi(2) + 1.0;
        let want = [1.0 / q, -(sigma as f64) / q.sqrt(), 1.0 / q.sqrt(), 0.25 * (sigma as f64).ln()];
        for (got, want) in [s.c_skip, s.c_out, s.c_in, s.c_noise].iter().zip(want) {
            assert!((*got as f64 - want).abs() <= 1e-6 * want.abs().max(1e-3), "σ {sigma}: {got} vs {want}");
        }
        assert!((loss_weighting(sigma) as f64 * (sigma as f64).powi(2) - 1.0).abs() < 1e-6);
    }
    assert_eq!(LATENT_ALIGNMENT_WEIGHT, 0.01);
    assert_eq!(DIFFUSION_LOSS_WEIGHT, 1.0);
    assert_eq!(COND_AUG, 0.02);
}

/// With the output conv zeroed and its bias b, the UNet predicts v ≡ b: the loss has a closed form that pins
/// the noising, every scaling, the σ⁻² weighting and the reduction; and b = the v-target gives exactly 0.
#[test]
fn diffusion_loss_closed_form_and_zero_at_the_target() {
    let c = case();
    let w = var_named(&c.vars, "out.2.weight");
    w.set(&w.as_tensor().zeros_like().unwrap()).unwrap();
    let bias = var_named(&c.vars, "out.2.bias");
    let b = [0.3f32, -0.7, 1.1, 0.05];
    bias.set(&Tensor::new(&b, &Device::Cpu).unwrap()).unwrap();

    let (x, n) = (flat(&c.latents), flat(&c.noise));
    let per = x.len() / 3;
    let mut want = 0f64;
    for (i, (&xi, &ni)) in x.iter().zip(&n).enumerate() {
        let s = c.sigmas[i / per] as f64;
        let q = s * s + 1.0;
        let d = -s / q.sqrt() * b[(i % per) / 16] as f64 + (xi as f64 + s * ni as f64) / q;
        want += (d - xi as f64).powi(2) / (s * s);
    }
    want /= x.len() as f64;
    let got = scalar(&c.loss());
    eprintln!("closed form {want:.8e}, loss {got:.8e}");
    assert!((got / want - 1.0).abs() < 1e-5, "loss {got} vs closed form {want}");

    // x ≡ x_c, n ≡ n_c per channel, one σ: b_c = (n_c − σ·x_c)/√(σ²+1) makes D = x.
    let sigma = 1.7f32;
    let (xc, nc) = ([0.4f32, -1.2, 0.9, 0.0], [-0.3f32, 0.8, 1.5, -2.0]);
    let fill = |v: &[f32; 4]| Tensor::new(v, &Device::Cpu).unwrap().reshape((1, 4, 1, 1)).unwrap().broadcast_as((3, 4, 4, 4)).unwrap().contiguous().unwrap();
    let (lat, noise) = (fill(&xc), fill(&nc));
    let v_target: Vec<f32> = xc.iter().zip(&nc).map(|(x, n)| (n - sigma * x) / (sigma * sigma + 1.0).sqrt()).collect();
    let run = |bv: &[f32]| {
        bias.set(&Tensor::new(bv, &Device::Cpu).unwrap()).unwrap();
        scalar(&diffusion_loss(&c.unet, &lat, c.features.as_tensor(), &c.ctx, &[sigma; 3], &noise, 3).unwrap())
    };
    let at_target = run(&v_target);
    let flipped: Vec<f32> = v_target.iter().map(|v| -v).collect();
    let wrong = run(&flipped);
    eprintln!("loss at the v-target {at_target:e}, with the v-target's sign flipped {wrong:e}");
    assert!(at_target < 1e-12, "{at_target}");
    assert!(wrong > 0.1, "{wrong}");
    // x = 0, n = 0, v = 0: exactly zero.
    let z = lat.zeros_like().unwrap();
    bias.set(&bias.as_tensor().zeros_like().unwrap()).unwrap();
    let l = diffusion_loss(&c.unet, &z, c.features.as_tensor(), &c.ctx, &[sigma; 3], &z, 3).unwrap();
    assert_eq!(l.to_scalar::<f32>().unwrap(), 0.0);
}

#[test]
fn diffusion_loss_gradient_wrt_features_matches_finite_differences() {
    let c = case();
    let grads = c.loss().backward().unwrap();
    let g = flat(grads.get(c.features.as_tensor()).expect("gradient on the rendered features"));
    // A few entries in every frame, plus the largest gradient.
    let imax = (0..g.len()).max_by(|&a, &b| g[a].abs().total_cmp(&g[b].abs())).unwrap();
    let idx = [0usize, 37, 70, 101, 150, 191, imax];
    let pairs: Vec<(f64, f64)> = idx.iter().map(|&i| (g[i] as f64, central_diff(&c.features, i, 2e-2, &|| scalar(&c.loss())))).collect();
    check_fd("d loss / d features", &pairs);
    assert!(!kernels::is_differentiable(), "the loss must leave the fast path on");
}

#[test]
fn diffusion_loss_gradient_wrt_unet_weights_matches_finite_differences() {
    let c = case();
    let grads = c.loss().backward().unwrap();
    let picks = [
        ("input_blocks.0.0.weight", 5usize),
        ("input_blocks.1.0.time_stack.in_layers.2.weight", 17),
        ("input_blocks.1.1.transformer_blocks.0.attn1.to_q.weight", 40),
        ("input_blocks.3.1.time_stack.0.attn1.to_k.weight", 3),
        ("middle_block.0.time_mixer.mix_factor", 0),
        ("middle_block.1.time_mixer.mix_factor", 0),
        ("label_emb.0.0.weight", 9),
        ("out.2.bias", 2),
    ];
    let mut pairs = Vec::new();
    for (name, i) in picks {
        let v = var_named(&c.vars, name);
        let g = flat(grads.get(v.as_tensor()).unwrap_or_else(|| panic!("no gradient for {name}")))[i] as f64;
        pairs.push((g, central_diff(v, i, 2e-2, &|| scalar(&c.loss()))));
    }
    check_fd("d loss / d weights", &pairs);
}

#[test]
fn latent_alignment_loss_value_zero_and_gradient() {
    let dev = Device::Cpu;
    let vae = tiny_vae();
    let (h, w) = (16, 24);
    let targets = Tensor::rand(0f32, 1.0, (2, 3, h, w), &dev).unwrap();
    let noise = Tensor::randn(0f32, 1.0, (2, 3, 2 * h, 2 * w), &dev).unwrap();
    // E by hand: an independent ×2 bilinear (align_corners) resize, [-1, 1], + 0.02·noise, posterior mean.
    let up = resize_reference(&targets, 2 * h, 2 * w).unwrap();
    let x = ((up * 2.0).unwrap() - 1.0).unwrap();
    let x = (x + (&noise * 0.02).unwrap()).unwrap();
    let (e, _) = vae.encode(&x).unwrap();
    assert_eq!(e.dims(), &[2, 4, h / 4, w / 4]);
    let e_lib = alignment_target(&vae, &targets, Some(&noise)).unwrap();
    let de = flat(&(&e_lib - &e).unwrap().abs().unwrap()).into_iter().fold(0f32, f32::max);
    assert!(de < 1e-4, "alignment target differs from the hand-made one by {de}");
    let without_noise = alignment_target(&vae, &targets, None).unwrap();
    assert!(flat(&(&without_noise - &e).unwrap().abs().unwrap()).into_iter().fold(0f32, f32::max) > 1e-4, "noise must be used");

    let feats = Var::from_tensor(&Tensor::randn(0f32, 1.0, e.dims(), &dev).unwrap()).unwrap();
    let loss = latent_alignment_loss(&vae, feats.as_tensor(), &targets, Some(&noise)).unwrap();
    let (fv, ev) = (flat(feats.as_tensor()), flat(&e));
    let want = 0.01 * fv.iter().zip(&ev).map(|(f, e)| ((f - e) as f64).powi(2)).sum::<f64>() / fv.len() as f64;
    assert!((scalar(&loss) / want - 1.0).abs() < 1e-4, "{} vs {want}", scalar(&loss));
    // Features equal to E: exactly zero.
    assert_eq!(latent_alignment_loss_to(&e_lib, &e_lib).unwrap().to_scalar::<f32>().unwrap(), 0.0);

    let grads = loss.backward().unwrap();
    let g = flat(grads.get(feats.as_tensor()).expect("gradient on the features"));
    let target = alignment_target(&vae, &targets, Some(&noise)).unwrap();
    let l = || scalar(&latent_alignment_loss_to(feats.as_tensor(), &target).unwrap());
    let pairs: Vec<(f64, f64)> = [0usize, 13, 47, 95].iter().map(|&i| (g[i] as f64, central_diff(&feats, i, 2e-2, &l))).collect();
    check_fd("d alignment / d features", &pairs);
    // Closed form 2·0.01·(F − E)/numel.
    for i in [0usize, 13, 47, 95] {
        let want = 0.02 * (fv[i] - ev[i]) as f64 / fv.len() as f64;
        assert!((g[i] as f64 - want).abs() < 1e-4 * want.abs() + 1e-9, "{} vs {want}", g[i]);
    }
}

#[test]
fn target_latents_are_the_scaled_posterior_sample() {
    let dev = Device::Cpu;
    let vae = tiny_vae();
    let targets = Tensor::rand(0f32, 1.0, (1, 3, 16, 16), &dev).unwrap();
    let x = ((resize_reference(&targets, 32, 32).unwrap() * 2.0).unwrap() - 1.0).unwrap();
    let (mean, logvar) = vae.encode(&x).unwrap();
    let eps = Tensor::randn(0f32, 1.0, mean.dims(), &dev).unwrap();
    let want = ((&mean + (&logvar * 0.5).unwrap().exp().unwrap().mul(&eps).unwrap()).unwrap() * 0.18215).unwrap();
    let got = target_latents(&vae, &targets, Some(&eps)).unwrap();
    let d = flat(&(&got - &want).unwrap().abs().unwrap()).into_iter().fold(0f32, f32::max);
    assert!(d < 1e-5, "{d}");
    let mode = target_latents(&vae, &targets, None).unwrap();
    let d = flat(&(&mode - (&mean * 0.18215).unwrap()).unwrap().abs().unwrap()).into_iter().fold(0f32, f32::max);
    assert!(d < 1e-5, "{d}");
}

#[test]
fn feature_resize_matches_reference_and_is_differentiable() {
    let dev = Device::Cpu;
    let f = Var::from_tensor(&Tensor::randn(0f32, 1.0, (2, 4, 18, 26), &dev).unwrap()).unwrap();
    let got = features_to_latent(f.as_tensor()).unwrap();
    assert_eq!(got.dims(), &[2, 4, 4, 6]);
    let want = resize_reference(f.as_tensor(), 4, 6).unwrap();
    let d = flat(&(&got - &want).unwrap().abs().unwrap()).into_iter().fold(0f32, f32::max);
    assert!(d < 1e-5, "{d}");
    // The corners map to the corners; the gradient of the sum is each input's total interpolation weight,
    // which sums to the number of outputs.
    let grads = got.sum_all().unwrap().backward().unwrap();
    let gv = flat(grads.get(f.as_tensor()).unwrap());
    let total: f32 = gv.iter().sum();
    assert!((total - (2 * 4 * 4 * 6) as f32).abs() < 1e-3, "{total}");
    assert!((gv[0] - 1.0).abs() < 1e-6, "corner weight {}", gv[0]);
}
