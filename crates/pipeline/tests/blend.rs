//! The learned blender: its inputs against a closed form (linear photos sampled at points projected by
//! `Camera::project`), its untrained head against the softmax it starts as, and a model folder with a `blend`
//! key through `render` (on by default, `--no-blend` gives the plain 3DGS frames, bad settings name the file).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use mvsplat360_camera::Camera;
use mvsplat360_pipeline::blend::{candidates, BlendNet, BlendSettings, PREFIX};
use mvsplat360_pipeline::model::{self, ModelArgs};
use mvsplat360_pipeline::render::{self, RefineSettings, RenderRequest, Silent};
use mvsplat360_pipeline::views::{ContextSpec, TargetSpec};
use nalgebra::{Rotation3, Vector3};

fn cam(yaw_deg: f64, t: [f64; 3]) -> Camera {
    let r = Rotation3::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians());
    let mut c2w = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            c2w[i][j] = r[(i, j)];
        }
        c2w[i][3] = t[i];
    }
    c2w[3][3] = 1.0;
    Camera { fx: 20.0, fy: 20.0, cx: 16.0, cy: 8.0, width: 32, height: 16, c2w }
}

/// A photo whose channels are linear in the pixel index coordinates, so that bilinear sampling is exact inside.
fn linear(a: [f32; 3], bx: f32, by: f32) -> (Vec<f32>, impl Fn(usize, f64, f64) -> f64) {
    let (w, h) = (32usize, 16usize);
    let mut img = vec![0f32; 3 * w * h];
    for c in 0..3 {
        for y in 0..h {
            for x in 0..w {
                img[c * w * h + y * w + x] = a[c] + bx * x as f32 + by * y as f32;
            }
        }
    }
    (img, move |c: usize, x: f64, y: f64| a[c] as f64 + bx as f64 * x + by as f64 * y)
}

#[test]
fn candidates_sample_the_context_photos_at_the_lifted_points() {
    let s = BlendSettings { planes: 3, span: 1.5, views: 2, width: 4 };
    let (w, h) = (32usize, 16usize);
    let target = cam(0.0, [0.0, 0.0, 0.0]);
    // Context 0 is farther from the target than context 1, so the sampled order is 1, then 0.
    let context = vec![cam(-20.0, [2.0, 0.0, 0.5]), cam(8.0, [-0.6, 0.1, 0.0])];
    let (p0, f0) = linear([0.2, 0.5, 0.1], 0.01, 0.02);
    let (p1, f1) = linear([0.7, 0.1, 0.3], -0.005, 0.03);
    let rgb: Vec<f32> = (0..3 * w * h).map(|i| (i % 97) as f32 / 97.0).collect();
    let (near, far) = (1.0, 50.0);
    // Opacity 0.8 at rendered z 4 (the rasterizer's depth is Σ w·z = 3.2), except a band at 0.3 (sweep near…far).
    let alpha: Vec<f32> = (0..w * h).map(|i| if (i / w) == 5 { 0.3 } else { 0.8 }).collect();
    let depth: Vec<f32> = alpha.iter().map(|&a| a * 4.0).collect();
    let x = candidates(&s, &target, &rgb, &alpha, &depth, &context, &[&p0, &p1], near, far);
    assert_eq!(x.len(), s.channels() * w * h);
    assert_eq!(&x[..3 * w * h], &rgb[..]);
    assert_eq!(&x[3 * w * h..4 * w * h], &alpha[..]);
    let (mut inside, mut fallback) = (0, 0);
    for (j, (v, photo)) in [(&context[1], &f1), (&context[0], &f0)].into_iter().enumerate() {
        for k in 0..s.planes {
            let t = 2.0 * k as f64 / (s.planes - 1) as f64 - 1.0;
            for py in 0..h {
                for px in 0..w {
                    let i = py * w + px;
                    let z = if alpha[i] >= 0.5 { 4.0 * 1.5f64.powf(t) } else { near * (far / near).powf((t + 1.0) / 2.0) };
                    let xc = Vector3::new((px as f64 + 0.5 - 16.0) / 20.0 * z, (py as f64 + 0.5 - 8.0) / 20.0 * z, z);
                    let (u, vv, zc) = v.project(&(target.rotation() * xc + target.center()));
                    for c in 0..3 {
                        let got = x[(4 + 3 * (j * s.planes + k) + c) * w * h + i] as f64;
                        if zc <= 0.0 || u < 0.0 || vv < 0.0 || u >= w as f64 || vv >= h as f64 {
                            assert_eq!(got, rgb[c * w * h + i] as f64, "view {j} plane {k} pixel {px},{py}: outside → the render");
                            fallback += 1;
                        } else if (0.5..=w as f64 - 0.5).contains(&u) && (0.5..=h as f64 - 0.5).contains(&vv) {
                            let want = photo(c, u - 0.5, vv - 0.5);
                            assert!((got - want).abs() < 1e-4, "view {j} plane {k} pixel {px},{py} channel {c}: {got} vs {want}");
                            inside += 1;
                        }
                    }
                }
            }
        }
    }
    // Both branches are exercised, most pixels inside.
    assert!(inside > 3 * 2 * 3 * w * h / 3 && fallback > 100, "inside {inside}, fallback {fallback}");
}

#[test]
fn untrained_head_starts_as_a_softmax_that_favours_the_render() {
    let s = BlendSettings { planes: 2, span: 1.3, views: 2, width: 6 };
    let vm = VarMap::new();
    let net = BlendNet::new(VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu).pp(PREFIX), &s).unwrap();
    for (k, v) in vm.data().lock().unwrap().iter() {
        assert!(k.starts_with("blend."), "{k}");
        if k.starts_with("blend.out.") {
            v.set(&v.zeros_like().unwrap()).unwrap();
        }
    }
    let (n, h, w) = (2, 8, 12);
    let x = Tensor::rand(0f32, 1f32, (n, s.channels(), h, w), &Device::Cpu).unwrap();
    let y: Vec<f32> = net.forward(&x).unwrap().flatten_all().unwrap().to_vec1().unwrap();
    let xv: Vec<f32> = x.flatten_all().unwrap().to_vec1().unwrap();
    // Zero logits plus the render's +2: weights e²/(e² + 4) for the render, 1/(e² + 4) for each of 4 candidates.
    let e2 = 2f64.exp();
    let ch = s.channels();
    for b in 0..n {
        for c in 0..3 {
            for i in 0..h * w {
                let at = |chan: usize| xv[(b * ch + chan) * h * w + i] as f64;
                let want = (e2 * at(c) + (0..4).map(|q| at(4 + 3 * q + c)).sum::<f64>()) / (e2 + 4.0);
                let got = y[(b * 3 + c) * h * w + i] as f64;
                assert!((got - want).abs() < 1e-5, "{got} vs {want}");
            }
        }
    }
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn render_one(m: &Path, out: &Path, no_blend: bool) -> (Vec<u8>, serde_json::Value, Vec<u8>) {
    let req = RenderRequest {
        scene: root().join("assets/woodbox"),
        scene_key: None,
        context: ContextSpec::Views(vec![0, 6, 12, 18]),
        targets: TargetSpec::Views(vec![3]),
        model: ModelArgs { ckpt: Some(m.to_path_buf()), no_blend, ..Default::default() },
        size: None,
        scene_scale: Default::default(),
        refine: RefineSettings::default(),
        splat: false,
        metrics: false,
        fid_variant: Default::default(),
        weights_dir: None,
        video: false,
        fps: 8,
        out: out.to_path_buf(),
        resume: false,
    };
    render::run(&req, &Silent).unwrap();
    let j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    let f = image::open(out.join("frames/final/0000.png")).unwrap().to_rgb8().into_raw();
    // frames/gsplat always holds the rasterized Gaussians; frames/blended exists exactly when the blender ran.
    let gs = image::open(out.join("frames/gsplat/0000.png")).unwrap().to_rgb8().into_raw();
    let blended = out.join("frames/blended/0000.png");
    if j["settings"]["blend"].is_null() {
        assert!(!blended.exists());
        assert_eq!(f, gs);
    } else {
        assert_eq!(f, image::open(blended).unwrap().to_rgb8().into_raw());
    }
    (f, j, gs)
}

#[test]
fn model_folder_blend_on_by_default_off_with_no_blend() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = model::tiny_config(false);
    let mut sd = model::random_state_dict(&cfg, 3).unwrap();
    let plain = tmp.path().join("plain");
    model::write_model_dir(&plain, &cfg, &sd).unwrap();
    let s = BlendSettings { planes: 3, span: 1.5, views: 2, width: 4 };
    let vm = VarMap::new();
    BlendNet::new(VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu).pp(PREFIX), &s).unwrap();
    let blend: HashMap<String, Tensor> = vm.data().lock().unwrap().iter().map(|(k, v)| (k.clone(), v.as_tensor().clone())).collect();
    sd.extend(blend);
    let blended = tmp.path().join("blended");
    model::write_model_dir(&blended, &model::ModelConfig { blend: Some(s), ..cfg.clone() }, &sd).unwrap();

    let (base, j0, _) = render_one(&plain, &tmp.path().join("o-plain"), false);
    assert!(j0["settings"]["blend"].is_null());
    let (on, j1, on_gs) = render_one(&blended, &tmp.path().join("o-on"), false);
    assert_eq!(j1["settings"]["blend"]["planes"], 3, "{}", j1["settings"]);
    assert_ne!(base, on, "the blender changes the frame");
    assert_eq!(base, on_gs, "the rasterized frame is the same with and without the blender");
    let (off, _, _) = render_one(&blended, &tmp.path().join("o-off"), true);
    assert_eq!(base, off, "--no-blend gives the plain 3DGS frame");

    // A key that was measured and not adopted stops the run with its name, the study and the fix.
    for (section, key, study) in
        [("blend", "visibility", "visibility-blender.md"), ("fit", "size_lr_scale", "fit-size-factor.md"), ("fit", "sweep", "plane-sweep.md")]
    {
        let mut j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(blended.join("config.json")).unwrap()).unwrap();
        j[section][key] = serde_json::json!(0);
        let dir = tmp.path().join(format!("removed-{key}"));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("config.json"), j.to_string()).unwrap();
        std::fs::copy(blended.join("model.safetensors"), dir.join("model.safetensors")).unwrap();
        let e = model::read_model_dir(&dir).unwrap_err().to_string();
        assert!(e.contains("config.json") && e.contains(&format!("`{section}.{key}`")) && e.contains(study) && e.contains("delete the key"), "{e}");
    }

    // Bad settings and missing weights name the file and the part.
    let mut j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(blended.join("config.json")).unwrap()).unwrap();
    j["blend"]["planes"] = 0.into();
    std::fs::write(blended.join("config.json"), j.to_string()).unwrap();
    let e = model::read_model_dir(&blended).unwrap_err().to_string();
    assert!(e.contains("config.json") && e.contains("blend") && e.contains("planes"), "{e}");
    j["blend"]["planes"] = 3.into();
    std::fs::write(blended.join("config.json"), j.to_string()).unwrap();
    std::fs::copy(plain.join("model.safetensors"), blended.join("model.safetensors")).unwrap();
    let spec = model::read_model_dir(&blended).unwrap();
    let (bs, wf) = spec.blend.unwrap();
    let e = BlendNet::load(&wf, &bs, &Device::Cpu).err().expect("no blend weights").to_string();
    assert!(e.contains("model.safetensors") && e.contains("blend"), "{e}");
}
