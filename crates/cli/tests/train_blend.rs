//! `mvsplat360 train-blend` end to end: a blender trained on a generated scene, the written model folder rendered
//! by `render` (which then writes blended frames), and a clear error for a missing scene folder.

use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
}

#[test]
fn train_blend_writes_a_model_folder_that_render_blends_with() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = mvsplat360_pipeline::model::tiny_config(false);
    let m = tmp.path().join("tiny");
    mvsplat360_pipeline::model::write_model_dir(&m, &cfg, &mvsplat360_pipeline::model::random_state_dict(&cfg, 4).unwrap()).unwrap();
    let out = tmp.path().join("blend");
    let o = bin()
        .arg("train-blend")
        .arg("--model")
        .arg(&m)
        .args(["--train", "procedural:3", "--steps", "2", "--every", "1", "--width", "4", "--layout", "3x2x1.5", "--fit-steps", "0", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), out.join("model").display().to_string());
    assert!(err.contains("step 2: train MSE"), "{err}");
    let written: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("model/config.json")).unwrap()).unwrap();
    assert_eq!(written["blend"], serde_json::json!({"planes": 3, "span": 1.5, "views": 2, "width": 4}));

    let r = tmp.path().join("render");
    let o = bin()
        .args(["--quiet", "render"])
        .arg(out.join("procedural/proc-3"))
        .arg("--ckpt")
        .arg(out.join("model"))
        .args(["--num-context", "5", "--targets", "1,2", "--no-metrics", "--no-video", "--out"])
        .arg(&r)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(r.join("frames/blended/0000.png").is_file() && r.join("frames/blended/0001.png").is_file());

    let o = bin().arg("train-blend").arg("--model").arg(&m).args(["--train", "/no/such/scenes", "--out"]).arg(tmp.path().join("x")).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("/no/such/scenes") && err.contains("procedural:"), "{err}");
}
