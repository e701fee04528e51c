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
//!
//! A set `PxVxS` is the candidates' layout: P depth planes for each of the V nearest context views, spread over
//! a factor S either side of the rendered depth (the default, `BlendSettings::default()`, is 7x2x1.6); `PxVxSv`
//! adds the visibility channels (`BlendSettings::visibility`). Without
//! `--sets`, `cache` writes the default layout into OUT_DIR; with it, one folder OUT_DIR/PxVxS per set, all from
//! the same fit. `--truth` (an oracle, for the ceiling of blending): the candidates are lifted around each target
//! pixel's *true* depth (opacity 1 where known) and the visibility channels read the context views' true depths;
//! only scenes that know their depths. `add` writes a copy of a model folder with the blender's weights and its
//! `blend` settings added.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, IndexOp, Tensor};
use candle_nn::{Optimizer, VarBuilder, VarMap};
use mvsplat360_pipeline::blend::{candidates, depth_map, BlendNet, BlendSettings, PREFIX};
use mvsplat360_pipeline::render::raster_camera;
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
                ex.context_cameras
                    .iter()
                    .map(|c| -> anyhow::Result<Vec<f32>> {
                        let r = mvsplat360_splat::render(&g, &raster_camera(c, near as f32, far as f32), &RenderOptions::default())?;
                        Ok(depth_map(&r.depth.flatten_all()?.to_vec1()?, &r.alpha.flatten_all()?.to_vec1()?))
                    })
                    .collect::<anyhow::Result<_>>()?
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
                let tensors: HashMap<String, Tensor> = [("x".to_string(), Tensor::stack(&xs, 0)?), ("target".to_string(), target.clone())].into();
                let tmp = d.join(format!("{name}.tmp"));
                candle_core::safetensors::save(&tensors, &tmp)?;
                std::fs::rename(&tmp, d.join(&file))?;
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

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(!args.is_empty(), "usage: blend cache|train|add …");
    let cmd = args.remove(0);
    match cmd.as_str() {
        "cache" => cache(&mut args),
        "train" => train(&mut args),
        "add" => add(&mut args),
        c => anyhow::bail!("blend cache|train|add, got {c}"),
    }
}
