//! `mvsplat360 metrics` as a user runs it: the JSON fields, the table, `--out`, errors for mismatched
//! folders, and missing metric weights (empty `--weights-dir` and `$MVSPLAT360_METRIC_WEIGHTS`) → nulls, a
//! warning, exit 0.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The binary with every weights location pointed at `empty` (so a developer's cached weights are not found).
fn bin(empty: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_mvsplat360"));
    c.env("MVSPLAT360_METRIC_WEIGHTS", empty).env("XDG_CACHE_HOME", empty).env("HOME", empty);
    c
}

fn save_png(path: &Path, w: u32, h: u32, f: impl Fn(u32, u32, usize) -> u8) {
    image::RgbImage::from_fn(w, h, |x, y| image::Rgb([f(x, y, 0), f(x, y, 1), f(x, y, 2)])).save(path).unwrap();
}

/// tmp/{pred,gt,empty}: three 32×24 pairs, the predictions a brightened copy of the ground truth.
fn setup(tmp: &Path) -> (PathBuf, PathBuf, PathBuf) {
    let (p, g, e) = (tmp.join("pred"), tmp.join("gt"), tmp.join("empty"));
    for d in [&p, &g, &e] {
        std::fs::create_dir_all(d).unwrap();
    }
    for (i, n) in ["000.png", "001.png", "002.png"].iter().enumerate() {
        let base = move |x: u32, y: u32, c: usize| ((x * 7 + y * 3 + c as u32 * 50 + i as u32 * 30) % 200) as u8;
        save_png(&g.join(n), 32, 24, base);
        save_png(&p.join(n), 32, 24, move |x, y, c| base(x, y, c) + ((x + y) % 3) as u8 * 5);
    }
    (p, g, e)
}

#[test]
fn json_report_with_missing_weights_is_nulls_warning_exit_zero() {
    let tmp = tempfile::tempdir().unwrap();
    let (p, g, e) = setup(tmp.path());
    let out = bin(&e).args(["metrics", "--json", "--weights-dir"]).arg(&e).arg(&p).arg(&g).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object on stdout");
    let mut keys: Vec<&str> = v.as_object().unwrap().keys().map(String::as_str).collect();
    keys.sort();
    assert_eq!(keys, ["dists", "fid", "fid_variant", "lpips", "per_image", "psnr", "ssim"]);
    assert_eq!(v["fid_variant"], "pytorch-fid");
    assert!(v["lpips"].is_null() && v["dists"].is_null() && v["fid"].is_null(), "{v}");
    let psnr = v["psnr"].as_f64().unwrap();
    let ssim = v["ssim"].as_f64().unwrap();
    assert!(psnr > 20.0 && psnr < 60.0 && ssim > 0.5 && ssim < 1.0, "{v}");
    let per = v["per_image"].as_array().unwrap();
    assert_eq!(per.len(), 3);
    assert_eq!(per[0]["name"], "000.png");
    let mut pkeys: Vec<&str> = per[0].as_object().unwrap().keys().map(String::as_str).collect();
    pkeys.sort();
    assert_eq!(pkeys, ["lpips", "name", "psnr", "ssim"]);
    assert!(per.iter().all(|x| x["lpips"].is_null()));
    let mean_psnr = per.iter().map(|x| x["psnr"].as_f64().unwrap()).sum::<f64>() / 3.0;
    assert!((mean_psnr - psnr).abs() < 1e-9);
    // Warnings name what is missing and how to fetch it.
    for what in ["LPIPS", "DISTS", "FID"] {
        assert!(err.lines().any(|l| l.starts_with(&format!("warning: {what}")) && l.contains("scripts/metric-weights/fetch")), "{err}");
    }
}

#[test]
fn table_in_paper_order_and_out_file() {
    let tmp = tempfile::tempdir().unwrap();
    let (p, g, e) = setup(tmp.path());
    let dir = tmp.path().join("report");
    let out = bin(&e).args(["metrics", "--quiet", "--out"]).arg(&dir).arg(&p).arg(&g).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s = String::from_utf8_lossy(&out.stdout);
    let lines: Vec<&str> = s.lines().collect();
    let cols: Vec<&str> = lines[0].split_whitespace().collect();
    assert_eq!(cols, ["PSNR↑", "SSIM↑", "LPIPS↓", "DISTS↓", "FID↓"], "{s}");
    let vals: Vec<&str> = lines[1].split_whitespace().collect();
    assert_eq!(&vals[2..], ["-", "-", "-"], "{s}");
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("metrics.json")).unwrap()).unwrap();
    let psnr: f64 = vals[0].parse().unwrap();
    assert!((v["psnr"].as_f64().unwrap() - psnr).abs() < 0.006, "{s} vs {v}");
    assert_eq!(v["per_image"].as_array().unwrap().len(), 3);
}

#[test]
fn mismatched_names_exit_nonzero_naming_the_files() {
    let tmp = tempfile::tempdir().unwrap();
    let (p, g, e) = setup(tmp.path());
    std::fs::rename(p.join("001.png"), p.join("001_pred.png")).unwrap();
    let out = bin(&e).args(["metrics", "--json"]).arg(&p).arg(&g).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(out.stdout.is_empty());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.starts_with("error: ") && err.contains("001_pred.png") && err.contains("`001.png`"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
}

#[test]
fn size_mismatch_and_missing_folder_exit_nonzero() {
    let tmp = tempfile::tempdir().unwrap();
    let (p, g, e) = setup(tmp.path());
    save_png(&p.join("002.png"), 31, 24, |_, _, _| 9);
    let out = bin(&e).arg("metrics").arg(&p).arg(&g).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("`002.png`") && err.contains("31×24") && err.contains("32×24"), "{err}");
    let out = bin(&e).arg("metrics").arg(tmp.path().join("missing")).arg(&g).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("missing"));
    // Usage errors: clap's exit code 2.
    assert_eq!(bin(&e).args(["metrics", "--batch-size", "0"]).arg(&p).arg(&g).output().unwrap().status.code(), Some(2));
    assert_eq!(bin(&e).args(["metrics"]).arg(&p).output().unwrap().status.code(), Some(2));
}
