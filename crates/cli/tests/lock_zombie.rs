//! A render killed while it holds `--out/.render/lock` holds nothing: the lock is the kernel's (`flock`), gone
//! with its process, whether or not its parent has reaped it yet, and whatever pid its record names.
#![cfg(target_os = "linux")]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use mvsplat360_dataset::owner::{proc_stat, Owner};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The bundled scene with the shipped model (no refiner): about a second on two cores for 6 frames.
fn render(out: &Path, frames: &str) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_mvsplat360"));
    c.args(["--quiet", "render"]).arg(root().join("assets/woodbox"));
    c.args(["--orbit", frames, "--num-context", "3", "--fit-steps", "0", "--no-video", "--no-metrics", "--out"]).arg(out);
    c
}

/// Starts a long render into `out` and SIGKILLs it once it holds the lock (its record is written); not reaped.
fn killed_holding_the_lock(out: &Path) -> (Child, Owner) {
    let mut child = render(out, "400").stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
    let lock = out.join(".render/lock");
    let t = Instant::now();
    let owner = loop {
        if let Some(o) = std::fs::read_to_string(&lock).ok().and_then(|s| Owner::parse(&s)).filter(|o| o.pid == child.id()) {
            break o;
        }
        let state = proc_stat(child.id()).ok().flatten().map(|s| s.state);
        assert!(!matches!(state, Some('Z' | 'X') | None), "the render ended before it took its lock");
        assert!(t.elapsed() < Duration::from_secs(120), "the render never took its lock");
        std::thread::sleep(Duration::from_millis(2));
    };
    child.kill().unwrap();
    (child, owner)
}

fn completes(out: &Path) {
    let o = render(out, "6").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.join("run.json").is_file() && !out.join(".render/lock").exists());
}

#[test]
fn a_render_killed_and_not_reaped_does_not_hold_its_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let (mut child, owner) = killed_holding_the_lock(&out);
    // A zombie: its /proc entry stays until its parent (this test) reaps it.
    let t = Instant::now();
    while proc_stat(child.id()).ok().flatten().map(|s| (s.state, s.threads)) != Some(('Z', 1)) {
        assert!(t.elapsed() < Duration::from_secs(60), "the killed render never became a zombie");
        std::thread::sleep(Duration::from_millis(2));
    }
    assert!(Path::new(&format!("/proc/{}", child.id())).exists());
    assert_eq!(Owner::parse(&std::fs::read_to_string(out.join(".render/lock")).unwrap()), Some(owner), "SIGKILL runs no clean-up");
    completes(&out);
    child.wait().unwrap();
}

#[test]
fn a_killed_renders_lock_naming_a_live_unrelated_process_is_taken_over() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let (mut child, owner) = killed_holding_the_lock(&out);
    child.wait().unwrap();
    // Its pid, as if handed to another process since: a live one that has nothing to do with the folder.
    let mut other = Command::new("sleep").arg("30").spawn().unwrap();
    let record = Owner { pid: other.id(), ..owner }.record();
    std::fs::write(out.join(".render/lock"), format!("{record}\n")).unwrap();
    completes(&out);
    other.kill().unwrap();
    other.wait().unwrap();
}
