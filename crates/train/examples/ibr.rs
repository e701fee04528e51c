//! Exploration (not part of the pipeline): image-based rendering on the held-out protocol. Each target pixel is
//! lifted to 3D with a depth (the fitted Gaussians' rendered depth, or the true depth where the scene knows it)
//! and coloured from the context photos that see that point (visibility by the context views' depths), weighted
//! by the angle between the target's ray and each context ray. Compared with the 3DGS render it would replace.
//! Also a target-view plane sweep (photo-consistency of the context views over depths around the rendered one)
//! as a third depth source. Columns: render, IBR with the rendered depth, IBR with the swept depth (without and
//! with visibility), the swept IBR averaged with the render, IBR with the true depth, and the mean |ln z − ln z_true|
//! of the rendered and the swept depths (the last three only where the scene knows its depths).
//! `--noise S1,S2,…` adds one column per level: IBR with the true depth times exp(S·n), n a standard normal field
//! drawn on a grid of `--noise-cell` pixels and bilinearly interpolated (1: independent per pixel) — how exact the
//! depth must be for the true-depth figure. `--no-sweep` skips the sweep columns (the slow part).
//!
//!     cargo run --release -p mvsplat360-train --example ibr -- CONFIG.toml MODEL_DIR [--sigma 5] [--tol 0.05]
//!         [--span 2] [--planes 33] [--win 2] [--lambda 0.002] [--cost-sigma 30] [--noise S,…]
//!         [--noise-cell 8] [--no-sweep] SEED|DIR…

use candle_core::IndexOp;
use mvsplat360_camera::Camera;
use mvsplat360_pipeline::render::raster_camera;
use mvsplat360_splat::RenderOptions;
use mvsplat360_train::trainer::Model;
use nalgebra::Vector3;

mod common;

use mvsplat360_pipeline::blend::bilinear;

/// A context view: camera, photo (3,H,W) and z-depth per pixel (infinite where unknown).
struct View {
    cam: Camera,
    img: Vec<f32>,
    z: Vec<f32>,
}

/// Colours a target from the views where `z` (the target's z-depth per pixel) is known and some view sees the
/// point; elsewhere keeps `fallback`. Returns the image and the fraction of pixels it coloured.
fn warp(t: &Camera, z: &[f32], views: &[View], sigma_deg: f64, tol: f32, fallback: &[f32]) -> (Vec<f32>, f64) {
    let (w, h) = (t.width as usize, t.height as usize);
    let mut out = fallback.to_vec();
    let rot = t.rotation();
    let c = t.center();
    let w2c: Vec<_> = views.iter().map(|v| v.cam.w2c_matrix()).collect();
    let mut done = 0usize;
    for py in 0..h {
        for px in 0..w {
            let zt = z[py * w + px] as f64;
            if !zt.is_finite() || zt <= 0.0 {
                continue;
            }
            let d = Vector3::new((px as f64 + 0.5 - t.cx) / t.fx, (py as f64 + 0.5 - t.cy) / t.fy, 1.0);
            let x = c + rot * (d * zt);
            let (mut acc, mut ws) = ([0f64; 3], 0f64);
            for (v, m) in views.iter().zip(&w2c) {
                let p = m.transform_point(&x.into());
                if p.z <= 1e-6 {
                    continue;
                }
                let (u, vv) = (v.cam.fx * p.x / p.z + v.cam.cx, v.cam.fy * p.y / p.z + v.cam.cy);
                if u < 0.0 || vv < 0.0 || u >= w as f64 || vv >= h as f64 {
                    continue;
                }
                let zi = v.z[(vv as usize) * w + u as usize];
                if zi.is_finite() && (p.z as f32) > zi * (1.0 + tol) {
                    continue;
                }
                let a = (x - c).normalize().dot(&(x - v.cam.center()).normalize()).clamp(-1.0, 1.0).acos().to_degrees();
                let wt = (-(a / sigma_deg).powi(2) / 2.0).exp().max(1e-12);
                let col = bilinear(&v.img, w, h, u, vv);
                for k in 0..3 {
                    acc[k] += wt * col[k] as f64;
                }
                ws += wt;
            }
            if ws > 0.0 {
                for k in 0..3 {
                    out[k * w * h + py * w + px] = (acc[k] / ws) as f32;
                }
                done += 1;
            }
        }
    }
    (out, done as f64 / (w * h) as f64)
}

/// Target-view plane sweep: per pixel, the depth among `cands(pixel)` whose projections into the views agree best
/// (angle-weighted colour variance, summed over a (2r+1)² window), plus `lambda`·|ln(z/z_prior)|.
#[allow(clippy::too_many_arguments)]
fn sweep(t: &Camera, prior: &[f32], views: &[View], factors: &[f64], range: (f64, f64), r: usize, lambda: f64, sigma_deg: f64) -> Vec<f32> {
    let (w, h) = (t.width as usize, t.height as usize);
    let nd = factors.len();
    let rot = t.rotation();
    let c = t.center();
    let w2c: Vec<_> = views.iter().map(|v| v.cam.w2c_matrix()).collect();
    let cand = |i: usize, k: usize| -> f64 {
        let p = prior[i] as f64;
        if p.is_finite() && p > 0.0 {
            p * factors[k]
        } else {
            range.0 * (range.1 / range.0).powf(k as f64 / (nd - 1).max(1) as f64)
        }
    };
    let mut cost = vec![0f64; nd * w * h];
    for py in 0..h {
        for px in 0..w {
            let i = py * w + px;
            let d = Vector3::new((px as f64 + 0.5 - t.cx) / t.fx, (py as f64 + 0.5 - t.cy) / t.fy, 1.0);
            for k in 0..nd {
                let x = c + rot * (d * cand(i, k));
                let (mut s1, mut s2, mut ws, mut nv) = ([0f64; 3], 0f64, 0f64, 0);
                for (v, m) in views.iter().zip(&w2c) {
                    let p = m.transform_point(&x.into());
                    if p.z <= 1e-6 {
                        continue;
                    }
                    let (u, vv) = (v.cam.fx * p.x / p.z + v.cam.cx, v.cam.fy * p.y / p.z + v.cam.cy);
                    if u < 0.0 || vv < 0.0 || u >= w as f64 || vv >= h as f64 {
                        continue;
                    }
                    let a = (x - c).normalize().dot(&(x - v.cam.center()).normalize()).clamp(-1.0, 1.0).acos().to_degrees();
                    let wt = (-(a / sigma_deg).powi(2) / 2.0).exp().max(1e-9);
                    let col = bilinear(&v.img, w, h, u, vv);
                    for j in 0..3 {
                        s1[j] += wt * col[j] as f64;
                        s2 += wt * (col[j] as f64).powi(2);
                    }
                    ws += wt;
                    nv += 1;
                }
                cost[k * w * h + i] = if nv >= 2 { (s2 / ws - s1.iter().map(|a| (a / ws).powi(2)).sum::<f64>()).max(0.0) } else { 0.05 };
            }
        }
    }
    let mut z = vec![f32::INFINITY; w * h];
    for py in 0..h {
        for px in 0..w {
            let i = py * w + px;
            let (mut best, mut bk) = (f64::INFINITY, 0);
            for k in 0..nd {
                let mut s = 0.0;
                for yy in py.saturating_sub(r)..(py + r + 1).min(h) {
                    for xx in px.saturating_sub(r)..(px + r + 1).min(w) {
                        s += cost[k * w * h + yy * w + xx];
                    }
                }
                let p = prior[i] as f64;
                let reg = if p.is_finite() { lambda * factors[k].ln().abs() } else { 0.0 };
                if s / ((2 * r + 1) * (2 * r + 1)) as f64 + reg < best {
                    best = s / ((2 * r + 1) * (2 * r + 1)) as f64 + reg;
                    bk = k;
                }
            }
            z[i] = cand(i, bk) as f32;
        }
    }
    z
}

fn log_err(a: &[f32], b: &[f32]) -> f64 {
    let (mut s, mut n) = (0.0, 0);
    for (&x, &y) in a.iter().zip(b) {
        if x.is_finite() && y.is_finite() && x > 0.0 && y > 0.0 {
            s += ((x / y) as f64).ln().abs();
            n += 1;
        }
    }
    s / n.max(1) as f64
}

fn psnr(a: &[f32], b: &[f32]) -> f64 {
    let a: Vec<f32> = a.iter().map(|x| x.clamp(0.0, 1.0)).collect();
    mvsplat360_metrics::psnr::psnr(&a, b)
}

/// `z` times exp(`s`·n) where n is a standard normal field on a grid of `cell` pixels, bilinearly interpolated.
fn perturb(z: &[f32], w: usize, h: usize, s: f64, cell: usize, rng: &mut impl rand::Rng) -> Vec<f32> {
    let (gw, gh) = (w.div_ceil(cell) + 1, h.div_ceil(cell) + 1);
    let grid: Vec<f64> = (0..gw * gh).map(|_| rng.sample::<f64, _>(rand_distr::StandardNormal)).collect();
    (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f64 / cell as f64, (i / w) as f64 / cell as f64);
            let (x0, y0) = (x.floor() as usize, y.floor() as usize);
            let (fx, fy) = (x - x0 as f64, y - y0 as f64);
            let g = |a: usize, b: usize| grid[b * gw + a];
            let n = (1.0 - fy) * ((1.0 - fx) * g(x0, y0) + fx * g(x0 + 1, y0)) + fy * ((1.0 - fx) * g(x0, y0 + 1) + fx * g(x0 + 1, y0 + 1));
            (z[i] as f64 * (s * n).exp()) as f32
        })
        .collect()
}

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut take = |f: &str, d: &str| common::take_flag(&mut args, f, d);
    let sigma: f64 = take("--sigma", "5").parse()?;
    let tol: f32 = take("--tol", "0.05").parse()?;
    let span: f64 = take("--span", "2").parse()?;
    let planes: usize = take("--planes", "33").parse()?;
    let win: usize = take("--win", "2").parse()?;
    let lambda: f64 = take("--lambda", "0.002").parse()?;
    let csigma: f64 = take("--cost-sigma", "30").parse()?;
    let noise: Vec<f64> = take("--noise", "").split(',').filter(|x| !x.is_empty()).map(|x| x.parse()).collect::<Result<_, _>>()?;
    let cell: usize = take("--noise-cell", "8").parse::<usize>()?.max(1);
    let no_sweep = args.iter().position(|a| a == "--no-sweep").map(|i| args.remove(i)).is_some();
    let mut rng = <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(7);
    anyhow::ensure!(args.len() >= 3, "usage: ibr CONFIG.toml MODEL_DIR [flags] SEED|DIR…");
    let model = Model::encoder_with_weights(args[0].as_ref(), args[1].as_ref())?;
    let cfg = model.cfg.clone();
    let (near, far) = (cfg.model.near, cfg.model.far);
    let factors: Vec<f64> = (0..planes).map(|k| span.powf(2.0 * k as f64 / (planes - 1) as f64 - 1.0)).collect();
    let mut names: Vec<String> =
        ["render", "ibr-render-z", "ibr-sweep", "ibr-sweep-vis", "blend", "oracle-ibr", "zerr-render", "zerr-sweep"].map(String::from).to_vec();
    names.extend(noise.iter().map(|s| format!("oracle-ibr-noise-{s}")));
    let mut sums = vec![0f64; names.len()];
    let mut nscenes = vec![0usize; names.len()];
    println!("columns: {names:?}");
    for arg in &args[2..] {
        let fitted = common::fitted(&model, arg)?;
        let truth = common::true_z(&fitted);
        let common::Fitted { label, ex, photos, gaussians: g, .. } = fitted;
        let zmap = |c: &Camera, min_alpha: f32| -> anyhow::Result<(Vec<f32>, Vec<f32>)> {
            let r = mvsplat360_splat::render(&g, &raster_camera(c, near, far), &RenderOptions::default())?;
            let a: Vec<f32> = r.alpha.flatten_all()?.to_vec1()?;
            let d: Vec<f32> = r.depth.flatten_all()?.to_vec1()?;
            let z = a.iter().zip(&d).map(|(&a, &d)| if a >= min_alpha { d / a } else { f32::INFINITY }).collect();
            Ok((z, r.rgb.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?))
        };
        let views: Vec<View> = ex
            .context_cameras
            .iter()
            .zip(&photos)
            .map(|(c, p)| Ok(View { cam: c.clone(), img: p.data.clone(), z: zmap(c, 0.5)?.0 }))
            .collect::<anyhow::Result<_>>()?;
        let oviews: Option<Vec<View>> =
            truth.as_ref().map(|(zc, _)| views.iter().zip(zc).map(|(vw, z)| View { cam: vw.cam.clone(), img: vw.img.clone(), z: z.clone() }).collect());
        let mut row = vec![0f64; names.len()];
        let n = ex.target_cameras.len();
        for (k, t) in ex.target_cameras.iter().enumerate() {
            let photo: Vec<f32> = ex.target_images.i(k)?.flatten_all()?.to_vec1()?;
            let (z, rgb) = zmap(t, 0.5)?;
            row[0] += psnr(&rgb, &photo);
            row[1] += psnr(&warp(t, &z, &views, sigma, tol, &rgb).0, &photo);
            let zs = (!no_sweep).then(|| sweep(t, &z, &views, &factors, (near as f64, far as f64), win, lambda, csigma));
            if let Some(zs) = &zs {
                let im = warp(t, zs, &views, sigma, f32::INFINITY, &rgb).0;
                row[2] += psnr(&im, &photo);
                row[3] += psnr(&warp(t, zs, &views, sigma, tol, &rgb).0, &photo);
                let blend: Vec<f32> = im.iter().zip(&rgb).map(|(a, b)| 0.5 * (a + b)).collect();
                row[4] += psnr(&blend, &photo);
            } else {
                row[2..5].fill(f64::NAN);
            }
            if let (Some((_, zts)), Some(ov)) = (&truth, &oviews) {
                let zt = &zts[k];
                row[5] += psnr(&warp(t, zt, ov, sigma, tol, &rgb).0, &photo);
                row[6] += log_err(&z, zt);
                row[7] += zs.as_ref().map_or(f64::NAN, |zs| log_err(zs, zt));
                for (j, &s) in noise.iter().enumerate() {
                    let zn = perturb(zt, t.width as usize, t.height as usize, s, cell, &mut rng);
                    row[8 + j] += psnr(&warp(t, &zn, ov, sigma, tol, &rgb).0, &photo);
                }
            }
        }
        print!("{label}:");
        for (j, x) in row.iter().enumerate() {
            if j >= 5 && truth.is_none() {
                continue;
            }
            sums[j] += x / n as f64;
            nscenes[j] += 1;
            print!(" {:.3}", x / n as f64);
        }
        println!();
    }
    print!("mean:");
    for j in 0..names.len() {
        if nscenes[j] > 0 {
            print!(" {:.3}", sums[j] / nscenes[j] as f64);
        }
    }
    println!();
    Ok(())
}
