//! `mvsplat360 train-blend` (`mvsplat360_train::blend`): its cached inputs are what `render` blends, the model
//! folder it writes renders with the trained blender, a resumed run ends where an uninterrupted one does, and
//! training lowers the loss.

use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use mvsplat360_pipeline::blend::{BlendNet, BlendSettings};
use mvsplat360_pipeline::model::{self, ModelArgs, RefinerArg};
use mvsplat360_pipeline::render::{self, Silent};
use mvsplat360_train::blend::{self, BlendLogRecord, BlendRequest, SceneSource};

/// A random tiny model folder (128×64, no refiner, no fitting).
fn tiny_model(dir: &Path) -> PathBuf {
    let cfg = model::tiny_config(false);
    let m = dir.join("tiny");
    model::write_model_dir(&m, &cfg, &model::random_state_dict(&cfg, 3).unwrap()).unwrap();
    m
}

fn request(model: &Path, out: &Path, steps: u64) -> BlendRequest {
    BlendRequest {
        model: model.to_path_buf(),
        fit_steps: Some(1),
        compute: Default::default(),
        train: vec![SceneSource::Procedural { first: 5, last: 5 }],
        val: vec![],
        layout: BlendSettings { planes: 3, views: 2, span: 1.6, width: 4 },
        steps,
        lr: 1e-2,
        batch: 2,
        seed: 9,
        every: 2,
        resume: false,
        stop_after: None,
        out: out.to_path_buf(),
    }
}

fn blend_weights(model_dir: &Path) -> Vec<(String, Vec<f32>)> {
    let mut v: Vec<(String, Vec<f32>)> = candle_core::safetensors::load(model_dir.join(model::MODEL_WEIGHTS), &Device::Cpu)
        .unwrap()
        .into_iter()
        .filter(|(k, _)| k.starts_with("blend."))
        .map(|(k, t)| (k, t.flatten_all().unwrap().to_vec1().unwrap()))
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

#[test]
fn cached_inputs_are_what_render_blends() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(tmp.path());
    let out = tmp.path().join("run");
    let req = request(&m, &out, 2);
    let s = blend::run(&req, &Silent).unwrap();
    let folder = s.model.expect("a finished run writes the model folder");
    assert_eq!((s.train_scenes, s.train_images), (1, 27), "32 views, 5 context, 27 targets");

    // `render`'s path on the written scene with the written folder, at the protocol's targets.
    let scene = out.join("procedural/proc-5");
    let model = ModelArgs { ckpt: Some(folder.clone()), refiner: Some(RefinerArg::None), fit_steps: Some(1), ..Default::default() };
    let p = mvsplat360_pipeline::eval_scenes::protocol_prepared(&scene, model, 5, None).unwrap();
    let g = render::encode(&p, &Silent).unwrap();
    let (g, _) = render::fit_to_context(&p, g, &Silent).unwrap();
    let frames = render::frames_3dgs(&p, &g, &Silent).unwrap();

    let cache = candle_core::safetensors::load(out.join("cache/train/proc-5.safetensors"), &Device::Cpu).unwrap();
    let (x, t) = (&cache["x"], &cache["target"]);
    assert_eq!(x.dims(), &[27, req.layout.channels(), 64, 128]);
    let (bs, wf) = model::read_model_dir(&folder).unwrap().blend.expect("the folder has the blender");
    assert_eq!(bs, req.layout);
    let net = BlendNet::load(&wf, &bs, &Device::Cpu).unwrap();
    // `render` clamps the blender's frames to [0, 1].
    let y = net.forward(x).unwrap().clamp(0f32, 1f32).unwrap();
    for (k, f) in frames.iter().enumerate() {
        let blended = f.blended.as_ref().expect("render blends with the written folder");
        let d = (blended - y.get(k).unwrap()).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(d < 1e-5, "target {k}: render's blended frame and the blender on the cached input differ by {d}");
        // The first three channels are the render, the targets the photos.
        let r = (f.rgb.clamp(0f32, 1f32).unwrap() - x.get(k).unwrap().narrow(0, 0, 3).unwrap()).unwrap().abs().unwrap().max_all().unwrap();
        assert!(r.to_scalar::<f32>().unwrap() < 1e-6);
        let photo = p.target_photos[k].as_ref().unwrap();
        let tp = Tensor::from_slice(&photo.data, (3, 64, 128), &Device::Cpu).unwrap();
        assert_eq!((tp - t.get(k).unwrap()).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap(), 0.0);
    }

    // Another layout into the same folder would mix inputs: refused, naming the file.
    let mut other = request(&m, &out, 2);
    other.layout.planes = 5;
    let e = blend::run(&other, &Silent).unwrap_err().to_string();
    assert!(e.contains("settings.json") && e.contains("another --out"), "{e}");
    // A validation scene that is also trained on is refused.
    let both = BlendRequest { val: vec![SceneSource::Procedural { first: 4, last: 5 }], ..request(&m, &tmp.path().join("both"), 2) };
    let e = blend::run(&both, &Silent).unwrap_err().to_string();
    assert!(e.contains("`proc-5` is both a training and a validation scene"), "{e}");
    // A finished run is not silently restarted.
    let e = blend::run(&request(&m, &out, 2), &Silent).unwrap_err().to_string();
    assert!(e.contains("--resume"), "{e}");
}

#[test]
fn resumed_run_ends_where_an_uninterrupted_one_does_and_the_loss_falls() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(tmp.path());
    let full = tmp.path().join("full");
    let s = blend::run(&request(&m, &full, 40), &Silent).unwrap();
    let want = blend_weights(&s.model.unwrap());

    let cut = tmp.path().join("cut");
    std::fs::create_dir_all(&cut).unwrap();
    // The inputs are the same; copying them keeps the test short.
    let copy = |rel: &str| {
        std::fs::create_dir_all(cut.join(rel).parent().unwrap()).unwrap();
        std::fs::copy(full.join(rel), cut.join(rel)).unwrap();
    };
    copy("cache/settings.json");
    copy("cache/train/proc-5.safetensors");
    copy("procedural/proc-5/transforms.json");
    let first = blend::run(&BlendRequest { stop_after: Some(17), ..request(&m, &cut, 40) }, &Silent).unwrap();
    assert!(first.model.is_none() && first.step == 17);
    let e = blend::run(&request(&m, &cut, 40), &Silent).unwrap_err().to_string();
    assert!(e.contains("--resume"), "{e}");
    let e = blend::run(&BlendRequest { resume: true, lr: 2e-2, ..request(&m, &cut, 40) }, &Silent).unwrap_err().to_string();
    assert!(e.contains("same flags"), "{e}");
    let s = blend::run(&BlendRequest { resume: true, ..request(&m, &cut, 40) }, &Silent).unwrap();
    assert_eq!(blend_weights(&s.model.unwrap()), want, "resumed at step 17 of 40: the weights differ from the uninterrupted run");

    // The loss: mean training MSE of the first two steps against the last two (the log's records).
    let log: Vec<BlendLogRecord> = std::fs::read_to_string(full.join("log.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(log.iter().map(|r| r.step).collect::<Vec<_>>(), (1..=20).map(|k| 2 * k).collect::<Vec<_>>());
    let (a, b) = (log[0].mse, log[log.len() - 1].mse);
    assert!(b < 0.8 * a, "training MSE {a} → {b}: the blender did not learn");
    // The resumed run's log has each step once.
    let cut_log: Vec<BlendLogRecord> = std::fs::read_to_string(cut.join("log.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let steps: Vec<u64> = cut_log.iter().map(|r| r.step).collect();
    assert_eq!(steps, [2, 4, 6, 8, 10, 12, 14, 16, 17, 18, 20, 22, 24, 26, 28, 30, 32, 34, 36, 38, 40]);
}

#[test]
fn scene_sources_parse_with_clear_errors() {
    assert_eq!("procedural:7".parse::<SceneSource>().unwrap(), SceneSource::Procedural { first: 7, last: 7 });
    assert_eq!("procedural:3-9".parse::<SceneSource>().unwrap(), SceneSource::Procedural { first: 3, last: 9 });
    assert_eq!("data/x".parse::<SceneSource>().unwrap(), SceneSource::Folder("data/x".into()));
    assert!("procedural:9-3".parse::<SceneSource>().unwrap_err().contains("below"));
    assert!("procedural:a".parse::<SceneSource>().unwrap_err().contains("procedural:FIRST-LAST"));
}
