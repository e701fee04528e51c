//! Exploration (not part of the pipeline): how much a small residual CNN applied to the fitted 3DGS renders
//! adds on the held-out protocol (32-view loop, 5 context views by farthest-point sampling, the other 27 as
//! targets).
//!
//! `cache` renders each scene's targets with the model and its shipped test-time fitting (30 steps, lr 0.03,
//! cosine) and stores (render, alpha, photo) in DIR/<label>.safetensors (a scene already there is skipped, so an
//! interrupted run resumes). `train` fits the CNN (MSE, Adam) on one cache folder and reports the mean target PSNR
//! of another before and after it, every `--every` steps.
//!
//!     cargo run --release -p mvsplat360-train --example post -- cache CONFIG.toml MODEL_DIR OUT_DIR SEED|DIR…
//!     cargo run --release -p mvsplat360-train --example post -- train TRAIN_DIR VAL_DIR [--steps 2000]
//!         [--lr 1e-3] [--batch 8] [--width 32] [--every 250] [--seed 1] [--save NET.safetensors]

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, IndexOp, Module, Tensor};
use candle_nn::{conv2d, Conv2d, Conv2dConfig, Optimizer, VarBuilder, VarMap};
use mvsplat360_pipeline::render::raster_camera;
use mvsplat360_splat::RenderOptions;
use mvsplat360_train::trainer::Model;
use rand::{Rng, SeedableRng};

mod common;

fn cache(args: &[String]) -> anyhow::Result<()> {
    anyhow::ensure!(args.len() >= 4, "usage: post cache CONFIG.toml MODEL_DIR OUT_DIR SEED|DIR…");
    let out = PathBuf::from(&args[2]);
    std::fs::create_dir_all(&out)?;
    for arg in &args[3..] {
        let name = match arg.parse::<u64>() {
            Ok(seed) => format!("proc-{seed}"),
            Err(_) => Path::new(arg).file_name().map_or(arg.clone(), |n| n.to_string_lossy().to_string()),
        };
        let file = out.join(format!("{name}.safetensors"));
        if file.exists() {
            continue;
        }
        let t0 = std::time::Instant::now();
        let model = Model::encoder_with_weights(args[0].as_ref(), args[1].as_ref())?;
        let cfg = model.cfg.clone();
        let (w, h) = (cfg.model.width, cfg.model.height);
        let (near, far) = (cfg.model.near, cfg.model.far);
        let common::Fitted { ex, gaussians: g, .. } = common::fitted(&model, arg)?;
        let (mut rgb, mut alpha) = (Vec::new(), Vec::new());
        for c in &ex.target_cameras {
            let r = mvsplat360_splat::render(&g, &raster_camera(c, near, far), &RenderOptions::default())?;
            rgb.push(r.rgb.clamp(0f32, 1f32)?);
            alpha.push(r.alpha.reshape((1, h as usize, w as usize))?);
        }
        let tensors: HashMap<String, Tensor> = [
            ("render".to_string(), Tensor::stack(&rgb, 0)?),
            ("alpha".to_string(), Tensor::stack(&alpha, 0)?),
            ("target".to_string(), ex.target_images.clone()),
        ]
        .into();
        let tmp = out.join(format!("{name}.tmp"));
        candle_core::safetensors::save(&tensors, &tmp)?;
        std::fs::rename(&tmp, &file)?;
        println!("{name}: {} targets, {:.0} s", ex.target_cameras.len(), t0.elapsed().as_secs_f64());
    }
    Ok(())
}

/// (render, alpha, target) of every scene in a cache folder, concatenated: (N,3,H,W), (N,1,H,W), (N,3,H,W).
fn load(dir: &Path) -> anyhow::Result<(Tensor, Tensor, Tensor, usize)> {
    let mut files: Vec<PathBuf> =
        std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|e| e == "safetensors")).collect();
    files.sort();
    anyhow::ensure!(!files.is_empty(), "{}: no cached scenes", dir.display());
    let (mut r, mut a, mut t) = (Vec::new(), Vec::new(), Vec::new());
    for f in &files {
        let m = candle_core::safetensors::load(f, &Device::Cpu)?;
        r.push(m["render"].clone());
        a.push(m["alpha"].clone());
        t.push(m["target"].clone());
    }
    Ok((Tensor::cat(&r, 0)?, Tensor::cat(&a, 0)?, Tensor::cat(&t, 0)?, files.len()))
}

/// Residual CNN: full-resolution convs, one level at half resolution, a skip; the last conv starts at zero so
/// that the untrained net is the identity.
struct Net {
    inp: Conv2d,
    a: Conv2d,
    down: [Conv2d; 3],
    fuse: Conv2d,
    b: Conv2d,
    out: Conv2d,
}

impl Net {
    fn new(vb: VarBuilder, c: usize) -> anyhow::Result<Self> {
        let k3 = Conv2dConfig { padding: 1, ..Default::default() };
        Ok(Self {
            inp: conv2d(4, c, 3, k3, vb.pp("inp"))?,
            a: conv2d(c, c, 3, k3, vb.pp("a"))?,
            down: [conv2d(c, 2 * c, 3, k3, vb.pp("d0"))?, conv2d(2 * c, 2 * c, 3, k3, vb.pp("d1"))?, conv2d(2 * c, c, 3, k3, vb.pp("d2"))?],
            fuse: conv2d(2 * c, c, 3, k3, vb.pp("fuse"))?,
            b: conv2d(c, c, 3, k3, vb.pp("b"))?,
            out: conv2d(c, 3, 3, k3, vb.pp("out"))?,
        })
    }

    fn forward(&self, rgb: &Tensor, alpha: &Tensor) -> anyhow::Result<Tensor> {
        let x = Tensor::cat(&[rgb, alpha], 1)?;
        let x = self.inp.forward(&x)?.gelu()?;
        let x = self.a.forward(&x)?.gelu()?;
        let (_, _, h, w) = x.dims4()?;
        let mut y = x.avg_pool2d(2)?;
        for c in &self.down {
            y = c.forward(&y)?.gelu()?;
        }
        let y = y.upsample_nearest2d(h, w)?;
        let z = self.fuse.forward(&Tensor::cat(&[&x, &y], 1)?)?.gelu()?;
        let z = self.b.forward(&z)?.gelu()?;
        Ok((rgb + self.out.forward(&z)?)?)
    }
}

fn mean_psnr(pred: &Tensor, target: &Tensor) -> anyhow::Result<f64> {
    let n = pred.dim(0)?;
    let mut s = 0.0;
    for i in 0..n {
        s += common::psnr(&pred.i(i)?, &target.i(i)?)?;
    }
    Ok(s / n as f64)
}

fn evaluate(net: &Net, r: &Tensor, a: &Tensor, t: &Tensor) -> anyhow::Result<f64> {
    let n = r.dim(0)?;
    let mut outs = Vec::new();
    for s in (0..n).step_by(27) {
        let k = 27.min(n - s);
        outs.push(net.forward(&r.narrow(0, s, k)?, &a.narrow(0, s, k)?)?.detach());
    }
    mean_psnr(&Tensor::cat(&outs, 0)?, t)
}

fn train(args: &mut Vec<String>) -> anyhow::Result<()> {
    let mut take = |flag: &str, default: &str| common::take_flag(args, flag, default);
    let steps: usize = take("--steps", "2000").parse()?;
    let lr: f64 = take("--lr", "1e-3").parse()?;
    let batch: usize = take("--batch", "8").parse()?;
    let width: usize = take("--width", "32").parse()?;
    let every: usize = take("--every", "250").parse()?;
    let seed: u64 = take("--seed", "1").parse()?;
    let save = take("--save", "");
    anyhow::ensure!(args.len() == 2, "usage: post train TRAIN_DIR VAL_DIR [flags]");
    let (tr, ta, tt, ns) = load(Path::new(&args[0]))?;
    let (vr, va, vt, nv) = load(Path::new(&args[1]))?;
    println!("train: {} images of {ns} scenes; validation: {} images of {nv} scenes", tr.dim(0)?, vr.dim(0)?);
    let vm = VarMap::new();
    let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
    let net = Net::new(vb, width)?;
    // The untrained net must be the identity: zero its last conv.
    for (k, v) in vm.data().lock().unwrap().iter() {
        if k.starts_with("out.") {
            v.set(&v.zeros_like()?)?;
        }
    }
    let mut opt = candle_nn::AdamW::new(vm.all_vars(), candle_nn::ParamsAdamW { lr, weight_decay: 0.0, ..Default::default() })?;
    println!(
        "step 0: validation PSNR {:.3} (renders as they are {:.3}), train {:.3}",
        evaluate(&net, &vr, &va, &vt)?,
        mean_psnr(&vr, &vt)?,
        mean_psnr(&tr, &tt)?
    );
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let n = tr.dim(0)?;
    let t0 = std::time::Instant::now();
    let mut run = 0.0;
    for step in 1..=steps {
        let f = 0.5 * (1.0 + (std::f64::consts::PI * step as f64 / steps as f64).cos());
        opt.set_learning_rate(lr * f);
        let idx: Vec<u32> = (0..batch).map(|_| rng.gen_range(0..n as u32)).collect();
        let idx = Tensor::from_vec(idx, batch, &Device::Cpu)?;
        let (r, a, t) = (tr.index_select(&idx, 0)?, ta.index_select(&idx, 0)?, tt.index_select(&idx, 0)?);
        // Random horizontal flips: the renders' errors have no handedness.
        let (r, a, t) = if rng.gen_bool(0.5) { (r.flip(&[3])?, a.flip(&[3])?, t.flip(&[3])?) } else { (r, a, t) };
        let loss = (net.forward(&r, &a)? - &t)?.sqr()?.mean_all()?;
        opt.backward_step(&loss)?;
        run += loss.to_scalar::<f32>()? as f64;
        if step % every == 0 || step == steps {
            println!(
                "step {step}: train MSE {:.5} (mean of the last {every}), validation PSNR {:.3}, {:.2} s/step",
                run / every as f64,
                evaluate(&net, &vr, &va, &vt)?,
                t0.elapsed().as_secs_f64() / step as f64
            );
            run = 0.0;
        }
    }
    if !save.is_empty() {
        vm.save(&save)?;
    }
    Ok(())
}

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(!args.is_empty(), "usage: post cache|train …");
    let cmd = args.remove(0);
    match cmd.as_str() {
        "cache" => cache(&args),
        "train" => train(&mut args),
        c => anyhow::bail!("post cache|train, got {c}"),
    }
}
