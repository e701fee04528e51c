//! Progress bars on stderr for the pipeline's stages, and clean-up of half-written files on Ctrl-C.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use indicatif::{ProgressBar, ProgressStyle};
use mvsplat360_pipeline::render::Progress;

pub struct Bars {
    quiet: bool,
    bar: Mutex<Option<ProgressBar>>,
}

impl Bars {
    pub fn new(quiet: bool) -> Self {
        Self { quiet, bar: Mutex::new(None) }
    }
}

impl Bars {
    fn with_bar(&self, f: impl FnOnce(&ProgressBar)) {
        if let Ok(b) = self.bar.lock() {
            if let Some(pb) = b.as_ref() {
                f(pb);
            }
        }
    }
}

/// `pose` feeds its bars from COLMAP's log lines, which say where a stage is rather than how far it moved.
impl mvsplat360_pose::Progress for Bars {
    fn begin(&self, stage: &str, total: u64) {
        Progress::begin(self, stage, total)
    }
    fn set(&self, pos: u64) {
        self.with_bar(|pb| pb.set_position(pos));
    }
    fn set_total(&self, total: u64) {
        self.with_bar(|pb| pb.set_length(total));
    }
    fn end(&self) {
        Progress::end(self)
    }
    fn note(&self, msg: &str) {
        Progress::note(self, msg)
    }
}

impl Progress for Bars {
    fn begin(&self, stage: &str, total: u64) {
        if self.quiet {
            return;
        }
        let pb = if total > 0 {
            let pb = ProgressBar::new(total);
            pb.set_style(
                ProgressStyle::with_template("{msg:>14} [{bar:30}] {pos}/{len} {elapsed_precise} ETA {eta}")
                    .unwrap_or_else(|_| ProgressStyle::default_bar())
                    .progress_chars("=> "),
            );
            pb
        } else {
            let pb = ProgressBar::new_spinner();
            pb.enable_steady_tick(std::time::Duration::from_millis(200));
            pb
        };
        pb.set_message(stage.to_string());
        if let Ok(mut b) = self.bar.lock() {
            *b = Some(pb);
        }
    }

    fn advance(&self, n: u64) {
        if let Ok(b) = self.bar.lock() {
            if let Some(pb) = b.as_ref() {
                pb.inc(n);
            }
        }
    }

    fn end(&self) {
        if let Ok(mut b) = self.bar.lock() {
            if let Some(pb) = b.take() {
                pb.finish();
            }
        }
    }

    fn note(&self, msg: &str) {
        if self.quiet {
            return;
        }
        match self.bar.lock().ok().and_then(|b| b.clone()) {
            // A hidden bar (stderr not a terminal: logs, pipes) would drop the line.
            Some(pb) if !pb.is_hidden() => pb.println(msg),
            _ => eprintln!("{msg}"),
        }
    }
}

static OUT_DIRS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// On Ctrl-C (or SIGTERM) remove the `*.partial` files under `dir` before exiting with 130, so the folder
/// holds only complete files.
pub fn clean_partials_on_interrupt(dir: &Path) {
    if let Ok(mut d) = OUT_DIRS.lock() {
        d.push(dir.to_path_buf());
    }
    let _ = ctrlc::set_handler(|| {
        // COLMAP and ffmpeg run in their own process groups, which the terminal's Ctrl-C does not reach.
        mvsplat360_pose::stop_children();
        // Held until exit: the write in progress finishes (renamed into place) and no new one starts.
        let _gate = mvsplat360_pipeline::output::stop_writes();
        if let Ok(d) = OUT_DIRS.lock() {
            for dir in d.iter() {
                mvsplat360_pipeline::output::remove_partials(dir);
            }
        }
        eprintln!("interrupted: complete files were kept, partial ones removed");
        std::process::exit(130);
    });
}

/// A download bar for the Hub client (weights and data by name): bytes with speed and ETA on stderr, the
/// client's notes (waiting for another process, a cached copy used offline) as lines; nothing when quiet.
pub struct DownloadBar {
    quiet: bool,
    bar: Mutex<Option<ProgressBar>>,
}

impl DownloadBar {
    pub fn new(quiet: bool) -> Self {
        Self { quiet, bar: Mutex::new(None) }
    }
}

impl mvsplat360_hub::Progress for DownloadBar {
    fn note(&self, msg: &str) {
        if self.quiet {
            return;
        }
        match self.bar.lock().ok().and_then(|b| b.clone()) {
            Some(pb) if !pb.is_hidden() => pb.println(msg),
            _ => eprintln!("{msg}"),
        }
    }
    fn start(&self, file: &str, total: Option<u64>, resumed_from: u64) {
        if self.quiet {
            return;
        }
        let pb = ProgressBar::new(total.unwrap_or(0));
        pb.set_style(
            ProgressStyle::with_template("{msg:>14} [{bar:30}] {bytes}/{total_bytes} {bytes_per_sec} ETA {eta}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        pb.set_position(resumed_from);
        let name = file.rsplit('/').next().unwrap_or(file);
        pb.set_message(name.to_string());
        if pb.is_hidden() {
            let from = if resumed_from > 0 { format!(" (resuming at {resumed_from} bytes)") } else { String::new() };
            eprintln!("downloading {file}{from}");
        }
        if let Ok(mut b) = self.bar.lock() {
            *b = Some(pb);
        }
    }
    fn advance(&self, bytes: u64) {
        if let Ok(b) = self.bar.lock() {
            if let Some(pb) = b.as_ref() {
                pb.inc(bytes);
            }
        }
    }
    fn finish(&self, _file: &str) {
        if let Ok(mut b) = self.bar.lock() {
            if let Some(pb) = b.take() {
                pb.finish_and_clear();
            }
        }
    }
}
