//! `export` on the bundled scene with the official-architecture fixture weights (random values, official key
//! names): the .ply must re-read with one Gaussian per context pixel and finite values; bad input must fail cleanly.

use std::path::PathBuf;
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

#[test]
fn export_writes_a_readable_ply_and_splat() {
    let ckpt = mvsplat360_testkit::fixture("encoder/state_dict.safetensors");
    let tmp = tempfile::tempdir().unwrap();
    let (ply, splat) = (tmp.path().join("scene.ply"), tmp.path().join("scene.splat"));
    // 448×256 views resized to 128×73, centre-cropped to 128×64: 5 views × 8,192 pixels.
    let out = bin()
        .args(["--quiet", "export", "--num-context", "5", "--size", "128x64", "--ckpt"])
        .arg(&ckpt)
        .arg(root().join("assets/woodbox"))
        .arg("--out")
        .arg(&ply)
        .arg("--splat")
        .arg(&splat)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let g = mvsplat360_splat::io::read_ply(&ply).unwrap();
    let n = 5 * 128 * 64;
    assert_eq!(g.means.len(), n);
    let flat = g.means.iter().chain(&g.scales).flatten().chain(&g.opacities).chain(&g.sh);
    assert!(flat.into_iter().all(|v| v.is_finite()));
    assert_eq!(std::fs::metadata(&splat).unwrap().len(), (n * 32) as u64);
    let left: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().map(|e| e.unwrap().file_name()).filter(|n| n.to_string_lossy().ends_with(".partial")).collect();
    assert!(left.is_empty(), "temporary files left: {left:?}");
}

#[test]
fn export_bad_inputs_fail_with_one_message() {
    let ckpt = mvsplat360_testkit::fixture("encoder/state_dict.safetensors");
    let tmp = tempfile::tempdir().unwrap();
    let garbage = tmp.path().join("garbage.ckpt");
    std::fs::write(&garbage, "not weights").unwrap();
    let scene = root().join("assets/woodbox");
    let cases: Vec<(Vec<std::ffi::OsString>, &str)> = vec![
        (vec!["--ckpt".into(), garbage.into_os_string(), scene.clone().into()], "garbage.ckpt"),
        (vec!["--ckpt".into(), ckpt.clone().into(), scene.clone().into(), "--num-context".into(), "1".into()], "--num-context: need at least 2 context views"),
        (vec!["--ckpt".into(), ckpt.clone().into(), scene.clone().into(), "--num-context".into(), "99".into()], "fewer than 99"),
        (vec!["--ckpt".into(), ckpt.into(), tmp.path().join("nope").into()], "no such file"),
    ];
    for (args, needle) in cases {
        let out = bin().args(["--quiet", "export", "--out"]).arg(tmp.path().join("x.ply")).args(&args).output().unwrap();
        assert_eq!(out.status.code(), Some(1), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle) && !err.contains("panicked"), "{args:?}: {err}");
        assert!(!tmp.path().join("x.ply").exists());
    }
}
