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

/// z-depth from a ray distance map of `cam`.
pub fn ray_to_z(cam: &mvsplat360_camera::Camera, dist: &[f32]) -> Vec<f32> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    (0..w * h)
        .map(|i| {
            let (px, py) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
            let n = (((px - cam.cx) / cam.fx).powi(2) + ((py - cam.cy) / cam.fy).powi(2) + 1.0).sqrt();
            (dist[i] as f64 / n) as f32
        })
        .collect()
}

/// The scene's true z-depth maps of the example's context and target views (in that order), scaled as the
/// example scaled the scene (the ratio of two context cameras' distances); `None` where the scene has no depths.
pub fn true_z(f: &Fitted) -> Option<(Vec<Vec<f32>>, Vec<Vec<f32>>)> {
    let d = f.scene.depths.as_ref()?;
    let (a, b) = (&f.scene.cameras[f.views.context[0]], &f.scene.cameras[f.views.context[1]]);
    let s = (f.ex.context_cameras[0].center() - f.ex.context_cameras[1].center()).norm() / (a.center() - b.center()).norm();
    let z = |cam: &mvsplat360_camera::Camera, i: usize| -> Vec<f32> { ray_to_z(cam, &d[i]).into_iter().map(|z| (z as f64 * s) as f32).collect() };
    let ctx = f.ex.context_cameras.iter().zip(&f.views.context).map(|(c, &i)| z(c, i)).collect();
    let tgt = f.ex.target_cameras.iter().zip(&f.views.target).map(|(c, &i)| z(c, i)).collect();
    Some((ctx, tgt))
}
