//! The binary as a user runs it: output, exit codes, one readable error line, never a panic.

use std::path::PathBuf;
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

#[test]
fn inspect_bundled_scene_json() {
    let out = bin().args(["inspect", "--json", "--num-context", "4"]).arg(root().join("assets/woodbox")).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("valid JSON on stdout");
    assert_eq!(v["views"], 24);
    assert_eq!(v["width"], 448);
    assert_eq!(v["height"], 256);
    assert_eq!(v["suggested_context"].as_array().unwrap().len(), 4);
    assert_eq!(v["suggested_context"][0], 0);
    assert_eq!(v["context_local_groups"][0].as_array().unwrap().len(), 3);
}

/// Views of different sizes (photos from two cameras): the summary lists each size with its view count.
#[test]
fn inspect_names_every_image_size() {
    let tmp = tempfile::tempdir().unwrap();
    let src = root().join("assets/woodbox");
    let mut t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(src.join("transforms.json")).unwrap()).unwrap();
    std::fs::create_dir_all(tmp.path().join("images")).unwrap();
    for (i, f) in t["frames"].as_array_mut().unwrap().iter_mut().enumerate() {
        let rel = f["file_path"].as_str().unwrap().to_string();
        let img = image::open(src.join(&rel)).unwrap();
        let name = format!("images/{i:03}.png");
        if i < 3 {
            // Half size, intrinsics halved with it.
            img.resize_exact(224, 128, image::imageops::FilterType::Triangle).save(tmp.path().join(&name)).unwrap();
            for (k, v) in
                [("w", 224.0), ("h", 128.0), ("fl_x", 387.979_380_895_428_56 / 2.0), ("fl_y", 387.979_380_895_428_56 / 2.0), ("cx", 112.0), ("cy", 64.0)]
            {
                f[k] = v.into();
            }
        } else {
            img.save(tmp.path().join(&name)).unwrap();
        }
        f["file_path"] = name.into();
    }
    std::fs::write(tmp.path().join("transforms.json"), t.to_string()).unwrap();
    let out = bin().arg("inspect").arg(tmp.path()).output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.contains("sizes differ: 224x128 (3 views), 448x256 (21 views)"), "{text}");
    let out = bin().args(["inspect", "--json"]).arg(tmp.path()).output().unwrap();
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["sizes"][0], serde_json::json!([224, 128]));
    assert_eq!(v["sizes"][23], serde_json::json!([448, 256]));
}

#[test]
fn inspect_human_and_chunk() {
    let out = bin().arg("inspect").arg(root().join("assets/woodbox")).output().unwrap();
    assert!(out.status.success());
    let s = String::from_utf8_lossy(&out.stdout);
    assert!(s.contains("views      24") && s.contains("448x256"), "{s}");
    let chunk = root().join("crates/dataset/tests/data/chunk/000000.torch");
    let out = bin().args(["inspect", "--scene-key", "woodbox_b", "--json"]).arg(&chunk).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["name"], "woodbox_b");
    assert_eq!(v["views"], 2);
}

#[test]
fn errors_are_one_line_and_exit_nonzero() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = tmp.path().join("transforms.json");
    std::fs::write(&bad, "{ broken").unwrap();
    for (arg, needle) in [(tmp.path().join("missing"), "no such file or folder"), (bad.clone(), "invalid JSON")] {
        let out = bin().arg("inspect").arg(&arg).output().unwrap();
        assert_eq!(out.status.code(), Some(1));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.starts_with("error: ") && err.contains(needle), "{err}");
        assert!(!err.contains("panicked") && !err.contains("RUST_BACKTRACE"), "{err}");
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    }
    // The parser's message once, not repeated by the error chain.
    let err = String::from_utf8_lossy(&bin().arg("inspect").arg(&bad).output().unwrap().stderr).to_string();
    let cause = serde_json::from_str::<serde_json::Value>("{ broken").unwrap_err().to_string();
    assert_eq!(err.matches(&cause).count(), 1, "{err}");
    // Unknown flag: clap's usage error, exit code 2.
    let out = bin().args(["inspect", "--nope"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
}
