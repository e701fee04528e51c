//! Test-time fitting on the context photos alone, measured on the held-out protocol's targets (32-view loop, 5
//! context views by farthest-point sampling, the other 27 views as targets): target PSNR after each listed
//! step count. Modes:
//! - `product`: `render`'s fitting (`mvsplat360_pipeline::fit`) with `--lr`, `--self`, `--mask`, `--size`,
//!   `--eps` (Adam's ε); `--flip 1|2` first averages the encoder's per-pixel distances (1: also its opacities)
//!   with those of a run on the mirrored photos (test-time augmentation, as training's flips); `--cosine 1`
//!   decays the rates to 0 over each run's steps; `--pixel-colour 1|2` sets each Gaussian's SH DC to its
//!   pixel's colour (1: keeps the higher orders, 2: zeroes them); `--hyp F,… --hyp-opacity O` adds copies of
//!   every Gaussian at those distance factors with O × its opacity before fitting (`--copies N --copy-ratio R
//!   --copy-opacity O`: the same by `render`'s fit settings, factors R^±1…±N); `--nearest 4,3` also scores each target rendered from its K nearest context views'
//!   Gaussians only; `--sweep 1 [--sweep-range R]` runs `render`'s plane sweep (`fit.sweep`) in the fit;
//!   `--mvs all|cons:N [--mvs-d 64 --mvs-r 2 --mvs-k 2 --mvs-range 0 --mvs-trunc 0.2]` applies it before the fit
//!   and prints its context distance errors; on procedural scenes the row ends with the fitted distances' mean |ln d − ln truth|;
//! - `gauss`: the exploration variant it came from (own loop; `--pyramid` levels of 2× pooling in the loss,
//!   `--colour S` also fits the SH DC at S × the rate);
//! - `net`: fine-tunes the encoder's weights on the same leave-one-out loss instead.
//!
//!     cargo run --release -p mvsplat360-train --example tto -- CONFIG.toml MODEL_DIR \
//!         [--mode product|gauss|net] [--steps 0,25,50,100] [--lr 0.01] [--mask 0.5] [--self 0] \
//!         [--pyramid 3] [--colour 0] [--size 0] [--eps 1e-8] [--flip 0] [--cosine 0] [--nearest K,…] SEED|DIR…

use candle_core::{DType, Device, IndexOp, Tensor, Var};
use mvsplat360_pipeline::render::raster_camera;
use mvsplat360_splat::{Gaussians, RenderOptions};
use mvsplat360_train::optim::{Adam, Param};
use mvsplat360_train::scenes::protocol_scene;
use mvsplat360_train::trainer::{example_from_views, render_example_full, Example, Model};

mod common;

fn targets_psnr(g: &Gaussians, ex: &Example, near: f32, far: f32) -> anyhow::Result<f64> {
    targets_psnr_nearest(g, ex, near, far, usize::MAX)
}

/// Each target rendered from the Gaussians of its `k` nearest context views (camera centres) only.
fn targets_psnr_nearest(g: &Gaussians, ex: &Example, near: f32, far: f32, k: usize) -> anyhow::Result<f64> {
    let v = ex.context_cameras.len();
    let per = g.means.dim(0)? / v;
    let mut s = 0.0;
    for (t, c) in ex.target_cameras.iter().enumerate() {
        let sub;
        let g = if k < v {
            let mut order: Vec<usize> = (0..v).collect();
            order.sort_by(|&a, &b| (ex.context_cameras[a].center() - c.center()).norm().total_cmp(&(ex.context_cameras[b].center() - c.center()).norm()));
            let mut idx: Vec<u32> = order[..k].iter().flat_map(|&j| (j * per) as u32..((j + 1) * per) as u32).collect();
            idx.sort_unstable();
            let n = idx.len();
            sub = g.select(&Tensor::from_vec(idx, n, &Device::Cpu)?)?;
            &sub
        } else {
            g
        };
        let r = mvsplat360_splat::render(g, &raster_camera(c, near, far), &RenderOptions::default())?;
        s += common::psnr(&r.rgb, &ex.target_images.i(t)?)?;
    }
    Ok(s / ex.target_cameras.len() as f64)
}

/// (n,3): the ray origin of each of `n` view-major Gaussians, its view's camera centre.
fn ray_origins(ex: &Example, n: usize) -> anyhow::Result<Tensor> {
    let per = n / ex.context_cameras.len();
    let orig: Vec<f32> = (0..n)
        .flat_map(|i| {
            let c = ex.context_cameras[i / per].center();
            [c.x as f32, c.y as f32, c.z as f32]
        })
        .collect();
    Ok(Tensor::from_vec(orig, (n, 3), &Device::Cpu)?)
}

/// `ex` with its context photos mirrored left-right and the matching cameras (the world mirrored by x → −x).
fn mirrored(ex: &Example) -> anyhow::Result<Example> {
    let w = ex.context_images.dim(3)?;
    let rev = Tensor::from_vec((0..w as u32).rev().collect::<Vec<_>>(), w, ex.context_images.device())?;
    Ok(Example {
        context_images: ex.context_images.index_select(&rev, 3)?,
        context_cameras: ex.context_cameras.iter().map(mvsplat360_train::sampler::flip_camera).collect(),
        target_images: ex.target_images.clone(),
        target_cameras: ex.target_cameras.clone(),
        context_depths: None,
    })
}

/// The encoder's Gaussians of `ex` with each pixel's distance along its ray replaced by the geometric mean of its
/// own and the mirrored run's (`gm`, Gaussians of `mirrored(ex)`) for the same pixel; covariances scale with it.
/// `opacity`: also average the opacities. Colours stay the unmirrored run's.
fn flip_average(g: &Gaussians, gm: &Gaussians, ex: &Example, opacity: bool) -> anyhow::Result<Gaussians> {
    let (v, _, h, w) = ex.context_images.dims4()?;
    let n = g.means.dim(0)?;
    anyhow::ensure!(n == v * h * w, "one Gaussian per pixel expected");
    // Pixel (y, x) of view k is the mirrored run's pixel (y, w − 1 − x).
    let perm: Vec<u32> = (0..n)
        .map(|i| {
            let (k, y, x) = (i / (h * w), (i / w) % h, i % w);
            ((k * h + y) * w + (w - 1 - x)) as u32
        })
        .collect();
    let perm = Tensor::from_vec(perm, n, &Device::Cpu)?;
    let orig = ray_origins(ex, n)?;
    let sign = Tensor::new(&[-1f32, 1.0, 1.0], &Device::Cpu)?;
    let means_m = gm.means.index_select(&perm, 0)?.broadcast_mul(&sign)?;
    let dist = |m: &Tensor| -> anyhow::Result<Tensor> { Ok(m.sub(&orig)?.sqr()?.sum_keepdim(1)?.sqrt()?) };
    let (d, dm) = (dist(&g.means)?, dist(&means_m)?);
    let factor = (dm.log()? - d.log()?)?.affine(0.5, 0.0)?.exp()?; // sqrt(dm / d)
    let means = (&orig + g.means.sub(&orig)?.broadcast_mul(&factor)?)?;
    let covariances = g.covariances.broadcast_mul(&factor.sqr()?.unsqueeze(2)?)?;
    let opacities = if opacity { ((&g.opacities + gm.opacities.index_select(&perm, 0)?)? * 0.5)? } else { g.opacities.clone() };
    Ok(Gaussians { means, covariances, opacities, harmonics: g.harmonics.clone(), feature_harmonics: g.feature_harmonics.clone() })
}

/// `g` with each Gaussian's SH DC set to its source pixel's colour in the context photo (`rest`: keep the
/// encoder's higher-order coefficients, else zero them).
fn pixel_colours(g: &Gaussians, ex: &Example, rest: bool) -> anyhow::Result<Gaussians> {
    let (v, _, h, w) = ex.context_images.dims4()?;
    let n = g.means.dim(0)?;
    anyhow::ensure!(n == v * h * w, "one Gaussian per pixel expected");
    let rgb = ex.context_images.permute((0, 2, 3, 1))?.reshape((n, 3, 1))?;
    let dc = rgb.affine(1.0 / mvsplat360_splat::sh::C0 as f64, -0.5 / mvsplat360_splat::sh::C0 as f64)?;
    let k = g.harmonics.dim(2)?;
    let higher = g.harmonics.narrow(2, 1, k - 1)?;
    let higher = if rest { higher } else { higher.zeros_like()? };
    Ok(Gaussians { harmonics: Tensor::cat(&[&dc, &higher], 2)?.contiguous()?, ..g.clone() })
}

/// Depth hypotheses: each view's Gaussians followed by copies at each factor of `factors` along their rays
/// (covariances scaled with the distance, so the footprint in their own view stays), opacities × `op`.
/// View-major with `1 + factors.len()` times as many Gaussians per view.
fn hypotheses(g: &Gaussians, ex: &Example, factors: &[f64], op: f64) -> anyhow::Result<Gaussians> {
    let v = ex.context_cameras.len();
    let n = g.means.dim(0)?;
    let per = n / v;
    let orig = ray_origins(ex, n)?;
    let off = g.means.sub(&orig)?;
    let mut parts: Vec<Gaussians> = Vec::new();
    for k in 0..v {
        let sl = |t: &Tensor| t.narrow(0, k * per, per);
        let base = Gaussians {
            means: sl(&g.means)?,
            covariances: sl(&g.covariances)?,
            opacities: sl(&g.opacities)?,
            harmonics: sl(&g.harmonics)?,
            feature_harmonics: sl(&g.feature_harmonics)?,
        };
        parts.push(base.clone());
        for &f in factors {
            parts.push(Gaussians {
                means: (sl(&orig)? + (sl(&off)? * f)?)?,
                covariances: (sl(&g.covariances)? * (f * f))?,
                opacities: (sl(&g.opacities)? * op)?,
                ..base.clone()
            });
        }
    }
    let cat = |f: &dyn Fn(&Gaussians) -> Tensor| -> anyhow::Result<Tensor> { Ok(Tensor::cat(&parts.iter().map(f).collect::<Vec<_>>(), 0)?) };
    Ok(Gaussians {
        means: cat(&|p| p.means.clone())?,
        covariances: cat(&|p| p.covariances.clone())?,
        opacities: cat(&|p| p.opacities.clone())?,
        harmonics: cat(&|p| p.harmonics.clone())?,
        feature_harmonics: cat(&|p| p.feature_harmonics.clone())?,
    })
}

/// The plane sweep's diagnostics (`--mvs`): the encoder's Gaussians with each pixel's distance replaced by
/// `render`'s plane sweep's (`sw`; everywhere for `all`, where ≥ N other views confirm it for `cons:N`), and, when
/// the truth is known, the context distance errors of the encoder and the sweep by confirmation count.
fn mvs_distances(g: &Gaussians, ex: &Example, near: f32, far: f32, sw: &mvsplat360_pipeline::sweep::SweepSettings, mode: &str) -> anyhow::Result<Gaussians> {
    let (v, _, h, w) = ex.context_images.dims4()?;
    let n = g.means.dim(0)?;
    anyhow::ensure!(n == v * h * w, "one Gaussian per pixel expected");
    let need: u32 = match mode.split(':').collect::<Vec<_>>().as_slice() {
        ["all"] => 0,
        ["cons", k] => k.parse()?,
        _ => anyhow::bail!("--mvs all|cons:N, got {mode}"),
    };
    let orig = ray_origins(ex, n)?;
    let off: Vec<f32> = g.means.sub(&orig)?.flatten_all()?.to_vec1()?;
    let prior: Vec<f32> = (0..n).map(|i| (off[3 * i].powi(2) + off[3 * i + 1].powi(2) + off[3 * i + 2].powi(2)).sqrt()).collect();
    let dirs: Vec<[f64; 3]> = (0..n).map(|i| [0, 1, 2].map(|c| off[3 * i + c] as f64 / prior[i] as f64)).collect();
    let photos: Vec<mvsplat360_dataset::ImageF32> = (0..v)
        .map(|k| Ok(mvsplat360_dataset::ImageF32 { width: w as u32, height: h as u32, data: ex.context_images.i(k)?.flatten_all()?.to_vec1()? }))
        .collect::<anyhow::Result<_>>()?;
    let t0 = std::time::Instant::now();
    let s = mvsplat360_pipeline::sweep::sweep(&photos, &ex.context_cameras, &prior, &dirs, near as f64, far as f64, sw);
    let take: Vec<bool> = (0..n).map(|i| s.confirmations[i] >= need).collect();
    let new: Vec<f32> = (0..n).map(|i| if take[i] { s.distance[i] } else { prior[i] }).collect();
    if let Some(depths) = ex.context_depths.as_ref() {
        let truth: Vec<f32> = depths.flatten_all()?.to_vec1()?;
        let err = |d: &[f32], sel: &dyn Fn(usize) -> bool| {
            let (mut s, mut c) = (0.0, 0);
            for i in 0..n {
                if truth[i] < 0.9 * far && sel(i) {
                    s += (d[i] as f64 / truth[i] as f64).ln().abs();
                    c += 1;
                }
            }
            (s / c.max(1) as f64, c)
        };
        let (e_enc, _) = err(&prior, &|_| true);
        let (e_new, _) = err(&new, &|_| true);
        let (e_sel_enc, c) = err(&prior, &|i| take[i]);
        let (e_sel_mvs, _) = err(&s.distance, &|i| take[i]);
        println!(
            "  sweep {:.1} s: context distance error encoder {e_enc:.3} → fused {e_new:.3}; on the {c} replaced pixels encoder {e_sel_enc:.3} vs sweep {e_sel_mvs:.3}",
            t0.elapsed().as_secs_f64()
        );
        for k in [1u32, 2] {
            let (a, c) = err(&prior, &|i| s.confirmations[i] >= k);
            let (b, _) = err(&s.distance, &|i| s.confirmations[i] >= k);
            println!("    confirmed by ≥ {k}: {c} pixels, encoder {a:.3}, sweep {b:.3}");
        }
    }
    let factor: Vec<f32> = (0..n).map(|i| new[i] / prior[i]).collect();
    let factor = Tensor::from_vec(factor, (n, 1), &Device::Cpu)?;
    let means = (&orig + g.means.sub(&orig)?.broadcast_mul(&factor)?)?;
    let covariances = g.covariances.broadcast_mul(&factor.sqr()?.unsqueeze(2)?)?;
    Ok(Gaussians { means, covariances, ..g.clone() })
}

struct Opts {
    mask: f32,
    pyramid: usize,
    self_weight: f64,
}

/// Leave-one-out loss: each context view rendered from the other views' Gaussians against its photo, at
/// `pyramid` scales (2× average pooling each), only where the render covers the pixel (α > mask, if > 0).
fn loo_loss(g: &Gaussians, ex: &Example, near: f32, far: f32, o: &Opts) -> anyhow::Result<Tensor> {
    let v = ex.context_cameras.len();
    let n = g.means.dim(0)?;
    let per = n / v;
    let mut total: Option<Tensor> = None;
    for (j, c) in ex.context_cameras.iter().enumerate() {
        if o.self_weight > 0.0 {
            let r = mvsplat360_splat::render(g, &raster_camera(c, near, far), &RenderOptions::default())?;
            let l = ((r.rgb - ex.context_images.i(j)?)?.sqr()?.mean_all()? * o.self_weight)?;
            total = Some(match total {
                Some(t) => (t + l)?,
                None => l,
            });
        }
        let idx: Vec<u32> = (0..n as u32).filter(|&i| (i as usize) / per != j).collect();
        let idx = Tensor::from_vec(idx, n - per, &Device::Cpu)?;
        let r = mvsplat360_splat::render(&g.select(&idx)?, &raster_camera(c, near, far), &RenderOptions::default())?;
        let gt = ex.context_images.i(j)?;
        let mut diff = (r.rgb - gt)?;
        if o.mask > 0.0 {
            let m = r.alpha.detach().ge(o.mask)?.to_dtype(DType::F32)?;
            diff = diff.broadcast_mul(&m)?;
        }
        let mut d = diff.unsqueeze(0)?;
        for _ in 0..o.pyramid.max(1) {
            let l = d.sqr()?.mean_all()?;
            total = Some(match total {
                Some(t) => (t + l)?,
                None => l,
            });
            d = d.avg_pool2d(2)?;
        }
    }
    Ok(total.expect("views"))
}

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut take = |flag: &str, default: &str| common::take_flag(&mut args, flag, default);
    let mode = take("--mode", "gauss");
    let steps: Vec<usize> = take("--steps", "0,25,50,100").split(',').map(|s| s.parse()).collect::<Result<_, _>>()?;
    let lr: f64 = take("--lr", if mode == "net" { "2e-5" } else { "0.01" }).parse()?;
    let colour: f64 = take("--colour", "0").parse()?;
    let size: f64 = take("--size", "0").parse()?;
    let adam_eps: f64 = take("--eps", "1e-8").parse()?;
    let flip: u32 = take("--flip", "0").parse()?;
    let cosine = take("--cosine", "0") == "1";
    let pixel: u32 = take("--pixel-colour", "0").parse()?;
    let hyp: Vec<f64> = take("--hyp", "").split(',').filter(|s| !s.is_empty()).map(|s| s.parse()).collect::<Result<_, _>>()?;
    let hyp_op: f64 = take("--hyp-opacity", "0.3").parse()?;
    let copies: usize = take("--copies", "0").parse()?;
    let copy_ratio: f64 = take("--copy-ratio", "1.33").parse()?;
    let copy_opacity: f64 = take("--copy-opacity", "0.1").parse()?;
    // Product mode: also score each target rendered from its K nearest context views' Gaussians, K in this list.
    let nearest: Vec<usize> = take("--nearest", "").split(',').filter(|s| !s.is_empty()).map(|s| s.parse()).collect::<Result<_, _>>()?;
    // The plane sweep's diagnostics: "" off; `all` replaces every distance; `cons:N` where ≥ N views confirm it.
    let mvs_mode = take("--mvs", "");
    let sw = mvsplat360_pipeline::sweep::SweepSettings {
        candidates: take("--mvs-d", "64").parse()?,
        radius: take("--mvs-r", "2").parse()?,
        views: take("--mvs-k", "2").parse()?,
        range: take("--mvs-range", "0").parse()?,
        truncation: take("--mvs-trunc", "0.2").parse()?,
        ..Default::default()
    };
    // `render`'s plane sweep (`fit.sweep`, default settings) before the fit.
    let sweep = take("--sweep", "0") == "1";
    let sweep_range: f64 = take("--sweep-range", "0").parse()?;
    let o = Opts { mask: take("--mask", "0.5").parse()?, pyramid: take("--pyramid", "3").parse()?, self_weight: take("--self", "0").parse()? };
    anyhow::ensure!(args.len() >= 3, "usage: tto CONFIG.toml MODEL_DIR [flags] SEED|DIR…");
    let max_steps = *steps.iter().max().unwrap_or(&0);
    println!("mode {mode}, lr {lr}, mask {}, pyramid {}", o.mask, o.pyramid);
    println!("| scene | {} |\n|---|{}", steps.iter().map(|s| format!("step {s}")).collect::<Vec<_>>().join(" | "), "---|".repeat(steps.len()));
    if !nearest.is_empty() {
        println!("(each step count: all views, then nearest {nearest:?})");
    }
    let mut sums = vec![0.0; steps.len() * (1 + nearest.len())];
    let nscenes = args.len() - 2;
    for arg in &args[2..] {
        let model = Model::encoder_with_weights(args[0].as_ref(), args[1].as_ref())?;
        let cfg = model.cfg.clone();
        let (w, h) = (cfg.model.width, cfg.model.height);
        let (near, far) = (cfg.model.near, cfg.model.far);
        let (scene, v, label) = protocol_scene(arg, w, h, cfg.model.encoder.image_multiple() as u32)?;
        let ex = example_from_views(&scene, &v, near, far)?;
        let mut row = Vec::new();
        let mut derr: Vec<String> = Vec::new();
        let t0 = std::time::Instant::now();
        match mode.as_str() {
            "gauss" => {
                let g0 = render_example_full(&model, &ex)?.gaussians;
                let g0 = g0.detach();
                let n = g0.means.dim(0)?;
                let orig = ray_origins(&ex, n)?;
                let log_s = Var::zeros((n, 1), DType::F32, &Device::Cpu)?;
                let op0 = g0.opacities.clamp(1e-4f32, 1.0 - 1e-4)?;
                let logit = Var::from_tensor(&(op0.log()? - (op0.neg()? + 1.0)?.log()?)?)?;
                let dc = Var::from_tensor(&g0.harmonics.narrow(2, 0, 1)?.contiguous()?)?;
                let rest = g0.harmonics.narrow(2, 1, g0.harmonics.dim(2)? - 1)?.contiguous()?;
                let mut params =
                    vec![Param { name: "log_s".into(), var: log_s.clone(), lr_scale: 1.0 }, Param { name: "logit".into(), var: logit.clone(), lr_scale: 5.0 }];
                if colour > 0.0 {
                    params.push(Param { name: "dc".into(), var: dc.clone(), lr_scale: colour });
                }
                let mut opt = Adam::new(params)?;
                let build = || -> anyhow::Result<Gaussians> {
                    let s = log_s.as_tensor().exp()?;
                    let means = (&orig + (g0.means.sub(&orig)?.broadcast_mul(&s)?))?;
                    let covariances = g0.covariances.broadcast_mul(&s.sqr()?.unsqueeze(2)?)?;
                    let opacities = candle_nn::ops::sigmoid(logit.as_tensor())?;
                    Ok(Gaussians {
                        means,
                        covariances,
                        opacities,
                        harmonics: Tensor::cat(&[dc.as_tensor(), &rest], 2)?,
                        feature_harmonics: g0.feature_harmonics.clone(),
                    })
                };
                for step in 0..=max_steps {
                    if steps.contains(&step) {
                        row.push(targets_psnr(&build()?, &ex, near, far)?);
                    }
                    if step == max_steps {
                        break;
                    }
                    let loss = loo_loss(&build()?, &ex, near, far, &o)?;
                    let grads = loss.backward()?;
                    let gs: Vec<Option<Tensor>> = opt.params.iter().map(|p| grads.get(p.var.as_tensor()).cloned()).collect();
                    opt.step(&gs, lr)?;
                }
            }
            "product" => {
                // `render`'s fitting with these settings, scored after each listed step count.
                let mut g0 = render_example_full(&model, &ex)?.gaussians;
                if flip > 0 {
                    let gm = render_example_full(&model, &mirrored(&ex)?)?.gaussians;
                    g0 = flip_average(&g0, &gm, &ex, flip == 1)?;
                }
                if !mvs_mode.is_empty() {
                    g0 = mvs_distances(&g0, &ex, near, far, &sw, &mvs_mode)?;
                }
                if pixel > 0 {
                    g0 = pixel_colours(&g0, &ex, pixel == 1)?;
                }
                if !hyp.is_empty() {
                    g0 = hypotheses(&g0, &ex, &hyp, hyp_op)?;
                }
                let photos: Vec<mvsplat360_dataset::ImageF32> = (0..ex.context_cameras.len())
                    .map(|i| Ok(mvsplat360_dataset::ImageF32 { width: w, height: h, data: ex.context_images.i(i)?.flatten_all()?.to_vec1()? }))
                    .collect::<anyhow::Result<_>>()?;
                for &n in &steps {
                    let fs = mvsplat360_pipeline::fit::FitSettings {
                        steps: n,
                        lr,
                        self_weight: o.self_weight,
                        min_alpha: o.mask,
                        size_lr_scale: size,
                        adam_eps,
                        cosine,
                        copies,
                        copy_ratio,
                        copy_opacity,
                        sweep: sweep.then(|| mvsplat360_pipeline::sweep::SweepSettings { range: sweep_range, ..Default::default() }),
                        ..Default::default()
                    };
                    let (g, _) = mvsplat360_pipeline::fit::fit(&g0, &ex.context_cameras, &photos, near, far, &fs, &mvsplat360_pipeline::render::Silent)?;
                    row.push(targets_psnr(&g, &ex, near, far)?);
                    // One Gaussian per context pixel only (not with --hyp's copies).
                    if hyp.is_empty() && copies == 0 {
                        if let Some(e) = ex.context_distance_error(&g, far)? {
                            derr.push(format!("{e:.3}"));
                        }
                    }
                    for &k in &nearest {
                        row.push(targets_psnr_nearest(&g, &ex, near, far, k)?);
                    }
                }
            }
            "net" => {
                let vars = model.vars();
                let mut opt = Adam::new(vars.iter().map(|(k, v)| Param { name: k.clone(), var: v.clone(), lr_scale: 1.0 }).collect())?;
                for step in 0..=max_steps {
                    let r = render_example_full(&model, &ex)?;
                    if steps.contains(&step) {
                        let gd = r.gaussians.detach();
                        row.push(targets_psnr(&gd, &ex, near, far)?);
                    }
                    if step == max_steps {
                        break;
                    }
                    let loss = loo_loss(&r.gaussians, &ex, near, far, &o)?;
                    let grads = loss.backward()?;
                    let mut gs: Vec<Option<Tensor>> = opt.params.iter().map(|p| grads.get(p.var.as_tensor()).cloned()).collect();
                    mvsplat360_train::optim::clip_grad_norm(&mut gs, 0.5)?;
                    opt.step(&gs, lr)?;
                }
            }
            m => anyhow::bail!("--mode gauss|net, got {m}"),
        }
        println!(
            "| {label} | {} |  ({:.0} s){}",
            row.iter().map(|x| format!("{x:.2}")).collect::<Vec<_>>().join(" | "),
            t0.elapsed().as_secs_f64(),
            if derr.is_empty() { String::new() } else { format!(" depth error {}", derr.join(" / ")) }
        );
        for (s, r) in sums.iter_mut().zip(&row) {
            *s += r / nscenes as f64;
        }
    }
    println!("| **mean** | {} |", sums.iter().map(|x| format!("{x:.2}")).collect::<Vec<_>>().join(" | "));
    Ok(())
}
