//! The loop learns, and a run killed with SIGKILL and resumed follows the uninterrupted run's loss curve.

mod common;

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use mvsplat360_train::{log, Quiet, RunOptions};

#[test]
fn tiny_config_loss_decreases() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = common::tiny_config(dir.path(), 20, "");
    cfg.train.accumulate = 1;
    // One scene, no flips: what changes between steps is only which views are targets.
    cfg.data.sources = vec![mvsplat360_train::config::Source::Procedural { count: 1, seed: 3, views: 12 }];
    cfg.data.flip = false;
    let s = mvsplat360_train::run(&cfg, &RunOptions::default(), &Quiet).unwrap();
    assert_eq!(s.steps, 20);
    let recs = log::read(&dir.path().join("log.jsonl")).unwrap();
    assert_eq!(recs.len(), 20);
    let first: f64 = recs[..5].iter().map(|r| r.mse).sum::<f64>() / 5.0;
    let last: f64 = recs[15..].iter().map(|r| r.mse).sum::<f64>() / 5.0;
    assert!(last < 0.8 * first, "MSE did not drop by 20%: first 5 steps {first:.5}, last 5 {last:.5}");
    // The model folder renders with `render --ckpt`.
    let spec = mvsplat360_pipeline::model::read_model_dir(&s.model_dir).unwrap();
    assert_eq!(spec.encoder.num_depth_candidates, 16);
    assert!(dir.path().join("loss.png").is_file());
    assert!(!dir.path().join("train.lock").exists(), "a finished run leaves no lock");
}

fn write_config(dir: &std::path::Path, out: &std::path::Path, sources: Option<Vec<mvsplat360_train::config::Source>>) -> std::path::PathBuf {
    let mut cfg = common::tiny_config(out, 10, "");
    if let Some(s) = sources {
        cfg.data.sources = s;
    }
    let p = dir.join("cfg.toml");
    std::fs::write(&p, cfg.to_toml()).unwrap();
    p
}

#[test]
fn killed_and_resumed_run_matches_uninterrupted() {
    kill_and_resume(None);
}

/// The same from `.torch` chunks (a folder of two): the chunk read at each step does not depend on what the
/// process read before, so the resumed run reads what the uninterrupted one did.
#[test]
fn killed_and_resumed_chunk_run_matches_uninterrupted() {
    let dir = tempfile::tempdir().unwrap();
    let chunk = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../dataset/tests/data/chunk/000000.torch");
    for name in ["000000.torch", "000001.torch"] {
        std::fs::copy(&chunk, dir.path().join(name)).unwrap();
    }
    kill_and_resume(Some(vec![mvsplat360_train::config::Source::Chunks { path: dir.path().to_path_buf() }]));
}

fn kill_and_resume(sources: Option<Vec<mvsplat360_train::config::Source>>) {
    let bin = env!("CARGO_BIN_EXE_mvsplat360-train");
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let ca = write_config(dir.path(), &a, sources.clone());
    let st = Command::new(bin).args(["--config", ca.to_str().unwrap()]).stdout(Stdio::null()).status().unwrap();
    assert!(st.success());
    let full = log::read(&a.join("log.jsonl")).unwrap();
    assert_eq!(full.len(), 10);

    std::fs::create_dir_all(dir.path().join("kb")).unwrap();
    let cb = write_config(&dir.path().join("kb"), &b, sources);
    let mut child = Command::new(bin).args(["--config", cb.to_str().unwrap()]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
    // Kill between checkpoints (after step 5 is logged; the last checkpoint is step 4).
    let t0 = Instant::now();
    loop {
        let n = log::read(&b.join("log.jsonl")).unwrap().len();
        if n >= 5 {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "the run did not reach step 5");
        assert!(child.try_wait().unwrap().is_none(), "the run ended before it could be killed");
        std::thread::sleep(Duration::from_millis(20));
    }
    // SIGKILL: no handler runs.
    child.kill().unwrap();
    child.wait().unwrap();
    let partial = log::read(&b.join("log.jsonl")).unwrap();
    assert!(partial.len() < 10, "killed too late to test anything ({} steps)", partial.len());
    let st = Command::new(bin).args(["--config", cb.to_str().unwrap(), "--resume"]).stdout(Stdio::null()).status().unwrap();
    assert!(st.success());
    let resumed = log::read(&b.join("log.jsonl")).unwrap();
    assert_eq!(resumed.len(), 10);
    for (x, y) in full.iter().zip(&resumed) {
        assert_eq!(x.step, y.step);
        let rel = (x.loss - y.loss).abs() / x.loss.abs().max(1e-12);
        assert!(rel <= 1e-6, "step {}: loss {} uninterrupted vs {} resumed", x.step, x.loss, y.loss);
        assert!((x.lr - y.lr).abs() <= 1e-15 * x.lr.abs().max(1.0));
    }
    // The final weights agree too.
    let wa = candle_core::safetensors::load(a.join("model/model.safetensors"), &candle_core::Device::Cpu).unwrap();
    let wb = candle_core::safetensors::load(b.join("model/model.safetensors"), &candle_core::Device::Cpu).unwrap();
    let mut worst = 0f32;
    for (k, ta) in &wa {
        let d = (ta - &wb[k]).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap();
        worst = worst.max(d);
    }
    assert!(worst <= 1e-6, "final weights differ by up to {worst}");
}

/// A checkpoint exported as a model folder holds the weights the run had at that step: the last one equals the
/// run's own final model folder, an earlier one differs; a missing step names the steps there are; a changed
/// config is refused; the stand-alone binary's `--export` writes the same folder.
#[test]
fn checkpoint_exports_as_a_model_folder() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = common::tiny_config(dir.path(), 4, "");
    cfg.train.keep_checkpoints = 2;
    mvsplat360_train::run(&cfg, &RunOptions::default(), &Quiet).unwrap();
    let load = |p: &std::path::Path| candle_core::safetensors::load(p.join("model.safetensors"), &candle_core::Device::Cpu).unwrap();
    let max_diff = |a: &std::collections::HashMap<String, candle_core::Tensor>, b: &std::collections::HashMap<String, candle_core::Tensor>| {
        assert_eq!(a.len(), b.len());
        a.iter().map(|(k, x)| (x - &b[k]).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()).fold(0f32, f32::max)
    };
    let final_dir = dir.path().join("model");
    let (step, last) = mvsplat360_train::export_checkpoint(&cfg, None, None).unwrap();
    assert_eq!((step, last.clone()), (4, dir.path().join("model-4")));
    assert_eq!(max_diff(&load(&last), &load(&final_dir)), 0.0);
    assert_eq!(std::fs::read_to_string(last.join("config.json")).unwrap(), std::fs::read_to_string(final_dir.join("config.json")).unwrap());
    mvsplat360_pipeline::model::read_model_dir(&last).unwrap();

    let to = dir.path().join("earlier");
    assert_eq!(mvsplat360_train::export_checkpoint(&cfg, Some(2), Some(&to)).unwrap(), (2, to.clone()));
    assert!(max_diff(&load(&to), &load(&final_dir)) > 1e-6, "steps 2 and 4 have the same weights");

    let e = mvsplat360_train::export_checkpoint(&cfg, Some(3), None).unwrap_err().to_string();
    assert!(e.contains("no checkpoint of step 3") && e.contains("steps 2, 4"), "{e}");
    let mut other = cfg.clone();
    other.train.lr = 5e-4;
    let e = mvsplat360_train::export_checkpoint(&other, Some(4), None).unwrap_err().to_string();
    assert!(e.contains("different config"), "{e}");

    let p = dir.path().join("cfg.toml");
    std::fs::write(&p, cfg.to_toml()).unwrap();
    let bin_dir = dir.path().join("from-bin");
    let st = Command::new(env!("CARGO_BIN_EXE_mvsplat360-train"))
        .args(["--config", p.to_str().unwrap(), "--export", "latest", "--export-to", bin_dir.to_str().unwrap()])
        .status()
        .unwrap();
    assert!(st.success());
    assert_eq!(max_diff(&load(&bin_dir), &load(&final_dir)), 0.0);
    let st = Command::new(env!("CARGO_BIN_EXE_mvsplat360-train")).args(["--config", p.to_str().unwrap(), "--export", "last"]).status().unwrap();
    assert_eq!(st.code(), Some(2), "a bad step is a usage error");
}

#[test]
fn resume_refuses_a_changed_config_and_fresh_runs_refuse_old_checkpoints() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = common::tiny_config(dir.path(), 2, "");
    mvsplat360_train::run(&cfg, &RunOptions::default(), &Quiet).unwrap();
    let e = mvsplat360_train::run(&cfg, &RunOptions::default(), &Quiet).unwrap_err().to_string();
    assert!(e.contains("--resume"), "{e}");
    let mut other = cfg.clone();
    other.train.lr = 5e-4;
    let e = mvsplat360_train::run(&other, &RunOptions { resume: true, ..Default::default() }, &Quiet).unwrap_err().to_string();
    assert!(e.contains("different config"), "{e}");
    // A checkpoint written before a field existed (its config text lacks the field) resumes when the field has
    // its default value.
    let state = dir.path().join("checkpoints/step-0000002/state.json");
    let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
    let text = v["config"].as_str().unwrap().to_string();
    assert!(text.contains("refiner_weight = 1.0\n"), "{text}");
    v["config"] = serde_json::Value::String(text.replace("refiner_weight = 1.0\n", ""));
    std::fs::write(&state, v.to_string()).unwrap();
    let mut longer = cfg.clone();
    longer.train.steps = 3;
    let e = mvsplat360_train::run(&longer, &RunOptions { resume: true, ..Default::default() }, &Quiet).unwrap_err().to_string();
    assert!(e.contains("different config"), "steps differ, so the configs differ: {e}");
    let s = mvsplat360_train::run(&cfg, &RunOptions { resume: true, ..Default::default() }, &Quiet).unwrap();
    assert_eq!(s.steps, 2);
    // Written by 2 ranks (a global batch of 2 × accumulate): resuming on 1 is refused unless asked for.
    let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
    assert_eq!(v["world"], 1, "the checkpoint records its world size");
    v["world"] = 2.into();
    std::fs::write(&state, v.to_string()).unwrap();
    let e = mvsplat360_train::run(&cfg, &RunOptions { resume: true, ..Default::default() }, &Quiet).unwrap_err().to_string();
    assert!(e.contains("written by 2 rank(s)") && e.contains("--world-size 2") && e.contains("--allow-world-change"), "{e}");
    let s = mvsplat360_train::run(&cfg, &RunOptions { resume: true, allow_world_change: true, ..Default::default() }, &Quiet).unwrap();
    assert_eq!(s.steps, 2);
}

/// A `.torch` chunk source (the committed two-scene test chunk) streams scenes into training.
#[test]
fn chunk_source_trains() {
    let chunk = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../dataset/tests/data/chunk/000000.torch");
    let src = mvsplat360_train::config::Source::Chunks { path: chunk.clone() };
    let mut s = mvsplat360_train::scenes::SceneSource::open(&src, 64, 64, 64).unwrap();
    use rand::SeedableRng;
    let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    let keys: Vec<String> = mvsplat360_dataset::torch_chunk::read_chunk(&chunk).unwrap().into_iter().map(|c| c.key).collect();
    for _ in 0..3 {
        let scene = s.draw(&mut rng, 0, 0).unwrap();
        assert!(keys.iter().any(|k| scene.name.contains(k.as_str())), "{} not among {keys:?}", scene.name);
        assert!(scene.images.iter().all(|im| (im.width, im.height) == (64, 64)));
        assert_eq!(scene.images.len(), scene.cameras.len());
    }
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = common::tiny_config(dir.path(), 2, "");
    cfg.data.sources = vec![src];
    cfg.train.accumulate = 1;
    let sum = mvsplat360_train::run(&cfg, &RunOptions::default(), &Quiet).unwrap();
    assert!(sum.last.unwrap().loss.is_finite());
}

/// Micro-batches on parallel threads give the sequential run's losses and weights (the kernels' own summation
/// order is the same; only the threads differ), and the curriculum's window is used from step 0.
#[test]
fn parallel_micro_batches_match_sequential() {
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str, parallel: bool| {
        let mut cfg = common::tiny_config(&dir.path().join(name), 2, "");
        cfg.train.parallel_micro_batches = parallel;
        cfg.data.gap_initial = Some([4, 6]);
        cfg.data.gap_warm_up_steps = 10;
        let s = mvsplat360_train::run(&cfg, &RunOptions::default(), &Quiet).unwrap();
        let recs = log::read(&dir.path().join(name).join("log.jsonl")).unwrap();
        let w = candle_core::safetensors::load(s.model_dir.join("model.safetensors"), &candle_core::Device::Cpu).unwrap();
        (recs, w)
    };
    let (ra, wa) = run("seq", false);
    let (rb, wb) = run("par", true);
    assert_eq!(ra.len(), 2);
    for (a, b) in ra.iter().zip(&rb) {
        assert!((a.loss - b.loss).abs() <= 1e-6 * a.loss.abs().max(1e-12), "step {}: {} vs {}", a.step, a.loss, b.loss);
        assert!((a.grad_norm - b.grad_norm).abs() <= 1e-5 * a.grad_norm, "step {}: grad norm {} vs {}", a.step, a.grad_norm, b.grad_norm);
    }
    let mut worst = 0f32;
    for (k, ta) in &wa {
        let d = (ta - &wb[k]).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap();
        worst = worst.max(d);
    }
    assert!(worst <= 1e-6, "weights differ by {worst}");
}

/// SIGTERM (how background jobs are stopped) finishes the step, writes a checkpoint of it and exits with 130.
#[test]
fn sigterm_checkpoints_the_last_step() {
    let bin = env!("CARGO_BIN_EXE_mvsplat360-train");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t");
    let mut cfg = common::tiny_config(&out, 50, "");
    cfg.train.checkpoint_every = 1000;
    let p = dir.path().join("cfg.toml");
    std::fs::write(&p, cfg.to_toml()).unwrap();
    let mut child = Command::new(bin).args(["--config", p.to_str().unwrap()]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
    let t0 = Instant::now();
    while log::read(&out.join("log.jsonl")).unwrap().len() < 2 {
        assert!(t0.elapsed() < Duration::from_secs(120), "the run did not reach step 2");
        assert!(child.try_wait().unwrap().is_none(), "the run ended early");
        std::thread::sleep(Duration::from_millis(20));
    }
    let st = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(st.success());
    let code = child.wait().unwrap().code();
    assert_eq!(code, Some(130), "expected exit 130 after SIGTERM");
    let steps = log::read(&out.join("log.jsonl")).unwrap().len();
    assert!(steps < 50, "stopped too late to test anything");
    let ck = mvsplat360_train::checkpoint::list(&out).unwrap();
    let (newest, path) = ck.last().expect("a checkpoint was written on SIGTERM");
    assert_eq!(*newest as usize, steps, "newest checkpoint {} after {steps} logged steps", path.display());
}

/// While a run is alive, a second one on its folder is refused by name; SIGKILL leaves the lock behind, and the
/// next run (e.g. `--resume`) takes it over.
#[test]
fn second_run_on_a_live_folder_is_refused_and_a_killed_runs_lock_taken_over() {
    let bin = env!("CARGO_BIN_EXE_mvsplat360-train");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o");
    let cfg = write_config(dir.path(), &out, None);
    let mut child = Command::new(bin).args(["--config", cfg.to_str().unwrap()]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
    let lock = out.join("train.lock");
    let t0 = Instant::now();
    while std::fs::read_to_string(&lock).map_or(true, |s| s.trim().is_empty()) {
        assert!(t0.elapsed() < Duration::from_secs(120), "the run never took its lock");
        assert!(child.try_wait().unwrap().is_none(), "the run ended before the lock was checked");
        std::thread::sleep(Duration::from_millis(20));
    }
    let err = mvsplat360_train::checkpoint::RunLock::acquire(&out).err().expect("a second run on a live folder is refused");
    assert!(err.to_string().contains(&format!("process {}", child.id())), "{err}");
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(lock.is_file(), "SIGKILL runs no clean-up: the lock stays");
    let taken = mvsplat360_train::checkpoint::RunLock::acquire(&out).expect("a killed run's lock is taken over");
    assert_eq!(std::fs::read_to_string(&lock).unwrap().trim(), mvsplat360_dataset::owner::Owner::me().record());
    drop(taken);
    assert!(!lock.exists(), "the lock is removed when its run ends");
}

/// A build without CUDA refuses `--device cuda` by name before touching the output folder's checkpoints.
#[cfg(not(feature = "cuda"))]
#[test]
fn cuda_device_in_a_cpu_build_is_refused_with_the_fix() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = common::tiny_config(dir.path(), 1, "");
    let opts = RunOptions { device: mvsplat360_pipeline::compute::DeviceSpec::Cuda(0), ..Default::default() };
    let e = mvsplat360_train::run(&cfg, &opts, &Quiet).unwrap_err().to_string();
    assert!(e.contains("--device") && e.contains("built without CUDA") && e.contains("--features cuda"), "{e}");
    assert!(!dir.path().join("checkpoints").exists() && !dir.path().join("train.lock").exists());
}
