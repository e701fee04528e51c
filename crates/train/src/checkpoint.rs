//! Checkpoints: `<out>/checkpoints/step-NNNNNNN/{model,optimizer}.safetensors + state.json`, each written to a
//! temporary folder and renamed into place, so a kill at any moment leaves the previous checkpoint intact.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
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
}

pub fn dir(out: &Path) -> PathBuf {
    out.join("checkpoints")
}

fn step_dir(out: &Path, step: u64) -> PathBuf {
    dir(out).join(format!("step-{step:07}"))
}

/// Write a checkpoint and delete all but the newest `keep`.
pub fn save(out: &Path, state: &State, model: &[(String, Tensor)], optim: &[(String, Tensor)], keep: usize) -> Result<PathBuf> {
    let werr = |p: &Path, e: &dyn std::fmt::Display| TrainError::Write { path: p.to_path_buf(), msg: e.to_string() };
    let root = dir(out);
    std::fs::create_dir_all(&root).map_err(|e| werr(&root, &e))?;
    let tmp = root.join(format!(".tmp-step-{:07}", state.step));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(|e| werr(&tmp, &e))?;
    }
    std::fs::create_dir_all(&tmp).map_err(|e| werr(&tmp, &e))?;
    let save_map = |name: &str, t: &[(String, Tensor)]| -> Result<()> {
        let map: HashMap<String, Tensor> = t.iter().cloned().collect();
        let p = tmp.join(name);
        candle_core::safetensors::save(&map, &p).map_err(|e| werr(&p, &e))?;
        Ok(())
    };
    save_map("model.safetensors", model)?;
    save_map("optimizer.safetensors", optim)?;
    let js = serde_json::to_string_pretty(state).map_err(|e| werr(&tmp, &e))?;
    std::fs::write(tmp.join("state.json"), js).map_err(|e| werr(&tmp, &e))?;
    sync_dir(&tmp);
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

fn sync_dir(p: &Path) {
    if let Ok(f) = std::fs::File::open(p) {
        let _ = f.sync_all();
    }
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

pub fn load_latest(out: &Path) -> Result<Option<Loaded>> {
    let Some((_, p)) = list(out)?.pop() else { return Ok(None) };
    load(p).map(Some)
}

/// A step as given on a command line: a number, or `latest` (`None`: the newest checkpoint).
pub fn parse_step(s: &str) -> std::result::Result<Option<u64>, String> {
    match s {
        "latest" => Ok(None),
        n => n.parse::<u64>().map(Some).map_err(|_| format!("`{n}` is neither a step number nor `latest`")),
    }
}

/// The checkpoint of `step`, or the newest when `None`; the error lists the steps there are.
pub fn load_step(out: &Path, step: Option<u64>) -> Result<Loaded> {
    let all = list(out)?;
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
    let model = candle_core::safetensors::load(p.join("model.safetensors"), &Device::Cpu).map_err(|e| cerr(&e))?;
    let optim = candle_core::safetensors::load(p.join("optimizer.safetensors"), &Device::Cpu).map_err(|e| cerr(&e))?;
    Ok(Loaded { state, model, optim, path: p })
}

/// One training run per output folder: `<out>/train.lock` holds the writer's process id while it runs and is
/// removed when the run ends (also on Ctrl-C or an error). A lock left by a killed run is taken over, so
/// `--resume` after SIGKILL works; a second run while the first is alive is refused instead of mixing two
/// runs' checkpoints and logs.
pub struct RunLock {
    path: PathBuf,
}

impl RunLock {
    pub fn acquire(out: &Path) -> Result<Self> {
        let path = out.join("train.lock");
        for _ in 0..2 {
            match std::fs::OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(mut f) => {
                    use std::io::Write;
                    writeln!(f, "{}", std::process::id()).map_err(|e| TrainError::Write { path: path.clone(), msg: e.to_string() })?;
                    return Ok(Self { path });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let owner = std::fs::read_to_string(&path).ok().and_then(|s| s.trim().parse::<u32>().ok());
                    if let Some(pid) = owner.filter(|&p| process_alive(p)) {
                        return Err(TrainError::Checkpoint(format!(
                            "{}: another training run (process {pid}) is writing to this folder; wait for it, stop it, or \
                             choose another `train.out` (delete the file if process {pid} is not a training run)",
                            path.display()
                        )));
                    }
                    // Left by a run that was killed: take it over.
                    std::fs::remove_file(&path).map_err(|e| TrainError::Write { path: path.clone(), msg: e.to_string() })?;
                }
                Err(e) => return Err(TrainError::Write { path, msg: e.to_string() }),
            }
        }
        Err(TrainError::Checkpoint(format!("{}: could not take the run lock; retry", path.display())))
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Whether a process with this id runs (Linux: /proc; elsewhere a lock is always treated as stale).
fn process_alive(pid: u32) -> bool {
    cfg!(target_os = "linux") && Path::new(&format!("/proc/{pid}")).exists()
}
