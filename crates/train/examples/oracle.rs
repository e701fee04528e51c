//! How far 3DGS from 5 views can go on this protocol: procedural scenes (never trained on: seeds far from the
//! training configs' ranges) with the held-out protocol (32 views on a loop, 5 context views by farthest-point
//! sampling, the other 27 views as targets, 128×64). PSNR of
//! - the nearest context photo (the goal's baseline),
//! - a model (the encoder's Gaussians, 3DGS renders),
//! - the *depth oracle*: one opaque Gaussian per context pixel at the ray caster's true depth with the pixel's
//!   colour (isotropic, σ = `--sigma` × the pixel footprint; sky pixels at 0.9 × far) — the best pixel-aligned
//!   Gaussians with exact geometry and no view-dependent colour can do; what is left is disocclusion and
//!   resampling.
//!
//! A scene folder with depth maps (`scripts/render-povray-sets` writes them) instead of a seed runs the same on
//! that scene, with the context views `heldout` chooses (unknown depths — sky, clipped colours — sit at 0.9 × far).
//!
//!     cargo run --release -p mvsplat360-train --example oracle -- CONFIG.toml MODEL_DIR [--sigma 0.6] SEED|DIR…

use candle_core::{Device, Tensor};
use mvsplat360_pipeline::render::raster_camera;
use mvsplat360_splat::{Gaussians, RenderOptions};
use mvsplat360_train::scenes::protocol_scene;
use mvsplat360_train::trainer::{example_from_views, render_example_full, Example, Model};

fn psnr(a: &Tensor, b: &Tensor) -> anyhow::Result<f64> {
    let a: Vec<f32> = a.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
    let b: Vec<f32> = b.flatten_all()?.to_vec1()?;
    Ok(mvsplat360_metrics::psnr::psnr(&a, &b))
}

/// Pixel-aligned Gaussians at the true ray distances of the example's context views.
fn oracle_gaussians(ex: &Example, far: f32, sigma: f64) -> anyhow::Result<Gaussians> {
    let depths = ex.context_depths.as_ref().ok_or_else(|| anyhow::anyhow!("the scene has no depths"))?;
    let (v, _, h, w) = ex.context_images.dims4()?;
    let imgs: Vec<f32> = ex.context_images.flatten_all()?.to_vec1()?;
    let ds: Vec<f32> = depths.flatten_all()?.to_vec1()?;
    let (mut means, mut covs, mut sh) = (Vec::new(), Vec::new(), Vec::new());
    let c0 = mvsplat360_splat::sh::C0;
    for (k, cam) in ex.context_cameras.iter().enumerate() {
        let c2w = cam.c2w;
        for y in 0..h {
            for x in 0..w {
                let i = (k * h + y) * w + x;
                let d = (ds[i] as f64).min(0.9 * far as f64);
                let dc = [(x as f64 + 0.5 - cam.cx) / cam.fx, (y as f64 + 0.5 - cam.cy) / cam.fy, 1.0];
                let n = (dc[0] * dc[0] + dc[1] * dc[1] + 1.0).sqrt();
                for r in 0..3 {
                    let dir = (c2w[r][0] * dc[0] + c2w[r][1] * dc[1] + c2w[r][2] * dc[2]) / n;
                    means.push((c2w[r][3] + d * dir) as f32);
                }
                let s = sigma * d / cam.fx;
                let var = (s * s) as f32;
                covs.extend_from_slice(&[var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var]);
                for c in 0..3 {
                    let col = imgs[((k * 3 + c) * h + y) * w + x];
                    sh.push((col - 0.5) / c0);
                    sh.extend(std::iter::repeat_n(0.0, 24));
                }
            }
        }
    }
    let n = v * h * w;
    let dev = Device::Cpu;
    Ok(Gaussians {
        means: Tensor::from_vec(means, (n, 3), &dev)?,
        covariances: Tensor::from_vec(covs, (n, 3, 3), &dev)?,
        opacities: Tensor::full(0.99f32, n, &dev)?,
        harmonics: Tensor::from_vec(sh, (n, 3, 25), &dev)?,
        feature_harmonics: Tensor::zeros((n, 4, 9), candle_core::DType::F32, &dev)?,
    })
}

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut sigma = 0.6;
    if let Some(i) = args.iter().position(|a| a == "--sigma") {
        sigma = args.get(i + 1).ok_or_else(|| anyhow::anyhow!("--sigma needs a value"))?.parse()?;
        args.drain(i..i + 2);
    }
    anyhow::ensure!(args.len() >= 3, "usage: oracle CONFIG.toml MODEL_DIR [--sigma S] SEED|DIR…");
    let model = Model::encoder_with_weights(args[0].as_ref(), args[1].as_ref())?;
    let cfg = &model.cfg;
    let (w, h) = (cfg.model.width, cfg.model.height);
    let (near, far) = (cfg.model.near, cfg.model.far);
    println!("| scene | nearest context | model (3DGS) | depth oracle (σ = {sigma} px) | model depth error |\n|---|---|---|---|---|");
    let mut sums = [0.0f64; 4];
    for arg in &args[2..] {
        let (scene, v, label) = protocol_scene(arg, w, h, cfg.model.encoder.image_multiple() as u32)?;
        anyhow::ensure!(scene.depths.is_some(), "{arg}: no depth/depth.json (render it with scripts/render-povray-scene --depth)");
        let ex = example_from_views(&scene, &v, near, far)?;
        let mut base = 0.0;
        for (t, tc) in ex.target_cameras.iter().enumerate() {
            let k = (0..ex.context_cameras.len())
                .min_by(|&a, &b| (ex.context_cameras[a].center() - tc.center()).norm().total_cmp(&(ex.context_cameras[b].center() - tc.center()).norm()))
                .unwrap_or(0);
            base += psnr(&ex.context_images.get(k)?, &ex.target_images.get(t)?)?;
        }
        let nt = ex.target_cameras.len() as f64;
        let full = render_example_full(&model, &ex)?;
        let renders = full.rgb;
        // The model's context depths against the truth: mean |ln d̂ − ln d| (the depth loss), unknown pixels out.
        let depth_err =
            mvsplat360_train::loss::depth_log_l1(&full.depths, ex.context_depths.as_ref().expect("depths checked"), near, far)?.to_scalar::<f32>()?;
        let mut m = 0.0;
        for t in 0..ex.target_cameras.len() {
            m += psnr(&renders.get(t)?, &ex.target_images.get(t)?)?;
        }
        let og = oracle_gaussians(&ex, far, sigma)?;
        let mut o = 0.0;
        for (t, tc) in ex.target_cameras.iter().enumerate() {
            let r = mvsplat360_splat::render(&og, &raster_camera(tc, near, far), &RenderOptions::default())?;
            o += psnr(&r.rgb, &ex.target_images.get(t)?)?;
        }
        // Sanity check of the oracle: context view 0 from its own camera.
        let r = mvsplat360_splat::render(&og, &raster_camera(&ex.context_cameras[0], near, far), &RenderOptions::default())?;
        let own = (w * h) as usize;
        let g0 = Gaussians {
            means: og.means.narrow(0, 0, own)?,
            covariances: og.covariances.narrow(0, 0, own)?,
            opacities: og.opacities.narrow(0, 0, own)?,
            harmonics: og.harmonics.narrow(0, 0, own)?,
            feature_harmonics: og.feature_harmonics.narrow(0, 0, own)?,
        };
        let r0 = mvsplat360_splat::render(&g0, &raster_camera(&ex.context_cameras[0], near, far), &RenderOptions::default())?;
        eprintln!(
            "{label}: oracle renders context view 0 from its own camera at {:.2} dB ({:.2} dB from its own Gaussians alone)",
            psnr(&r.rgb, &ex.context_images.get(0)?)?,
            psnr(&r0.rgb, &ex.context_images.get(0)?)?
        );
        let row = [base / nt, m / nt, o / nt, depth_err as f64];
        println!("| {label} | {:.2} | {:.2} | {:.2} | {:.3} |", row[0], row[1], row[2], row[3]);
        for (s, r) in sums.iter_mut().zip(row) {
            *s += r;
        }
    }
    let n = (args.len() - 2) as f64;
    println!("| **mean** | {:.2} | {:.2} | {:.2} | {:.3} |", sums[0] / n, sums[1] / n, sums[2] / n, sums[3] / n);
    Ok(())
}
