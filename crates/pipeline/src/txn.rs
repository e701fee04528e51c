//! A render as a transaction. A render writes its files into `OUT/.render/stage/` (under the lock
//! `OUT/.render/lock`, `PID HOST`) and leaves the run in `OUT` alone until the new one is complete; then it
//! renames the stage to `OUT/.render/commit/` — the commit point — and swaps the entries ([`ENTRIES`]) in by
//! renames: phase 1 moves the old run's entries into `OUT/.render/old/` (`run.json` first), the marker
//! `OUT/.render/installing` notes that phase 1 is done, phase 2 moves the new entries into `OUT` (`run.json`
//! last), and the leftovers are removed. A crash before the commit point leaves the old run whole (the next
//! render starts a fresh stage, or `--resume` continues it); a crash after it is finished by whichever process
//! opens the folder next ([`recover`]: the next render, `view`), so a folder holds one whole run, old or new, as
//! soon as anyone looks. Entries that are not the render's (a posed `scene/`, the user's own files) are never
//! moved.
//!
//! Resume: `OUT/.render/resume/key.json` names what the interrupted render was (input, model, settings,
//! targets, device, dtype) and `OUT/.render/resume/windows/` holds each refined window as it finishes;
//! `render --resume` with the same key skips those windows. The resume folder goes at the commit.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use mvsplat360_dataset::atomic::DirLock;

use crate::error::{PipelineError, Result};

/// The render's own entries in `OUT`, in the order phase 1 moves them out (phase 2 installs in reverse).
pub const ENTRIES: &[&str] = &["run.json", "metrics.json", "video.mp4", "compare.mp4", "frames", "gaussians.splat", "gaussians.ply", "cameras.json"];

pub const DIR: &str = ".render";

fn write_err(path: &Path) -> impl Fn(std::io::Error) -> PipelineError + '_ {
    move |e| PipelineError::Write { path: path.to_path_buf(), msg: e.to_string() }
}

/// An open render transaction: the lock is held, the stage is empty and ready.
pub struct Txn {
    out: PathBuf,
    pub stage: PathBuf,
    /// Where finished refined windows go (None: `--video-mode`, one call that cannot be split).
    pub windows: Option<PathBuf>,
    /// Windows already finished by the interrupted render being resumed.
    pub resumed: usize,
    _lock: DirLock,
}

/// What a render is, for `--resume`: each part a short description or a hash.
pub type ResumeKey = BTreeMap<String, String>;

impl Txn {
    /// Takes the lock, finishes an interrupted swap, and opens a fresh stage. With `resume`, the finished windows
    /// of an interrupted render with the same `key` are kept (another key is refused, naming what differs);
    /// without, they are discarded. `windows`: whether this render refines window by window.
    pub fn begin(out: &Path, key: &ResumeKey, resume: bool, windows: bool, note: &dyn Fn(&str)) -> Result<Self> {
        let dir = out.join(DIR);
        std::fs::create_dir_all(&dir).map_err(write_err(&dir))?;
        let lock =
            DirLock::acquire(&dir.join("lock"), "render", "choose another --out").map_err(|m| PipelineError::Write { path: dir.join("lock"), msg: m })?;
        if recover(out)? {
            note(&format!("{}: finished installing the render that was interrupted while it was being swapped in", out.display()));
        }
        let stage = dir.join("stage");
        if stage.exists() {
            std::fs::remove_dir_all(&stage).map_err(write_err(&stage))?;
        }
        std::fs::create_dir_all(&stage).map_err(write_err(&stage))?;
        let rdir = dir.join("resume");
        let key_path = rdir.join("key.json");
        let mut resumed = 0;
        if resume {
            match std::fs::read(&key_path).ok().and_then(|b| serde_json::from_slice::<ResumeKey>(&b).ok()) {
                None => note("--resume: no interrupted render here; starting from the beginning"),
                Some(old) if old != *key => {
                    let differ: Vec<&str> = key.keys().chain(old.keys()).filter(|k| old.get(*k) != key.get(*k)).map(String::as_str).collect();
                    let mut differ = differ;
                    differ.dedup();
                    return Err(PipelineError::Flag {
                        flag: "--resume",
                        msg: format!(
                            "the interrupted render in {} had another {} than this one; run with the same flags and files, or without --resume to start over",
                            out.display(),
                            differ.join(", ")
                        ),
                    });
                }
                Some(_) => {
                    resumed = count_windows(&rdir.join("windows"));
                }
            }
        } else if rdir.exists() {
            std::fs::remove_dir_all(&rdir).map_err(write_err(&rdir))?;
        }
        let wdir = rdir.join("windows");
        std::fs::create_dir_all(&wdir).map_err(write_err(&wdir))?;
        let text = serde_json::to_vec_pretty(key).map_err(|e| PipelineError::Write { path: key_path.clone(), msg: e.to_string() })?;
        crate::output::write_bytes(&key_path, &text)?;
        if !windows && resumed > 0 {
            // Video mode refines in one call: nothing to keep.
            std::fs::remove_dir_all(&wdir).and_then(|_| std::fs::create_dir_all(&wdir)).map_err(write_err(&wdir))?;
            resumed = 0;
        }
        Ok(Self { out: out.to_path_buf(), stage, windows: windows.then_some(wdir), resumed, _lock: lock })
    }

    /// Every file of the stage (relative names, `/`-separated) with its SHA-256, for `run.json`.
    pub fn hash_stage(&self) -> Result<BTreeMap<String, String>> {
        let mut files = BTreeMap::new();
        hash_tree(&self.stage, &self.stage, &mut files)?;
        Ok(files)
    }

    /// Swaps the complete stage in (see the module docs); the resume state goes with it.
    pub fn commit(self) -> Result<()> {
        let dir = self.out.join(DIR);
        sync_tree(&self.stage).map_err(write_err(&self.stage))?;
        let commit = dir.join("commit");
        if commit.exists() {
            std::fs::remove_dir_all(&commit).map_err(write_err(&commit))?;
        }
        std::fs::rename(&self.stage, &commit).map_err(write_err(&commit))?;
        sync_dir(&dir);
        recover(&self.out)?;
        let r = dir.join("resume");
        let _ = std::fs::remove_dir_all(&r);
        Ok(())
    }
}

/// A render that stops before its commit point (an error, Ctrl-C) takes its half-written stage with it: on a
/// full disk that space is what the next attempt needs. The refined windows stay for `--resume`.
impl Drop for Txn {
    fn drop(&mut self) {
        if self.stage.exists() {
            let _ = std::fs::remove_dir_all(&self.stage);
        }
    }
}

/// Finishes a swap whose commit point has passed (true when there was one); nothing to do otherwise. Safe to
/// repeat after a crash at any step.
pub fn recover(out: &Path) -> Result<bool> {
    swap_steps(out, usize::MAX)
}

/// [`recover`] stopping after `limit` renames (the crash tests).
pub(crate) fn swap_steps(out: &Path, mut limit: usize) -> Result<bool> {
    let dir = out.join(DIR);
    let (commit, old, installing) = (dir.join("commit"), dir.join("old"), dir.join("installing"));
    if !commit.is_dir() {
        return Ok(false);
    }
    let mut step = || {
        if limit == 0 {
            return false;
        }
        limit -= 1;
        true
    };
    if !installing.exists() {
        std::fs::create_dir_all(&old).map_err(write_err(&old))?;
        for e in ENTRIES {
            let (from, to) = (out.join(e), old.join(e));
            if from.symlink_metadata().is_ok() {
                if !step() {
                    return Ok(true);
                }
                remove_any(&to).map_err(write_err(&to))?;
                std::fs::rename(&from, &to).map_err(write_err(&from))?;
            }
        }
        sync_dir(out);
        if !step() {
            return Ok(true);
        }
        crate::output::write_bytes(&installing, b"phase 2: installing the new run\n")?;
        sync_dir(&dir);
    }
    for e in ENTRIES.iter().rev() {
        let (from, to) = (commit.join(e), out.join(e));
        if from.symlink_metadata().is_ok() {
            if !step() {
                return Ok(true);
            }
            std::fs::rename(&from, &to).map_err(write_err(&to))?;
        }
    }
    sync_dir(out);
    for p in [&old, &commit] {
        let _ = std::fs::remove_dir_all(p);
    }
    let _ = std::fs::remove_file(&installing);
    Ok(true)
}

fn remove_any(p: &Path) -> std::io::Result<()> {
    match p.symlink_metadata() {
        Ok(m) if m.is_dir() => std::fs::remove_dir_all(p),
        Ok(_) => std::fs::remove_file(p),
        Err(_) => Ok(()),
    }
}

fn count_windows(dir: &Path) -> usize {
    std::fs::read_dir(dir).map(|rd| rd.flatten().filter(|e| e.file_name().to_string_lossy().ends_with(".safetensors")).count()).unwrap_or(0)
}

/// The file of refined window `k` (by its first frame).
pub fn window_file(dir: &Path, start: usize) -> PathBuf {
    dir.join(format!("{start:05}.safetensors"))
}

fn hash_tree(root: &Path, dir: &Path, out: &mut BTreeMap<String, String>) -> Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir).map_err(write_err(dir))?.flatten().collect();
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        let p = e.path();
        let ft = e.file_type().map_err(write_err(&p))?;
        if ft.is_dir() {
            hash_tree(root, &p, out)?;
        } else if ft.is_file() {
            let rel = p.strip_prefix(root).unwrap_or(&p).components().map(|c| c.as_os_str().to_string_lossy()).collect::<Vec<_>>().join("/");
            out.insert(rel, mvsplat360_dataset::atomic::sha256_file(&p).map_err(write_err(&p))?);
        }
    }
    Ok(())
}

/// Files and folders to disk before the commit point (a power loss must not commit a stage of empty files).
fn sync_tree(dir: &Path) -> std::io::Result<()> {
    for e in std::fs::read_dir(dir)?.flatten() {
        let p = e.path();
        if e.file_type()?.is_dir() {
            sync_tree(&p)?;
        } else {
            std::fs::File::open(&p)?.sync_all()?;
        }
    }
    sync_dir(dir);
    Ok(())
}

fn sync_dir(dir: &Path) {
    if let Ok(f) = std::fs::File::open(dir) {
        let _ = f.sync_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tree(root: &Path) -> BTreeMap<String, Vec<u8>> {
        fn walk(root: &Path, d: &Path, m: &mut BTreeMap<String, Vec<u8>>) {
            for e in std::fs::read_dir(d).unwrap().flatten() {
                let p = e.path();
                let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
                if rel.starts_with(DIR) {
                    continue;
                }
                if p.is_dir() {
                    walk(root, &p, m);
                } else {
                    m.insert(rel, std::fs::read(&p).unwrap());
                }
            }
        }
        let mut m = BTreeMap::new();
        walk(root, root, &mut m);
        m
    }

    fn write_run(dir: &Path, tag: &str, splat: bool) {
        std::fs::create_dir_all(dir.join("frames/final")).unwrap();
        std::fs::write(dir.join("frames/final/0000.png"), format!("{tag} frame")).unwrap();
        std::fs::write(dir.join("gaussians.ply"), format!("{tag} ply")).unwrap();
        std::fs::write(dir.join("cameras.json"), format!("{tag} cams")).unwrap();
        std::fs::write(dir.join("run.json"), format!("{tag} run")).unwrap();
        if splat {
            std::fs::write(dir.join("gaussians.splat"), format!("{tag} splat")).unwrap();
        }
    }

    /// A crash after any number of the swap's renames, then recovery: always the whole new run, never a file of
    /// the old one (the old had a `gaussians.splat`, the new has none), the user's own file untouched. A crash
    /// before the commit point leaves the old run whole.
    #[test]
    fn a_swap_interrupted_anywhere_recovers_to_the_whole_new_run() {
        let key: ResumeKey = [("input".to_string(), "x".to_string())].into();
        let new_only = {
            let d = tempfile::tempdir().unwrap();
            write_run(d.path(), "new", false);
            tree(d.path())
        };
        for crash_after in 0..20 {
            let d = tempfile::tempdir().unwrap();
            let out = d.path();
            write_run(out, "old", true);
            std::fs::write(out.join("notes.txt"), "mine").unwrap();
            let old = tree(out);
            let t = Txn::begin(out, &key, false, true, &|_| {}).unwrap();
            write_run(&t.stage, "new", false);
            // Before the commit point: the old run, whole.
            assert_eq!(tree(out), old);
            let dir = out.join(DIR);
            std::fs::rename(dir.join("stage"), dir.join("commit")).unwrap();
            drop(t);
            let finished = swap_steps(out, crash_after).unwrap();
            assert!(finished);
            // What a crash left, then the next process's recovery (10 steps: 5 entries out, the marker, 4 in).
            assert_eq!(recover(out).unwrap(), crash_after < 10, "crash after {crash_after} renames");
            let mut want = new_only.clone();
            want.insert("notes.txt".into(), b"mine".to_vec());
            assert_eq!(tree(out), want, "crash after {crash_after} renames");
            assert!(!dir.join("commit").exists() && !dir.join("old").exists() && !dir.join("installing").exists());
        }
    }

    #[test]
    fn resume_keeps_windows_of_the_same_render_and_names_what_differs() {
        let d = tempfile::tempdir().unwrap();
        let key: ResumeKey = [("input".to_string(), "a".to_string()), ("device".to_string(), "cpu".to_string())].into();
        let t = Txn::begin(d.path(), &key, false, true, &|_| {}).unwrap();
        let w = t.windows.clone().unwrap();
        std::fs::write(window_file(&w, 0), b"w").unwrap();
        std::fs::write(window_file(&w, 3), b"w").unwrap();
        std::fs::write(t.stage.join("frame.png"), b"half").unwrap();
        // Given up before the commit point (an error, Ctrl-C): the stage goes, the windows stay.
        drop(t);
        assert!(!d.path().join(DIR).join("stage").exists());
        let t = Txn::begin(d.path(), &key, true, true, &|_| {}).unwrap();
        assert_eq!(t.resumed, 2);
        drop(t);
        let mut other = key.clone();
        other.insert("device".into(), "cuda:0".into());
        let e = Txn::begin(d.path(), &other, true, true, &|_| {}).err().unwrap().to_string();
        assert!(e.contains("another device than this one") && e.contains("without --resume"), "{e}");
        // Without --resume the windows go.
        let t = Txn::begin(d.path(), &other, false, true, &|_| {}).unwrap();
        assert_eq!((t.resumed, count_windows(t.windows.as_ref().unwrap())), (0, 0));
        // A second render on the folder while one holds it is refused.
        let e = Txn::begin(d.path(), &other, false, true, &|_| {}).err().unwrap().to_string();
        assert!(e.contains("another render"), "{e}");
    }
}
