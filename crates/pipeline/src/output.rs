//! Output writers. Every file is written under a temporary name in the same folder and renamed into place,
//! so an interrupted run leaves only complete files; `.partial` leftovers of this process or of a killed one on
//! this host are removed by the next run (and by the Ctrl-C handler of the CLI); other processes' are left alone.

use std::path::Path;

use mvsplat360_dataset::ImageF32;

use crate::error::{PipelineError, Result};

pub use mvsplat360_dataset::atomic::PARTIAL_SUFFIX;

/// Held (shared) by every write in progress; an interrupt handler takes it exclusively, so that once it holds
/// it no temporary file is being written or can appear (see [`stop_writes`]).
static WRITE_GATE: std::sync::RwLock<()> = std::sync::RwLock::new(());

/// Wait for the writes in progress to finish and keep new ones from starting (for as long as the returned
/// guard lives; an interrupt handler cleans up and exits while holding it).
pub fn stop_writes() -> std::sync::RwLockWriteGuard<'static, ()> {
    WRITE_GATE.write().unwrap_or_else(|e| e.into_inner())
}

/// Write `path` through `write(tmp)` then rename; on failure the temporary file is removed.
pub fn atomic_write(path: &Path, write: impl FnOnce(&Path) -> std::result::Result<(), String>) -> Result<()> {
    let _gate = WRITE_GATE.read().unwrap_or_else(|e| e.into_inner());
    atomic_write_ungated(path, write)
}

/// [`atomic_write`] outside the interrupt gate, for long writes outside the output folder (the converted-weights
/// cache) that Ctrl-C should not wait for; a leftover `.partial` there is overwritten by the next conversion.
pub fn atomic_write_ungated(path: &Path, write: impl FnOnce(&Path) -> std::result::Result<(), String>) -> Result<()> {
    mvsplat360_dataset::atomic::write_atomic(path, |tmp| write(tmp).map_err(std::io::Error::other))
        .map_err(|e| PipelineError::Write { path: path.to_path_buf(), msg: e.to_string() })
}

/// Write bytes atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    atomic_write(path, |p| std::fs::write(p, bytes).map_err(|e| e.to_string()))
}

/// Whether an error's text is the OS's "no space left" (ENOSPC; also what a quota or a full tmpfs says).
pub fn disk_full(msg: &str) -> bool {
    msg.contains("No space left on device") || msg.contains("(os error 28)") || msg.contains("Disk quota exceeded")
}

/// Write a JSON value atomically (pretty-printed).
/// `create_dir_all`, its failure a write error naming the folder.
pub fn create_dir(d: &Path) -> Result<()> {
    std::fs::create_dir_all(d).map_err(|e| PipelineError::Write { path: d.to_path_buf(), msg: e.to_string() })
}

pub fn write_json(path: &Path, v: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(v).map_err(|e| PipelineError::Write { path: path.to_path_buf(), msg: e.to_string() })?;
    write_bytes(path, text.as_bytes())
}

/// Write an f32 CHW image as an 8-bit PNG atomically.
pub fn write_png(path: &Path, img: &ImageF32) -> Result<()> {
    let rgb = img.to_rgb8();
    atomic_write(path, |p| rgb.save_with_format(p, image::ImageFormat::Png).map_err(|e| e.to_string()))
}

/// Remove this process's `*.partial` files and those of dead processes on this host, recursively under `dir`
/// ([`mvsplat360_dataset::atomic::stale_partial`]).
pub fn remove_partials(dir: &Path) {
    let Ok(rd) = std::fs::read_dir(dir) else { return };
    for e in rd.flatten() {
        let p = e.path();
        if p.is_dir() {
            remove_partials(&p);
        } else if mvsplat360_dataset::atomic::stale_partial(&p) {
            let _ = std::fs::remove_file(&p);
        }
    }
}

/// Make sure `dir` exists and is writable before the heavy work starts (the flag is named on failure).
pub fn check_writable(dir: &Path, flag: &'static str) -> Result<()> {
    let err = |msg: String| PipelineError::Flag { flag, msg: format!("{}: {msg}", dir.display()) };
    if dir.exists() && !dir.is_dir() {
        return Err(err("exists and is not a folder".into()));
    }
    std::fs::create_dir_all(dir).map_err(|e| err(format!("cannot create the folder: {e}")))?;
    let probe = dir.join(format!(".write-test-{}{PARTIAL_SUFFIX}", std::process::id()));
    std::fs::write(&probe, b"").map_err(|e| err(format!("folder is not writable: {e}")))?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

/// (3,H,W) f32 tensor → image.
pub fn tensor_image(t: &candle_core::Tensor) -> Result<ImageF32> {
    let (c, h, w) = t.dims3().map_err(crate::error::compute("image"))?;
    if c != 3 {
        return Err(PipelineError::Compute { stage: "image", msg: format!("expected 3 channels, got {c}") });
    }
    let data = t.to_dtype(candle_core::DType::F32).and_then(|t| t.flatten_all()).and_then(|t| t.to_vec1::<f32>()).map_err(crate::error::compute("image"))?;
    Ok(ImageF32 { width: w as u32, height: h as u32, data })
}

/// f32 image → 8-bit video frame.
pub fn video_frame(img: &ImageF32) -> crate::video::Frame {
    crate::video::Frame { width: img.width, height: img.height, rgb: img.to_rgb8().into_raw() }
}
