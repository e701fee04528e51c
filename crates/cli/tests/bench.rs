//! `mvsplat360 bench` on tiny inputs: each subcommand prints one JSON line with the documented fields, and
//! `--threads` means what its help says (0 = all cores, N = N) for every bench. No timing is asserted, only that
//! the timing fields are non-negative numbers.

use std::process::Command;

use serde_json::Value;

fn cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}

/// Run `mvsplat360 bench <args>` and parse its one stdout line.
fn bench(args: &[&str]) -> Value {
    bench_env(args, &[])
}

fn bench_env(args: &[&str], env: &[(&str, &str)]) -> Value {
    let home = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
        .arg("bench")
        .args(args)
        .env_remove("MVSPLAT360_PROFILE")
        .envs(env.iter().copied())
        // No metric-network weights: keeps `bench metrics` to the closed-form metrics (and fast).
        .env("MVSPLAT360_METRIC_WEIGHTS", home.path())
        .env("HOME", home.path())
        .env_remove("RAYON_NUM_THREADS")
        .output()
        .unwrap();
    assert!(out.status.success(), "bench {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 1, "one JSON line expected, got {stdout:?}");
    serde_json::from_str(lines[0]).unwrap_or_else(|e| panic!("not JSON ({e}): {}", lines[0]))
}

fn time_field(v: &Value, key: &str) {
    let t = v[key].as_f64().unwrap_or_else(|| panic!("`{key}` is not a number in {v}"));
    assert!(t.is_finite() && t >= 0.0, "`{key}` = {t} in {v}");
}

#[test]
fn raster_fields_and_threads() {
    for (threads, want) in [("0", cores()), ("1", 1), ("2", 2)] {
        let v = bench(&["raster", "--gaussians", "3000", "--width", "48", "--height", "32", "--features", "3", "--runs", "1", "--threads", threads]);
        assert_eq!(v["bench"], "raster");
        assert_eq!(
            (v["gaussians"].as_u64(), v["width"].as_u64(), v["height"].as_u64(), v["features"].as_u64()),
            (Some(3000), Some(48), Some(32), Some(3)),
            "{v}"
        );
        time_field(&v, "forward_ms");
        time_field(&v, "forward_backward_ms");
        assert!(v["pairs"].as_u64().is_some_and(|p| p > 0), "{v}");
        assert!(v["visible"].as_u64().is_some_and(|n| n > 0 && n <= 3000), "{v}");
        assert_eq!(v["threads"].as_u64(), Some(want as u64), "--threads {threads}: {v}");
    }
}

#[test]
fn encoder_fields_and_threads() {
    for (extra, name) in [(None, "encoder"), (Some("--backbone-only"), "encoder_backbone")] {
        for (threads, want) in [("0", cores()), ("1", 1)] {
            let mut args = vec!["encoder", "--views", "3", "--height", "64", "--width", "64", "--runs", "1", "--threads", threads];
            args.extend(extra);
            let v = bench(&args);
            assert_eq!(v["bench"], name);
            assert_eq!((v["views"].as_u64(), v["height"].as_u64(), v["width"].as_u64()), (Some(3), Some(64), Some(64)), "{v}");
            time_field(&v, "forward_ms");
            time_field(&v, "peak_mib");
            assert_eq!(v["threads"].as_u64(), Some(want as u64), "--threads {threads}: {v}");
            assert_eq!((v["dtype"].as_str(), v["cpu_bf16"].as_str()), (Some("f32"), None), "{v}");
        }
    }
    // --dtype bf16: packed weights, and the JSON names the path the products took on this CPU.
    let v = bench(&["encoder", "--views", "3", "--height", "64", "--width", "64", "--runs", "1", "--threads", "1", "--dtype", "bf16"]);
    let path = if mvsplat360_nn::bf16::hardware_dpbf16() { "avx512bf16" } else { "storage-only (no bf16 dot product on this CPU)" };
    assert_eq!((v["dtype"].as_str(), v["cpu_bf16"].as_str()), (Some("bf16"), Some(path)), "{v}");
    time_field(&v, "forward_ms");
}

#[test]
fn metrics_fields_and_threads() {
    for (threads, want) in [("0", cores()), ("1", 1)] {
        let v = bench(&["metrics", "--width", "16", "--height", "12", "--runs", "1", "--threads", threads]);
        assert_eq!(v["bench"], "metrics");
        assert_eq!((v["width"].as_u64(), v["height"].as_u64(), v["runs"].as_u64()), (Some(16), Some(12), Some(1)), "{v}");
        assert_eq!(v["threads"].as_u64(), Some(want as u64), "--threads {threads}: {v}");
        let ips = &v["images_per_s"];
        for k in ["psnr", "ssim"] {
            assert!(ips[k].as_f64().is_some_and(|x| x > 0.0), "{k}: {v}");
        }
        // Without weights the networks are null and `notes` says why.
        for k in ["lpips", "dists", "fid"] {
            assert!(ips[k].is_null(), "{k} without weights: {v}");
        }
        assert_eq!(v["notes"].as_array().map(|n| n.len()), Some(3), "{v}");
        time_field(&v, "frechet_ms");
    }
}

#[test]
fn bad_sizes_are_clear_errors() {
    for (args, needle) in [
        (&["raster", "--width", "0"][..], "must be positive"),
        (&["encoder", "--height", "100"][..], "multiples of 64"),
        (&["encoder", "--dtype", "f16"][..], "f32 or bf16"),
        (&["scene", "--tiny", "--encoder-dtype", "f16"][..], "f32 or bf16"),
        (&["refiner", "--latent-h", "12"][..], "multiples of 8"),
        (&["metrics", "--width", "5"][..], "at least 11"),
        (&["fit", "--steps", "0"][..], "--steps ≥ 1"),
        (&["fit", "--scene", "/nonexistent-scene"][..], "/nonexistent-scene"),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_mvsplat360")).arg("bench").args(args).output().unwrap();
        assert!(!out.status.success(), "{args:?} should fail");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{args:?}: expected `{needle}` in {err}");
    }
}

#[test]
fn fit_times_the_shipped_models_fitting_on_the_bundled_scene() {
    let v = bench(&["fit", "--steps", "2", "--runs", "1", "--warmup", "0", "--threads", "1"]);
    assert_eq!(v["bench"], "fit");
    assert_eq!((v["views"].as_u64(), v["steps"].as_u64(), v["runs"].as_u64(), v["threads"].as_u64()), (Some(5), Some(2), Some(1), Some(1)), "{v}");
    // The shipped model's input size; one pixel-aligned Gaussian per context pixel.
    assert_eq!((v["width"].as_u64(), v["height"].as_u64(), v["gaussians"].as_u64()), (Some(128), Some(64), Some(5 * 128 * 64)), "{v}");
    for k in ["fit_seconds", "fit_seconds_fastest", "seconds_per_step"] {
        time_field(&v, k);
    }
    let (l0, l1) = (v["loss_before"].as_f64().unwrap(), v["loss_after"].as_f64().unwrap());
    assert!(l0.is_finite() && l1.is_finite() && l1 < l0, "two fitting steps must lower the loss: {v}");
    assert!(v["peak_rss_mib"].as_f64().is_some_and(|m| m > 0.0), "{v}");
}

#[test]
fn scene_runs_the_whole_pipeline() {
    let v = bench(&["scene", "--tiny", "--views", "3", "--height", "64", "--width", "128", "--frames", "2", "--steps", "1", "--threads", "1"]);
    assert_eq!(v["bench"], "scene");
    assert_eq!((v["views"].as_u64(), v["frames"].as_u64(), v["steps"].as_u64(), v["threads"].as_u64()), (Some(3), Some(2), Some(1), Some(1)), "{v}");
    assert_eq!(v["refiner"], true, "{v}");
    assert_eq!((v["device"].as_str(), v["refiner_dtype"].as_str()), (Some("cpu"), Some("f32")), "{v}");
    // One pixel-aligned Gaussian per context pixel.
    assert_eq!(v["gaussians"].as_u64(), Some(3 * 64 * 128), "{v}");
    time_field(&v, "total_seconds");
    let stages = v["stage_seconds"].as_object().unwrap_or_else(|| panic!("no stage_seconds in {v}"));
    assert!(stages.len() >= 3, "expected encoder, rasterizer and refiner stages: {v}");
    for k in stages.keys() {
        time_field(&v["stage_seconds"], k);
    }
    assert!(stages.keys().any(|k| k.contains("refin")), "no refiner stage in {v}");
    assert!(v["peak_rss_mib"].as_f64().is_some_and(|m| m > 0.0), "{v}");
    assert!(v["gpu_peak_mib"].is_null(), "no GPU memory on the CPU: {v}");
    assert!(v.get("profile").is_none(), "profile without MVSPLAT360_PROFILE: {v}");
    // Profiled: the encoder's stages and the refiner's modules (one 2-frame window, 1 guided step: UNet, VAE, CLIP).
    let p = bench_env(
        &["scene", "--tiny", "--views", "3", "--height", "64", "--width", "128", "--frames", "2", "--steps", "1", "--threads", "1"],
        &[("MVSPLAT360_PROFILE", "1")],
    );
    let prof = p["profile"].as_object().unwrap_or_else(|| panic!("no profile in {p}"));
    for k in ["encoder.cnn", "encoder.gaussian_adapter", "unet.conv", "group_norm", "attention_core", "vae.decoder_total", "clip.block"] {
        let e = &prof.get(k).unwrap_or_else(|| panic!("no `{k}` in {p}"));
        assert!(e["calls"].as_u64().is_some_and(|n| n > 0), "{k}: {e}");
        time_field(e, "ms");
    }
    // A warm-up run is left out of the profile (and of the timings): the same calls as one run alone.
    let w = bench_env(
        &["scene", "--tiny", "--views", "3", "--height", "64", "--width", "128", "--frames", "2", "--steps", "1", "--threads", "1", "--warmup", "1"],
        &[("MVSPLAT360_PROFILE", "1")],
    );
    assert_eq!((w["warmup"].as_u64(), w["runs"].as_u64()), (Some(1), Some(1)), "{w}");
    for (k, e) in prof {
        assert_eq!(w["profile"][k]["calls"], e["calls"], "{k}: warm-up counted in {w}");
    }
    // 3DGS only: no refiner stage.
    let v = bench(&["scene", "--tiny", "--no-refiner", "--views", "2", "--height", "64", "--width", "64", "--frames", "1", "--threads", "1"]);
    assert!(!v["stage_seconds"].as_object().unwrap().keys().any(|k| k.contains("refin")), "{v}");
}

#[test]
fn scene_refuses_bad_sizes_devices_and_dtypes() {
    let mut cases = vec![
        (&["scene", "--tiny", "--height", "100"][..], "multiples of 64"),
        (&["scene", "--tiny", "--device", "gpu"][..], "cpu, cuda or cuda:N"),
        (&["scene", "--tiny", "--dtype", "f64"][..], "f32, f16 or bf16"),
    ];
    if !cfg!(feature = "cuda") {
        cases.push((&["scene", "--tiny", "--device", "cuda"][..], "--features cuda"));
    }
    for (args, needle) in cases {
        let out = Command::new(env!("CARGO_BIN_EXE_mvsplat360")).arg("bench").args(args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && !err.contains("panicked"), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: expected `{needle}` in {err}");
    }
}

/// `--dtype bf16` on the CPU runs the refiner with packed bf16 weights end to end, and the JSON names the path the
/// products took on this CPU.
#[test]
fn scene_runs_the_refiner_in_bf16_on_the_cpu() {
    let v =
        bench(&["scene", "--tiny", "--dtype", "bf16", "--views", "2", "--height", "64", "--width", "64", "--frames", "2", "--steps", "1", "--threads", "1"]);
    assert_eq!((v["device"].as_str(), v["refiner_dtype"].as_str()), (Some("cpu"), Some("bf16")), "{v}");
    let path = if mvsplat360_nn::bf16::hardware_dpbf16() { "avx512bf16" } else { "storage-only (no bf16 dot product on this CPU)" };
    assert_eq!(v["cpu_bf16"].as_str(), Some(path), "{v}");
    assert!(v["stage_seconds"].as_object().unwrap().keys().any(|k| k.contains("refin")), "{v}");
}

/// `--dtype f16` runs the refiner in half precision end to end and the JSON says so.
#[test]
fn scene_runs_the_refiner_in_f16() {
    let v = bench(&["scene", "--tiny", "--dtype", "f16", "--views", "2", "--height", "64", "--width", "64", "--frames", "2", "--steps", "1", "--threads", "1"]);
    assert_eq!((v["device"].as_str(), v["refiner_dtype"].as_str()), (Some("cpu"), Some("f16")), "{v}");
    assert!(v["stage_seconds"].as_object().unwrap().keys().any(|k| k.contains("refin")), "{v}");
}
