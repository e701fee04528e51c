//! `eval-scenes`: a model on posed scene folders by the held-out protocol of the shipped model's card — per scene,
//! `num_context` context views by farthest-point sampling (started at the first view, as `render --num-context`)
//! and every other view a target. Scored ([`mvsplat360_metrics::score::score_images`], frames as rendered, no
//! 8-bit rounding): the model's frames (3DGS, after the model's test-time fit and blender; with a refiner also its
//! refined and final frames) and the baseline that copies, for each target, the context photo whose camera
//! centre is nearest.

use std::path::{Path, PathBuf};

use mvsplat360_dataset::ImageF32;
use mvsplat360_metrics::score::{score_images, RgbImage, ScoreOptions};
use serde::Serialize;

use crate::error::{compute, flag, PipelineError, Result};
use crate::model::ModelArgs;
use crate::progress::{Progress, Silent};
use crate::render::{self, Prepared, RenderRequest};
use crate::scale::SceneScale;
use crate::views::{ContextSpec, TargetSpec};

/// What `eval-scenes` evaluates.
#[derive(Debug, Clone)]
pub struct ScenesRequest {
    /// Scene folders (anything `render` reads), each with at least `num_context + 1` views.
    pub scenes: Vec<PathBuf>,
    pub model: ModelArgs,
    pub num_context: usize,
    /// `--scene-scale`; None: the model's own (see [`crate::scale::resolve`]).
    pub scene_scale: Option<SceneScale>,
    /// Folder with the metric weights (LPIPS); without them LPIPS is null with a warning.
    pub weights_dir: Option<PathBuf>,
}

/// One method's scores on one scene (means over its targets).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Row {
    pub scene: String,
    pub method: String,
    pub psnr: f64,
    pub ssim: f64,
    pub lpips: Option<f64>,
    pub targets: usize,
}

/// A scene prepared by the protocol: `num_context` context views by farthest-point sampling, every other view a
/// target (its photo preprocessed as the context photos are).
pub fn protocol_prepared(scene: &Path, model: ModelArgs, num_context: usize, scene_scale: Option<SceneScale>) -> Result<Prepared> {
    let n = mvsplat360_dataset::read_scene(scene)?.len();
    let req = RenderRequest {
        scene: scene.to_path_buf(),
        scene_key: None,
        context: ContextSpec::Count(num_context),
        targets: TargetSpec::Views((0..n).collect()),
        model,
        size: None,
        scene_scale,
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
    let keep: Vec<usize> = (0..n).filter(|i| !p.choice.context.contains(i)).collect();
    if keep.is_empty() {
        return Err(flag("--num-context", format!("{}: {n} views leave no target after {num_context} context views", scene.display())));
    }
    p.target_cameras = keep.iter().map(|&i| p.target_cameras[i].clone()).collect();
    p.target_photos = keep.iter().map(|&i| p.target_photos[i].clone()).collect();
    Ok(p)
}

fn rgb(im: &ImageF32) -> RgbImage {
    RgbImage { width: im.width as usize, height: im.height as usize, data: im.data.clone() }
}

fn host_image(t: &candle_core::Tensor, stage: &'static str) -> Result<ImageF32> {
    let (_, h, w) = t.dims3().map_err(compute(stage))?;
    let data = t
        .to_device(&candle_core::Device::Cpu)
        .and_then(|t| t.clamp(0f32, 1f32))
        .and_then(|t| t.flatten_all())
        .and_then(|t| t.to_vec1())
        .map_err(compute(stage))?;
    Ok(ImageF32 { width: w as u32, height: h as u32, data })
}

/// Score every method on every scene; `warn` receives each metric warning once (e.g. missing LPIPS weights).
pub fn run(req: &ScenesRequest, progress: &dyn Progress, warn: &dyn Fn(&str)) -> Result<Vec<Row>> {
    if req.scenes.is_empty() {
        return Err(flag("SCENE", "give at least one scene folder"));
    }
    let opts = ScoreOptions { weights_dir: req.weights_dir.clone(), dists: false, fid: false, ..ScoreOptions::default() };
    let mut warned = std::collections::BTreeSet::new();
    let mut rows = Vec::new();
    for scene in &req.scenes {
        let name = scene.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| scene.display().to_string());
        let p = protocol_prepared(scene, req.model.clone(), req.num_context, req.scene_scale)?;
        let gts: Vec<ImageF32> = p.target_photos.iter().map(|x| x.clone().expect("every target is a view with a photo")).collect();
        let mut score = |method: String, preds: &[ImageF32]| -> Result<()> {
            let pairs: Vec<(String, RgbImage, RgbImage)> = preds.iter().zip(&gts).enumerate().map(|(i, (a, b))| (format!("{i:04}"), rgb(a), rgb(b))).collect();
            let r = score_images(&pairs, &opts).map_err(|e| PipelineError::Compute { stage: "scoring", msg: format!("{}: {e}", scene.display()) })?;
            for w in &r.warnings {
                if warned.insert(w.clone()) {
                    warn(w);
                }
            }
            rows.push(Row { scene: name.clone(), method, psnr: r.psnr, ssim: r.ssim, lpips: r.lpips, targets: gts.len() });
            Ok(())
        };
        let nearest: Vec<ImageF32> = p
            .target_cameras
            .iter()
            .map(|t| {
                let d = |k: usize| (p.context_cameras[k].center() - t.center()).norm();
                let k = (0..p.context_cameras.len()).min_by(|&a, &b| d(a).total_cmp(&d(b))).unwrap_or(0);
                p.context_images[k].clone()
            })
            .collect();
        score("nearest context photo".into(), &nearest)?;
        let g = render::encode(&p, progress)?;
        let (g, fitted) = render::fit_to_context(&p, g, progress)?;
        let mut kind = if fitted.is_some() { format!("3DGS, fitted {}", p.spec.fit.steps) } else { "3DGS".to_string() };
        if p.spec.blend.is_some() {
            kind.push_str(", blended");
        }
        let out = render::frames_3dgs(&p, &g, progress)?;
        let splats: Vec<ImageF32> = out.iter().map(|r| host_image(r.output(), "3DGS frames")).collect::<Result<_>>()?;
        score(kind, &splats)?;
        if let Some((_, w)) = &p.spec.refiner {
            let file = crate::model::refiner_safetensors(w, &|m| progress.note(m))?;
            let feats: Vec<candle_core::Tensor> = out.iter().map(|r| r.features.clone()).collect();
            let refined: Vec<ImageF32> = render::refine_frames(&p, &feats, &file, &Default::default(), progress)?
                .iter()
                .map(|f| host_image(f, "refined frames"))
                .collect::<Result<_>>()?;
            let fin: Vec<ImageF32> = refined.iter().zip(&splats).map(|(r, g)| render::histogram_match(r, g)).collect::<Result<_>>()?;
            score("refined".into(), &refined)?;
            score("final (refined, histogram-matched)".into(), &fin)?;
        }
    }
    Ok(rows)
}

/// The rows as one table: a line per method, PSNR per scene, then the means over the scenes.
pub fn markdown(rows: &[Row]) -> String {
    let mut scenes: Vec<&str> = Vec::new();
    let mut methods: Vec<&str> = Vec::new();
    for r in rows {
        if !scenes.contains(&r.scene.as_str()) {
            scenes.push(&r.scene);
        }
        if !methods.contains(&r.method.as_str()) {
            methods.push(&r.method);
        }
    }
    let mut s = format!("| method | {} | PSNR ↑ | SSIM ↑ | LPIPS ↓ |\n|---|{}---|---|---|\n", scenes.join(" | "), "---|".repeat(scenes.len()));
    for m in methods {
        let mine: Vec<&Row> = rows.iter().filter(|r| r.method == m).collect();
        let cell = |sc: &str| mine.iter().find(|r| r.scene == sc).map_or("–".to_string(), |r| format!("{:.2}", r.psnr));
        let mean = |f: &dyn Fn(&Row) -> Option<f64>| -> Option<f64> {
            let v: Vec<f64> = mine.iter().map(|r| f(r)).collect::<Option<_>>()?;
            Some(v.iter().sum::<f64>() / v.len() as f64)
        };
        let fmt = |v: Option<f64>, d: usize| v.map_or("–".to_string(), |x| format!("{x:.d$}"));
        s.push_str(&format!(
            "| {m} | {} | {} | {} | {} |\n",
            scenes.iter().map(|sc| cell(sc)).collect::<Vec<_>>().join(" | "),
            fmt(mean(&|r| Some(r.psnr)), 2),
            fmt(mean(&|r| Some(r.ssim)), 3),
            fmt(mean(&|r| r.lpips), 3)
        ));
    }
    s
}
