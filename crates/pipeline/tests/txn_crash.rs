//! The render transaction's swap killed at every file-system step (a child process that exits there, leaving its
//! lock and everything else behind, as a SIGKILL would), then the folder opened each way a user opens it next:
//! `view`'s recovery, the next render, `view`'s recovery itself killed at every step. Each time the folder holds
//! one whole run — the old one when the crash came before the commit point, else the new one, every file byte
//! for byte, `run.json`'s hashes those of the files — and a later render works. While a render holds the lock,
//! `view` changes nothing.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use mvsplat360_dataset::atomic::DirLock;
use mvsplat360_pipeline::txn::{self, Recovery, ResumeKey, Txn};

/// Set in the child: `commit:K` (commit the new run, dying before step K) or `view:K` (`view`'s recovery, dying
/// before step K).
const CHILD: &str = "MVSPLAT360_TXN_CRASH_CHILD";
const CHILD_OUT: &str = "MVSPLAT360_TXN_CRASH_OUT";

fn key(tag: &str) -> ResumeKey {
    [("input".to_string(), tag.to_string())].into()
}

/// A render's files. The runs have different entries (the old one a `.splat`, videos and ground truth; the new
/// one metrics and refined frames), so a folder mixing them differs from both.
fn run_files(tag: &str) -> Vec<(&'static str, String)> {
    let mut f = vec![
        ("frames/final/0000.png", format!("{tag} frame 0")),
        ("frames/final/0001.png", format!("{tag} frame 1")),
        ("gaussians.ply", format!("{tag} ply")),
        ("cameras.json", format!("{tag} cameras")),
    ];
    if tag == "old" {
        f.extend([
            ("frames/gt/0000.png", format!("{tag} gt")),
            ("gaussians.splat", format!("{tag} splat")),
            ("video.mp4", format!("{tag} video")),
            ("compare.mp4", format!("{tag} compare")),
        ]);
    } else {
        f.extend([("frames/refined/0000.png", format!("{tag} refined")), ("metrics.json", format!("{tag} metrics"))]);
    }
    f
}

/// Writes the run into the stage as `render` does: files, a finished refined window, then `run.json` with every
/// file's hash.
fn stage_run(t: &Txn, tag: &str) {
    for (rel, text) in run_files(tag) {
        let p = t.stage.join(rel);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, text).unwrap();
    }
    std::fs::write(txn::window_file(t.windows.as_ref().unwrap(), 0), tag).unwrap();
    let run = serde_json::json!({ "tag": tag, "files": t.hash_stage().unwrap() });
    std::fs::write(t.stage.join("run.json"), serde_json::to_vec_pretty(&run).unwrap()).unwrap();
}

fn render(out: &Path, tag: &str) {
    let t = Txn::begin(out, &key(tag), false, true, &|_| {}).unwrap();
    stage_run(&t, tag);
    t.commit().unwrap();
}

/// The user's own files beside the run: never moved.
fn add_user_files(out: &Path) {
    std::fs::create_dir_all(out.join("scene/images")).unwrap();
    std::fs::write(out.join("scene/images/a.png"), "photo").unwrap();
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
}

/// Every file under `root` (`.render/` too when `all`), by relative path, with its bytes; folders as `NAME/`.
fn tree(root: &Path, all: bool) -> BTreeMap<String, Vec<u8>> {
    fn walk(root: &Path, d: &Path, all: bool, m: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(d).unwrap().flatten() {
            let p = e.path();
            let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
            if !all && rel.starts_with(txn::DIR) {
                continue;
            }
            if p.is_dir() {
                m.insert(format!("{rel}/"), Vec::new());
                walk(root, &p, all, m);
            } else {
                m.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    let mut m = BTreeMap::new();
    walk(root, root, all, &mut m);
    m
}

/// The folder a render of `tag` leaves (user files included), outside `.render/`.
fn whole(tag: &str) -> BTreeMap<String, Vec<u8>> {
    let d = tempfile::tempdir().unwrap();
    render(d.path(), tag);
    add_user_files(d.path());
    tree(d.path(), false)
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let (p, q) = (e.path(), to.join(e.file_name()));
        if p.is_dir() {
            copy_tree(&p, &q);
        } else {
            std::fs::copy(&p, &q).unwrap();
        }
    }
}

/// Runs the child `what:k` on `out`: true when it crashed before step `k`, false when it finished.
fn child(what: &str, k: usize, out: &Path) -> bool {
    let o = Command::new(std::env::current_exe().unwrap())
        .args(["crash_child", "--exact", "--test-threads=1", "--nocapture"])
        .env(CHILD, format!("{what}:{k}"))
        .env(CHILD_OUT, out)
        .output()
        .unwrap();
    match o.status.code() {
        Some(0) => false,
        Some(txn::CRASH_EXIT) => true,
        _ => panic!("{what}:{k}: {}\n{}{}", o.status, String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)),
    }
}

/// The child process (does nothing in a plain test run).
#[test]
fn crash_child() {
    let Ok(spec) = std::env::var(CHILD) else { return };
    let out = PathBuf::from(std::env::var_os(CHILD_OUT).unwrap());
    let (what, k) = spec.split_once(':').unwrap();
    let k: usize = k.parse().unwrap();
    match what {
        "commit" => {
            let t = Txn::begin(&out, &key("new"), false, true, &|_| {}).unwrap();
            stage_run(&t, "new");
            txn::crash_after_steps(k);
            t.commit().unwrap();
        }
        "view" => {
            txn::crash_after_steps(k);
            txn::recover_if_free(&out).unwrap();
        }
        _ => unreachable!(),
    }
}

/// One whole run: `want` byte for byte outside `.render/`, `run.json` naming each render file with its hash, no
/// swap folder left.
fn assert_whole(out: &Path, want: &BTreeMap<String, Vec<u8>>, what: &str) {
    let got = tree(out, false);
    if got != *want {
        let keys = |m: &BTreeMap<String, Vec<u8>>| m.keys().cloned().collect::<Vec<_>>();
        panic!(
            "{what}: the folder is not one whole run\ngot:  {:?}\nwant: {:?}\n.render: {:?}",
            keys(&got),
            keys(want),
            keys(&tree(&out.join(txn::DIR), true))
        );
    }
    let run: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("run.json")).unwrap()).unwrap();
    let files = run["files"].as_object().unwrap();
    for (rel, sha) in files {
        assert_eq!(mvsplat360_dataset::atomic::sha256_file(&out.join(rel)).unwrap(), sha.as_str().unwrap(), "{what}: {rel}");
    }
    let listed = got.keys().filter(|k| !k.ends_with('/') && *k != "run.json" && !k.starts_with("scene") && *k != "notes.txt").count();
    assert_eq!(listed, files.len(), "{what}: files not in run.json");
    for left in ["commit", "install", "trash", "old", "installing"] {
        assert!(!out.join(txn::DIR).join(left).exists(), "{what}: .render/{left} left");
    }
}

/// The folder after the new run's commit was killed before step `k` (over the old run and the user's files):
/// whether it crashed.
fn crashed_commit(out: &Path, k: usize) -> bool {
    std::fs::create_dir(out).unwrap();
    render(out, "old");
    add_user_files(out);
    child("commit", k, out)
}

/// Everything under `.render/` but the lock (its record names the process).
fn swap_state(out: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut t = tree(&out.join(txn::DIR), true);
    t.remove("lock");
    t
}

fn is_pending(state: &BTreeMap<String, Vec<u8>>, dirs: &[&str]) -> bool {
    state.keys().any(|k| dirs.iter().any(|d| k.starts_with(&format!("{d}/"))))
}

#[test]
fn a_crash_at_every_step_of_the_swap_then_render_or_view_leaves_one_whole_run() {
    let t0 = std::time::Instant::now();
    let (old, new, later) = (whole("old"), whole("new"), whole("later"));
    let d = tempfile::tempdir().unwrap();
    // What `.render/` holds after a crash before each step.
    let mut states = Vec::new();
    for k in 0.. {
        let crashed_in = d.path().join(format!("crashed_{k}"));
        let crashed = crashed_commit(&crashed_in, k);
        let want = if k == 0 { &old } else { &new };
        let what = format!("crash before step {k}");
        let state = swap_state(&crashed_in);
        if !crashed {
            assert_whole(&crashed_in, &new, "no crash");
        }

        // `view` while a render holds the lock: nothing changes.
        let out = d.path().join("view_busy");
        copy_tree(&crashed_in, &out);
        let lock = DirLock::acquire(&out.join(".render/lock"), "render", "wait").unwrap();
        let before = tree(&out, true);
        match txn::recover_if_free(&out).unwrap() {
            Recovery::Busy(why) => assert!(why.contains("render"), "{what}: {why}"),
            Recovery::Nothing if !is_pending(&state, &["commit", "install", "trash"]) => {}
            r => panic!("{what}: {r:?} while a render holds the lock"),
        }
        assert_eq!(tree(&out, true), before, "{what}: view changed the folder while a render held the lock");
        drop(lock);
        std::fs::remove_dir_all(&out).unwrap();

        // `view` next, then later renders.
        let out = d.path().join("view");
        copy_tree(&crashed_in, &out);
        let r = txn::recover_if_free(&out).unwrap();
        assert_eq!(r == Recovery::Finished, is_pending(&state, &["commit", "install"]), "{what}: {r:?}");
        assert_whole(&out, want, &format!("{what}, then view"));
        render(&out, "later");
        assert_whole(&out, &later, &format!("{what}, then view, then a render"));
        assert!(!out.join(".render/resume").exists(), "{what}: the resume state outlived the swap");
        render(&out, "new");
        assert_whole(&out, &new, &format!("{what}, then view, then two renders"));
        std::fs::remove_dir_all(&out).unwrap();

        // The next render: its begin finishes the swap, its commit replaces the run.
        let out = crashed_in;
        let t = Txn::begin(&out, &key("later"), false, true, &|_| {}).unwrap();
        assert_whole(&out, want, &format!("{what}, then a render's begin"));
        stage_run(&t, "later");
        t.commit().unwrap();
        assert_whole(&out, &later, &format!("{what}, then a render"));
        std::fs::remove_dir_all(&out).unwrap();

        states.push(state);
        if !crashed {
            break;
        }
    }
    let steps = states.len() - 1;
    // The commit point; phase 1: `.old/`, the old run's 7 entries, the rename to `install/`; phase 2: the new
    // run's 5 entries, the resume state, the rename to `trash/`; then the trash's 18 files and folders.
    assert_eq!(steps, 35, "the steps of the swap changed: adjust this count after checking the crash hook still runs");

    // `view`'s recovery killed before each of its steps, from right after the commit point (where it has every
    // step left to do): it stops where the commit would have (the recovery continues the same sequence of steps),
    // and `view` again finishes it.
    for j in 0.. {
        let out = d.path().join(format!("view_crash_{j}"));
        assert!(crashed_commit(&out, 1));
        let view_crashed = child("view", j, &out);
        assert_eq!(swap_state(&out), states[(1 + j).min(steps)], "view crashing before its step {j}");
        let r = txn::recover_if_free(&out).unwrap();
        assert!(!matches!(r, Recovery::Busy(_)), "view crashing before its step {j}, then view: {r:?}");
        assert_whole(&out, &new, &format!("view crashing before its step {j}, then view"));
        std::fs::remove_dir_all(&out).unwrap();
        if !view_crashed {
            assert_eq!(j, steps - 1);
            break;
        }
    }
    eprintln!("{steps} steps, {:.1} s", t0.elapsed().as_secs_f64());
}

/// What the previous version of the swap left when killed (the marker file `installing` that its clean-up removed
/// after `commit/`, its `old/` folder): the next render or `view` finishes it, and later renders work.
#[test]
fn an_older_versions_half_swap_is_finished() {
    let new = whole("new");
    let later = whole("later");
    let staged = tempfile::tempdir().unwrap();
    render(staged.path(), "new");
    const ALL_OLD: &[&str] = &["run.json", "video.mp4", "compare.mp4", "frames", "gaussians.splat", "gaussians.ply", "cameras.json"];
    // (entries moved out by its phase 1, entries installed by its phase 2, marker, `commit/` still there)
    let cases: &[(&[&str], &[&str], bool, bool)] = &[
        (&["run.json", "video.mp4"], &[], false, true),
        (ALL_OLD, &[], true, true),
        (ALL_OLD, &["cameras.json", "gaussians.ply"], true, true),
        // The bug: killed between removing `commit/` and the marker; every later render failed.
        (ALL_OLD, &["cameras.json", "gaussians.ply", "frames", "metrics.json", "run.json"], true, false),
    ];
    for (i, (moved, installed, marker, commit_left)) in cases.iter().enumerate() {
        for by_view in [false, true] {
            let d = tempfile::tempdir().unwrap();
            let out = d.path();
            render(out, "old");
            add_user_files(out);
            let dir = out.join(txn::DIR);
            let (commit, old) = (dir.join("commit"), dir.join("old"));
            std::fs::create_dir_all(&old).unwrap();
            copy_tree(staged.path(), &commit);
            std::fs::remove_dir_all(commit.join(txn::DIR)).unwrap();
            for e in *moved {
                std::fs::rename(out.join(e), old.join(e)).unwrap();
            }
            if *marker {
                std::fs::write(dir.join("installing"), "phase 2: installing the new run\n").unwrap();
            }
            for e in *installed {
                std::fs::rename(commit.join(e), out.join(e)).unwrap();
            }
            if !commit_left {
                std::fs::remove_dir_all(&old).unwrap();
                std::fs::remove_dir_all(&commit).unwrap();
            }
            let what = format!("case {i}, then {}", if by_view { "view" } else { "a render" });
            if by_view {
                assert_eq!(txn::recover_if_free(out).unwrap(), if *commit_left { Recovery::Finished } else { Recovery::Nothing }, "{what}");
                assert_whole(out, &new, &what);
            }
            render(out, "later");
            assert_whole(out, &later, &format!("{what}, then a render"));
        }
    }
}
