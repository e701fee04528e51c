//! `mvsplat360 render` as a user runs it: the official-architecture encoder fixture with `--refiner none`,
//! bad inputs rejected before any heavy work (one message naming the file/view/flag, exit 1, nothing
//! written), and an interrupted run leaving only complete files.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &dst.join(e.file_name()));
        } else {
            std::fs::copy(&p, dst.join(e.file_name())).unwrap();
        }
    }
}

fn files(dir: &Path) -> Vec<PathBuf> {
    let mut v = Vec::new();
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                v.extend(files(&p));
            } else {
                v.push(p);
            }
        }
    }
    v
}

fn tiny_model(dir: &Path) -> PathBuf {
    let cfg = mvsplat360_pipeline::model::tiny_config(true);
    let sd = mvsplat360_pipeline::model::random_state_dict(&cfg, 5).unwrap();
    let m = dir.join("tiny");
    mvsplat360_pipeline::model::write_model_dir(&m, &cfg, &sd).unwrap();
    m
}

#[test]
fn render_with_encoder_fixture_and_no_refiner() {
    let enc = mvsplat360_testkit::fixture("encoder/state_dict.safetensors");
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let o = bin()
        .args(["--quiet", "render"])
        .arg(root().join("assets/woodbox"))
        .arg("--encoder")
        .arg(&enc)
        .args(["--refiner", "none", "--context", "0,6,12,18", "--targets", "3,9,15", "--size", "128x64", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for d in ["gsplat", "final", "gt"] {
        for i in 0..3 {
            let img = image::open(out.join(format!("frames/{d}/{i:04}.png"))).unwrap();
            assert_eq!((img.width(), img.height()), (128, 64));
        }
    }
    assert!(!out.join("frames/refined").exists());
    for f in ["gaussians.ply", "video.mp4", "compare.mp4", "cameras.json", "run.json"] {
        assert!(out.join(f).is_file(), "{f}");
    }
}

#[test]
fn no_model_anywhere_says_what_to_pass() {
    // Run from a folder without assets/: the default model is looked up relative to the working directory
    // and the build tree; the message must say what to pass either way.
    let tmp = tempfile::tempdir().unwrap();
    let o = bin().current_dir(tmp.path()).args(["render", "--refiner", "weights.safetensors"]).arg(root().join("assets/woodbox")).output().unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--encoder"), "{err}");
}

/// Each bad input: exit 1, one `error:` line naming the culprit, no output folder content.
#[test]
fn bad_inputs_fail_before_any_work() {
    let enc = mvsplat360_testkit::fixture("encoder/state_dict.safetensors");
    let tmp = tempfile::tempdir().unwrap();
    let good = root().join("assets/woodbox");
    let mk = |name: &str, edit: &dyn Fn(&Path)| -> PathBuf {
        let d = tmp.path().join(name);
        copy_dir(&good, &d);
        edit(&d);
        d
    };
    let truncated = mk("truncated", &|d| {
        let p = d.join("images/005.jpg");
        let b = std::fs::read(&p).unwrap();
        std::fs::write(&p, &b[..b.len() / 3]).unwrap();
    });
    let empty = mk("empty", &|d| std::fs::write(d.join("images/007.jpg"), b"").unwrap());
    let not_image = mk("notimage", &|d| std::fs::write(d.join("images/002.jpg"), b"hello, not a picture").unwrap());
    let wrong_size = mk("wrongsize", &|d| {
        image::RgbImage::new(100, 50).save_with_format(d.join("images/003.jpg"), image::ImageFormat::Jpeg).unwrap();
    });
    let bad_pose = mk("badpose", &|d| {
        let p = d.join("transforms.json");
        let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        // A scaled rotation: not a rigid pose.
        v["frames"][4]["transform_matrix"][0][0] = serde_json::json!(2.0);
        std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
    });
    let readonly = tmp.path().join("readonly");
    std::fs::create_dir_all(&readonly).unwrap();
    let file_as_out = tmp.path().join("a-file");
    std::fs::write(&file_as_out, b"x").unwrap();
    let base = |scene: &Path| -> Vec<std::ffi::OsString> {
        vec![scene.into(), "--encoder".into(), enc.clone().into(), "--refiner".into(), "none".into(), "--size".into(), "128x64".into()]
    };
    let with = |scene: &Path, extra: &[&str]| -> Vec<std::ffi::OsString> {
        let mut v = base(scene);
        v.extend(extra.iter().map(|s| s.into()));
        v
    };
    let cases: Vec<(Vec<std::ffi::OsString>, Vec<&str>)> = vec![
        (with(&truncated, &[]), vec!["005.jpg"]),
        (with(&empty, &[]), vec!["007.jpg"]),
        (with(&not_image, &[]), vec!["002.jpg"]),
        (with(&wrong_size, &[]), vec!["003", "100x50"]),
        (with(&bad_pose, &[]), vec!["004", "orthonormal"]),
        (with(&good, &["--context", "0,6,99"]), vec!["--context", "99"]),
        (with(&good, &["--context", "0,6,6"]), vec!["--context", "twice"]),
        (with(&good, &["--context", "3"]), vec!["--context", "at least 2"]),
        (with(&good, &["--num-context", "1"]), vec!["--num-context", "at least 2"]),
        (with(&good, &["--targets", "1,30"]), vec!["--targets", "30"]),
        (with(&good, &["--steps", "0", "--orbit", "0"]), vec!["--orbit"]),
        (with(&good, &["--fps", "0"]), vec!["--fps", "1..=1000"]),
    ];
    for (i, (args, needles)) in cases.iter().enumerate() {
        let out = tmp.path().join(format!("out{i}"));
        let o = bin().args(["--quiet", "render", "--out"]).arg(&out).args(args).output().unwrap();
        assert_eq!(o.status.code(), Some(1), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
        let err = String::from_utf8_lossy(&o.stderr);
        for n in needles {
            assert!(err.contains(n), "{args:?}: `{n}` not in: {err}");
        }
        assert!(!err.contains("panicked"), "{err}");
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
        assert!(files(&out).is_empty(), "{args:?} wrote {:?}", files(&out));
    }
    // Unwritable --out: a file where the folder should be, and a read-only folder (skipped as root, which
    // ignores permissions).
    let o = bin().args(["--quiet", "render", "--out"]).arg(&file_as_out).args(base(&good)).output().unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--out") && err.contains("a-file"), "{err}");
    // inspect runs the same image checks.
    for (scene, needle) in [(&truncated, "005.jpg"), (&empty, "007.jpg"), (&not_image, "002.jpg"), (&wrong_size, "100x50")] {
        let o = bin().arg("inspect").arg(scene).output().unwrap();
        assert_eq!(o.status.code(), Some(1), "inspect {}", scene.display());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(needle) && !err.contains("panicked"), "{err}");
    }
    let _ = readonly;
}

fn wait_for(dir: &Path, pred: impl Fn(&[PathBuf]) -> bool, limit: Duration) -> bool {
    let t = Instant::now();
    while t.elapsed() < limit {
        if pred(&files(dir)) {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    false
}

/// Ctrl-C mid-run: exit 130, no partial files, every file that is there is complete.
#[test]
fn interrupted_render_leaves_only_complete_files() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(tmp.path());
    for signal in ["-INT", "-KILL"] {
        let out = tmp.path().join(format!("out{signal}"));
        let mut child = bin()
            .args(["--quiet", "render"])
            .arg(root().join("assets/woodbox"))
            .arg("--ckpt")
            .arg(&m)
            .args(["--orbit", "400", "--steps", "2", "--num-context", "3", "--out"])
            .arg(&out)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // Kill while the 3DGS frames are being written.
        let started = wait_for(&out, |f| f.iter().filter(|p| p.to_string_lossy().contains("gsplat")).count() >= 5, Duration::from_secs(60));
        assert!(started, "render did not start writing frames");
        Command::new("kill").arg(signal).arg(child.id().to_string()).status().unwrap();
        let status = child.wait().unwrap();
        if signal == "-INT" {
            assert_eq!(status.code(), Some(130));
            assert!(files(&out).iter().all(|p| !p.to_string_lossy().ends_with(".partial")), "{:?}", files(&out));
        }
        // Everything not named *.partial is complete: PNGs decode, JSON parses, the .ply reads back.
        for p in files(&out) {
            let s = p.to_string_lossy().to_string();
            if s.ends_with(".partial") {
                continue;
            }
            if s.ends_with(".png") {
                image::open(&p).unwrap_or_else(|e| panic!("{s}: {e}"));
            } else if s.ends_with(".json") {
                let _: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap_or_else(|e| panic!("{s}: {e}"));
            } else if s.ends_with(".ply") {
                mvsplat360_splat::io::read_ply(&p).unwrap_or_else(|e| panic!("{s}: {e}"));
            }
        }
        assert!(!out.join("run.json").exists(), "run.json is written last");
    }
}

/// The bundled scene's photos and cameras, with every camera position multiplied by `scale`.
fn scaled_woodbox(dst: &Path, scale: f64) {
    std::fs::create_dir_all(dst).unwrap();
    copy_dir(&root().join("assets/woodbox/images"), &dst.join("images"));
    let mut t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(root().join("assets/woodbox/transforms.json")).unwrap()).unwrap();
    for f in t["frames"].as_array_mut().unwrap() {
        for r in 0..3 {
            let v = f["transform_matrix"][r][3].as_f64().unwrap();
            f["transform_matrix"][r][3] = serde_json::json!(v * scale);
        }
    }
    std::fs::write(dst.join("transforms.json"), serde_json::to_string(&t).unwrap()).unwrap();
}

fn mean_psnr(a: &Path, b: &Path, n: usize) -> f64 {
    let mut s = 0.0;
    for i in 0..n {
        let (x, y) = (image::open(a.join(format!("{i:04}.png"))).unwrap().to_rgb8(), image::open(b.join(format!("{i:04}.png"))).unwrap().to_rgb8());
        let se: f64 = x.as_raw().iter().zip(y.as_raw()).map(|(&p, &q)| ((p as f64 - q as f64) / 255.0).powi(2)).sum();
        s += -10.0 * (se / x.as_raw().len() as f64).max(1e-12).log10();
    }
    s / n as f64
}

/// The shipped model scales scenes by its config.json (`auto`): the bundled scene given in 5× larger units renders
/// (encoder and rasterizer) the frames of its own units (model-space cameras equal up to rounding: ≥ 40 dB between the two, where the
/// 8-bit frames of one run differ from the other's by at most a level here and there), and run.json says why;
/// `--scene-scale none` overrides it and the same scene, now ≈ 65 units away, comes out a different picture.
#[test]
fn the_model_folder_decides_the_scene_scale() {
    let tmp = tempfile::tempdir().unwrap();
    let (orig, big) = (tmp.path().join("orig"), tmp.path().join("big"));
    scaled_woodbox(&orig, 1.0);
    scaled_woodbox(&big, 5.0);
    let render = |scene: &Path, out: &str, extra: &[&str]| {
        let out = tmp.path().join(out);
        let o = bin()
            .env("RAYON_NUM_THREADS", "2")
            .args(["--quiet", "render"])
            .arg(scene)
            .args(["--context", "0,5,10,14,19", "--targets", "3,12", "--no-video", "--no-metrics"])
            .args(extra)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        out
    };
    // The encoder alone (the fit and the blender do not depend on the scale rule and cost most of the time).
    let fast = ["--fit-steps", "0", "--no-blend"];
    let (a, b) = (render(&orig, "a", &fast), render(&big, "b", &fast));
    let run: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(b.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["settings"]["scene_scale"], "Auto");
    assert_eq!(run["settings"]["scene_scale_source"], "the model's config.json");
    let same = mean_psnr(&a.join("frames/final"), &b.join("frames/final"), 2);
    println!("5x units, model's scaling: {same:.1} dB from the original units' frames");
    assert!(same >= 40.0, "5× units: {same:.1} dB from the original units' frames");
    let d = render(&big, "d", &[&fast[..], &["--scene-scale", "none"]].concat());
    let run: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["settings"]["scene_scale_source"], "--scene-scale");
    let other = mean_psnr(&a.join("frames/final"), &d.join("frames/final"), 2);
    println!("5x units, --scene-scale none: {other:.1} dB from the original units' frames");
    assert!(other < 30.0, "--scene-scale none on 5× units: {other:.1} dB from the original frames, expected a different picture");
}

/// Files outside `.render/` (the transaction's own folder), by relative path, with their bytes.
fn run_files(out: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    files(out)
        .into_iter()
        .filter_map(|p| {
            let rel = p.strip_prefix(out).unwrap().to_string_lossy().into_owned();
            (!rel.starts_with(".render")).then(|| (rel, std::fs::read(&p).unwrap()))
        })
        .collect()
}

/// A render killed (SIGKILL) during refinement leaves the previous render in `--out` byte for byte; `--resume`
/// keeps the refined windows it finished and gives the frames of an uninterrupted run; `run.json` lists every
/// file of the run with its SHA-256, and nothing else is there.
#[test]
fn a_killed_render_keeps_the_previous_one_and_resumes_to_the_same_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tiny_model(tmp.path());
    let (out, reference) = (tmp.path().join("out"), tmp.path().join("ref"));
    const WINDOWS: usize = 8;
    let render = |dir: &Path, seed: &str, extra: &[&str]| {
        let mut c = bin();
        c.arg("render").arg(root().join("assets/woodbox")).arg("--ckpt").arg(&m);
        c.args(["--orbit", "8", "--window", "1", "--steps", "2", "--num-context", "3", "--no-metrics", "--seed", seed, "--out"]).arg(dir).args(extra);
        c
    };
    let ok = |mut c: Command| {
        let o = c.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    ok(render(&out, "1", &["--no-video"]));
    let previous = run_files(&out);
    ok(render(&reference, "2", &[]));

    let mut child = render(&out, "2", &[]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
    let windows = out.join(".render/resume/windows");
    let count = || std::fs::read_dir(&windows).map(|d| d.flatten().filter(|e| e.path().extension().is_some_and(|x| x == "safetensors")).count()).unwrap_or(0);
    let t = Instant::now();
    while count() < 1 {
        assert!(t.elapsed() < Duration::from_secs(120), "no refined window was saved");
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let done = count();
    assert!(done < WINDOWS, "the render finished refining before the kill ({done} windows): nothing left to resume");
    assert!(run_files(&out) == previous, "the killed render changed the previous one");

    let said = ok(render(&out, "2", &["--resume"]));
    assert!(said.contains(&format!("keeping the {done} refined window(s)")), "{said}");
    let (got, want) = (run_files(&out), run_files(&reference));
    let frames = |m: &std::collections::BTreeMap<String, Vec<u8>>| {
        m.iter().filter(|(k, _)| k.starts_with("frames/")).map(|(k, v)| (k.clone(), v.clone())).collect::<Vec<_>>()
    };
    assert_eq!(frames(&got).len(), 3 * WINDOWS, "gsplat, refined and final frames");
    assert!(frames(&got) == frames(&want), "the resumed render's frames differ from an uninterrupted run's");
    assert_eq!(got["video.mp4"], want["video.mp4"]);
    // run.json names exactly the files there (the first render's are gone), each with its hash.
    let run: serde_json::Value = serde_json::from_slice(&got["run.json"]).unwrap();
    let listed = run["files"].as_object().unwrap();
    let present: Vec<&String> = got.keys().filter(|k| *k != "run.json").collect();
    assert_eq!(listed.keys().collect::<Vec<_>>(), present);
    for (k, h) in listed {
        assert_eq!(h.as_str().unwrap(), mvsplat360_dataset::atomic::sha256_file(&out.join(k)).unwrap(), "{k}");
    }
    assert!(!out.join(".render/resume").exists() && !out.join(".render/stage").exists());
}
