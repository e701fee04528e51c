//! Where a training step's time goes (forward encoder, rasterize, loss, backward) for a config.
//!
//!     cargo run --release -p mvsplat360-lab --example step_profile -- CONFIG.toml

use std::time::Instant;

use mvsplat360_train::trainer::{make_example, render_example, Model};
use rand::SeedableRng;

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let path = std::env::args().nth(1).ok_or_else(|| anyhow::anyhow!("usage: step_profile CONFIG.toml"))?;
    let cfg = mvsplat360_train::TrainConfig::from_file(path.as_ref())?;
    let model = Model::new(&cfg)?;
    let mut src = mvsplat360_train::scenes::SceneSource::open(&cfg.data.sources[0], cfg.model.width, cfg.model.height, 64)?;
    let s = mvsplat360_train::sampler::SamplerSettings {
        num_context: cfg.data.num_context,
        num_target: cfg.data.num_target,
        gap: cfg.data.gap,
        gap_initial: None,
        warm_up: 1.0,
        closed_loop: true,
        flip: false,
    };
    for it in 0..3 {
        let mut rng = rand::rngs::StdRng::seed_from_u64(it);
        let t = Instant::now();
        let scene = src.draw(&mut rng, cfg.train.seed, it)?;
        let ex = make_example(&scene, &s, cfg.model.near, cfg.model.far, &mut rng)?.expect("example");
        let t_data = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (pred, _) = render_example(&model, &ex)?;
        let t_fwd = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let loss = mvsplat360_train::loss::mse(&pred, &ex.target_images)?;
        let _g = loss.backward()?;
        let t_bwd = t.elapsed().as_secs_f64();
        // The rasterizer's share: the same renders from detached Gaussians.
        let (_, g) = render_example(&model, &ex)?;
        let v = |t: &candle_core::Tensor| candle_core::Var::from_tensor(&t.detach()).map(|v| v.as_tensor().clone());
        let gs = mvsplat360_splat::Gaussians {
            means: v(&g.means)?,
            covariances: v(&g.covariances)?,
            opacities: v(&g.opacities)?,
            harmonics: v(&g.harmonics)?,
            feature_harmonics: v(&g.feature_harmonics)?,
        };
        let t = Instant::now();
        let mut r = Vec::new();
        for c in &ex.target_cameras {
            r.push(mvsplat360_splat::render(&gs, &mvsplat360_splat::camera::RasterCamera::from_camera(c, 1.0, 100.0), &Default::default())?.rgb);
        }
        let l = mvsplat360_train::loss::mse(&candle_core::Tensor::stack(&r, 0)?, &ex.target_images)?;
        let t_rf = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let _ = l.backward()?;
        let t_rb = t.elapsed().as_secs_f64();
        println!("data {t_data:.2}s forward {t_fwd:.2}s backward {t_bwd:.2}s | rasterizer alone: forward {t_rf:.2}s backward {t_rb:.2}s");
    }
    Ok(())
}
