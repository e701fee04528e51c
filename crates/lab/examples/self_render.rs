//! Diagnostics of a model on one scene: the context views rendered from their own cameras (pixel-aligned
//! Gaussians reproduce them whatever the depth, unless the Gaussians are large or transparent) and quantiles
//! of the Gaussians' size, opacity and distance to the first context camera.
//!
//!     cargo run --release -p mvsplat360-lab --example self_render -- MODEL_DIR SCENE

use candle_core::{DType, IndexOp, Tensor};
use mvsplat360_pipeline::model::{ModelArgs, RefinerArg};
use mvsplat360_pipeline::render::{self, RenderRequest, Silent};
use mvsplat360_pipeline::views::{ContextSpec, TargetSpec};

fn quantiles(t: &Tensor, name: &str) -> anyhow::Result<()> {
    let mut v: Vec<f32> = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
    v.sort_by(|a, b| a.total_cmp(b));
    let q = |f: f64| v[((v.len() - 1) as f64 * f) as usize];
    println!("{name}: p5 {:.4}  p50 {:.4}  p95 {:.4}  max {:.4}", q(0.05), q(0.5), q(0.95), q(1.0));
    Ok(())
}

fn main() -> anyhow::Result<()> {
    mvsplat360_pipeline::setup::init_process();
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(args.len() == 2, "usage: self_render MODEL_DIR SCENE");
    let n = mvsplat360_dataset::read_scene(args[1].as_ref())?.len();
    let req = RenderRequest {
        scene: args[1].clone().into(),
        scene_key: None,
        context: ContextSpec::Count(5),
        targets: TargetSpec::Views((0..n).collect()),
        model: ModelArgs { ckpt: Some(args[0].clone().into()), refiner: Some(RefinerArg::None), ..Default::default() },
        size: None,
        scene_scale: Some(mvsplat360_pipeline::scale::SceneScale::Auto),
        refine: Default::default(),
        splat: false,
        metrics: false,
        fid_variant: Default::default(),
        weights_dir: None,
        video: false,
        fps: 8,
        out: std::env::temp_dir(),
        resume: false,
    };
    let mut p = render::prepare(&req, &Silent)?;
    let ctx = p.choice.context.clone();
    p.target_cameras = ctx.iter().map(|&i| p.target_cameras[i].clone()).collect();
    p.target_photos = ctx.iter().map(|&i| p.target_photos[i].clone()).collect();
    let g = render::encode(&p, &Silent)?;
    let out = render::rasterize_targets(&g, &p.target_cameras, p.spec.data.near, p.spec.data.far, &Silent)?;
    for (k, (rgb, _)) in out.iter().enumerate() {
        let pred: Vec<f32> = rgb.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
        let gt = p.target_photos[k].as_ref().ok_or_else(|| anyhow::anyhow!("view {} has no photo", ctx[k]))?;
        println!("context view {:2} rendered from its own camera: PSNR {:.2} dB", ctx[k], mvsplat360_metrics::psnr::psnr(&pred, &gt.data));
    }
    let cov = g.covariances.to_dtype(DType::F32)?;
    quantiles(&(cov.i((.., 0, 0))? + cov.i((.., 1, 1))? + cov.i((.., 2, 2))?)?.sqrt()?, "size √tr(Σ)")?;
    quantiles(&g.opacities, "opacity")?;
    let c = p.context_cameras[0].center();
    let centre = Tensor::new(&[[c[0] as f32, c[1] as f32, c[2] as f32]], &candle_core::Device::Cpu)?;
    quantiles(&g.means.to_dtype(DType::F32)?.broadcast_sub(&centre)?.sqr()?.sum(1)?.sqrt()?, "distance to context camera 0")?;
    Ok(())
}
