//! The pose tests' video: the test scene's 24 views (`assets/pose-test/orbit24`) as an H.264 video.

use std::path::{Path, PathBuf};
use std::process::Command;

/// `dir/orbit.mp4` made with `ffmpeg` (a program name or path).
pub fn orbit_video(dir: &Path, ffmpeg: &Path) -> PathBuf {
    let images = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/pose-test/orbit24/images");
    let mut frames: Vec<PathBuf> = std::fs::read_dir(&images).unwrap().map(|e| e.unwrap().path()).collect();
    frames.sort();
    let list = dir.join("frames.txt");
    std::fs::write(&list, frames.iter().map(|f| format!("file '{}'\nduration 0.125\n", f.display())).collect::<String>()).unwrap();
    let video = dir.join("orbit.mp4");
    let st = Command::new(ffmpeg)
        .args(["-v", "error", "-y", "-f", "concat", "-safe", "0", "-i"])
        .arg(&list)
        .args(["-c:v", "libx264", "-pix_fmt", "yuv420p", "-r", "8"])
        .arg(&video)
        .status()
        .expect("ffmpeg is not installed (scripts/test installs it: apt-get install -y ffmpeg colmap)");
    assert!(st.success());
    video
}
