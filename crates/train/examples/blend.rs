//! Exploration: a learned image-based blender on the held-out protocol (32-view loop, 5 context views by
//! farthest-point sampling, the other 27 as targets). The product command is `mvsplat360 train-blend`
//! (`mvsplat360_train::blend`: `render`'s path, checkpoints, resume); this example keeps what exploration needs
//! (several layouts from one fit, nets compared on the same caches, the GPU runs of `scripts/gpu-blend`).
//!
//! `cache` renders each target with the model and its shipped test-time fitting and stores, per target, the
//! blender's input (`mvsplat360_pipeline::blend::candidates`: the render, its alpha and the colours that the
//! nearest context photos give each pixel lifted to depths around the rendered one) with the target photo.
//! `train` fits the blender (`BlendNet`) with MSE and Adam, and reports the mean target PSNR of another cache
//! folder every `--every` steps; `--save` writes its weights (keys `blend.*`).
//!
//!     cargo run --release -p mvsplat360-train --example blend -- cache CONFIG.toml MODEL_DIR OUT_DIR SEED|DIR…
//!         [--device cpu|cuda] [--sets 7x2x1.6,9x3x1.6] [--truth]
//!     cargo run --release -p mvsplat360-train --example blend -- train TRAIN_DIR VAL_DIR [--steps 1000]
//!         [--lr 1e-3] [--batch 8] [--width 16] [--set 7x2x1.6] [--every 100] [--seed 1] [--device cpu|cuda]
//!         [--save NET.safetensors] [--init NET.safetensors]
//!     cargo run --release -p mvsplat360-train --example blend -- add MODEL_DIR NET.safetensors OUT_DIR
//!         [--width 16] [--set 7x2x1.6]
//!     cargo run --release -p mvsplat360-train --example blend -- depth CONFIG.toml MODEL_DIR SCENE…
//!     cargo run --release -p mvsplat360-train --example blend -- loo CONFIG.toml MODEL_DIR OUT_DIR SCENE_DIR…
//!
//! A set `PxVxS` is the candidates' layout: P depth planes for each of the V nearest context views, spread over
//! a factor S either side of the rendered depth (the default, `BlendSettings::default()`, is 7x2x1.6); `PxVxSv`
//! adds the visibility channels (`BlendSettings::visibility`). Without
//! `--sets`, `cache` writes the default layout into OUT_DIR; with it, one folder OUT_DIR/PxVxS per set, all from
//! the same fit. `--truth` (an oracle, for the ceiling of blending): the candidates are lifted around each target
//! pixel's *true* depth (opacity 1 where known) and the visibility channels read the context views' true depths;
//! only scenes that know their depths. `add` writes a copy of a model folder with the blender's weights and its
//! `blend` settings added. `depth` (a diagnostic, on scenes that know their depths) scores against the true
//! z-depths: the encoder's (alone, and averaged with its run on the mirrored example) and the fitted Gaussians'
//! depth at the context views, and at the targets the rendered depth, the median depth, the nearest of the
//! candidate planes and the depth the model's blender implies. `loo` caches leave-one-out inputs in the default
//! layout (each context view rendered from the other views' fitted Gaussians, its candidates from the other context
//! photos, its own photo as the target), for adapting the blender to a scene with `train --init` at test time.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, IndexOp, Tensor};
use candle_nn::{Optimizer, VarBuilder, VarMap};
use mvsplat360_pipeline::blend::{candidates, BlendNet, BlendSettings, PREFIX};
use mvsplat360_pipeline::render::{depth_maps, raster_camera};
use mvsplat360_splat::RenderOptions;
use mvsplat360_train::trainer::Model;
use rand::{Rng, SeedableRng};

mod common;

/// A `PxVxS` set (planes, views, span; a trailing `v`: with visibility channels) with `width`; the empty string is
/// the default.
fn settings(spec: &str, width: usize) -> anyhow::Result<BlendSettings> {
    let d = BlendSettings { width, ..Default::default() };
    if spec.is_empty() {
        return Ok(d);
    }
    let (spec, visibility) = match spec.strip_suffix('v') {
        Some(s) => (s, true),
        None => (spec, false),
    };
    let d = BlendSettings { visibility, ..d };
    let p: Vec<&str> = spec.split('x').collect();
    anyhow::ensure!(p.len() == 3, "`{spec}` is not a set: use PLANESxVIEWSxSPAN, e.g. 7x2x1.6");
    let s = BlendSettings { planes: p[0].parse()?, views: p[1].parse()?, span: p[2].parse()?, ..d };
    s.validate().map_err(|e| anyhow::anyhow!("set `{spec}`: {e}"))?;
    Ok(s)
}

fn device(spec: &str) -> anyhow::Result<Device> {
    Ok(spec.parse::<mvsplat360_pipeline::compute::DeviceSpec>().map_err(anyhow::Error::msg)?.open()?)
}

fn cache(args: &mut Vec<String>) -> anyhow::Result<()> {
    let dev = device(&common::take_flag(args, "--device", "cpu"))?;
    let specs = common::take_flag(args, "--sets", "");
    let truth = args.iter().position(|a| a == "--truth").map(|i| args.remove(i)).is_some();
    anyhow::ensure!(args.len() >= 4, "usage: blend cache CONFIG.toml MODEL_DIR OUT_DIR SEED|DIR… [--device D] [--sets LIST] [--truth]");
    let out = PathBuf::from(&args[2]);
    let sets: Vec<(PathBuf, BlendSettings)> = if specs.is_empty() {
        vec![(out.clone(), BlendSettings::default())]
    } else {
        specs.split(',').map(|sp| Ok((out.join(sp), settings(sp, 16)?))).collect::<anyhow::Result<_>>()?
    };
    for (d, _) in &sets {
        std::fs::create_dir_all(d)?;
    }
    let model = Model::encoder_with_weights_on(args[0].as_ref(), args[1].as_ref(), &dev)?;
    let cfg = model.cfg.clone();
    let (w, h) = (cfg.model.width, cfg.model.height);
    let (near, far) = (cfg.model.near as f64, cfg.model.far as f64);
    let mut failed = 0;
    for arg in &args[3..] {
        let name = match arg.parse::<u64>() {
            Ok(seed) => format!("proc-{seed}"),
            Err(_) => Path::new(arg).file_name().map_or(arg.clone(), |n| n.to_string_lossy().to_string()),
        };
        let file = format!("{name}.safetensors");
        if sets.iter().all(|(d, _)| d.join(&file).exists()) {
            continue;
        }
        let t0 = std::time::Instant::now();
        let one = || -> anyhow::Result<usize> {
            let fitted = common::fitted_on(&model, arg, &dev)?;
            let oracle = if truth { Some(common::true_z(&fitted).ok_or_else(|| anyhow::anyhow!("--truth: {arg} has no depths"))?) } else { None };
            let common::Fitted { ex, photos, gaussians: g, .. } = fitted;
            let refs: Vec<&[f32]> = photos.iter().map(|p| p.data.as_slice()).collect();
            let mut xs: Vec<Vec<Tensor>> = vec![Vec::new(); sets.len()];
            let ctx: Vec<Vec<f32>> = if let Some((c, _)) = &oracle {
                c.iter().map(|z| z.iter().map(|&z| if z.is_finite() && z > 0.0 { z } else { f32::NAN }).collect()).collect()
            } else if sets.iter().any(|(_, bs)| bs.visibility) {
                depth_maps(&g, &ex.context_cameras, near as f32, far as f32)?
            } else {
                Vec::new()
            };
            for (k, t) in ex.target_cameras.iter().enumerate() {
                let r = mvsplat360_splat::render(&g, &raster_camera(t, near as f32, far as f32), &RenderOptions::default())?;
                let rgb: Vec<f32> = r.rgb.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
                let (a, d): (Vec<f32>, Vec<f32>) = match &oracle {
                    // Σ w·z with alpha 1 is the depth itself; unknown depths get alpha 0 (log-uniform planes).
                    Some((_, zt)) => zt[k].iter().map(|&z| if z.is_finite() && z > 0.0 { (1.0, z) } else { (0.0, 0.0) }).unzip(),
                    None => (r.alpha.flatten_all()?.to_vec1()?, r.depth.flatten_all()?.to_vec1()?),
                };
                for ((_, bs), xs) in sets.iter().zip(xs.iter_mut()) {
                    let x = candidates(bs, t, &rgb, &a, &d, &ex.context_cameras, &refs, &ctx, near, far);
                    xs.push(Tensor::from_vec(x, (bs.channels(), h as usize, w as usize), &Device::Cpu)?);
                }
            }
            let target = ex.target_images.to_device(&Device::Cpu)?;
            for ((d, _), xs) in sets.iter().zip(xs) {
                save_cache(d, &name, &xs, &target)?;
            }
            Ok(ex.target_cameras.len())
        };
        match one() {
            Ok(n) => println!("{name}: {n} targets, {:.0} s", t0.elapsed().as_secs_f64()),
            // One unreadable scene must not cost the others (the GPU run caches many at once).
            Err(e) => {
                eprintln!("{name}: skipped: {e:#}");
                failed += 1;
            }
        }
    }
    anyhow::ensure!(failed == 0, "{failed} scene(s) skipped");
    println!("done");
    Ok(())
}

/// One scene's cache file `dir/name.safetensors` (inputs `x` stacked, `target`), written under a temporary name
/// first so that an interrupted run leaves no half file that a rerun would skip.
fn save_cache(dir: &Path, name: &str, xs: &[Tensor], target: &Tensor) -> anyhow::Result<()> {
    let tensors: HashMap<String, Tensor> = [("x".to_string(), Tensor::stack(xs, 0)?), ("target".to_string(), target.clone())].into();
    let tmp = dir.join(format!("{name}.tmp"));
    candle_core::safetensors::save(&tensors, &tmp)?;
    std::fs::rename(&tmp, dir.join(format!("{name}.safetensors")))?;
    Ok(())
}

/// Leave-one-out inputs for test-time adaptation: each context view rendered from the other views' fitted
/// Gaussians, its candidates from the other context photos; the target is its own photo. One file per scene.
fn cache_loo(args: &mut Vec<String>) -> anyhow::Result<()> {
    anyhow::ensure!(args.len() >= 4, "usage: blend loo CONFIG.toml MODEL_DIR OUT_DIR DIR…");
    let out = PathBuf::from(&args[2]);
    std::fs::create_dir_all(&out)?;
    let model = Model::encoder_with_weights_on(args[0].as_ref(), args[1].as_ref(), &Device::Cpu)?;
    let cfg = model.cfg.clone();
    let (w, h) = (cfg.model.width, cfg.model.height);
    let (near, far) = (cfg.model.near as f64, cfg.model.far as f64);
    let bs = BlendSettings::default();
    for arg in &args[3..] {
        let name = Path::new(arg).file_name().map_or(arg.clone(), |n| n.to_string_lossy().to_string());
        let common::Fitted { ex, photos, gaussians: g, .. } = common::fitted_on(&model, arg, &Device::Cpu)?;
        let v = ex.context_cameras.len();
        // View-major pixel-aligned Gaussians: view i owns [i·per, (i+1)·per).
        anyhow::ensure!(g.means.dim(0)? % v == 0, "{name}: {} Gaussians do not split into {v} views", g.means.dim(0)?);
        let per = g.means.dim(0)? / v;
        let mut xs = Vec::new();
        for i in 0..v {
            let idx: Vec<u32> = (0..(v * per) as u32).filter(|&k| k as usize / per != i).collect();
            let gi = g.select(&Tensor::from_vec(idx, v * per - per, &Device::Cpu)?)?;
            let t = &ex.context_cameras[i];
            let r = mvsplat360_splat::render(&gi, &raster_camera(t, near as f32, far as f32), &RenderOptions::default())?;
            let rgb: Vec<f32> = r.rgb.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
            let (a, d): (Vec<f32>, Vec<f32>) = (r.alpha.flatten_all()?.to_vec1()?, r.depth.flatten_all()?.to_vec1()?);
            let others: Vec<usize> = (0..v).filter(|&k| k != i).collect();
            let cams: Vec<_> = others.iter().map(|&k| ex.context_cameras[k].clone()).collect();
            let refs: Vec<&[f32]> = others.iter().map(|&k| photos[k].data.as_slice()).collect();
            let x = candidates(&bs, t, &rgb, &a, &d, &cams, &refs, &[], near, far);
            xs.push(Tensor::from_vec(x, (bs.channels(), h as usize, w as usize), &Device::Cpu)?);
        }
        save_cache(&out, &name, &xs, &ex.context_images.to_device(&Device::Cpu)?)?;
        println!("{name}: {v} leave-one-out views");
    }
    Ok(())
}

/// (x, target) of every scene in a cache folder, concatenated: (N,C,H,W), (N,3,H,W).
fn load(dir: &Path) -> anyhow::Result<(Tensor, Tensor, usize)> {
    let mut files: Vec<PathBuf> =
        std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|e| e == "safetensors")).collect();
    files.sort();
    anyhow::ensure!(!files.is_empty(), "{}: no cached scenes", dir.display());
    let (mut x, mut t) = (Vec::new(), Vec::new());
    for f in &files {
        let m = candle_core::safetensors::load(f, &Device::Cpu)?;
        x.push(m["x"].clone());
        t.push(m["target"].clone());
    }
    Ok((Tensor::cat(&x, 0)?, Tensor::cat(&t, 0)?, files.len()))
}

fn mean_psnr(pred: &Tensor, target: &Tensor) -> anyhow::Result<f64> {
    let n = pred.dim(0)?;
    let mut s = 0.0;
    for i in 0..n {
        s += common::psnr(&pred.i(i)?, &target.i(i)?)?;
    }
    Ok(s / n as f64)
}

fn evaluate(net: &BlendNet, x: &Tensor, t: &Tensor) -> anyhow::Result<f64> {
    let n = x.dim(0)?;
    let mut outs = Vec::new();
    for s in (0..n).step_by(27) {
        outs.push(net.forward(&x.narrow(0, s, 27.min(n - s))?)?.detach());
    }
    mean_psnr(&Tensor::cat(&outs, 0)?, t)
}

/// A horizontal flip of cached inputs is a flip of every channel (the candidates come from the same pixels).
fn flip(x: &Tensor) -> candle_core::Result<Tensor> {
    x.flip(&[3])
}

fn train(args: &mut Vec<String>) -> anyhow::Result<()> {
    let mut take = |flag: &str, default: &str| common::take_flag(args, flag, default);
    let steps: usize = take("--steps", "1000").parse()?;
    let lr: f64 = take("--lr", "1e-3").parse()?;
    let batch: usize = take("--batch", "8").parse()?;
    let width: usize = take("--width", "16").parse()?;
    let every: usize = take("--every", "100").parse()?;
    let seed: u64 = take("--seed", "1").parse()?;
    let set = take("--set", "");
    let dev = device(&take("--device", "cpu"))?;
    let save = take("--save", "");
    let init = take("--init", "");
    anyhow::ensure!(args.len() == 2, "usage: blend train TRAIN_DIR VAL_DIR [flags]");
    let (tx, tt, ns) = load(Path::new(&args[0]))?;
    let (vx, vt, nv) = load(Path::new(&args[1]))?;
    println!("train: {} images of {ns} scenes; validation: {} images of {nv} scenes; {} channels", tx.dim(0)?, vx.dim(0)?, tx.dim(1)?);
    let (tx, tt, vx, vt) = (tx.to_device(&dev)?, tt.to_device(&dev)?, vx.to_device(&dev)?, vt.to_device(&dev)?);
    let mut vm = VarMap::new();
    let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
    let bs = settings(&set, width)?;
    anyhow::ensure!(tx.dim(1)? == bs.channels(), "cached inputs have {} channels, the blender takes {}", tx.dim(1)?, bs.channels());
    let net = BlendNet::new(vb.pp(PREFIX), &bs)?;
    for (k, v) in vm.data().lock().unwrap().iter() {
        if k.starts_with("blend.out.") {
            v.set(&v.zeros_like()?)?;
        }
    }
    if !init.is_empty() {
        vm.load(&init)?;
    }
    let mut opt = candle_nn::AdamW::new(vm.all_vars(), candle_nn::ParamsAdamW { lr, weight_decay: 0.0, ..Default::default() })?;
    println!(
        "step 0: validation PSNR {:.3} (renders as they are {:.3}, nearest view at the rendered depth {:.3})",
        evaluate(&net, &vx, &vt)?,
        mean_psnr(&vx.narrow(1, 0, 3)?, &vt)?,
        mean_psnr(&vx.narrow(1, 4 + 3 * (bs.planes / 2), 3)?, &vt)?
    );
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let n = tx.dim(0)?;
    let t0 = std::time::Instant::now();
    let mut run = 0.0;
    for step in 1..=steps {
        let f = 0.5 * (1.0 + (std::f64::consts::PI * step as f64 / steps as f64).cos());
        opt.set_learning_rate(lr * f);
        let idx: Vec<u32> = (0..batch).map(|_| rng.gen_range(0..n as u32)).collect();
        let idx = Tensor::from_vec(idx, batch, &dev)?;
        let (x, t) = (tx.index_select(&idx, 0)?, tt.index_select(&idx, 0)?);
        let (x, t) = if rng.gen_bool(0.5) { (flip(&x)?, flip(&t)?) } else { (x, t) };
        let loss = (net.forward(&x)? - &t)?.sqr()?.mean_all()?;
        opt.backward_step(&loss)?;
        run += loss.to_scalar::<f32>()? as f64;
        if step % every == 0 || step == steps {
            println!(
                "step {step}: train MSE {:.5} (mean of the last {every}), validation PSNR {:.3}, {:.2} s/step",
                run / every as f64,
                evaluate(&net, &vx, &vt)?,
                t0.elapsed().as_secs_f64() / step as f64
            );
            run = 0.0;
            if !save.is_empty() {
                vm.save(&save)?;
            }
        }
    }
    println!("done");
    Ok(())
}

fn add(args: &mut Vec<String>) -> anyhow::Result<()> {
    let width: usize = common::take_flag(args, "--width", "16").parse()?;
    let bs = settings(&common::take_flag(args, "--set", ""), width)?;
    anyhow::ensure!(args.len() == 3, "usage: blend add MODEL_DIR NET.safetensors OUT_DIR [--width 16] [--set PxVxS]");
    let (src, net, out) = (Path::new(&args[0]), Path::new(&args[1]), Path::new(&args[2]));
    let mut cfg: mvsplat360_pipeline::model::ModelConfig = serde_json::from_str(&std::fs::read_to_string(src.join(mvsplat360_pipeline::model::MODEL_CONFIG))?)?;
    cfg.blend = Some(bs);
    let mut tensors: Vec<(String, Tensor)> = candle_core::safetensors::load(src.join(mvsplat360_pipeline::model::MODEL_WEIGHTS), &Device::Cpu)?
        .into_iter()
        .filter(|(k, _)| !k.starts_with("blend."))
        .collect();
    let blend = candle_core::safetensors::load(net, &Device::Cpu)?;
    anyhow::ensure!(!blend.is_empty() && blend.keys().all(|k| k.starts_with("blend.")), "{}: expected only `blend.*` weights", net.display());
    tensors.extend(blend);
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    mvsplat360_pipeline::model::write_model_dir(out, &cfg, &tensors)?;
    // The folder must load as the pipeline loads it.
    let spec = mvsplat360_pipeline::model::read_model_dir(out)?;
    let (s, f) = spec.blend.ok_or_else(|| anyhow::anyhow!("written folder has no blend"))?;
    BlendNet::load(&f, &s, &Device::Cpu)?;
    println!("{}: {} tensors, blend {:?}", out.display(), tensors.len(), s);
    Ok(())
}

/// The median z-depth of each pixel (where the accumulated opacity first reaches half of the pixel's alpha),
/// from one rasterization whose features are indicators [z_gaussian < τ] for `k` thresholds τ log-spaced in
/// near…far, interpolated in ln τ; NaN where alpha < 0.5.
fn median_depth(g: &mvsplat360_splat::Gaussians, cam: &mvsplat360_splat::RasterCamera, near: f64, far: f64, k: usize) -> anyhow::Result<Vec<f32>> {
    let n = g.means.dim(0)?;
    let means: Vec<f32> = g.means.flatten_all()?.to_vec1()?;
    let cov: Vec<f32> = g.covariances.flatten_all()?.to_vec1()?;
    let cov6: Vec<f32> = cov.chunks_exact(9).flat_map(|c| [c[0], c[1], c[2], c[4], c[5], c[8]]).collect();
    let op: Vec<f32> = g.opacities.flatten_all()?.to_vec1()?;
    let sh = vec![0f32; 3 * n];
    let v = cam.viewmatrix;
    let tau: Vec<f64> = (0..k).map(|i| near * (far / near).powf(i as f64 / (k - 1) as f64)).collect();
    let mut feats = vec![0f32; k * n];
    for i in 0..n {
        let p = &means[3 * i..3 * i + 3];
        let z = (v[2][0] * p[0] + v[2][1] * p[1] + v[2][2] * p[2] + v[2][3]) as f64;
        for (j, &t) in tau.iter().enumerate() {
            feats[k * i + j] = if z < t { 1.0 } else { 0.0 };
        }
    }
    let inp = mvsplat360_splat::RasterInputs {
        means: &means,
        cov: mvsplat360_splat::CovInput::Cov3d(&cov6),
        opacities: &op,
        sh: &sh,
        sh_coeffs: 1,
        sh_degree: 0,
        features: &feats,
        num_features: k,
    };
    let out = mvsplat360_splat::cpu::forward(&inp, &mvsplat360_splat::RasterSettings { camera: *cam, background: [0.0; 3] })?;
    let hw = out.width * out.height;
    Ok((0..hw)
        .map(|i| {
            let a = out.alpha[i];
            if a < 0.5 {
                return f32::NAN;
            }
            let half = 0.5 * a;
            let f = |j: usize| out.features[j * hw + i];
            match (0..k).find(|&j| f(j) >= half) {
                Some(0) => tau[0] as f32,
                Some(j) => {
                    let (f0, f1) = (f(j - 1), f(j));
                    let u = ((half - f0) / (f1 - f0).max(1e-9)) as f64;
                    (tau[j - 1].ln() * (1.0 - u) + tau[j].ln() * u).exp() as f32
                }
                None => far as f32,
            }
        })
        .collect())
}

/// Depth errors against the truth (mean |ln ratio|, true depths within near…far): the encoder's (also averaged
/// in ln z with its run on the mirrored example) and the fitted Gaussians' at the context views; at the targets
/// the rendered (Σ w·z / alpha) and median depth and the nearest candidate plane (the layout's quantisation), and
/// where the candidates carry at least half of the blender's weight the depth its weights imply (averaged in ln z)
/// against the rendered one.
fn depth(args: &mut Vec<String>) -> anyhow::Result<()> {
    anyhow::ensure!(args.len() >= 3, "usage: blend depth CONFIG.toml MODEL_DIR SCENE…");
    let model = Model::encoder_with_weights_on(args[0].as_ref(), args[1].as_ref(), &Device::Cpu)?;
    let spec = mvsplat360_pipeline::model::read_model_dir(Path::new(&args[1]))?;
    let (bs, wf) = spec.blend.ok_or_else(|| anyhow::anyhow!("{}: the model has no blender", args[1]))?;
    let net = BlendNet::load(&wf, &bs, &Device::Cpu)?;
    let cfg = model.cfg.clone();
    let (w, h) = (cfg.model.width as usize, cfg.model.height as usize);
    let (near, far) = (cfg.model.near as f64, cfg.model.far as f64);
    // Sums: pixels, |ln| of the render, of the nearest plane, blended pixels, render and implied |ln| there, median.
    let report = |label: &str, a: &[f64; 7]| {
        println!(
            "{label}: render |ln| {:.3}, median {:.3}, best plane {:.3}; {:.0} % of pixels blended, there render {:.3} implied {:.3}",
            a[1] / a[0],
            a[6] / a[0],
            a[2] / a[0],
            100.0 * a[3] / a[0],
            a[4] / a[3].max(1.0),
            a[5] / a[3].max(1.0)
        )
    };
    let mut tot = [0f64; 7];
    for arg in &args[2..] {
        let fitted = common::fitted_on(&model, arg, &Device::Cpu)?;
        let (zc, zt) = common::true_z(&fitted).ok_or_else(|| anyhow::anyhow!("{arg} has no depths"))?;
        let g0 = mvsplat360_train::trainer::render_example_full(&model, &fitted.ex)?.gaussians;
        // Test-time augmentation: the encoder on the mirrored example, its context depths mirrored back.
        let mut vf = fitted.views.clone();
        vf.flip = true;
        let exf = mvsplat360_train::trainer::example_from_views(&fitted.scene, &vf, cfg.model.near, cfg.model.far)?;
        let gf = mvsplat360_train::trainer::render_example_full(&model, &exf)?.gaussians;
        let (nf, ff) = (near as f32, far as f32);
        let encoder = depth_maps(&g0, &fitted.ex.context_cameras, nf, ff)?;
        let mirrored = depth_maps(&gf, &exf.context_cameras, nf, ff)?;
        let fit = depth_maps(&fitted.gaussians, &fitted.ex.context_cameras, nf, ff)?;
        let common::Fitted { ex, photos, gaussians: g, label, .. } = fitted;
        let (mut n, mut e0, mut e1, mut e2) = (0f64, 0f64, 0f64, 0f64);
        for ((d0, df), z) in encoder.iter().zip(&mirrored).zip(&zc) {
            for (i, &t) in z.iter().enumerate() {
                let (x, y) = (i % w, i / w);
                let (a, b) = (d0[i], df[y * w + (w - 1 - x)]);
                if a.is_finite() && a > 0.0 && b.is_finite() && b > 0.0 && t.is_finite() && (near..=far).contains(&(t as f64)) {
                    let lt = (t as f64).ln();
                    n += 1.0;
                    e0 += ((a as f64).ln() - lt).abs();
                    e1 += ((b as f64).ln() - lt).abs();
                    e2 += (0.5 * ((a as f64).ln() + (b as f64).ln()) - lt).abs();
                }
            }
        }
        println!("{label}: context depths: encoder {:.3}, mirrored {:.3}, mean of both {:.3}", e0 / n, e1 / n, e2 / n);
        for (name, maps) in [("encoder", &encoder), ("fitted", &fit)] {
            let (mut n, mut e) = (0f64, 0f64);
            for (dm, z) in maps.iter().zip(&zc) {
                for (&d, &t) in dm.iter().zip(z) {
                    if d.is_finite() && d > 0.0 && t.is_finite() && (near..=far).contains(&(t as f64)) {
                        n += 1.0;
                        e += ((d / t) as f64).ln().abs();
                    }
                }
            }
            println!("{label}: {name} Gaussians at the context views |ln| {:.3} on {:.0} % of pixels", e / n, 100.0 * n / (zc.len() * w * h) as f64);
        }
        let refs: Vec<&[f32]> = photos.iter().map(|p| p.data.as_slice()).collect();
        let mut acc = [0f64; 7];
        for (k, t) in ex.target_cameras.iter().enumerate() {
            let rc = raster_camera(t, near as f32, far as f32);
            let r = mvsplat360_splat::render(&g, &rc, &RenderOptions::default())?;
            let rgb: Vec<f32> = r.rgb.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
            let a: Vec<f32> = r.alpha.flatten_all()?.to_vec1()?;
            let d: Vec<f32> = r.depth.flatten_all()?.to_vec1()?;
            let med = median_depth(&g, &rc, near, far, 96)?;
            let x = candidates(&bs, t, &rgb, &a, &d, &ex.context_cameras, &refs, &[], near, far);
            let x = Tensor::from_vec(x, (1, bs.channels(), h, w), &Device::Cpu)?;
            let (wts, _) = net.heads(&x)?;
            let wts: Vec<f32> = wts.flatten_all()?.to_vec1()?;
            let n = w * h;
            for i in 0..n {
                let z = zt[k][i];
                if !(z.is_finite() && (near..=far).contains(&(z as f64))) || a[i] < 0.5 {
                    continue;
                }
                let zr = (d[i] / a[i]) as f64;
                let (mut sw, mut sl) = (0f64, 0f64);
                let mut best = f64::INFINITY;
                for v in 0..bs.views {
                    for p in 0..bs.planes {
                        let f = p as f64 / (bs.planes - 1).max(1) as f64;
                        let lz = zr.ln() + (2.0 * f - 1.0) * bs.span.ln();
                        let wv = wts[(1 + v * bs.planes + p) * n + i] as f64;
                        sw += wv;
                        sl += wv * lz;
                        best = best.min((lz - (z as f64).ln()).abs());
                    }
                }
                let lt = (z as f64).ln();
                acc[0] += 1.0;
                acc[1] += (zr.ln() - lt).abs();
                acc[2] += best;
                acc[6] += ((med[i] as f64).ln() - lt).abs();
                if sw >= 0.5 {
                    acc[3] += 1.0;
                    acc[4] += (zr.ln() - lt).abs();
                    acc[5] += ((sl / sw) - lt).abs();
                }
            }
        }
        report(&label, &acc);
        for (t, a) in tot.iter_mut().zip(acc) {
            *t += a;
        }
    }
    report("all", &tot);
    Ok(())
}

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(!args.is_empty(), "usage: blend cache|train|add|depth|loo …");
    let cmd = args.remove(0);
    match cmd.as_str() {
        "cache" => cache(&mut args),
        "loo" => cache_loo(&mut args),
        "train" => train(&mut args),
        "add" => add(&mut args),
        "depth" => depth(&mut args),
        c => anyhow::bail!("blend cache|train|add|depth|loo, got {c}"),
    }
}
