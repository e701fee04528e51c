//! The stop (Ctrl-C) and the spawns, in a process of their own (the stop is for the whole process): a child
//! running when it comes is ended, and none starts after it.

use std::time::{Duration, Instant};

use mvsplat360_pose::engine::{run_logged, was_stopped};

#[test]
fn after_the_stop_no_child_runs_and_none_starts() {
    let d = tempfile::tempdir().unwrap();
    let pids = d.path().join("pids");
    let log = d.path().join("child.log");
    let argv: Vec<String> = ["sh".to_string(), "-c".into(), format!("echo $$ >> '{}'; exec sleep 1000", pids.display())].into();
    let (tx, rx) = std::sync::mpsc::channel();
    // Children one after another, as the stages start them, until a spawn is refused.
    std::thread::spawn(move || loop {
        if let Err(e) = run_logged("t", &argv, &log, &mut |_| {}) {
            let _ = tx.send(e.to_string());
            return;
        }
    });
    let t = Instant::now();
    while std::fs::read_to_string(&pids).unwrap_or_default().lines().next().is_none() {
        assert!(t.elapsed() < Duration::from_secs(30), "no child started within 30 s");
        std::thread::sleep(Duration::from_millis(5));
    }
    mvsplat360_pose::stop_children();
    assert!(was_stopped());
    // A child missed by the stop would sleep on and keep the loop from ever reaching a refused spawn.
    let msg = rx.recv_timeout(Duration::from_secs(30)).expect("30 s after the stop a child still runs");
    assert!(msg.contains("not started") && msg.contains("interrupted"), "{msg}");
    for pid in std::fs::read_to_string(&pids).unwrap().lines() {
        let state = std::fs::read_to_string(format!("/proc/{pid}/stat"))
            .ok()
            .and_then(|s| s.rsplit(')').next().and_then(|r| r.split_whitespace().next().map(String::from)));
        assert!(matches!(state.as_deref(), None | Some("Z")), "child {pid} is still running ({state:?})");
    }
}
