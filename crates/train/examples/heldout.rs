//! Held-out table for MODEL.md: per scene, 5 context views by farthest-point sampling, every other view a
//! target; PSNR / SSIM / LPIPS (VGG) of each model's 3DGS renders and of the baseline that copies the photo of
//! the context camera nearest each target. A model folder with a refiner also gets rows for its refined frames
//! (25 EDM steps, guidance 1 → 2.5, windows of 14, as `render`) and the final frames (refined, then
//! histogram-matched to the 3DGS renders); `--refiner none` as a second `--model` entry skips them
//! (`--model name=DIR:norefine`).
//!
//! The 3DGS renders are `render`'s: after the model's default test-time fitting (`--fit-steps N` overrides it
//! for every model, 0 = none; the row says "fitted N" when it ran) and, for a model with a learned blender, after
//! it (`--no-blend` skips it; the row says "blended").
//!
//!     cargo run --release -p mvsplat360-train --example heldout -- \
//!         --model step0=out/train/shipped/model-step0 --model final=assets/models/default data/heldout/*

use std::path::PathBuf;

use candle_core::{Device, Tensor};
use mvsplat360_dataset::ImageF32;
use mvsplat360_pipeline::model::ModelArgs;
use mvsplat360_pipeline::render::{self, Silent};

fn scores(lp: &mvsplat360_metrics::lpips::Lpips, preds: &[ImageF32], gts: &[ImageF32]) -> anyhow::Result<[f64; 3]> {
    let (mut p, mut s, mut l) = (0.0, 0.0, 0.0);
    for (a, b) in preds.iter().zip(gts) {
        let (w, h) = (a.width as usize, a.height as usize);
        p += mvsplat360_metrics::psnr::psnr(&a.data, &b.data);
        s += mvsplat360_metrics::ssim::ssim(&a.data, &b.data, 3, h, w)?;
        let ta = Tensor::from_slice(&a.data, (1, 3, h, w), &Device::Cpu)?;
        let tb = Tensor::from_slice(&b.data, (1, 3, h, w), &Device::Cpu)?;
        l += lp.distance(&ta, &tb)?[0] as f64;
    }
    let n = preds.len().max(1) as f64;
    Ok([p / n, s / n, l / n])
}

/// Rows of (prediction | photo) for every 4th target, to look at.
fn contact_sheet(path: &std::path::Path, preds: &[ImageF32], gts: &[ImageF32]) -> anyhow::Result<()> {
    let rows: Vec<usize> = (0..preds.len()).step_by(4).collect();
    let (w, h) = (preds[0].width, preds[0].height);
    let mut img = image::RgbImage::new(2 * w, h * rows.len() as u32);
    for (r, &i) in rows.iter().enumerate() {
        for (col, src) in [&preds[i], &gts[i]].into_iter().enumerate() {
            let plane = (w * h) as usize;
            for y in 0..h {
                for x in 0..w {
                    let k = (y * w + x) as usize;
                    let px = std::array::from_fn(|c| (src.data[c * plane + k].clamp(0.0, 1.0) * 255.0).round() as u8);
                    img.put_pixel(col as u32 * w + x, r as u32 * h + y, image::Rgb(px));
                }
            }
        }
    }
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    img.save(path)?;
    Ok(())
}

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let mut models: Vec<(String, PathBuf, bool)> = Vec::new();
    let mut scenes: Vec<PathBuf> = Vec::new();
    let mut json_out: Option<PathBuf> = None;
    let mut dump: Option<PathBuf> = None;
    let mut fit_steps: Option<usize> = None;
    let mut no_blend = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--model" => {
                let v = args.next().ok_or_else(|| anyhow::anyhow!("--model name=DIR"))?;
                let (n, d) = v.split_once('=').ok_or_else(|| anyhow::anyhow!("--model name=DIR, got {v}"))?;
                let (d, refine) = match d.strip_suffix(":norefine") {
                    Some(d) => (d, false),
                    None => (d, true),
                };
                models.push((n.into(), d.into(), refine));
            }
            "--json" => json_out = args.next().map(Into::into),
            "--dump" => dump = args.next().map(Into::into),
            "--fit-steps" => fit_steps = Some(args.next().ok_or_else(|| anyhow::anyhow!("--fit-steps N"))?.parse()?),
            "--no-blend" => no_blend = true,
            _ => scenes.push(a.into()),
        }
    }
    anyhow::ensure!(
        !models.is_empty() && !scenes.is_empty(),
        "usage: heldout --model name=DIR [--model …] [--fit-steps N] [--no-blend] [--json FILE] [--dump DIR] SCENE…"
    );
    let lp = mvsplat360_metrics::lpips::Lpips::load(None, mvsplat360_metrics::lpips::Net::Vgg, &Device::Cpu)?;
    let mut rows = Vec::new();
    println!("| scene | method | PSNR ↑ | SSIM ↑ | LPIPS ↓ |\n|---|---|---|---|---|");
    for scene in &scenes {
        let name = scene.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
        let mut baseline_done = false;
        for (mname, dir, refine) in &models {
            let model = ModelArgs {
                ckpt: Some(dir.clone()),
                refiner: (!refine).then_some(mvsplat360_pipeline::model::RefinerArg::None),
                fit_steps,
                no_blend,
                ..Default::default()
            };
            // Targets = every view that is not a context view.
            let p = mvsplat360_train::scenes::protocol_prepared(scene, model)?;
            let gts: Vec<ImageF32> = p.target_photos.iter().map(|x| x.clone().expect("view targets have photos")).collect();
            if !baseline_done {
                let preds: Vec<ImageF32> = p
                    .target_cameras
                    .iter()
                    .map(|t| {
                        let k = (0..p.context_cameras.len())
                            .min_by(|&a, &b| {
                                (p.context_cameras[a].center() - t.center()).norm().total_cmp(&(p.context_cameras[b].center() - t.center()).norm())
                            })
                            .unwrap_or(0);
                        p.context_images[k].clone()
                    })
                    .collect();
                let [ps, ss, ls] = scores(&lp, &preds, &gts)?;
                println!("| {name} | nearest context photo | {ps:.2} | {ss:.3} | {ls:.3} |");
                rows.push(serde_json::json!({"scene": name, "method": "nearest-context", "psnr": ps, "ssim": ss, "lpips": ls, "targets": gts.len()}));
                baseline_done = true;
            }
            let g = render::encode(&p, &Silent)?;
            let (g, fitted) = render::fit_to_context(&p, g, &Silent)?;
            let mut kind = if fitted.is_some() { format!("3DGS, fitted {}", p.spec.fit.steps) } else { "3DGS".to_string() };
            if p.spec.blend.is_some() {
                kind.push_str(", blended");
            }
            let out = render::frames_3dgs(&p, &g, &Silent)?;
            let preds: Vec<ImageF32> = out
                .iter()
                .map(|r| {
                    let rgb = r.output();
                    let (_, h, w) = rgb.dims3().unwrap();
                    ImageF32 { width: w as u32, height: h as u32, data: rgb.clamp(0f32, 1f32).unwrap().flatten_all().unwrap().to_vec1().unwrap() }
                })
                .collect();
            if let Some(d) = &dump {
                contact_sheet(&d.join(format!("{name}-{mname}.png")), &preds, &gts)?;
            }
            let [ps, ss, ls] = scores(&lp, &preds, &gts)?;
            println!("| {name} | {mname} ({kind}) | {ps:.2} | {ss:.3} | {ls:.3} |");
            rows.push(serde_json::json!({"scene": name, "method": format!("{mname} {kind}"), "psnr": ps, "ssim": ss, "lpips": ls, "targets": gts.len()}));
            if let Some((rcfg, w)) = &p.spec.refiner {
                let file = mvsplat360_pipeline::model::refiner_safetensors(w, &|_| {})?;
                // What the refiner's decoder can give at best: the photos encoded (posterior mode) and decoded.
                use mvsplat360_refiner::vae::{frames_from_decoded, prepare_encoder_input, AutoencoderKL};
                let vae = AutoencoderKL::load(&file, None, &rcfg.vae, &Device::Cpu)?;
                let (gh, gw) = (gts[0].height as usize, gts[0].width as usize);
                let photos = Tensor::stack(&gts.iter().map(|g| Tensor::from_slice(&g.data, (3, gh, gw), &Device::Cpu)).collect::<Result<Vec<_>, _>>()?, 0)?;
                let (mean, _) = vae.encode(&prepare_encoder_input(&photos, 2)?)?;
                let rec = frames_from_decoded(&vae.decode(&mean, 1)?, 2)?;
                let rec: Vec<ImageF32> = (0..gts.len())
                    .map(|i| Ok(ImageF32 { width: gw as u32, height: gh as u32, data: rec.get(i)?.flatten_all()?.to_vec1()? }))
                    .collect::<anyhow::Result<_>>()?;
                let [ps, ss, ls] = scores(&lp, &rec, &gts)?;
                println!("| {name} | {mname} (its VAE on the photos: encode, decode) | {ps:.2} | {ss:.3} | {ls:.3} |");
                rows.push(serde_json::json!({"scene": name, "method": format!("{mname} VAE reconstruction"), "psnr": ps, "ssim": ss, "lpips": ls, "targets": gts.len()}));
                let feats: Vec<Tensor> = out.iter().map(|r| r.features.clone()).collect();
                let refined = render::refine_frames(&p, &feats, &file, &Default::default(), &Silent)?;
                let refined: Vec<ImageF32> = refined
                    .iter()
                    .map(|f| {
                        let (_, h, w) = f.dims3()?;
                        Ok(ImageF32 { width: w as u32, height: h as u32, data: f.to_device(&Device::Cpu)?.flatten_all()?.to_vec1()? })
                    })
                    .collect::<anyhow::Result<_>>()?;
                let fin: Vec<ImageF32> = refined.iter().zip(&preds).map(|(r, g)| render::histogram_match(r, g)).collect::<Result<_, _>>()?;
                for (label, frames) in [("refined", &refined), ("final", &fin)] {
                    if let Some(d) = &dump {
                        contact_sheet(&d.join(format!("{name}-{mname}-{label}.png")), frames, &gts)?;
                    }
                    let [ps, ss, ls] = scores(&lp, frames, &gts)?;
                    println!("| {name} | {mname} ({label}) | {ps:.2} | {ss:.3} | {ls:.3} |");
                    rows.push(
                        serde_json::json!({"scene": name, "method": format!("{mname} {label}"), "psnr": ps, "ssim": ss, "lpips": ls, "targets": gts.len()}),
                    );
                }
            }
        }
    }
    if let Some(j) = json_out {
        std::fs::write(&j, serde_json::to_string_pretty(&rows)?)?;
    }
    Ok(())
}
