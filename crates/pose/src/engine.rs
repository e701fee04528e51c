//! The external programs `pose` drives (COLMAP, ffmpeg, ffprobe): finding them, reading COLMAP's version and
//! GPU support from `colmap -h`, and running each as a child in its own process group so that an interrupt
//! stops the whole tree (COLMAP starts worker threads, ffmpeg may start filters) and nothing outlives us.

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use serde::Serialize;

use crate::error::PoseError;

/// Debian's package for each program (the one-line fix of a missing program).
fn install_hint(program: &str) -> &'static str {
    match program {
        "colmap" => "sudo apt-get install -y colmap (or pass --colmap PATH)",
        _ => "sudo apt-get install -y ffmpeg (or pass --ffmpeg PATH)",
    }
}

/// An explicit path, else the first executable `name` on `PATH`.
pub fn find_program(name: &str, explicit: Option<&Path>) -> Result<PathBuf, PoseError> {
    if let Some(p) = explicit {
        if is_executable(p) {
            return Ok(p.to_path_buf());
        }
        return Err(PoseError::MissingProgram { program: name.into(), looked: p.display().to_string(), install: install_hint(name).into() });
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    for dir in std::env::split_paths(&path) {
        let p = dir.join(name);
        if is_executable(&p) {
            return Ok(p);
        }
    }
    Err(PoseError::MissingProgram { program: name.into(), looked: "PATH".into(), install: install_hint(name).into() })
}

fn is_executable(p: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(p).map(|m| m.is_file() && m.permissions().mode() & 0o111 != 0).unwrap_or(false)
}

/// `--colmap-gpu`: `auto` asks for COLMAP's GPU paths (SIFT extraction and matching) when it was built with
/// CUDA; `off` keeps a CUDA build on the CPU (`use_gpu 0`; its bundle adjustment runs on the CPU either way:
/// 3.x has no GPU option for it, later versions default it off).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ColmapGpu {
    #[default]
    Auto,
    Off,
}

/// What `colmap -h` says of the build.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ColmapInfo {
    pub path: PathBuf,
    /// As printed, e.g. `3.8` or `3.13.0`.
    pub version: String,
    /// Built with CUDA (`with CUDA` in the build line); only then are the GPU paths asked for.
    pub cuda: bool,
}

/// Parses the banner of `colmap -h`: `COLMAP 3.8 -- Structure-from-Motion …` then `(Commit … with CUDA)` or
/// `without CUDA` (3.x), or `COLMAP 4.1.0 (Commit … without GPU support)` (4.x).
pub fn parse_colmap_help(text: &str) -> Option<(String, bool)> {
    let line = text.lines().map(str::trim).find(|l| l.starts_with("COLMAP "))?;
    let version = line.split_whitespace().nth(1)?.to_string();
    if !version.starts_with(|c: char| c.is_ascii_digit()) {
        return None;
    }
    Some((version, text.contains("with CUDA")))
}

/// `3.13.0` → (3, 13, 0); missing parts are 0, a suffix such as `-dev` is ignored.
pub fn version_tuple(v: &str) -> (u32, u32, u32) {
    let mut it = v.split('.').map(|p| p.chars().take_while(char::is_ascii_digit).collect::<String>().parse::<u32>().unwrap_or(0));
    (it.next().unwrap_or(0), it.next().unwrap_or(0), it.next().unwrap_or(0))
}

impl ColmapInfo {
    pub fn probe(path: &Path) -> Result<ColmapInfo, PoseError> {
        let out = Command::new(path)
            .arg("-h")
            .stdin(Stdio::null())
            .output()
            .map_err(|e| PoseError::Engine { program: path.display().to_string(), msg: format!("cannot start it: {e}") })?;
        let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        let (version, cuda) = parse_colmap_help(&text).ok_or_else(|| PoseError::Engine {
            program: path.display().to_string(),
            msg: "`-h` printed no `COLMAP <version>` banner; is this COLMAP?".into(),
        })?;
        Ok(ColmapInfo { path: path.to_path_buf(), version, cuda })
    }

    /// 3.13 renamed `SiftExtraction.use_gpu` / `SiftMatching.use_gpu` (the options moved to
    /// `FeatureExtraction` / `FeatureMatching` when non-SIFT features came in).
    fn renamed_feature_options(&self) -> bool {
        version_tuple(&self.version) >= (3, 13, 0)
    }

    /// Whether the GPU paths are asked for: only from a CUDA build, and not under `--colmap-gpu off`.
    pub fn uses_gpu(&self, gpu: ColmapGpu) -> bool {
        self.cuda && gpu == ColmapGpu::Auto
    }

    pub fn extraction_gpu_flag(&self, gpu: ColmapGpu) -> [String; 2] {
        let name = if self.renamed_feature_options() { "FeatureExtraction" } else { "SiftExtraction" };
        [format!("--{name}.use_gpu"), if self.uses_gpu(gpu) { "1" } else { "0" }.into()]
    }

    pub fn matching_gpu_flag(&self, gpu: ColmapGpu) -> [String; 2] {
        let name = if self.renamed_feature_options() { "FeatureMatching" } else { "SiftMatching" };
        [format!("--{name}.use_gpu"), if self.uses_gpu(gpu) { "1" } else { "0" }.into()]
    }
}

/// The first line of `ffmpeg -version` (`ffmpeg version 5.1.6-0+deb12u1 Copyright …` → `5.1.6-0+deb12u1`).
pub fn ffmpeg_version(path: &Path) -> Result<String, PoseError> {
    let out = Command::new(path)
        .arg("-version")
        .stdin(Stdio::null())
        .output()
        .map_err(|e| PoseError::Engine { program: path.display().to_string(), msg: format!("cannot start it: {e}") })?;
    let text = String::from_utf8_lossy(&out.stdout);
    let first = text.lines().next().unwrap_or_default();
    Ok(first.split_whitespace().nth(2).unwrap_or("unknown").to_string())
}

/// One command as run, for the report.
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct CommandRecord {
    pub stage: String,
    pub argv: Vec<String>,
    pub seconds: f64,
    pub exit_code: Option<i32>,
}

/// The children now running (their process groups) and whether [`stop_children`] was called, under one lock:
/// a spawn registers its child before the lock is released, and the stop kills under it, so no child is
/// registered after the stop looked, and none starts after it.
struct Children {
    groups: Vec<i32>,
    stopped: bool,
}

static CHILDREN: Mutex<Children> = Mutex::new(Children { groups: Vec::new(), stopped: false });
static STOPPED: AtomicBool = AtomicBool::new(false);

/// The lock, even if a thread panicked while holding it (the list stays valid: every change is one push or
/// retain).
fn children() -> std::sync::MutexGuard<'static, Children> {
    CHILDREN.lock().unwrap_or_else(|e| e.into_inner())
}

/// Waits for `child` and unregisters it before reaping it: until reaped its pid (the group id) cannot be
/// reused, so the stop never signals another program's group.
pub(crate) fn wait_child(child: &mut std::process::Child) -> std::io::Result<std::process::ExitStatus> {
    let pid = child.id();
    loop {
        // SAFETY: waitid(2) writes only into `info`, a zeroed siginfo_t we own.
        let mut info: libc::siginfo_t = unsafe { std::mem::zeroed() };
        let r = unsafe { libc::waitid(libc::P_PID, pid as libc::id_t, &mut info, libc::WEXITED | libc::WNOWAIT) };
        if r == 0 || std::io::Error::last_os_error().raw_os_error() != Some(libc::EINTR) {
            break;
        }
    }
    children().groups.retain(|&p| p != pid as i32);
    child.wait()
}

/// Whether [`stop_children`] was called: a child's failure is then the interrupt, not the input's fault.
pub fn was_stopped() -> bool {
    STOPPED.load(Ordering::SeqCst)
}

/// Ends every child process group started by this crate (called from a Ctrl-C handler); later spawns are
/// refused.
pub fn stop_children() {
    let mut c = children();
    c.stopped = true;
    STOPPED.store(true, Ordering::SeqCst);
    for &pid in c.groups.iter() {
        // SAFETY: kill(2) on a process group id we created; no memory is touched.
        unsafe {
            libc::kill(-pid, libc::SIGTERM);
        }
    }
}

/// Starts `argv` (argv[0] = the program) with piped stdout and stderr in its own process group, registered for
/// [`stop_children`]; the caller waits for it with [`wait_child`]. Refused once the stop was called.
pub(crate) fn spawn_grouped(argv: &[String]) -> Result<std::process::Child, PoseError> {
    use std::os::unix::process::CommandExt;
    let program = argv.first().cloned().unwrap_or_default();
    let mut c = children();
    if c.stopped {
        return Err(PoseError::Engine { program, msg: "not started: pose was interrupted (Ctrl-C)".into() });
    }
    let child = Command::new(&program)
        .args(argv.get(1..).unwrap_or_default())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .process_group(0)
        .spawn()
        .map_err(|e| PoseError::Engine { program, msg: format!("cannot start it: {e}") })?;
    c.groups.push(child.id() as i32);
    Ok(child)
}

/// Runs `argv` (argv[0] = the program) in its own process group, feeding every line of its stdout and stderr
/// (merged, as the user would see them) to `on_line`, and keeping the whole log in `log_file`. A non-zero exit
/// is returned as the record's code, not as an error: the caller decides what a failure means (the mapper
/// exits 1 when it builds no model, which is a result).
pub fn run_logged(stage: &str, argv: &[String], log_file: &Path, on_line: &mut dyn FnMut(&str)) -> Result<CommandRecord, PoseError> {
    let t0 = Instant::now();
    let program = argv.first().cloned().unwrap_or_default();
    let engine_err = |msg: String| PoseError::Engine { program: program.clone(), msg };
    let mut log = std::fs::File::create(log_file).map_err(|e| PoseError::io(log_file, e))?;
    let mut child = spawn_grouped(argv)?;
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    let pump = |stream: Box<dyn Read + Send>, tx: std::sync::mpsc::Sender<String>| {
        std::thread::spawn(move || {
            // COLMAP ends progress lines with '\r' at times; split on both.
            let mut r = BufReader::new(stream);
            let mut buf = Vec::new();
            loop {
                buf.clear();
                match r.read_until(b'\n', &mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(_) => {
                        for part in String::from_utf8_lossy(&buf).split(['\r', '\n']).filter(|s| !s.is_empty()) {
                            if tx.send(part.to_string()).is_err() {
                                return;
                            }
                        }
                    }
                }
            }
        })
    };
    let h1 = child.stdout.take().map(|s| pump(Box::new(s), tx.clone()));
    let h2 = child.stderr.take().map(|s| pump(Box::new(s), tx.clone()));
    drop(tx);
    for line in rx {
        use std::io::Write;
        let _ = writeln!(log, "{line}");
        on_line(&line);
    }
    for h in [h1, h2].into_iter().flatten() {
        let _ = h.join();
    }
    let status = wait_child(&mut child).map_err(|e| engine_err(format!("lost the child process: {e}")))?;
    Ok(CommandRecord { stage: stage.into(), argv: argv.to_vec(), seconds: t0.elapsed().as_secs_f64(), exit_code: status.code() })
}

#[cfg(test)]
mod tests {
    use super::*;

    const HELP_3_8: &str = include_str!("../tests/data/help/colmap-3.8-help.txt");
    const HELP_3_13: &str = include_str!("../tests/data/help/colmap-3.13.0-cuda-help.txt");
    const HELP_4_1: &str = include_str!("../tests/data/help/colmap-4.1.0-help.txt");

    fn info(text: &str) -> ColmapInfo {
        let (version, cuda) = parse_colmap_help(text).expect("banner");
        ColmapInfo { path: "colmap".into(), version, cuda }
    }

    #[test]
    fn version_and_flags_from_recorded_help() {
        let i = info(HELP_3_8);
        assert_eq!((i.version.as_str(), i.cuda), ("3.8", false));
        assert_eq!(i.extraction_gpu_flag(ColmapGpu::Auto), ["--SiftExtraction.use_gpu".to_string(), "0".into()]);
        assert_eq!(i.matching_gpu_flag(ColmapGpu::Auto), ["--SiftMatching.use_gpu".to_string(), "0".into()]);

        let i = info(HELP_3_13);
        assert_eq!((i.version.as_str(), i.cuda), ("3.13.0", true));
        assert_eq!(i.extraction_gpu_flag(ColmapGpu::Auto), ["--FeatureExtraction.use_gpu".to_string(), "1".into()]);
        assert_eq!(i.matching_gpu_flag(ColmapGpu::Auto), ["--FeatureMatching.use_gpu".to_string(), "1".into()]);
        // `--colmap-gpu off` keeps a CUDA build on the CPU.
        assert_eq!(i.extraction_gpu_flag(ColmapGpu::Off), ["--FeatureExtraction.use_gpu".to_string(), "0".into()]);
        assert_eq!(i.matching_gpu_flag(ColmapGpu::Off), ["--FeatureMatching.use_gpu".to_string(), "0".into()]);

        let i = info(HELP_4_1);
        assert_eq!((i.version.as_str(), i.cuda), ("4.1.0", false));
        assert_eq!(i.extraction_gpu_flag(ColmapGpu::Auto)[0], "--FeatureExtraction.use_gpu");
    }

    #[test]
    fn not_colmap_is_refused() {
        assert_eq!(parse_colmap_help("usage: something else\n"), None);
        assert_eq!(parse_colmap_help("COLMAP is great\n"), None);
        assert_eq!(version_tuple("3.12.6"), (3, 12, 6));
        assert_eq!(version_tuple("3.8"), (3, 8, 0));
        assert_eq!(version_tuple("3.13.0-dev"), (3, 13, 0));
        assert!(version_tuple("3.12.6") < (3, 13, 0));
    }

    #[test]
    fn missing_program_names_the_install() {
        let e = find_program("colmap", Some(Path::new("/nonexistent/colmap"))).unwrap_err().to_string();
        assert!(e.contains("apt-get install -y colmap") && e.contains("/nonexistent/colmap"), "{e}");
        let e = find_program("ffmpeg", Some(Path::new("/nonexistent/ffmpeg"))).unwrap_err().to_string();
        assert!(e.contains("apt-get install -y ffmpeg"), "{e}");
    }

    #[test]
    fn children_log_lines_and_exit_codes() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("x.log");
        let mut lines = vec![];
        let argv: Vec<String> = ["sh", "-c", "echo one; printf 'two\\rthree\\n' >&2; exit 3"].iter().map(|s| s.to_string()).collect();
        let r = run_logged("t", &argv, &log, &mut |l| lines.push(l.to_string())).unwrap();
        assert_eq!(r.exit_code, Some(3));
        lines.sort();
        assert_eq!(lines, ["one", "three", "two"]);
        assert_eq!(std::fs::read_to_string(&log).unwrap().lines().count(), 3);
    }
}
