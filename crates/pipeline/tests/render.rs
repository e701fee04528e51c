//! `render` end to end on the bundled scene with a tiny random model: every output exists and decodes, sizes
//! are right, nothing is NaN, the `.ply` reproduces the 3DGS renders, target cameras and GT photos are the
//! preprocessed scene views.

use std::path::{Path, PathBuf};

use candle_core::Device;
use mvsplat360_pipeline::model::{self, ModelArgs, RefinerArg};
use mvsplat360_pipeline::preprocess::{InputSize, Preprocess};
use mvsplat360_pipeline::render::{self, RefineSettings, RenderRequest, Silent};
use mvsplat360_pipeline::views::{ContextSpec, TargetSpec};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn tiny_model(dir: &Path, refiner: bool) -> PathBuf {
    let cfg = model::tiny_config(refiner);
    let sd = model::random_state_dict(&cfg, 3).unwrap();
    let m = dir.join(if refiner { "tiny" } else { "tiny-3dgs" });
    model::write_model_dir(&m, &cfg, &sd).unwrap();
    m
}

fn request(model_dir: &Path, out: &Path, targets: TargetSpec) -> RenderRequest {
    RenderRequest {
        scene: root().join("assets/woodbox"),
        scene_key: None,
        context: ContextSpec::Views(vec![0, 6, 12, 18]),
        targets,
        model: ModelArgs { ckpt: Some(model_dir.to_path_buf()), ..Default::default() },
        size: None,
        scene_scale: Default::default(),
        refine: RefineSettings { steps: 2, window: 3, ..RefineSettings::default() },
        splat: true,
        metrics: false,
        fid_variant: Default::default(),
        weights_dir: None,
        video: true,
        fps: 8,
        out: out.to_path_buf(),
        resume: false,
    }
}

fn png(path: &Path) -> image::RgbImage {
    image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).to_rgb8()
}

#[test]
fn tiny_model_render_writes_every_output() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(tmp.path(), true);
    let out = std::env::var_os("KEEP_RENDER").map(PathBuf::from).unwrap_or_else(|| tmp.path().join("out"));
    let targets = vec![21, 1, 4, 7, 10, 13, 16, 19]; // unsorted on purpose: frames follow view order
    let mut req = request(&m, &out, TargetSpec::Views(targets.clone()));
    req.metrics = true;
    let s = render::run(&req, &Silent).unwrap();
    assert_eq!(s.frames, 8);
    assert!(s.refined);
    assert_eq!(s.gaussians, 4 * 128 * 64);
    let mut sorted = targets.clone();
    sorted.sort();
    for d in ["gsplat", "refined", "final", "gt"] {
        for i in 0..8 {
            let img = png(&out.join(format!("frames/{d}/{i:04}.png")));
            assert_eq!(img.dimensions(), (128, 64), "{d}/{i}");
        }
        assert!(!out.join(format!("frames/{d}/0008.png")).exists());
    }
    // Refined frames differ from the 3DGS renders (the refiner ran) and final frames carry the gsplat histogram.
    let g0 = png(&out.join("frames/gsplat/0000.png"));
    let r0 = png(&out.join("frames/refined/0000.png"));
    let f0 = png(&out.join("frames/final/0000.png"));
    assert_ne!(g0.as_raw(), r0.as_raw());
    // Histogram matching gives each channel the 3DGS render's distribution: mean/std within 8 levels (the random
    // refiner's near-flat output has few distinct values, so the matched quantiles are coarse; unmatched it is
    // 40 levels off in mean and 30–50 in std).
    let stats = |im: &image::RgbImage, c: usize| {
        let v: Vec<f64> = im.pixels().map(|p| p.0[c] as f64).collect();
        let m = v.iter().sum::<f64>() / v.len() as f64;
        (m, (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt())
    };
    for c in 0..3 {
        let ((mf, sf), (mg, sg)) = (stats(&f0, c), stats(&g0, c));
        assert!((mf - mg).abs() <= 8.0 && (sf - sg).abs() <= 8.0, "channel {c}: final {mf:.1}±{sf:.1}, gsplat {mg:.1}±{sg:.1}");
    }

    // cameras.json: 4 context + 8 targets; a target view's camera equals the preprocessed scene camera.
    let cams: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json")).unwrap()).unwrap();
    let list = cams["cameras"].as_array().unwrap();
    assert_eq!(list.len(), 12);
    assert_eq!(list.iter().filter(|c| c["role"] == "target").count(), 8);
    let scene = mvsplat360_dataset::read_scene(&root().join("assets/woodbox")).unwrap();
    let pre = Preprocess { size: InputSize::Fixed { width: 128, height: 64 }, multiple: 64 };
    for (k, &v) in sorted.iter().enumerate() {
        let c = &list[4 + k];
        assert_eq!(c["view"], v);
        assert_eq!(c["name"], scene.view_names[v].as_str());
        let want = pre.camera(&scene.cameras[v]).unwrap();
        assert_eq!((c["width"].as_u64().unwrap(), c["height"].as_u64().unwrap()), (want.width as u64, want.height as u64));
        let k_ = c["K"].as_array().unwrap();
        assert!((k_[0][0].as_f64().unwrap() - want.fx).abs() < 1e-9 && (k_[1][2].as_f64().unwrap() - want.cy).abs() < 1e-9);
        for r in 0..4 {
            for col in 0..4 {
                assert!((c["c2w"][r][col].as_f64().unwrap() - want.c2w[r][col]).abs() < 1e-12);
            }
        }
        // GT frame = the preprocessed photo (8-bit rounding only).
        let (img, _) = pre.view(&scene.image(v).unwrap(), &scene.cameras[v]).unwrap();
        assert_eq!(png(&out.join(format!("frames/gt/{k:04}.png"))).as_raw(), img.to_rgb8().as_raw());
    }

    // run.json: valid, with settings and stage times.
    let run: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["frames"], 8);
    assert_eq!(run["settings"]["context"], serde_json::json!([0, 6, 12, 18]));
    assert_eq!(run["settings"]["refine"]["steps"], 2);
    assert!(run["stage_seconds"]["encoder"].as_f64().unwrap() > 0.0);
    assert!(run["input_fingerprint"].as_str().unwrap().len() == 16);

    // metrics.json scores the refined frames against GT as the paper does, and the final frames as a second
    // row (PSNR/SSIM always; the networks when their weights are installed). PSNR checked against the saved
    // PNGs' 8-bit levels directly.
    let scores: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    let mean_psnr = |frames: &str| {
        let per: Vec<f64> = (0..8)
            .map(|k| {
                let (a, b) = (png(&out.join(format!("frames/{frames}/{k:04}.png"))), png(&out.join(format!("frames/gt/{k:04}.png"))));
                let se: f64 = a.as_raw().iter().zip(b.as_raw()).map(|(&x, &y)| ((x as f64 - y as f64) / 255.0).powi(2)).sum();
                -10.0 * (se / a.as_raw().len() as f64).log10()
            })
            .collect();
        per.iter().sum::<f64>() / 8.0
    };
    for (row, frames) in [(&scores, "refined"), (&scores["final"], "final")] {
        assert_eq!(row["frames"], frames);
        assert_eq!(row["per_image"].as_array().unwrap().len(), 8);
        assert_eq!(row["fid_variant"], "pytorch-fid");
        let psnr = row["psnr"].as_f64().unwrap();
        let want = mean_psnr(frames);
        assert!((psnr - want).abs() < 1e-6 * want, "{frames}: psnr {psnr}, from the PNGs {want}");
    }
    assert_ne!(scores["psnr"], scores["final"]["psnr"], "the two rows score different frames");

    // Videos: one H.264 track with one sample per frame at the frame size (compare = three frames wide).
    for (name, w) in [("video.mp4", 128), ("compare.mp4", 3 * 128)] {
        let (frames, width, height) = mp4_info(&out.join(name));
        assert_eq!((frames, width, height), (8, w, 64), "{name}");
    }

    // The .ply reproduces the 3DGS renders (float images).
    let eg = mvsplat360_splat::io::read_ply(&out.join("gaussians.ply")).unwrap();
    assert_eq!(eg.len(), 4 * 128 * 64);
    assert!(out.join("gaussians.splat").is_file());
    let g = eg.to_gaussians(4, &Device::Cpu).unwrap();
    let spec = model::read_model_dir(&m).unwrap();
    let cam0 = pre.camera(&scene.cameras[sorted[0]]).unwrap();
    let from_ply =
        mvsplat360_splat::op::render(&g, &mvsplat360_splat::camera::RasterCamera::from_camera(&cam0, spec.encoder.near, spec.encoder.far), &Default::default())
            .unwrap();
    // Re-run the encoder in memory for the reference render.
    let req = request(&m, &out, TargetSpec::Views(vec![sorted[0]]));
    let p = render::prepare(&req, &Silent).unwrap();
    let gm = render::encode(&p, &Silent).unwrap();
    let mem = mvsplat360_splat::op::render(
        &gm,
        &mvsplat360_splat::camera::RasterCamera::from_camera(&p.target_cameras[0], spec.encoder.near, spec.encoder.far),
        &Default::default(),
    )
    .unwrap();
    let d = (&from_ply.rgb - &mem.rgb).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
    assert!(d <= 1e-5, ".ply render differs from the in-memory render by {d}");
    let any: f32 = mem.rgb.abs().unwrap().max_all().unwrap().to_scalar().unwrap();
    assert!(any > 0.0, "render is blank");
    assert!(walk(&out).iter().all(|p| !p.to_string_lossy().ends_with(".partial")));
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut v = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            v.extend(walk(&p));
        } else {
            v.push(p);
        }
    }
    v
}

/// (sample count, width, height) of the only video track.
fn mp4_info(path: &Path) -> (usize, u32, u32) {
    let f = std::fs::File::open(path).unwrap();
    let size = f.metadata().unwrap().len();
    let r = mp4::Mp4Reader::read_header(std::io::BufReader::new(f), size).unwrap();
    let tracks: Vec<_> = r.tracks().values().collect();
    assert_eq!(tracks.len(), 1, "{}", path.display());
    let t = tracks[0];
    (t.sample_count() as usize, t.width() as u32, t.height() as u32)
}

#[test]
fn refiner_none_and_orbit() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(tmp.path(), true);
    let out = tmp.path().join("out");
    let mut req = request(&m, &out, TargetSpec::Orbit(5));
    req.model.refiner = Some(RefinerArg::None);
    req.video = false;
    let s = render::run(&req, &Silent).unwrap();
    assert!(!s.refined);
    assert_eq!(s.frames, 5);
    assert!(!out.join("frames/refined").exists() && !out.join("frames/gt").exists());
    for i in 0..5 {
        let a = png(&out.join(format!("frames/gsplat/{i:04}.png")));
        let b = png(&out.join(format!("frames/final/{i:04}.png")));
        assert_eq!(a.as_raw(), b.as_raw(), "final = gsplat without a refiner");
    }
    // Video mode: 5 frames in one call, attention groups of 3 (padded to 6).
    let outv = tmp.path().join("outv");
    let mut req = request(&m, &outv, TargetSpec::Orbit(5));
    req.refine.video_mode = true;
    req.video = false;
    let s = render::run(&req, &Silent).unwrap();
    assert!(s.refined && s.frames == 5);
    assert!(outv.join("frames/refined/0004.png").is_file() && !outv.join("frames/refined/0005.png").exists());
    // A folder without a refiner part renders 3DGS only.
    let m3 = tiny_model(tmp.path(), false);
    let out3 = tmp.path().join("out3");
    let mut req = request(&m3, &out3, TargetSpec::Path(4));
    req.video = false;
    let s = render::run(&req, &Silent).unwrap();
    assert!(!s.refined && s.frames == 4);
}

#[test]
fn windows_pad_the_last_one() {
    assert_eq!(render::windows(8, 3), vec![(0, 3), (3, 3), (6, 2)]);
    assert_eq!(render::windows(56, 14), vec![(0, 14), (14, 14), (28, 14), (42, 14)]);
    assert_eq!(render::windows(5, 14), vec![(0, 5)]);
}

/// A model folder's `fit` runs by default, `--fit-steps 0` turns it off (then the frames are the encoder's
/// Gaussians' renders, as for a folder without `fit`), and bad settings are refused naming the file and key.
#[test]
fn model_fit_settings_default_override_and_validation() {
    let tmp = tempfile::tempdir().unwrap();
    let plain = tiny_model(tmp.path(), false);
    let fitted = tmp.path().join("fitted");
    std::fs::create_dir_all(&fitted).unwrap();
    std::fs::copy(plain.join("model.safetensors"), fitted.join("model.safetensors")).unwrap();
    let mut cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(plain.join("config.json")).unwrap()).unwrap();
    cfg["fit"] = serde_json::json!({"steps": 3, "lr": 0.05, "self_weight": 1.0});
    std::fs::write(fitted.join("config.json"), cfg.to_string()).unwrap();
    let run = |m: &Path, name: &str, steps: Option<usize>| {
        let out = tmp.path().join(name);
        let mut req = request(m, &out, TargetSpec::Views(vec![3]));
        req.video = false;
        req.model.fit_steps = steps;
        render::run(&req, &Silent).unwrap();
        let j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
        (png(&out.join("frames/gsplat/0000.png")), j["settings"]["fit_loss"].clone())
    };
    let (base, none) = run(&plain, "plain", None);
    assert!(none.is_null());
    let (with_fit, losses) = run(&fitted, "fitted", None);
    let l: Vec<f64> = losses.as_array().expect("fit ran").iter().map(|x| x.as_f64().unwrap()).collect();
    assert!(l.len() == 2 && l.iter().all(|x| x.is_finite()), "{losses}");
    assert_ne!(base.as_raw(), with_fit.as_raw(), "3 fitting steps change the render");
    let (off, none) = run(&fitted, "off", Some(0));
    assert!(none.is_null());
    assert_eq!(base.as_raw(), off.as_raw(), "--fit-steps 0 renders the encoder's Gaussians");

    cfg["fit"] = serde_json::json!({"steps": 3, "lr": -1.0});
    std::fs::write(fitted.join("config.json"), cfg.to_string()).unwrap();
    let e = model::read_model_dir(&fitted).unwrap_err().to_string();
    assert!(e.contains("config.json") && e.contains("fit.lr"), "{e}");
    cfg["fit"] = serde_json::json!({"steps": 3, "min_alpha": 1.5});
    std::fs::write(fitted.join("config.json"), cfg.to_string()).unwrap();
    let e = model::read_model_dir(&fitted).unwrap_err().to_string();
    assert!(e.contains("config.json") && e.contains("fit.min_alpha"), "{e}");
    cfg["fit"] = serde_json::json!({"step": 3});
    std::fs::write(fitted.join("config.json"), cfg.to_string()).unwrap();
    let e = model::read_model_dir(&fitted).unwrap_err().to_string();
    assert!(e.contains("config.json") && e.contains("step"), "{e}");
}

/// Views of mixed sizes: each is preprocessed to the model's size on its own (and undistorted first, as
/// `Scene::image` does), while `--size native`, which would batch them at their own sizes, is refused naming them.
#[test]
fn mixed_sizes_and_lens_distortion_before_preprocessing() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(tmp.path(), false);
    let d = tmp.path().join("scene");
    std::fs::create_dir_all(&d).unwrap();
    let mut frames = Vec::new();
    for (i, (name, w, h)) in [("a.png", 160u32, 96u32), ("b.png", 96, 160), ("c.png", 160, 96)].into_iter().enumerate() {
        image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 255 / w) as u8, (y * 255 / h) as u8, ((x + y) % 256) as u8])).save(d.join(name)).unwrap();
        frames.push(format!(r#"{{"file_path": "{name}", "transform_matrix": [[1,0,0,{}],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}"#, i as f64 * 0.3));
    }
    std::fs::write(d.join("transforms.json"), format!(r#"{{"fl_x": 120, "k1": -0.05, "p1": 0.002, "frames": [{}]}}"#, frames.join(", "))).unwrap();
    let mut req = request(&m, &tmp.path().join("out"), TargetSpec::Views(vec![2]));
    req.scene = d.clone();
    req.context = ContextSpec::Views(vec![0, 1]);
    req.size = Some(InputSize::Native);
    let e = render::prepare(&req, &Silent).err().expect("native with mixed sizes must be refused").to_string();
    for needle in ["--size", "a.png is 160x96 (and 1 more)", "b.png is 96x160"] {
        assert!(e.contains(needle), "expected `{needle}` in `{e}`");
    }
    req.size = None;
    let p = render::prepare(&req, &Silent).unwrap();
    let sizes: Vec<(u32, u32)> = p.context_images.iter().chain(p.target_photos.iter().flatten()).map(|im| (im.width, im.height)).collect();
    assert_eq!(sizes, vec![(128, 64); 3]);
    // The context photo is the undistorted photo, preprocessed.
    let scene = mvsplat360_dataset::read_scene(&d).unwrap();
    let lens = scene.lens(1).copied().expect("the views carry the distortion");
    let raw = mvsplat360_dataset::ImageSource::File(d.join("b.png")).decode().unwrap();
    let want = p.pre.view(&mvsplat360_dataset::lens::undistort(&raw, &scene.cameras[1], &lens), &scene.cameras[1]).unwrap().0;
    assert_eq!(p.context_images[1], want);
    assert_ne!(p.context_images[1], p.pre.view(&raw, &scene.cameras[1]).unwrap().0, "the distortion is not a no-op here");
}
