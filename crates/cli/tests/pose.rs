//! `mvsplat360 pose` stopped by Ctrl-C (SIGINT) once a stage has finished: exit 130, no scene folder, COLMAP's
//! children gone, the finished stages kept; the rerun continues from them and writes the scene.
//! Needs Debian's colmap and ffmpeg (scripts/test installs them).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod orbit;
use orbit::orbit_video;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_mvsplat360")
}

/// The hidden work folder `pose` keeps beside the scene.
fn work_dir(parent: &Path) -> Option<PathBuf> {
    std::fs::read_dir(parent).unwrap().map(|e| e.unwrap().path()).find(|p| p.file_name().unwrap().to_string_lossy().starts_with(".scene.pose-"))
}

/// COLMAP processes whose command line names this test's folder.
fn colmap_children(dir: &Path) -> usize {
    let needle = dir.display().to_string();
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| std::fs::read(e.ok()?.path().join("cmdline")).ok())
        .map(|c| String::from_utf8_lossy(&c).replace('\0', " "))
        .filter(|c| c.contains("colmap") && c.contains(&needle))
        .count()
}

#[test]
fn an_interrupted_pose_leaves_no_scene_and_the_rerun_continues() {
    let d = tempfile::tempdir().unwrap();
    let video = orbit_video(d.path(), Path::new("ffmpeg"));
    let scene = d.path().join("scene");
    let mut child =
        Command::new(bin()).args(["--quiet", "pose"]).arg(&video).arg("--out").arg(&scene).args(["--frames", "24"]).stderr(Stdio::piped()).spawn().unwrap();
    // Stop it as soon as the features are extracted, while the matcher runs.
    let t = Instant::now();
    let work = loop {
        if let Some(w) = work_dir(d.path()).filter(|w| w.join("features.done").is_file()) {
            break w;
        }
        assert!(child.try_wait().unwrap().is_none(), "pose ended before its features were extracted");
        assert!(t.elapsed() < Duration::from_secs(60), "no features.done after 60 s");
        std::thread::sleep(Duration::from_millis(10));
    };
    let st = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(st.success());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{stderr}");
    assert!(stderr.contains("interrupted"), "{stderr}");
    assert!(!scene.exists(), "a half scene was left at {}", scene.display());
    for f in ["frames.json", "features.done", "database.db", "images"] {
        assert!(work.join(f).exists(), "{f} was not kept in {}", work.display());
    }
    // The matcher, in its own process group, was stopped too, not left running.
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(colmap_children(d.path()), 0, "COLMAP still runs after the interrupt");

    let out = Command::new(bin()).args(["--quiet", "pose"]).arg(&video).arg("--out").arg(&scene).args(["--frames", "24", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let reused: Vec<&str> = report["seconds"]["reused"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
    assert!(reused.starts_with(&["frames", "features"]), "reused {reused:?}");
    let stages: Vec<&str> = report["seconds"]["stages"].as_array().unwrap().iter().map(|s| s[0].as_str().unwrap()).collect();
    assert!(!stages.contains(&"frames") && !stages.contains(&"features"), "stages run again: {stages:?}");
    assert_eq!(report["registered"], 24);
    assert!(scene.join("sparse/0/images.bin").is_file() && scene.join("pose.json").is_file());
    assert!(work_dir(d.path()).is_none(), "the work folder is left after success");
}
