//! Progress bars on stderr for the pipeline's stages, or the same events as JSON lines (`--progress json`, read
//! by `mvsplat360 app`; format in docs/app.md), the `MVSPLAT360_HOLD_AT` test hook, and clean-up of
//! half-written files on Ctrl-C.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};
use mvsplat360_pipeline::render::Progress;

/// How progress is shown (`--progress`).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ProgressMode {
    /// Bars on stderr (hidden when stderr is not a terminal; notes as lines).
    Bars,
    /// One JSON object per line (begin, advance, position, end, note, then result or error) instead of bars and
    /// notes; other messages stay on stderr. See docs/app.md.
    Json,
}

/// Where JSON progress lines go, once `--progress json` is set: stdout, or the `--progress-file`.
struct JsonOut {
    sink: Mutex<Box<dyn Write + Send>>,
    t0: Instant,
    /// The stage under way, its position and total, and when an `advance` line was last written.
    state: Mutex<(String, u64, u64, Option<Instant>)>,
}

static JSON: OnceLock<JsonOut> = OnceLock::new();

/// Advances closer together than this are folded into the next line (a stage's last one is always written).
const JSON_EVERY: Duration = Duration::from_millis(100);

/// Turn JSON progress lines on (before any command runs): to `file` (created or truncated), or stdout.
pub fn enable_json(file: Option<&Path>) -> anyhow::Result<()> {
    let sink: Box<dyn Write + Send> = match file {
        Some(p) => Box::new(std::fs::File::create(p).map_err(|e| anyhow::anyhow!("--progress-file {}: {e}", p.display()))?),
        None => Box::new(std::io::stdout()),
    };
    let _ = JSON.set(JsonOut { sink: Mutex::new(sink), t0: Instant::now(), state: Mutex::new((String::new(), 0, 0, None)) });
    Ok(())
}

/// Whether JSON progress lines are on.
pub fn json_enabled() -> bool {
    JSON.get().is_some()
}

/// Write one JSON progress line (with `t`, seconds since the start) when JSON progress is on.
pub fn emit(mut v: serde_json::Value) {
    let Some(j) = JSON.get() else { return };
    if let Some(o) = v.as_object_mut() {
        o.insert("t".into(), serde_json::json!((j.t0.elapsed().as_secs_f64() * 1000.0).round() / 1000.0));
    }
    if let Ok(mut s) = j.sink.lock() {
        let _ = writeln!(s, "{v}");
        let _ = s.flush();
    }
}

fn json_begin(stage: &str, total: u64) {
    if let Some(j) = JSON.get() {
        if let Ok(mut st) = j.state.lock() {
            *st = (stage.to_string(), 0, total, None);
        }
        emit(serde_json::json!({"event": "begin", "stage": stage, "total": total}));
    }
}

/// A stage's position moved (`advance`: by `n`; `set`: to `pos`); written at most every [`JSON_EVERY`].
fn json_move(by: Option<u64>, to: Option<u64>, total: Option<u64>) {
    let Some(j) = JSON.get() else { return };
    let line = {
        let Ok(mut st) = j.state.lock() else { return };
        st.1 = to.unwrap_or(st.1 + by.unwrap_or(0));
        if let Some(t) = total {
            st.2 = t;
        }
        let last = st.1 >= st.2 && st.2 > 0;
        if !last && total.is_none() && st.3.is_some_and(|w| w.elapsed() < JSON_EVERY) {
            return;
        }
        st.3 = Some(Instant::now());
        serde_json::json!({"event": "advance", "stage": st.0, "pos": st.1, "total": st.2})
    };
    emit(line);
}

fn json_end() {
    let Some(j) = JSON.get() else { return };
    let (stage, pos, total) = match j.state.lock() {
        Ok(st) => (st.0.clone(), st.1, st.2),
        Err(_) => return,
    };
    emit(serde_json::json!({"event": "end", "stage": stage, "pos": pos, "total": total}));
}

/// The test hook (docs/app.md): with `MVSPLAT360_HOLD_AT=STAGE` and `MVSPLAT360_HOLD_WHILE=FILE` set, a stage
/// named STAGE waits after it begins while FILE exists, so a test can act on a job at a known point (cancel it,
/// reload the page) without sleeps. Not for normal use.
fn hold_hook(stage: &str) {
    let (Some(at), Some(file)) = (std::env::var_os("MVSPLAT360_HOLD_AT"), std::env::var_os("MVSPLAT360_HOLD_WHILE")) else { return };
    if at != stage {
        return;
    }
    let file = PathBuf::from(file);
    if file.exists() {
        emit(serde_json::json!({"event": "note", "msg": format!("held at stage {stage:?} while {} exists (MVSPLAT360_HOLD_AT test hook)", file.display())}));
    }
    while file.exists() {
        std::thread::sleep(Duration::from_millis(50));
    }
}

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
        json_move(None, Some(pos), None);
        self.with_bar(|pb| pb.set_position(pos));
    }
    fn set_total(&self, total: u64) {
        json_move(None, None, Some(total));
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
        if json_enabled() {
            json_begin(stage, total);
            hold_hook(stage);
            return;
        }
        hold_hook(stage);
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
        json_move(Some(n), None, None);
        if let Ok(b) = self.bar.lock() {
            if let Some(pb) = b.as_ref() {
                pb.inc(n);
            }
        }
    }

    fn end(&self) {
        json_end();
        if let Ok(mut b) = self.bar.lock() {
            if let Some(pb) = b.take() {
                pb.finish();
            }
        }
    }

    fn note(&self, msg: &str) {
        if json_enabled() {
            return emit(serde_json::json!({"event": "note", "msg": msg}));
        }
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
        emit(serde_json::json!({"event": "error", "code": 130, "msg": "interrupted: complete files were kept, partial ones removed"}));
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
