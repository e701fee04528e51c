//! Checkpoints: `<out>/checkpoints/step-NNNNNNN/{model,optimizer}.safetensors + state.json`, each written to a
//! temporary folder (files and folder synced to disk) and renamed into place, so a kill at any moment leaves the
//! previous checkpoint intact. `state.json` holds each file's SHA-256: a checkpoint whose files do not match (a
//! flipped byte, a truncation) is skipped by `--resume` and `export latest`, with a warning, for the one before.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use mvsplat360_dataset::atomic::sync_dir;
use serde::{Deserialize, Serialize};

use crate::error::{Result, TrainError};

/// What besides tensors a run needs to continue exactly: the step and the seed (every step's randomness is
/// derived from `(seed, step)`, so this is the whole RNG state).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct State {
    pub step: u64,
    pub seed: u64,
    /// The config the run started with (TOML), to refuse resuming with an incompatible one.
    pub config: String,
    /// Seconds of training so far (all sessions).
    pub train_seconds: f64,
    /// Ranks the run had when this was written: the global batch is `world × train.accumulate` (absent in
    /// checkpoints of earlier versions: not checked).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub world: Option<u64>,
    /// File name → SHA-256 (hex) of the tensor files (absent in checkpoints of earlier versions: not checked).
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub files: std::collections::BTreeMap<String, String>,
}

pub fn dir(out: &Path) -> PathBuf {
    out.join("checkpoints")
}

fn step_dir(out: &Path, step: u64) -> PathBuf {
    dir(out).join(format!("step-{step:07}"))
}

/// Write a checkpoint and delete all but the newest `keep`. A failed write removes its temporary folder and says
/// how much space the checkpoint needs.
pub fn save(out: &Path, state: &State, model: &[(String, Tensor)], optim: &[(String, Tensor)], keep: usize) -> Result<PathBuf> {
    let root = dir(out);
    let tmp = root.join(format!(".tmp-step-{:07}", state.step));
    let written = write_tmp(&root, &tmp, state, model, optim);
    if let Err(e) = written {
        let _ = std::fs::remove_dir_all(&tmp);
        let bytes: usize = model.iter().chain(optim).map(|(_, t)| t.elem_count() * t.dtype().size_in_bytes()).sum();
        return Err(match e {
            TrainError::Write { path, msg } => {
                TrainError::Write { path, msg: format!("{msg} (the checkpoint needs about {} on that disk; nothing of it was kept)", human_bytes(bytes)) }
            }
            other => other,
        });
    }
    let werr = |p: &Path, e: &dyn std::fmt::Display| TrainError::Write { path: p.to_path_buf(), msg: e.to_string() };
    let fin = step_dir(out, state.step);
    if fin.exists() {
        std::fs::remove_dir_all(&fin).map_err(|e| werr(&fin, &e))?;
    }
    std::fs::rename(&tmp, &fin).map_err(|e| werr(&fin, &e))?;
    sync_dir(&root);
    let all = list(out)?;
    if all.len() > keep {
        for (_, p) in &all[..all.len() - keep] {
            let _ = std::fs::remove_dir_all(p);
        }
    }
    Ok(fin)
}

fn human_bytes(n: usize) -> String {
    let n = n as f64;
    if n >= 1e9 {
        format!("{:.2} GB", n / 1e9)
    } else if n >= 1e6 {
        format!("{:.1} MB", n / 1e6)
    } else {
        format!("{:.0} KB", (n / 1e3).ceil())
    }
}

fn write_tmp(root: &Path, tmp: &Path, state: &State, model: &[(String, Tensor)], optim: &[(String, Tensor)]) -> Result<()> {
    let werr = |p: &Path, e: &dyn std::fmt::Display| TrainError::Write { path: p.to_path_buf(), msg: e.to_string() };
    std::fs::create_dir_all(root).map_err(|e| werr(root, &e))?;
    if tmp.exists() {
        std::fs::remove_dir_all(tmp).map_err(|e| werr(tmp, &e))?;
    }
    std::fs::create_dir_all(tmp).map_err(|e| werr(tmp, &e))?;
    let mut state = state.clone();
    for (name, t) in [("model.safetensors", model), ("optimizer.safetensors", optim)] {
        let map: HashMap<String, Tensor> = t.iter().cloned().collect();
        let p = tmp.join(name);
        candle_core::safetensors::save(&map, &p).map_err(|e| werr(&p, &e))?;
        std::fs::File::open(&p).and_then(|f| f.sync_all()).map_err(|e| werr(&p, &e))?;
        state.files.insert(name.to_string(), mvsplat360_dataset::atomic::sha256_file(&p).map_err(|e| werr(&p, &e))?);
    }
    let js = serde_json::to_string_pretty(&state).map_err(|e| werr(tmp, &e))?;
    let sp = tmp.join("state.json");
    std::fs::write(&sp, js).and_then(|()| std::fs::File::open(&sp)?.sync_all()).map_err(|e| werr(&sp, &e))?;
    sync_dir(tmp);
    Ok(())
}

/// Complete checkpoints, oldest first.
pub fn list(out: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let root = dir(out);
    let Ok(rd) = std::fs::read_dir(&root) else { return Ok(vec![]) };
    let mut v: Vec<(u64, PathBuf)> = rd
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().to_string();
            let step = name.strip_prefix("step-")?.parse::<u64>().ok()?;
            e.path().join("state.json").is_file().then(|| (step, e.path()))
        })
        .collect();
    v.sort();
    Ok(v)
}

/// A loaded checkpoint.
pub struct Loaded {
    pub state: State,
    pub model: HashMap<String, Tensor>,
    pub optim: HashMap<String, Tensor>,
    pub path: PathBuf,
}

/// The newest checkpoint that reads back whole; a damaged newer one is skipped with a warning naming it.
pub fn load_latest(out: &Path) -> Result<Option<Loaded>> {
    let all = list(out)?;
    if all.is_empty() {
        return Ok(None);
    }
    let mut damaged = Vec::new();
    for (_, p) in all.iter().rev() {
        match load(p.clone()) {
            Ok(l) => {
                for (bad, why) in &damaged {
                    tracing::warn!("skipping the damaged checkpoint {bad}: {why}; using {}", p.display());
                    eprintln!("warning: skipping the damaged checkpoint {bad} ({why}); using {}", p.display());
                }
                return Ok(Some(l));
            }
            Err(e) => damaged.push((p.display().to_string(), e.to_string())),
        }
    }
    let list: Vec<String> = damaged.iter().map(|(p, e)| format!("{p}: {e}")).collect();
    Err(TrainError::Checkpoint(format!("every checkpoint in {} is damaged:\n{}", dir(out).display(), list.join("\n"))))
}

/// A step as given on a command line: a number, or `latest` (`None`: the newest checkpoint).
pub fn parse_step(s: &str) -> std::result::Result<Option<u64>, String> {
    match s {
        "latest" => Ok(None),
        n => n.parse::<u64>().map(Some).map_err(|_| format!("`{n}` is neither a step number nor `latest`")),
    }
}

/// The checkpoint of `step`, or the newest whole one when `None`; the error lists the steps there are.
pub fn load_step(out: &Path, step: Option<u64>) -> Result<Loaded> {
    let all = list(out)?;
    if step.is_none() && !all.is_empty() {
        return load_latest(out).map(|l| l.expect("the list is not empty"));
    }
    let found = match step {
        Some(s) => all.iter().find(|(n, _)| *n == s),
        None => all.last(),
    };
    match found {
        Some((_, p)) => load(p.clone()),
        None if all.is_empty() => Err(TrainError::Checkpoint(format!("{} holds no checkpoints", dir(out).display()))),
        None => {
            let steps: Vec<String> = all.iter().map(|(n, _)| n.to_string()).collect();
            Err(TrainError::Checkpoint(format!(
                "{} has no checkpoint of step {}; it has steps {} (older ones are deleted: `train.keep_checkpoints`)",
                dir(out).display(),
                step.unwrap_or_default(),
                steps.join(", ")
            )))
        }
    }
}

fn load(p: PathBuf) -> Result<Loaded> {
    let cerr = |e: &dyn std::fmt::Display| TrainError::Checkpoint(format!("{}: {e}", p.display()));
    let text = std::fs::read_to_string(p.join("state.json")).map_err(|e| cerr(&e))?;
    let state: State = serde_json::from_str(&text).map_err(|e| cerr(&e))?;
    for (name, want) in &state.files {
        let got = mvsplat360_dataset::atomic::sha256_file(&p.join(name)).map_err(|e| cerr(&format!("{name}: {e}")))?;
        if &got != want {
            return Err(cerr(&format!("{name} does not match its SHA-256 in state.json (damaged or truncated)")));
        }
    }
    let model = candle_core::safetensors::load(p.join("model.safetensors"), &Device::Cpu).map_err(|e| cerr(&e))?;
    let optim = candle_core::safetensors::load(p.join("optimizer.safetensors"), &Device::Cpu).map_err(|e| cerr(&e))?;
    Ok(Loaded { state, model, optim, path: p })
}

/// One training run per output folder: `<out>/train.lock` holds the writer's process id while it runs and is
/// removed when the run ends (also on Ctrl-C or an error). A lock left by a killed run is taken over, so
/// `--resume` after SIGKILL works; a second run while the first is alive is refused instead of mixing two
/// runs' checkpoints and logs.
pub struct RunLock {
    _lock: mvsplat360_dataset::atomic::DirLock,
}

impl RunLock {
    pub fn acquire(out: &Path) -> Result<Self> {
        mvsplat360_dataset::atomic::DirLock::acquire(&out.join("train.lock"), "training run", "choose another `train.out`")
            .map(|l| Self { _lock: l })
            .map_err(TrainError::Checkpoint)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(step: u64) -> State {
        State { step, seed: 7, config: "x = 1".into(), train_seconds: 1.0, world: Some(1), files: Default::default() }
    }

    fn tensors(v: f32) -> Vec<(String, Tensor)> {
        vec![("w".to_string(), Tensor::full(v, (64, 16), &Device::Cpu).unwrap())]
    }

    #[test]
    fn a_damaged_newest_checkpoint_falls_back_to_the_one_before() {
        for damage in ["flip", "truncate", "state"] {
            let d = tempfile::tempdir().unwrap();
            save(d.path(), &state(10), &tensors(1.0), &tensors(0.1), 3).unwrap();
            let newest = save(d.path(), &state(20), &tensors(2.0), &tensors(0.2), 3).unwrap();
            assert_eq!(load_latest(d.path()).unwrap().unwrap().state.step, 20);
            let f = newest.join("model.safetensors");
            let mut bytes = std::fs::read(&f).unwrap();
            match damage {
                // A flipped byte in the tensor data (after the header), which safetensors alone would not notice.
                "flip" => {
                    let n = bytes.len();
                    bytes[n - 10] ^= 0x40;
                    std::fs::write(&f, &bytes).unwrap();
                }
                "truncate" => std::fs::write(&f, &bytes[..bytes.len() / 2]).unwrap(),
                _ => std::fs::write(newest.join("state.json"), "{ not json").unwrap(),
            }
            let l = load_latest(d.path()).unwrap().unwrap();
            assert_eq!(l.state.step, 10, "{damage}");
            assert_eq!(l.model["w"].flatten_all().unwrap().to_vec1::<f32>().unwrap()[0], 1.0);
            assert_eq!(load_step(d.path(), None).unwrap().state.step, 10, "{damage}: export latest");
            // Asked for by number, the damaged one is an error naming it.
            let e = load_step(d.path(), Some(20)).err().map(|e| e.to_string()).unwrap_or_default();
            assert!(e.contains("step-0000020"), "{damage}: {e}");
        }
    }

    #[test]
    fn every_checkpoint_damaged_is_one_error_listing_them() {
        let d = tempfile::tempdir().unwrap();
        for s in [1, 2] {
            let p = save(d.path(), &state(s), &tensors(1.0), &tensors(0.1), 3).unwrap();
            std::fs::write(p.join("optimizer.safetensors"), b"").unwrap();
        }
        let e = load_latest(d.path()).err().unwrap().to_string();
        assert!(e.contains("every checkpoint") && e.contains("step-0000001") && e.contains("step-0000002"), "{e}");
    }

    #[test]
    fn the_run_lock_names_its_host() {
        let d = tempfile::tempdir().unwrap();
        let lock = RunLock::acquire(d.path()).unwrap();
        let text = std::fs::read_to_string(d.path().join("train.lock")).unwrap();
        assert_eq!(text.trim(), mvsplat360_dataset::owner::Owner::me().record());
        assert!(RunLock::acquire(d.path()).err().unwrap().to_string().contains("another training run"));
        drop(lock);
        // Held on another machine: refused, naming it (its process cannot be checked from here).
        std::fs::write(d.path().join("train.lock"), "12 node-b\n").unwrap();
        let e = RunLock::acquire(d.path()).err().unwrap().to_string();
        assert!(e.contains("on node-b (process 12)"), "{e}");
        // A dead process on this machine (an old pid-only lock too): taken over.
        std::fs::write(d.path().join("train.lock"), "4294967295\n").unwrap();
        assert!(RunLock::acquire(d.path()).is_ok());
    }

    #[test]
    fn a_failed_save_leaves_nothing_and_says_the_size() {
        let d = tempfile::tempdir().unwrap();
        // `checkpoints` is a file: the save cannot create its folder.
        std::fs::write(d.path().join("checkpoints"), b"").unwrap();
        let e = save(d.path(), &state(1), &tensors(1.0), &tensors(0.1), 3).unwrap_err().to_string();
        assert!(e.contains("needs about 9 KB"), "{e}");
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
    }
}
