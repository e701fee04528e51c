//! Helpers shared by the exploration examples (`tto`, `post`, `ibr`, `blend`).
#![allow(dead_code)]

use candle_core::Tensor;

/// Removes `flag VALUE` from `args` and returns VALUE, or `default` when the flag is absent.
pub fn take_flag(args: &mut Vec<String>, flag: &str, default: &str) -> String {
    match args.iter().position(|a| a == flag) {
        Some(i) => {
            let v = args.remove(i + 1);
            args.remove(i);
            v
        }
        None => default.to_string(),
    }
}

/// PSNR of a prediction (clamped to [0, 1]) against its photo.
pub fn psnr(a: &Tensor, b: &Tensor) -> anyhow::Result<f64> {
    let a: Vec<f32> = a.clamp(0f32, 1f32)?.flatten_all()?.to_vec1()?;
    let b: Vec<f32> = b.flatten_all()?.to_vec1()?;
    Ok(mvsplat360_metrics::psnr::psnr(&a, &b))
}

/// One protocol scene (32-view loop, 5 context views by farthest-point sampling, the other views as targets) run
/// through the model's encoder and the shipped test-time fitting (30 steps, the default settings).
pub struct Fitted {
    pub scene: mvsplat360_train::scenes::TrainScene,
    pub views: mvsplat360_train::sampler::ViewSample,
    pub label: String,
    pub ex: mvsplat360_train::trainer::Example,
    /// The context photos (3,H,W) at model size.
    pub photos: Vec<mvsplat360_dataset::ImageF32>,
    pub gaussians: mvsplat360_splat::Gaussians,
}

pub fn fitted(model: &mvsplat360_train::trainer::Model, arg: &str) -> anyhow::Result<Fitted> {
    fitted_on(model, arg, &candle_core::Device::Cpu)
}

/// As [`fitted`], with the photos on `dev` (the model's device): the encoder and the fit run there.
pub fn fitted_on(model: &mvsplat360_train::trainer::Model, arg: &str, dev: &candle_core::Device) -> anyhow::Result<Fitted> {
    use candle_core::IndexOp;
    let cfg = &model.cfg.model;
    let (w, h) = (cfg.width, cfg.height);
    let (scene, views, label) = mvsplat360_train::scenes::protocol_scene(arg, w, h, cfg.encoder.image_multiple() as u32)?;
    let ex = mvsplat360_train::trainer::example_from_views(&scene, &views, cfg.near, cfg.far)?.to_device(dev)?;
    let g0 = mvsplat360_train::trainer::render_example_full(model, &ex)?.gaussians;
    let photos: Vec<mvsplat360_dataset::ImageF32> = (0..ex.context_cameras.len())
        .map(|i| Ok(mvsplat360_dataset::ImageF32 { width: w, height: h, data: ex.context_images.i(i)?.flatten_all()?.to_vec1()? }))
        .collect::<anyhow::Result<_>>()?;
    let fs = mvsplat360_pipeline::fit::FitSettings { steps: 30, ..Default::default() };
    let (gaussians, _) = mvsplat360_pipeline::fit::fit(&g0, &ex.context_cameras, &photos, cfg.near, cfg.far, &fs, &mvsplat360_pipeline::render::Silent)?;
    Ok(Fitted { scene, views, label, ex, photos, gaussians })
}
