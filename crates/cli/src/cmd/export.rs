//! `mvsplat360 export`: predict Gaussians for a scene with the encoder and write them as `.ply` (and `.splat`).

use std::path::PathBuf;

use anyhow::{bail, Context};
use candle_core::{Device, Tensor};
use mvsplat360_camera::Camera;
use mvsplat360_encoder::encoder_costvolume::{camera_tensors, to_splat_gaussians, EncoderCostVolume};
use mvsplat360_encoder::EncoderCostVolumeCfg;

#[derive(clap::Args)]
pub struct Args {
    /// Encoder weights: the released Lightning `.ckpt`, a `.pth`, or a safetensors file with `encoder.*` keys.
    #[arg(long)]
    ckpt: PathBuf,
    /// Scene: a transforms.json (or its folder), a COLMAP folder, or a `.torch` chunk (first scene).
    scene: PathBuf,
    /// Output `.ply` (standard 3DGS layout).
    #[arg(long)]
    out: PathBuf,
    /// Number of context views, picked by farthest-point sampling of the camera centres.
    #[arg(long, default_value_t = 5)]
    context: usize,
    /// Also write an antimatter15 `.splat` file.
    #[arg(long)]
    splat: Option<PathBuf>,
    /// Resize views to this width (aspect kept) before the centre crop to a multiple of 64; 0 keeps the size.
    /// The released model was trained on 480-pixel-wide DL3DV frames.
    #[arg(long, default_value_t = 480)]
    resize_width: u32,
    /// Near plane in scene units (DL3DV experiment: 1).
    #[arg(long, default_value_t = 1.0)]
    near: f32,
    /// Far plane in scene units (DL3DV experiment: 100).
    #[arg(long, default_value_t = 100.0)]
    far: f32,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<()> {
    let scene = mvsplat360_dataset::read_scene(&args.scene).with_context(|| format!("reading scene {}", args.scene.display()))?;
    if args.context < 2 {
        bail!("--context must be at least 2 (the encoder matches views against each other)");
    }
    if scene.len() < args.context {
        bail!("scene {} has {} views, fewer than --context {}", args.scene.display(), scene.len(), args.context);
    }
    if !(args.near > 0.0 && args.far > args.near) {
        bail!("need 0 < --near < --far, got {} and {}", args.near, args.far);
    }
    let views = mvsplat360_camera::select::farthest_point_sampling(&scene.cameras, args.context);
    let mut cfg = EncoderCostVolumeCfg { num_views: views.len(), ..Default::default() };
    cfg.near = args.near;
    cfg.far = args.far;
    let multiple = cfg.image_multiple() as u32;

    let mut images = Vec::with_capacity(views.len());
    let mut cams: Vec<Camera> = Vec::with_capacity(views.len());
    for &i in &views {
        let mut img = scene.image(i).with_context(|| format!("decoding view {}", scene.view_names[i]))?;
        let mut cam = scene.cameras[i].clone();
        if args.resize_width > 0 && img.width != args.resize_width {
            let h = ((img.height as f64 * args.resize_width as f64 / img.width as f64).round() as u32).max(1);
            img = img.resize_bilinear(args.resize_width, h);
            cam = cam.rescaled(args.resize_width, h);
        }
        let rect = cam.center_crop_rect(multiple).with_context(|| format!("view {}", scene.view_names[i]))?;
        images.push(img.crop(rect.x0, rect.y0, rect.width, rect.height));
        cams.push(cam.cropped(rect));
    }
    let (w, h) = (images[0].width as usize, images[0].height as usize);
    let v = images.len();
    let device = Device::Cpu;
    let data: Vec<f32> = images.iter().flat_map(|im| im.data.iter().copied()).collect();
    let images_t = Tensor::from_vec(data, (1, v, 3, h, w), &device)?;
    let k_norm: Vec<[f64; 4]> = cams.iter().map(|c| c.normalized_intrinsics()).collect();
    let c2w: Vec<[[f64; 4]; 4]> = cams.iter().map(|c| c.c2w).collect();
    let (intrinsics, extrinsics) = camera_tensors(&k_norm, &c2w, &device)?;
    let near = Tensor::full(args.near, (1, v), &device)?;
    let far = Tensor::full(args.far, (1, v), &device)?;

    if !quiet {
        eprintln!("loading encoder weights from {}", args.ckpt.display());
    }
    let encoder = EncoderCostVolume::load(&args.ckpt, &cfg, &device)?;
    if !quiet {
        let names: Vec<&str> = views.iter().map(|&i| scene.view_names[i].as_str()).collect();
        eprintln!("encoding {v} context views at {w}x{h}: {}", names.join(", "));
    }
    let t0 = std::time::Instant::now();
    let g = encoder.forward(&images_t, &intrinsics, &extrinsics, &near, &far).context("running the encoder")?;
    let gaussians = to_splat_gaussians(&g)?.remove(0);
    if !quiet {
        eprintln!("predicted {} Gaussians in {:.1} s", gaussians.means.dim(0)?, t0.elapsed().as_secs_f64());
    }
    write_outputs(&gaussians, &args.out, args.splat.as_deref())
}

fn write_outputs(g: &mvsplat360_splat::Gaussians, ply: &std::path::Path, splat: Option<&std::path::Path>) -> anyhow::Result<()> {
    use mvsplat360_splat::io::{write_ply, write_splat, ExportGaussians};
    let eg = ExportGaussians::from_gaussians(g).context("converting Gaussians to the file parameterisation")?;
    // Write beside the target and rename, so an interrupted run never leaves a truncated file behind.
    let atomic = |path: &std::path::Path, write: &dyn Fn(&std::path::Path) -> anyhow::Result<()>| -> anyhow::Result<()> {
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(".partial");
        let tmp = std::path::PathBuf::from(tmp);
        write(&tmp).with_context(|| format!("writing {}", path.display()))?;
        std::fs::rename(&tmp, path).with_context(|| format!("moving {} into place", tmp.display()))
    };
    atomic(ply, &|p| Ok(write_ply(p, &eg)?))?;
    if let Some(s) = splat {
        atomic(s, &|p| Ok(write_splat(p, &eg)?))?;
    }
    Ok(())
}
