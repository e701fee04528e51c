//! `train --world-size 2`: the command starts two ranks of itself on the CPU (host backend); rank 0 alone writes
//! the log and the model folder. Bad flags fail before anything starts.

use std::process::Command;

#[path = "../../train/tests/common/mod.rs"]
mod common;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
}

/// The train crate's tiny config (64×64, 3 context views, generated scenes), 2 steps, a checkpoint each.
fn tiny_config(out: &std::path::Path) -> String {
    let mut c = common::tiny_config(out, 2, "");
    c.train.accumulate = 1;
    c.train.checkpoint_every = 1;
    c.to_toml()
}

#[test]
fn two_ranks_train_and_rank_zero_writes_the_outputs() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let cfg = tmp.path().join("tiny.toml");
    std::fs::write(&cfg, tiny_config(&out)).unwrap();
    let o = bin().args(["--quiet", "train", "--world-size", "2", "--config"]).arg(&cfg).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let log = std::fs::read_to_string(out.join("log.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 2, "one line per step, from rank 0 only:\n{log}");
    assert!(out.join("model/model.safetensors").is_file());
    assert!(!out.join("train.lock").exists(), "the finished run leaves no lock");
}

#[test]
fn bad_data_parallel_flags_fail_cleanly() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tmp.path().join("tiny.toml");
    std::fs::write(&cfg, tiny_config(&tmp.path().join("run"))).unwrap();
    let o = bin().args(["train", "--world-size", "0", "--config"]).arg(&cfg).output().unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    let o = bin().args(["train", "--world-size", "2", "--dist-backend", "nccl", "--config"]).arg(&cfg).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("--dist-backend host"), "NCCL on the CPU names the fix: {err}");
    assert!(!tmp.path().join("run/log.jsonl").exists(), "nothing started");
}

/// `bench train` times real steps of a config in a throw-away folder: the config's own `train.out` stays
/// untouched, the JSON line counts only the timed steps, and `--runs 0` is refused before any work.
#[test]
fn bench_train_times_steps_without_touching_the_configs_output() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let cfg = tmp.path().join("tiny.toml");
    std::fs::write(&cfg, tiny_config(&out)).unwrap();
    let o = bin().args(["bench", "train", "--runs", "2", "--warmup", "1", "--threads", "1", "--config"]).arg(&cfg).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["bench"], "train");
    assert_eq!(v["runs"], 2, "the warm-up step is not timed: {v}");
    assert_eq!(v["threads"], 1);
    let (med, min) = (v["step_s"].as_f64().unwrap(), v["step_s_min"].as_f64().unwrap());
    assert!(min > 0.0 && min <= med && med.is_finite(), "{v}");
    assert!(v["peak_rss_mib"].as_f64().unwrap() > 0.0);
    assert!(!out.exists(), "the config's output folder is not written by a benchmark");
    let o = bin().args(["bench", "train", "--runs", "0", "--config"]).arg(&cfg).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--runs"), "{err}");
}

#[test]
fn plot_redraws_the_loss_curve_of_a_log() {
    let tmp = tempfile::tempdir().unwrap();
    let log = tmp.path().join("log.jsonl");
    let line = |s: u64, loss: f64| format!(r#"{{"step":{s},"loss":{loss},"mse":{},"lpips":null,"lr":0.001,"grad_norm":1.0,"seconds":0.5}}"#, loss / 2.0);
    std::fs::write(&log, [line(1, 0.4), line(2, 0.3), line(3, 0.25)].join("\n")).unwrap();
    let o = bin().args(["train", "--plot"]).arg(&log).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let png = image::open(tmp.path().join("loss.png")).unwrap();
    assert_eq!((png.width(), png.height()), (900, 500));
    // The curve is drawn: not a blank white image.
    assert!(png.to_rgb8().pixels().any(|p| p.0 != [255, 255, 255]));
    // An empty log, and neither --config nor --plot, are errors that say what to give.
    std::fs::write(&log, "").unwrap();
    let o = bin().args(["train", "--plot"]).arg(&log).output().unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("no log records"));
    let o = bin().arg("train").output().unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--config"), "{}", String::from_utf8_lossy(&o.stderr));
}
