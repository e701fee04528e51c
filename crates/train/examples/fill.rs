//! What to show where the Gaussians do not cover a target pixel (accumulated opacity α < 1): PSNR of the model's
//! 3DGS renders composited over several fills, on the held-out protocol (32-view loop, 5 context views by
//! farthest-point sampling, the other 27 as targets).
//!
//!     cargo run --release -p mvsplat360-train --example fill -- CONFIG.toml MODEL_DIR SEED|DIR…

use candle_core::IndexOp;
use mvsplat360_pipeline::render::raster_camera;
use mvsplat360_splat::RenderOptions;
use mvsplat360_train::scenes::protocol_scene;
use mvsplat360_train::trainer::{example_from_views, render_example_full, Model};

fn psnr(a: &[f32], b: &[f32]) -> f64 {
    let a: Vec<f32> = a.iter().map(|x| x.clamp(0.0, 1.0)).collect();
    mvsplat360_metrics::psnr::psnr(&a, b)
}

/// Pull-push fill: the covered colour (premultiplied `c`, coverage `a`) spread into uncovered pixels from a
/// pyramid of 2×2 block averages; returns the fill colour per pixel (3,H,W), computed from levels ≥ 1.
fn pull_push(c: &[f32], a: &[f32], h: usize, w: usize, fallback: [f32; 3]) -> Vec<f32> {
    // Level l holds (premultiplied colour sum, coverage sum) over blocks of 2^l × 2^l pixels (edges clamped).
    let mut levels: Vec<(usize, usize, Vec<f32>, Vec<f32>)> = vec![(h, w, c.to_vec(), a.to_vec())];
    while levels.last().is_some_and(|l| l.0 > 1 || l.1 > 1) {
        let (ph, pw, pc, pa) = levels.last().unwrap();
        let (nh, nw) = (ph.div_ceil(2), pw.div_ceil(2));
        let mut nc = vec![0.0; 3 * nh * nw];
        let mut na = vec![0.0; nh * nw];
        for y in 0..*ph {
            for x in 0..*pw {
                let j = (y / 2) * nw + x / 2;
                na[j] += pa[y * pw + x];
                for k in 0..3 {
                    nc[k * nh * nw + j] += pc[k * ph * pw + y * pw + x];
                }
            }
        }
        levels.push((nh, nw, nc, na));
    }
    // Push: from the coarsest level down, a level's own average where it has coverage, the coarser fill elsewhere.
    let top = levels.last().unwrap();
    let mut fill: Vec<f32> = (0..3).map(|k| if top.3[0] > 1e-6 { top.2[k] / top.3[0] } else { fallback[k] }).collect();
    let (mut fh, mut fw) = (1usize, 1usize);
    for l in (1..levels.len() - 1).rev() {
        let (lh, lw, lc, la) = &levels[l];
        let cap = (1usize << (2 * l)) as f32; // pixels per block
        let mut nf = upsample_bilinear(&fill, fh, fw, *lh, *lw);
        for j in 0..lh * lw {
            if la[j] > 1e-6 {
                let t = (4.0 * (la[j] / cap).min(1.0)).min(1.0);
                for k in 0..3 {
                    let up = &mut nf[k * lh * lw + j];
                    *up = t * (lc[k * lh * lw + j] / la[j]) + (1.0 - t) * *up;
                }
            }
        }
        fill = nf;
        fh = *lh;
        fw = *lw;
    }
    // The level-1 fill at full size.
    upsample_bilinear(&fill, fh, fw, h, w)
}

/// Bilinear resampling of (3, fh, fw) to (3, h, w), pixel centres aligned (edges clamped).
fn upsample_bilinear(f: &[f32], fh: usize, fw: usize, h: usize, w: usize) -> Vec<f32> {
    let mut out = vec![0.0; 3 * h * w];
    for y in 0..h {
        for x in 0..w {
            let sy = ((y as f32 + 0.5) * fh as f32 / h as f32 - 0.5).clamp(0.0, (fh - 1) as f32);
            let sx = ((x as f32 + 0.5) * fw as f32 / w as f32 - 0.5).clamp(0.0, (fw - 1) as f32);
            let (y0, x0) = (sy.floor() as usize, sx.floor() as usize);
            let (y1, x1) = ((y0 + 1).min(fh - 1), (x0 + 1).min(fw - 1));
            let (ty, tx) = (sy - y0 as f32, sx - x0 as f32);
            for k in 0..3 {
                let c = &f[k * fh * fw..(k + 1) * fh * fw];
                out[k * h * w + y * w + x] =
                    (1.0 - ty) * ((1.0 - tx) * c[y0 * fw + x0] + tx * c[y0 * fw + x1]) + ty * ((1.0 - tx) * c[y1 * fw + x0] + tx * c[y1 * fw + x1]);
            }
        }
    }
    out
}

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(args.len() >= 3, "usage: fill CONFIG.toml MODEL_DIR SEED|DIR…");
    let model = Model::encoder_with_weights(args[0].as_ref(), args[1].as_ref())?;
    let cfg = &model.cfg;
    let (w, h) = (cfg.model.width, cfg.model.height);
    let (near, far) = (cfg.model.near, cfg.model.far);
    let names = ["nearest context", "black (3DGS)", "context mean", "nearest photo", "pull-push", "un-premultiplied", "mean α", "α<0.5 share"];
    println!("| scene | {} |\n|---|{}", names.join(" | "), "---|".repeat(names.len()));
    let mut sums = vec![0.0f64; names.len()];
    for arg in &args[2..] {
        let (scene, v, label) = protocol_scene(arg, w, h, cfg.model.encoder.image_multiple() as u32)?;
        let ex = example_from_views(&scene, &v, near, far)?;
        let full = render_example_full(&model, &ex)?;
        let ctx: Vec<f32> = ex.context_images.flatten_all()?.to_vec1()?;
        let np = h as usize * w as usize;
        let nv = ex.context_cameras.len();
        let mean: [f32; 3] =
            std::array::from_fn(|k| (0..nv).map(|i| ctx[(i * 3 + k) * np..(i * 3 + k + 1) * np].iter().sum::<f32>()).sum::<f32>() / (nv * np) as f32);
        let mut row = vec![0.0f64; names.len()];
        for (t, tc) in ex.target_cameras.iter().enumerate() {
            let gt: Vec<f32> = ex.target_images.i(t)?.flatten_all()?.to_vec1()?;
            let k = (0..nv)
                .min_by(|&a, &b| (ex.context_cameras[a].center() - tc.center()).norm().total_cmp(&(ex.context_cameras[b].center() - tc.center()).norm()))
                .unwrap_or(0);
            let near_photo: Vec<f32> = ex.context_images.i(k)?.flatten_all()?.to_vec1()?;
            let r = mvsplat360_splat::render(&full.gaussians, &raster_camera(tc, near, far), &RenderOptions::default())?;
            let rgb: Vec<f32> = r.rgb.flatten_all()?.to_vec1()?;
            let a: Vec<f32> = r.alpha.flatten_all()?.to_vec1()?;
            let comp = |fill: &dyn Fn(usize, usize) -> f32| -> Vec<f32> { (0..3 * np).map(|i| rgb[i] + (1.0 - a[i % np]) * fill(i / np, i % np)).collect() };
            let pp = pull_push(&rgb, &a, h as usize, w as usize, mean);
            let unpre: Vec<f32> = (0..3 * np).map(|i| if a[i % np] > 0.05 { rgb[i] / a[i % np] } else { mean[i / np] }).collect();
            row[0] += psnr(&near_photo, &gt);
            row[1] += psnr(&rgb, &gt);
            row[2] += psnr(&comp(&|k, _| mean[k]), &gt);
            row[3] += psnr(&comp(&|k, p| near_photo[k * np + p]), &gt);
            row[4] += psnr(&comp(&|k, p| pp[k * np + p]), &gt);
            row[5] += psnr(&unpre, &gt);
            row[6] += a.iter().map(|&x| x as f64).sum::<f64>() / np as f64;
            row[7] += a.iter().filter(|&&x| x < 0.5).count() as f64 / np as f64;
        }
        let nt = ex.target_cameras.len() as f64;
        row.iter_mut().for_each(|x| *x /= nt);
        println!("| {label} | {} |", row.iter().map(|x| format!("{x:.3}")).collect::<Vec<_>>().join(" | "));
        for (s, r) in sums.iter_mut().zip(&row) {
            *s += r;
        }
    }
    let n = (args.len() - 2) as f64;
    println!("| **mean** | {} |", sums.iter().map(|x| format!("{:.3}", x / n)).collect::<Vec<_>>().join(" | "));
    Ok(())
}
