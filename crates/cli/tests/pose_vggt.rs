//! `mvsplat360 pose --engine vggt` as a user runs it, with a tiny random VGGT model folder (a reduced config,
//! same code paths) on five photos of the bundled scene: a scene folder that `inspect`, `render` and the COLMAP
//! reader take, cameras as pose.json records them; `--engine auto` and `render PHOTOS` take the same way. Bad
//! inputs each give one clear error and write nothing: one photo, a non-image, weights of another shape, no
//! weights, a video.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use candle_core::{Device, Tensor};
use mvsplat360_vggt::config::{CameraHeadConfig, DptConfig};
use mvsplat360_vggt::utils::pose_enc::pose_encoding_to_extri_intri;
use mvsplat360_vggt::{Vggt, VggtConfig};

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_mvsplat360"));
    c.env("RAYON_NUM_THREADS", "2");
    c
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The fixtures' reduced config (crates/vggt/tests/fixtures/model/README.md) with another width if asked.
fn tiny_config(embed_dim: usize) -> VggtConfig {
    VggtConfig {
        img_size: 70,
        embed_dim,
        depth: 4,
        num_heads: 2,
        patch_embed_depth: 2,
        patch_embed_num_heads: 2,
        camera_head: CameraHeadConfig { trunk_depth: 2, num_heads: 2, ..CameraHeadConfig::default() },
        dpt: DptConfig { features: 8, out_channels: [4, 8, 16, 16], intermediate_layer_idx: [0, 1, 2, 3], ..DptConfig::default() },
        ..VggtConfig::default()
    }
}

/// A VGGT model folder with seeded random weights of `weights_dim` and a config.json of `config_dim`.
fn tiny_vggt(dir: &Path, weights_dim: usize, config_dim: usize) -> PathBuf {
    let dev = Device::Cpu;
    let cfg = tiny_config(weights_dim);
    let mut t = mvsplat360_dataset::weights::random_tensors(7, &dev, |vb| Vggt::new(vb, &cfg)).unwrap();
    // The FoV (rows 7, 8 of the pose branch's last layer, summed over the 4 refinements, then a ReLU) of random
    // weights lands anywhere; keep it near 1 rad, varying a little per view, so the focal lengths are finite.
    let (wk, bk) = ("camera_head.pose_branch.fc2.weight", "camera_head.pose_branch.fc2.bias");
    let (rows, cols) = t[wk].dims2().unwrap();
    let mut wv = t[wk].flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let mut bv = t[bk].to_vec1::<f32>().unwrap();
    for r in [7, 8] {
        wv[r * cols..(r + 1) * cols].iter_mut().for_each(|v| *v *= 0.05);
        bv[r] = 0.25;
    }
    t.insert(wk.into(), Tensor::from_vec(wv, (rows, cols), &dev).unwrap());
    t.insert(bk.into(), Tensor::new(bv, &dev).unwrap());
    std::fs::create_dir_all(dir).unwrap();
    candle_core::safetensors::save(&t, dir.join("model.safetensors")).unwrap();
    std::fs::write(dir.join("config.json"), serde_json::to_string_pretty(&tiny_config(config_dim)).unwrap()).unwrap();
    dir.to_path_buf()
}

/// Five photos of the bundled scene, spread around it.
fn photos(dir: &Path, n: usize) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    for k in 0..n {
        let f = format!("{:03}.jpg", k * 5);
        std::fs::copy(root().join("assets/woodbox/images").join(&f), dir.join(&f)).unwrap();
    }
    dir.to_path_buf()
}

fn ok(o: Output) -> Output {
    assert!(o.status.success(), "exit {:?}\n{}", o.status.code(), String::from_utf8_lossy(&o.stderr));
    o
}

fn entries(dir: &Path) -> BTreeSet<String> {
    std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect()
}

/// Non-zero exit, one `error:` line (the message may span lines) holding every `expect`ed text, and nothing
/// new in `parent` (no scene, no hidden work folder).
fn refused(parent: &Path, args: &[&std::ffi::OsStr], expect: &[&str]) -> String {
    let before = entries(parent);
    let o = bin().args(args).output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert_eq!(stderr.matches("error:").count(), 1, "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    for e in expect {
        assert!(stderr.contains(e), "expected {e:?} in:\n{stderr}");
    }
    assert_eq!(entries(parent), before, "something was written: {stderr}");
    stderr
}

#[test]
fn vggt_poses_five_photos_into_a_scene_that_inspect_and_render_read() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tiny_vggt(&tmp.path().join("tiny"), 16, 16);
    let photos = photos(&tmp.path().join("photos"), 5);
    let scene = tmp.path().join("scene");
    let o = ok(bin()
        .args(["--quiet", "pose"])
        .arg(&photos)
        .args(["--engine", "vggt", "--vggt-weights"])
        .arg(&weights)
        .arg("--out")
        .arg(&scene)
        .arg("--json")
        .output()
        .unwrap());
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let on_disk: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(scene.join("pose.json")).unwrap()).unwrap();
    assert_eq!(report, on_disk);
    assert_eq!(report["engine"], "vggt");
    assert_eq!(report["settings"]["preprocessing"], "crop");
    // 448×256 photos: width 518, height round(256·518/448/14)·14 = 294, no crop.
    assert_eq!((report["model_input"]["width"].as_u64(), report["model_input"]["height"].as_u64()), (Some(518), Some(294)));
    assert_eq!(report["weights"]["sha256"].as_str().unwrap(), mvsplat360_dataset::atomic::sha256_file(&weights.join("model.safetensors")).unwrap());
    assert_eq!(report["weights"]["config"]["embed_dim"], 16);
    let notes = report["notes"].to_string();
    assert!(notes.contains("first camera as predicted") && notes.contains("normalised units"), "{notes}");
    let stages: Vec<&str> = report["seconds"]["stages"].as_array().unwrap().iter().map(|s| s[0].as_str().unwrap()).collect();
    assert_eq!(stages, ["fingerprint", "preprocess", "load", "forward", "write"]);
    let views = report["views"].as_array().unwrap();
    assert_eq!(views.len(), 5);
    assert!(!scene.with_file_name(".scene.pose-").exists() && entries(tmp.path()).iter().all(|e| !e.starts_with('.')));

    // The COLMAP model reads back: one PINHOLE camera per image, the cameras pose.json's encodings give.
    let s = mvsplat360_dataset::colmap::read(&scene).unwrap();
    assert_eq!(s.cameras.len(), 5);
    for (k, (c, rec)) in s.cameras.iter().zip(views).enumerate() {
        assert_eq!(s.view_names[k], rec["file"].as_str().unwrap());
        assert_eq!(rec["source"], format!("{:03}.jpg", k * 5));
        assert_eq!((rec["kept_size"][0].as_u64(), rec["kept_size"][1].as_u64()), (Some(448), Some(256)));
        let img = image::open(scene.join("images").join(rec["file"].as_str().unwrap())).unwrap();
        assert_eq!((img.width(), img.height()), (448, 256));
        let enc: Vec<f32> = rec["pose_encoding"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect();
        let cam = pose_encoding_to_extri_intri(&enc.try_into().unwrap(), 294, 518);
        let c2w = cam.cam_to_world();
        let worst = (0..12).map(|k| (c.c2w[k / 4][k % 4] - c2w[k / 4][k % 4]).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-9, "view {k}: c2w read back {:?}, from the pose encoding {:?}", c.c2w, c2w);
        // Model frame 518×294 → the 448×256 photo: a pure scale (no crop), centred principal point.
        let (sx, sy) = (448.0 / 518.0, 256.0 / 294.0);
        assert!((c.fx - cam.intrinsic[0][0] * sx).abs() < 1e-9 && (c.fy - cam.intrinsic[1][1] * sy).abs() < 1e-9);
        assert!((c.cx - 224.0).abs() < 1e-9 && (c.cy - 128.0).abs() < 1e-9, "principal point ({}, {})", c.cx, c.cy);
        assert!(rec["mean_depth_confidence"].as_f64().unwrap() >= 1.0);
    }
    let points = std::fs::read(scene.join("sparse/0/points3D.bin")).unwrap();
    let n = u64::from_le_bytes(points[..8].try_into().unwrap());
    assert_eq!(n, report["points"]["count"].as_u64().unwrap());
    assert!(n > 1000 && n <= 100_000, "{n} points");

    ok(bin().arg("inspect").arg(&scene).output().unwrap());
    // The same input and weights again: reused, not posed again.
    let o = ok(bin().arg("pose").arg(&photos).args(["--engine", "vggt", "--vggt-weights"]).arg(&weights).arg("--out").arg(&scene).output().unwrap());
    assert!(String::from_utf8_lossy(&o.stderr).contains("reusing"), "{}", String::from_utf8_lossy(&o.stderr));

    // `render` reads the scene (the shipped model, encoder only, two frames) ...
    let quick = ["--num-context", "5", "--targets", "1,3", "--fit-steps", "0", "--no-blend", "--no-video", "--no-metrics"];
    let out = tmp.path().join("render");
    ok(bin().args(["--quiet", "render"]).arg(&scene).args(quick).arg("--out").arg(&out).output().unwrap());
    for i in 0..2 {
        assert!(out.join(format!("frames/final/{i:04}.png")).is_file());
    }
    // ... and poses the photo folder the same way by itself: `auto`, 5 photos and weights → VGGT.
    let out2 = tmp.path().join("render2");
    let o = ok(bin().arg("render").arg(&photos).args(quick).arg("--vggt-weights").arg(&weights).arg("--out").arg(&out2).output().unwrap());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("auto: 5 photos (fewer than 20) and --vggt-weights → VGGT"), "{stderr}");
    let again: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out2.join("scene/pose.json")).unwrap()).unwrap();
    assert_eq!(again["fingerprint"], report["fingerprint"]);
    assert_eq!(again["views"], report["views"], "the same photos and weights gave other predictions");
    assert!(out2.join("frames/final/0001.png").is_file());
}

#[test]
fn bad_inputs_give_one_clear_error_and_write_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let weights = tiny_vggt(&t.join("tiny"), 16, 16);
    let good = photos(&t.join("good"), 5);
    let out = t.join("scene");
    let pose = |input: &Path, extra: &[&str]| -> Vec<std::ffi::OsString> {
        let mut a: Vec<std::ffi::OsString> = vec!["pose".into(), input.into()];
        a.extend(extra.iter().map(Into::into));
        a.extend(["--out".into(), out.clone().into_os_string()]);
        a
    };
    let run = |args: Vec<std::ffi::OsString>, expect: &[&str]| {
        let refs: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
        refused(t, &refs, expect)
    };
    let w = weights.to_str().unwrap();

    // One photo.
    let one = photos(&t.join("one"), 1);
    run(pose(&one, &["--engine", "vggt", "--vggt-weights", w]), &["holds 1 photo", "at least 2 views", "5 context views"]);

    // A file named like a photo that is not one: named.
    let bad = photos(&t.join("bad"), 4);
    std::fs::write(bad.join("photo.jpg"), b"this is not a JPEG").unwrap();
    run(pose(&bad, &["--engine", "vggt", "--vggt-weights", w]), &["photo.jpg", "cannot decode this photo"]);

    // Weights of another shape: a config 32 wide over 16-wide weights; the first mis-shaped keys are named.
    let wrong = tiny_vggt(&t.join("wrong"), 16, 32);
    let e = run(pose(&good, &["--engine", "vggt", "--vggt-weights", wrong.to_str().unwrap()]), &["model.safetensors", "shape mismatch `aggregator.", "more"]);
    assert!(e.lines().count() < 20, "the error lists every key:\n{e}");

    // No weights: where to get them and their licence.
    let help = ["huggingface.co/facebook/VGGT-1B", "CC BY-NC 4.0", "VGGT-1B-Commercial", "--vggt-weights"];
    run(pose(&good, &["--engine", "vggt"]), &help);
    let missing = t.join("nowhere/model.pt");
    let e = run(pose(&good, &["--engine", "vggt", "--vggt-weights", missing.to_str().unwrap()]), &help);
    assert!(e.contains("nowhere/model.pt"), "{e}");

    // A video is COLMAP's.
    let video = t.join("clip.mp4");
    std::fs::write(&video, b"not really a video").unwrap();
    run(pose(&video, &["--engine", "vggt", "--vggt-weights", w]), &["clip.mp4", "not a video", "--engine colmap"]);
}

/// `auto` on 20 or more photos runs COLMAP first; when COLMAP cannot pose them (here: 20 copies of one photo,
/// nothing to triangulate) VGGT takes over with weights, and COLMAP's message says how to get them without.
/// The photos are thin strips (518×28 for the model) so that 20 views stay quick. Needs Debian's colmap.
#[test]
fn auto_falls_back_to_vggt_when_colmap_cannot_pose_the_photos() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let weights = tiny_vggt(&t.join("tiny"), 16, 16);
    let same = t.join("same");
    std::fs::create_dir_all(&same).unwrap();
    let strip = image::open(root().join("assets/woodbox/images/000.jpg")).unwrap().crop_imm(0, 100, 448, 28).to_rgb8();
    for k in 0..20 {
        strip.save(same.join(format!("p{k:02}.png"))).unwrap();
    }
    let e = refused(t, &["pose".as_ref(), same.as_os_str(), "--out".as_ref(), t.join("a").as_os_str()], &["identical", "VGGT-1B", "CC BY-NC 4.0"]);
    assert!(e.contains("auto: 20 photos, no --vggt-weights → COLMAP"), "{e}");
    let scene = t.join("b");
    let o = ok(bin().arg("pose").arg(&same).arg("--vggt-weights").arg(&weights).arg("--out").arg(&scene).output().unwrap());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("20 or more) → COLMAP, VGGT if COLMAP cannot pose them") && stderr.contains("falling back to VGGT"), "{stderr}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(scene.join("pose.json")).unwrap()).unwrap();
    assert_eq!(r["engine"], "vggt");
    assert_eq!((r["model_input"]["width"].as_u64(), r["model_input"]["height"].as_u64(), r["views"].as_array().unwrap().len()), (Some(518), Some(28), 20));
    assert!(entries(t).iter().all(|e| !e.starts_with('.')), "a work folder was left: {:?}", entries(t));
}

/// `pose --encoder-dtype bf16` runs VGGT's packed trunk: pose.json says so, its fingerprint is not f32's (so an
/// f32 scene folder is not taken for it), and its pose encodings lie within the VGGT parity bound of f32's
/// (relative RMS ≤ 0.05, as `crates/vggt/tests/parity.rs` holds bf16 to the official f32 outputs) yet differ.
#[test]
fn vggt_poses_in_bf16_and_records_it() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tiny_vggt(&tmp.path().join("tiny"), 16, 16);
    let photos = photos(&tmp.path().join("photos"), 5);
    let pose = |dtype: &str, out: &Path| {
        ok(bin()
            .args(["--quiet", "pose"])
            .arg(&photos)
            .args(["--engine", "vggt", "--encoder-dtype", dtype, "--vggt-weights"])
            .arg(&weights)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap());
        serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(out.join("pose.json")).unwrap()).unwrap()
    };
    let (a, b) = (tmp.path().join("f32"), tmp.path().join("bf16"));
    let (f, h) = (pose("f32", &a), pose("bf16", &b));
    assert_eq!((f["settings"]["dtype"].as_str(), h["settings"]["dtype"].as_str()), (Some("f32"), Some("bf16")));
    assert_ne!(f["fingerprint"], h["fingerprint"]);
    let enc = |r: &serde_json::Value| -> Vec<f64> {
        r["views"]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|v| v["pose_encoding"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect::<Vec<_>>())
            .collect()
    };
    let (ef, eh) = (enc(&f), enc(&h));
    assert_eq!(ef.len(), 5 * 9);
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
    let diff: Vec<f64> = ef.iter().zip(&eh).map(|(x, y)| x - y).collect();
    let rel = rms(&diff) / rms(&ef);
    eprintln!("bf16 vs f32 pose encodings: relative RMS {rel:.2e}");
    assert!(rel > 0.0 && rel <= 0.05, "relative RMS {rel:.2e}");
    // The f32 folder is not reused for a bf16 run: it is refused, named, and left as it was.
    let before = std::fs::read(a.join("pose.json")).unwrap();
    let msg = refused(
        tmp.path(),
        &[
            "pose".as_ref(),
            photos.as_os_str(),
            "--engine".as_ref(),
            "vggt".as_ref(),
            "--encoder-dtype".as_ref(),
            "bf16".as_ref(),
            "--vggt-weights".as_ref(),
            weights.as_os_str(),
            "--out".as_ref(),
            a.as_os_str(),
        ],
        &["already exists", "settings"],
    );
    assert!(msg.contains(&*a.to_string_lossy()), "{msg}");
    assert_eq!(std::fs::read(a.join("pose.json")).unwrap(), before);
}
