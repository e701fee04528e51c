//! A render as a transaction. A render writes its files into `OUT/.render/stage/` (under the lock
//! `OUT/.render/lock`) and leaves the run in `OUT` alone until the new one is complete; then it swaps the new run
//! in. Every step of the swap is one file-system operation, and which folder exists under `OUT/.render/` says
//! how far it got, so that whoever opens the folder next ([`recover_if_free`]: `view`; [`Txn::begin`]: the next
//! render) finishes it from any step, a crash in that finishing included:
//!
//! 1. `stage/` → `commit/` (rename): the commit point. Before it the old run is whole (the next render starts a
//!    fresh stage, or `--resume` continues it).
//! 2. `commit/` present: phase 1 moves the old run's entries ([`ENTRIES`], `run.json` first) from `OUT` into
//!    `commit/.old/`, then renames `commit/` → `install/`; that rename is the phase's marker, so no marker file
//!    can outlive its folder.
//! 3. `install/` present: phase 2 moves the new entries into `OUT` (`run.json` last) and the resume state into
//!    `install/.resume/`, then renames `install/` → `trash/`: the swap is done.
//! 4. `trash/` present: the old run and the leftovers, removed file by file; anything under `trash/` is garbage.
//!
//! So a folder holds one whole run, old or new, as soon as anyone looks. Entries that are not the render's (a
//! posed `scene/`, the user's own files) are never moved. Recovery runs only under the lock: `view` finding a
//! render holding it leaves the folder as it is.
//!
//! Resume: `OUT/.render/resume/key.json` names what the interrupted render was (input, model, settings,
//! targets, device, dtype) and `OUT/.render/resume/windows/` holds each refined window as it finishes;
//! `render --resume` with the same key skips those windows. The resume folder goes with the swap (step 3).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use mvsplat360_dataset::atomic::{sync_dir, DirLock};

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
        if finish_swap(out)? {
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
        // The lock is held and `begin` finished any earlier swap: no `commit/`, `install/` or `trash/` is left.
        let commit = dir.join(COMMIT);
        step();
        std::fs::rename(&self.stage, &commit).map_err(write_err(&commit))?;
        sync_dir(&dir);
        finish_swap(&self.out)?;
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

const COMMIT: &str = "commit";
const INSTALL: &str = "install";
const TRASH: &str = "trash";
/// Inside `commit/` (then `install/`, `trash/`): the old run's entries, and the resume state.
const OLD: &str = ".old";
const RESUME: &str = ".resume";
/// What an older version of the swap left (its phase-1 folder and marker file): recognised and finished.
const LEGACY_OLD: &str = "old";
const LEGACY_MARKER: &str = "installing";

/// What [`recover_if_free`] did.
#[derive(Debug, PartialEq, Eq)]
pub enum Recovery {
    /// No swap was interrupted here (leftovers of a finished one may have been removed).
    Nothing,
    /// A swap interrupted after its commit point was finished: the folder holds the new run.
    Finished,
    /// An interrupted swap is there, but the render lock could not be taken (a render holds it: it is
    /// committing, and finishes the swap itself; or the folder cannot be written): left as it is. The lock's
    /// message.
    Busy(String),
}

/// For readers of a render's folder (`view`): finishes an interrupted swap under the render lock, then lets the
/// lock go. When a render holds the lock the folder is left alone (a reader shows it as it is). Takes no lock,
/// and writes nothing, when nothing is pending.
pub fn recover_if_free(out: &Path) -> Result<Recovery> {
    let dir = out.join(DIR);
    if ![COMMIT, INSTALL, TRASH, LEGACY_OLD, LEGACY_MARKER].iter().any(|n| dir.join(n).symlink_metadata().is_ok()) {
        return Ok(Recovery::Nothing);
    }
    let _lock = match DirLock::acquire(&dir.join("lock"), "render", "view the folder again when it is done") {
        Ok(l) => l,
        Err(m) => return Ok(Recovery::Busy(m)),
    };
    Ok(if finish_swap(out)? { Recovery::Finished } else { Recovery::Nothing })
}

/// Finishes a swap from whatever step it was interrupted at (true when one had passed its commit point); the
/// caller holds the render lock. Each state is recognised by the folder that exists, each step is one
/// file-system operation, so a crash anywhere here leaves a state this function finishes too.
fn finish_swap(out: &Path) -> Result<bool> {
    let dir = out.join(DIR);
    let (commit, install, trash) = (dir.join(COMMIT), dir.join(INSTALL), dir.join(TRASH));
    // Garbage of a finished swap (an older version's `old/` holds only the old run's entries, past its commit
    // point or finished).
    remove_tree(&trash)?;
    remove_tree(&dir.join(LEGACY_OLD))?;
    // An older version's marker: its phase 1 was done, `commit/` (if still there) is phase 2.
    let marker = dir.join(LEGACY_MARKER);
    if marker.symlink_metadata().is_ok() {
        if commit.is_dir() && install.symlink_metadata().is_err() {
            step();
            std::fs::rename(&commit, &install).map_err(write_err(&install))?;
            sync_dir(&dir);
        }
        step();
        std::fs::remove_file(&marker).map_err(write_err(&marker))?;
    }
    let mut swapped = false;
    if commit.is_dir() {
        move_old_out(out, &commit, &install)?;
        swapped = true;
    }
    if install.is_dir() {
        install_new(out, &install, &trash)?;
        swapped = true;
    }
    remove_tree(&trash)?;
    Ok(swapped)
}

/// Phase 1: the old run's entries from `OUT` into `commit/.old/`, then `commit/` → `install/`.
fn move_old_out(out: &Path, commit: &Path, install: &Path) -> Result<()> {
    let old = commit.join(OLD);
    if !old.is_dir() {
        step();
        std::fs::create_dir(&old).map_err(write_err(&old))?;
    }
    for e in ENTRIES {
        let (from, to) = (out.join(e), old.join(e));
        if from.symlink_metadata().is_ok() {
            // A rename moves: an entry is in one place or the other, unless someone put one back by hand.
            remove_tree(&to)?;
            step();
            std::fs::rename(&from, &to).map_err(write_err(&from))?;
        }
    }
    sync_dir(&old);
    sync_dir(out);
    step();
    std::fs::rename(commit, install).map_err(write_err(install))?;
    sync_dir(install.parent().unwrap_or(out));
    Ok(())
}

/// Phase 2: the new entries from `install/` into `OUT`, the resume state into `install/.resume/`, then
/// `install/` → `trash/`.
fn install_new(out: &Path, install: &Path, trash: &Path) -> Result<()> {
    for e in ENTRIES.iter().rev() {
        let (from, to) = (install.join(e), out.join(e));
        if from.symlink_metadata().is_ok() {
            // Phase 1 moved every entry out: one here was put back by hand (a folder would block the rename).
            remove_tree(&to)?;
            step();
            std::fs::rename(&from, &to).map_err(write_err(&to))?;
        }
    }
    // The resume state is the installed render's (the lock is held, and a render opens a new one only after
    // finishing any swap).
    let dir = install.parent().unwrap_or(out);
    let (resume, gone) = (dir.join("resume"), install.join(RESUME));
    if resume.symlink_metadata().is_ok() && gone.symlink_metadata().is_err() {
        step();
        std::fs::rename(&resume, &gone).map_err(write_err(&resume))?;
    }
    sync_dir(out);
    remove_tree(trash)?;
    step();
    std::fs::rename(install, trash).map_err(write_err(trash))?;
    sync_dir(dir);
    Ok(())
}

/// Removes a file or a folder (not following links), one file-system step per file and folder.
fn remove_tree(p: &Path) -> Result<()> {
    let Ok(m) = p.symlink_metadata() else { return Ok(()) };
    if m.is_dir() {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(p).map_err(write_err(p))?.flatten().map(|e| e.path()).collect();
        entries.sort();
        for e in entries {
            remove_tree(&e)?;
        }
        step();
        std::fs::remove_dir(p).map_err(write_err(p))
    } else {
        step();
        std::fs::remove_file(p).map_err(write_err(p))
    }
}

/// Steps left before the crash tests' crash (`usize::MAX`: none).
static CRASH_AFTER: AtomicUsize = AtomicUsize::new(usize::MAX);

/// Exit status of a process ended by [`crash_after_steps`].
#[doc(hidden)]
pub const CRASH_EXIT: i32 = 86;

/// For crash tests: the process exits ([`CRASH_EXIT`], no destructors run, the lock stays behind) just before
/// the swap's file-system step number `n` (0: before the commit point), in [`Txn::commit`] or a recovery.
#[doc(hidden)]
pub fn crash_after_steps(n: usize) {
    CRASH_AFTER.store(n, Ordering::SeqCst);
}

/// Called before each file-system step of the swap.
fn step() {
    let left = CRASH_AFTER.load(Ordering::SeqCst);
    if left == usize::MAX {
        return;
    }
    if left == 0 {
        std::process::exit(CRASH_EXIT);
    }
    CRASH_AFTER.store(left - 1, Ordering::SeqCst);
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

#[cfg(test)]
mod tests {
    use super::*;

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
