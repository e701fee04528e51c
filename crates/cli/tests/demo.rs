//! `mvsplat360 demo` (the README's first command) as a user runs it: the bundled scene with the shipped model,
//! a short orbit. What it must write (video, frames, Gaussians, cameras, run.json), the shipped model's fit
//! lowering its loss, `--encoder-dtype bf16` recorded in run.json, and a clear refusal of a device or precision
//! this build cannot use.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// `mvsplat360 demo ARGS --quiet --out TMP/demo` from the repository root: its output and folder.
fn demo(tmp: &Path, args: &[&str]) -> (Output, PathBuf) {
    let out = tmp.join("demo");
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let o = Command::new(env!("CARGO_BIN_EXE_mvsplat360")).current_dir(root).arg("demo").args(args).args(["--quiet", "--out"]).arg(&out).output().unwrap();
    (o, out)
}

#[test]
fn demo_renders_the_bundled_scene_with_the_shipped_model() {
    let tmp = tempfile::tempdir().unwrap();
    let (o, out) = demo(tmp.path(), &["--frames", "3"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "demo failed: {err}");
    for f in ["video.mp4", "gaussians.ply", "gaussians.splat", "cameras.json", "run.json", "frames/gsplat/0002.png", "frames/final/0002.png"] {
        assert!(out.join(f).is_file(), "demo did not write {f}: {err}");
    }
    let run: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["frames"], 3);
    assert_eq!((run["settings"]["encoder_dtype"].as_str(), run["settings"]["cpu_bf16"].as_str()), (Some("f32"), None));
    // 5 views of 128×64 pixel-aligned Gaussians (the shipped model's input size).
    assert_eq!(run["gaussians"], 5 * 128 * 64);
    let l = &run["settings"]["fit_loss"];
    let (before, after) = (l[0].as_f64().expect("the shipped model fits"), l[1].as_f64().unwrap());
    assert!(after < 0.5 * before, "fit loss {before} -> {after}");
    // A frame is an image of the scene, not a blank: its pixels vary.
    let img = image::open(out.join("frames/final/0000.png")).unwrap().to_rgb8();
    let px: Vec<f64> = img.as_raw().iter().map(|&v| v as f64).collect();
    let mean = px.iter().sum::<f64>() / px.len() as f64;
    let sd = (px.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / px.len() as f64).sqrt();
    assert!(sd > 10.0, "frame 0 is nearly flat (sd {sd:.1} levels)");
}

/// `--encoder-dtype bf16` runs the encoder on packed bf16 weights and run.json says so, with the path its
/// products took on this CPU; a precision the encoder has no path for is refused by the flag's name.
#[test]
fn demo_runs_the_encoder_in_bf16_and_records_it() {
    let tmp = tempfile::tempdir().unwrap();
    let (o, out) = demo(tmp.path(), &["--frames", "2", "--encoder-dtype", "bf16"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "demo failed: {err}");
    let run: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    let path = if mvsplat360_nn::bf16::hardware_dpbf16() { "avx512bf16" } else { "storage-only (no bf16 dot product on this CPU)" };
    assert_eq!((run["settings"]["encoder_dtype"].as_str(), run["settings"]["cpu_bf16"].as_str()), (Some("bf16"), Some(path)), "{run}");
    assert_eq!(run["settings"]["refiner_dtype"].as_str(), Some("f32"));
    assert!(out.join("frames/final/0001.png").is_file(), "{err}");

    let (o, out) = demo(&tmp.path().join("f16"), &["--encoder-dtype", "f16"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--encoder-dtype") && err.contains("f32 or bf16"), "{err}");
    assert!(!out.exists(), "a refused demo wrote its results");
}

/// The bf16 encoder's frames against the f32 encoder's on the demo's scene, model and orbit, before the
/// test-time fit: PSNR ≥ 35 dB on average and ≥ 30 dB on the worst frame (issue 73). After the fit no such
/// bound holds for any perturbation — one photo changed by 1/255 on 8×8 pixels moves the f32 frames by 73 dB
/// unfitted but 35 dB (worst 23 dB) fitted — so the fitted frames are compared with the held-out photos
/// instead (docs/research/fit-sensitivity.md). Measured 42.2 / 36.8 dB on 48 frames.
#[test]
fn bf16_encoder_frames_match_f32_before_the_fit() {
    let tmp = tempfile::tempdir().unwrap();
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let render = |dtype: &str| {
        let out = tmp.path().join(dtype);
        let o = Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
            .current_dir(&root)
            .args(["render", "assets/woodbox", "--orbit", "8", "--fit-steps", "0", "--encoder-dtype", dtype, "--quiet", "--out"])
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "render --encoder-dtype {dtype} failed: {}", String::from_utf8_lossy(&o.stderr));
        out
    };
    let (f32_out, bf16_out) = (render("f32"), render("bf16"));
    let psnr: Vec<f64> = (0..8)
        .map(|i| {
            let frame = |d: &Path| image::open(d.join(format!("frames/final/{i:04}.png"))).unwrap().to_rgb8().into_raw();
            let (a, b) = (frame(&f32_out), frame(&bf16_out));
            assert_eq!(a.len(), b.len());
            let mse = a.iter().zip(&b).map(|(&x, &y)| ((x as f64 - y as f64) / 255.0).powi(2)).sum::<f64>() / a.len() as f64;
            -10.0 * mse.max(1e-20).log10()
        })
        .collect();
    let mean = psnr.iter().sum::<f64>() / psnr.len() as f64;
    let worst = psnr.iter().cloned().fold(f64::INFINITY, f64::min);
    eprintln!("bf16 vs f32 encoder, unfitted frames: mean {mean:.1} dB, worst {worst:.1} dB ({psnr:.1?})");
    // Identical frames would mean the bf16 products never ran.
    assert!(mean >= 35.0 && worst >= 30.0 && worst < 100.0, "mean {mean:.1} dB, worst {worst:.1} dB: {psnr:.1?}");
}

#[cfg(not(feature = "cuda"))]
#[test]
fn demo_on_cuda_without_the_feature_says_how_to_build_it() {
    let tmp = tempfile::tempdir().unwrap();
    let (o, out) = demo(tmp.path(), &["--device", "cuda"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("--device") && err.contains("--features cuda"), "{err}");
    assert!(!out.join("run.json").exists(), "a refused demo wrote its results");
}
