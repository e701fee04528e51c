//! The app's jobs: one folder each under `WORKDIR/jobs/` (`input/`, the render's `out/`, `job.json`), run one at a
//! time by a runner thread as child processes of this binary (`render --progress json`) in process groups of
//! their own; their JSON progress lines and log become the page's events.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use mvsplat360_viewer::http::EventSource;
use serde::{Deserialize, Serialize};

use super::settings::Settings;

/// How long a cancelled job has after SIGTERM before its group gets SIGKILL.
pub const GRACE: Duration = Duration::from_secs(10);
/// Log lines kept in `job.json` (the last ones).
const LOG_KEEP: usize = 400;

#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum State {
    Queued,
    Running,
    Done,
    Failed,
    Cancelled,
    /// Running or queued when the app stopped: resumable.
    Interrupted,
}

/// One stage of a run, as the progress lines told it.
#[derive(Serialize, Deserialize, Clone, Debug, Default)]
pub struct Stage {
    pub name: String,
    pub pos: u64,
    pub total: u64,
    pub done: bool,
}

/// `job.json`.
#[derive(Serialize, Deserialize, Clone, Debug)]
pub struct Job {
    pub id: String,
    /// Seconds since the Unix epoch.
    pub created: u64,
    /// What was given: "12 photos + transforms.json", "a video", or the scene folder's path.
    pub input: String,
    /// The path `render` reads.
    pub scene: PathBuf,
    pub settings: Settings,
    pub state: State,
    /// The CLI's error (its `error` line, or its last stderr line) when failed.
    pub error: Option<String>,
    /// The stages of the last run, in order.
    pub stages: Vec<Stage>,
    /// The running child's process id (= its process group), while it runs.
    pub pid: Option<u32>,
    /// The next run continues the last (`render --resume`).
    pub resume: bool,
    pub log: Vec<String>,
}

impl Job {
    /// The job without its log (the events and the job list).
    pub fn summary(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(self).unwrap_or_default();
        if let Some(o) = v.as_object_mut() {
            o.remove("log");
            o.insert("log_lines".into(), self.log.len().into());
        }
        v
    }
}

/// The jobs, their folders and the queue; shared by the routes and the runner.
pub struct Jobs {
    pub root: PathBuf,
    pub events: EventSource,
    exe: PathBuf,
    inner: Mutex<Inner>,
    wake: Condvar,
}

struct Inner {
    jobs: Vec<Job>,
    queue: VecDeque<String>,
    /// The running job: its id, child pid and whether it was cancelled.
    running: Option<(String, u32, Arc<AtomicBool>)>,
    stopping: bool,
}

fn now() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

/// Signal a whole process group (`pid` is its leader's id).
pub fn signal_group(pid: u32, sig: libc::c_int) {
    // SAFETY: kill(2) with a negative id signals the group; no memory is passed.
    unsafe {
        libc::kill(-(pid as libc::pid_t), sig);
    }
}

/// Whether any process of the group is left.
pub fn group_alive(pid: u32) -> bool {
    // SAFETY: signal 0 checks only.
    unsafe { libc::kill(-(pid as libc::pid_t), 0) == 0 }
}

impl Jobs {
    /// Read the jobs under `root` (created when missing); those that were running or queued are interrupted.
    pub fn open(root: PathBuf, events: EventSource) -> anyhow::Result<Arc<Self>> {
        let exe = std::env::current_exe().map_err(|e| anyhow::anyhow!("this program's path: {e}"))?;
        let mut jobs = Vec::new();
        if let Ok(rd) = std::fs::read_dir(&root) {
            for e in rd.flatten() {
                let Ok(bytes) = std::fs::read(e.path().join("job.json")) else { continue };
                let Ok(mut j) = serde_json::from_slice::<Job>(&bytes) else { continue };
                if matches!(j.state, State::Running | State::Queued) {
                    j.state = State::Interrupted;
                    j.pid = None;
                    j.resume = true;
                    write_job(&root, &j);
                }
                jobs.push(j);
            }
        }
        jobs.sort_by(|a, b| a.id.cmp(&b.id));
        let inner = Inner { jobs, queue: VecDeque::new(), running: None, stopping: false };
        Ok(Arc::new(Self { root, events, exe, inner: Mutex::new(inner), wake: Condvar::new() }))
    }

    pub fn dir(&self, id: &str) -> PathBuf {
        self.root.join(id)
    }

    /// A new job's id and folder (created): `job-0001`, … one past the highest.
    pub fn new_dir(&self) -> std::io::Result<(String, PathBuf)> {
        std::fs::create_dir_all(&self.root)?;
        let inner = self.inner.lock().unwrap();
        let mut n = inner.jobs.iter().filter_map(|j| j.id.strip_prefix("job-")?.parse::<u32>().ok()).max().unwrap_or(0) + 1;
        loop {
            let id = format!("job-{n:04}");
            let dir = self.root.join(&id);
            match std::fs::create_dir(&dir) {
                Ok(()) => return Ok((id, dir)),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => n += 1,
                Err(e) => return Err(e),
            }
        }
    }

    /// Queue a new job (its folder made by [`Jobs::new_dir`], its input in place).
    pub fn add(&self, id: String, input: String, scene: PathBuf, settings: Settings) -> Job {
        let j = Job {
            id: id.clone(),
            created: now(),
            input,
            scene,
            settings,
            state: State::Queued,
            error: None,
            stages: Vec::new(),
            pid: None,
            resume: false,
            log: Vec::new(),
        };
        write_job(&self.root, &j);
        let mut inner = self.inner.lock().unwrap();
        inner.jobs.push(j.clone());
        inner.queue.push_back(id);
        drop(inner);
        self.publish(&j);
        self.wake.notify_all();
        j
    }

    pub fn list(&self) -> Vec<serde_json::Value> {
        self.inner.lock().unwrap().jobs.iter().rev().map(Job::summary).collect()
    }

    pub fn get(&self, id: &str) -> Option<Job> {
        self.inner.lock().unwrap().jobs.iter().find(|j| j.id == id).cloned()
    }

    /// Change a job, write its `job.json` and tell the pages.
    fn update(&self, id: &str, f: impl FnOnce(&mut Job)) -> Option<Job> {
        let j = {
            let mut inner = self.inner.lock().unwrap();
            let j = inner.jobs.iter_mut().find(|j| j.id == id)?;
            f(j);
            j.clone()
        };
        write_job(&self.root, &j);
        self.publish(&j);
        Some(j)
    }

    fn publish(&self, j: &Job) {
        self.events.send("job", &j.summary().to_string());
    }

    /// Cancel: a queued job leaves the queue; a running one gets SIGTERM on its group, SIGKILL after [`GRACE`].
    pub fn cancel(self: &Arc<Self>, id: &str) -> Result<Job, (u16, String)> {
        let mut inner = self.inner.lock().unwrap();
        let state = inner.jobs.iter().find(|j| j.id == id).map(|j| j.state).ok_or((404, "no such job".to_string()))?;
        match state {
            State::Queued => {
                inner.queue.retain(|q| q != id);
                drop(inner);
                Ok(self
                    .update(id, |j| {
                        j.state = State::Cancelled;
                        j.resume = true;
                    })
                    .unwrap())
            }
            State::Running => {
                if let Some((rid, pid, flag)) = inner.running.clone() {
                    if rid == id && !flag.swap(true, Ordering::SeqCst) {
                        signal_group(pid, libc::SIGTERM);
                        let me = self.clone();
                        std::thread::spawn(move || me.kill_after_grace(&rid, pid));
                    }
                }
                let j = inner.jobs.iter().find(|j| j.id == id).cloned().unwrap();
                Ok(j)
            }
            s => Err((409, format!("the job is {s:?}, not queued or running").to_lowercase())),
        }
    }

    fn kill_after_grace(&self, id: &str, pid: u32) {
        let t0 = std::time::Instant::now();
        while t0.elapsed() < GRACE {
            let same = self.inner.lock().unwrap().running.as_ref().is_some_and(|r| r.0 == id && r.1 == pid);
            if !same {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        signal_group(pid, libc::SIGKILL);
    }

    /// Queue an interrupted, cancelled or failed job again, continuing its render (`--resume`).
    pub fn resume(&self, id: &str) -> Result<Job, (u16, String)> {
        let mut inner = self.inner.lock().unwrap();
        let j = inner.jobs.iter().find(|j| j.id == id).ok_or((404, "no such job".to_string()))?;
        if !matches!(j.state, State::Interrupted | State::Cancelled | State::Failed) {
            return Err((409, format!("the job is {:?}; only an interrupted, cancelled or failed job resumes", j.state).to_lowercase()));
        }
        inner.queue.push_back(id.to_string());
        drop(inner);
        let j = self
            .update(id, |j| {
                j.state = State::Queued;
                j.error = None;
                j.resume = true;
            })
            .unwrap();
        self.wake.notify_all();
        Ok(j)
    }

    /// Stop for the app's exit: no new job starts; the running one's group gets SIGTERM, then SIGKILL after
    /// [`GRACE`]; it is marked interrupted.
    pub fn stop_all(&self) {
        let running = {
            let mut inner = self.inner.lock().unwrap();
            inner.stopping = true;
            inner.running.clone()
        };
        let Some((id, pid, _)) = running else { return };
        signal_group(pid, libc::SIGTERM);
        let t0 = std::time::Instant::now();
        while group_alive(pid) && t0.elapsed() < GRACE {
            std::thread::sleep(Duration::from_millis(50));
        }
        signal_group(pid, libc::SIGKILL);
        let mut inner = self.inner.lock().unwrap();
        if let Some(j) = inner.jobs.iter_mut().find(|j| j.id == id) {
            j.state = State::Interrupted;
            j.pid = None;
            j.resume = true;
            write_job(&self.root, j);
        }
    }

    /// The runner: takes queued jobs one at a time, for as long as the app runs. It must stay one long-lived
    /// thread: the children's parent-death signal follows the thread that started them.
    pub fn run_queue(self: Arc<Self>) {
        loop {
            let id = {
                let mut inner = self.inner.lock().unwrap();
                loop {
                    if !inner.stopping {
                        if let Some(id) = inner.queue.pop_front() {
                            break id;
                        }
                    }
                    inner = self.wake.wait(inner).unwrap();
                }
            };
            self.run_job(&id);
        }
    }

    fn run_job(self: &Arc<Self>, id: &str) {
        let Some(job) = self.get(id) else { return };
        let out = self.dir(id).join("out");
        let mut cmd = Command::new(&self.exe);
        cmd.args(["--progress", "json", "render"]).arg(&job.scene).arg("--out").arg(&out).args(job.settings.render_args());
        if job.resume && out.join(".render").exists() {
            cmd.arg("--resume");
        }
        cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
        start_in_own_group(&mut cmd);
        let child = match cmd.spawn() {
            Ok(c) => c,
            Err(e) => {
                self.update(id, |j| {
                    j.state = State::Failed;
                    j.error = Some(format!("cannot start {}: {e}", self.exe.display()));
                });
                return;
            }
        };
        let cancelled = Arc::new(AtomicBool::new(false));
        self.inner.lock().unwrap().running = Some((id.to_string(), child.id(), cancelled.clone()));
        self.update(id, |j| {
            j.state = State::Running;
            j.pid = Some(child.id());
            j.stages.clear();
            j.error = None;
            j.log.push(format!("$ mvsplat360 render {} --out {} {}", j.scene.display(), out.display(), j.settings.render_args().join(" ")));
        });
        let (code, error) = self.follow(id, child);
        let pid = self.inner.lock().unwrap().running.take().map(|r| r.1);
        // Nothing of the group may stay behind (a grandchild that ignored the signal).
        if let Some(pid) = pid {
            signal_group(pid, libc::SIGKILL);
        }
        let was_cancelled = cancelled.load(Ordering::SeqCst);
        let stopping = self.inner.lock().unwrap().stopping;
        self.update(id, |j| {
            j.pid = None;
            j.state = match (code, was_cancelled, stopping) {
                (_, _, true) => State::Interrupted,
                (_, true, _) => State::Cancelled,
                (Some(0), _, _) => State::Done,
                _ => State::Failed,
            };
            j.resume = j.state != State::Done;
            if j.state == State::Failed {
                j.error = Some(error.unwrap_or_else(|| format!("render exited with {}", code.map_or("a signal".into(), |c| format!("code {c}")))));
            }
        });
    }

    /// Read the child's progress (stdout) and log (stderr) until it exits: its exit code and its error line.
    fn follow(self: &Arc<Self>, id: &str, mut child: Child) -> (Option<i32>, Option<String>) {
        let err_lines = child.stderr.take().map(|e| {
            let me = self.clone();
            let id = id.to_string();
            std::thread::spawn(move || {
                let mut last = None;
                for line in BufReader::new(e).lines().map_while(Result::ok) {
                    if let Some(m) = line.strip_prefix("error: ") {
                        last = Some(m.to_string());
                    }
                    me.log(&id, line);
                }
                last
            })
        });
        let mut error = None;
        if let Some(o) = child.stdout.take() {
            for line in BufReader::new(o).lines().map_while(Result::ok) {
                match serde_json::from_str::<serde_json::Value>(&line) {
                    Ok(v) if v.get("event").is_some() => {
                        if v["event"] == "error" {
                            error = v["msg"].as_str().map(String::from);
                        }
                        self.progress(id, &v);
                    }
                    _ => self.log(id, line),
                }
            }
        }
        let code = child.wait().ok().and_then(|s| s.code());
        let stderr_error = err_lines.and_then(|t| t.join().ok()).flatten();
        (code, error.or(stderr_error))
    }

    fn log(&self, id: &str, line: String) {
        self.events.send("log", &serde_json::json!({"id": id, "line": line}).to_string());
        let mut inner = self.inner.lock().unwrap();
        if let Some(j) = inner.jobs.iter_mut().find(|j| j.id == id) {
            j.log.push(line);
            if j.log.len() > LOG_KEEP {
                let cut = j.log.len() - LOG_KEEP;
                j.log.drain(..cut);
            }
        }
    }

    /// One JSON progress line of the child.
    fn progress(&self, id: &str, v: &serde_json::Value) {
        let stage = v["stage"].as_str().unwrap_or("").to_string();
        let (pos, total) = (v["pos"].as_u64().unwrap_or(0), v["total"].as_u64().unwrap_or(0));
        match v["event"].as_str() {
            Some("begin") => {
                self.update(id, |j| j.stages.push(Stage { name: stage, pos: 0, total, done: false }));
            }
            Some("advance") => {
                self.update(id, |j| {
                    if let Some(s) = j.stages.last_mut() {
                        (s.pos, s.total) = (pos, total);
                    }
                });
            }
            Some("end") => {
                self.update(id, |j| {
                    if let Some(s) = j.stages.last_mut() {
                        s.done = true;
                        if s.total > 0 {
                            s.pos = s.total;
                        }
                    }
                });
            }
            Some("note") | Some("error") => self.log(id, v["msg"].as_str().unwrap_or("").to_string()),
            _ => {}
        }
    }
}

/// A process group of its own (the app's Ctrl-C does not reach it; cancel signals the group), and SIGTERM when
/// the app dies (Linux), so that no job outlives it.
fn start_in_own_group(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    cmd.process_group(0);
    #[cfg(target_os = "linux")]
    // SAFETY: prctl is async-signal-safe; nothing is allocated between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
            Ok(())
        });
    }
}

/// Write `job.json` whole (a temporary file renamed into place).
pub fn write_job(root: &Path, j: &Job) {
    let path = root.join(&j.id).join("job.json");
    let tmp = path.with_extension("json.tmp");
    if let Ok(bytes) = serde_json::to_vec_pretty(j) {
        if std::fs::write(&tmp, bytes).is_ok() {
            let _ = std::fs::rename(&tmp, &path);
        }
    }
}
