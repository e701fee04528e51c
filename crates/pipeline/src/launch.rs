//! The multi-process launcher of `train --world-size N` and `eval --world-size N`: one program runs itself again
//! as N *ranks*, each finding its place ([`Place::from_env`]) in the environment; the launcher waits for them,
//! forwards an interrupt, and stops the others when one fails. What the ranks share beyond their place (a
//! gradient hub, an NCCL id) is the caller's, passed as extra environment.

use std::process::{Child, Command, ExitStatus};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

pub const ENV_RANK: &str = "MVSPLAT360_DIST_RANK";
pub const ENV_WORLD: &str = "MVSPLAT360_DIST_WORLD";

/// Why a launch did not complete.
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    /// A rank exited with an error (the others were stopped).
    #[error("{0}; the other ranks were stopped")]
    Failed(String),
    /// The ranks stopped on request (exit code 130).
    #[error("interrupted")]
    Interrupted,
    #[error("launcher: {0}")]
    Io(String),
}

/// This process's place among the ranks of a launch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Place {
    pub rank: usize,
    pub world: usize,
}

impl Place {
    /// The launcher's variables, when this process is a rank (None when it is not).
    pub fn from_env() -> Result<Option<Self>, LaunchError> {
        let Ok(rank) = std::env::var(ENV_RANK) else { return Ok(None) };
        let num = |name: &str, v: &str| v.parse::<usize>().map_err(|_| LaunchError::Io(format!("{name}: `{v}` is not a number")));
        let rank = num(ENV_RANK, &rank)?;
        let world = num(ENV_WORLD, &std::env::var(ENV_WORLD).map_err(|_| LaunchError::Io(format!("{ENV_WORLD}: missing")))?)?;
        if world == 0 || rank >= world {
            return Err(LaunchError::Io(format!("{ENV_RANK}: rank {rank} of world size {world}")));
        }
        Ok(Some(Self { rank, world }))
    }
}

/// How the ranks of [`launch`] run.
pub struct LaunchSpec {
    pub world: usize,
    /// On the CPU the ranks share the cores: each gets `RAYON_NUM_THREADS` = cores / world unless set.
    pub cpu: bool,
    /// Given to every rank besides its place.
    pub env: Vec<(String, String)>,
}

/// Starts `spec.world` ranks, `command(r)` each with its place in the environment, and waits for them. Ranks
/// inherit stdout and stderr. When `stop` turns true the ranks are asked to stop (SIGTERM, once: each finishes
/// its unit of work). When a rank fails, the others are killed (a rank whose peer died may wait forever).
pub fn launch(spec: &LaunchSpec, mut command: impl FnMut(usize) -> Command, stop: &AtomicBool) -> Result<(), LaunchError> {
    let world = spec.world;
    if world == 0 {
        return Err(LaunchError::Io("--world-size must be at least 1".into()));
    }
    let threads = (spec.cpu && std::env::var_os("RAYON_NUM_THREADS").is_none())
        .then(|| (std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1) / world).max(1));
    let mut children: Vec<Child> = Vec::with_capacity(world);
    for r in 0..world {
        let mut c = command(r);
        c.envs(spec.env.iter().map(|(k, v)| (k.as_str(), v.as_str()))).env(ENV_WORLD, world.to_string()).env(ENV_RANK, r.to_string());
        // A group of their own: a terminal's Ctrl-C reaches the launcher only, which forwards one SIGTERM (a
        // second signal would make a rank exit without finishing its unit of work).
        #[cfg(unix)]
        std::os::unix::process::CommandExt::process_group(&mut c, 0);
        if let Some(t) = threads {
            c.env("RAYON_NUM_THREADS", t.to_string());
        }
        match c.spawn() {
            Ok(ch) => children.push(ch),
            Err(e) => {
                kill_all(&mut children);
                return Err(LaunchError::Io(format!("starting rank {r}: {e}")));
            }
        }
    }
    let mut status: Vec<Option<ExitStatus>> = vec![None; world];
    let mut forwarded = false;
    let mut failed: Vec<String> = Vec::new();
    while status.iter().any(Option::is_none) {
        if stop.load(Ordering::SeqCst) && !forwarded {
            forwarded = true;
            for (c, s) in children.iter().zip(&status) {
                if s.is_none() {
                    terminate(c);
                }
            }
        }
        for (r, c) in children.iter_mut().enumerate() {
            if status[r].is_none() {
                if let Some(s) = c.try_wait().map_err(|e| LaunchError::Io(format!("rank {r}: {e}")))? {
                    status[r] = Some(s);
                    if !s.success() && s.code() != Some(130) {
                        failed.push(format!("rank {r} {s}"));
                    }
                }
            }
        }
        if !failed.is_empty() {
            kill_all(&mut children);
            for (r, c) in children.iter_mut().enumerate() {
                if status[r].is_none() {
                    status[r] = c.wait().ok();
                }
            }
            return Err(LaunchError::Failed(failed.join(", ")));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    if status.iter().any(|s| s.is_some_and(|s| s.code() == Some(130))) {
        return Err(LaunchError::Interrupted);
    }
    Ok(())
}

/// Runs this program again as `spec.world` ranks with its arguments unchanged and waits for them.
pub fn launch_self(spec: &LaunchSpec, stop: &AtomicBool) -> Result<(), LaunchError> {
    let exe = std::env::current_exe().map_err(|e| LaunchError::Io(format!("this program's path: {e}")))?;
    let args: Vec<std::ffi::OsString> = std::env::args_os().skip(1).collect();
    launch(
        spec,
        |_| {
            let mut c = Command::new(&exe);
            c.args(&args);
            c
        },
        stop,
    )
}

fn kill_all(children: &mut [Child]) {
    for c in children.iter_mut() {
        let _ = c.kill();
    }
}

/// SIGTERM: the rank finishes its unit of work and exits (its handler), where SIGKILL would lose it.
fn terminate(c: &Child) {
    #[cfg(unix)]
    unsafe {
        libc::kill(c.id() as libc::pid_t, libc::SIGTERM);
    }
    #[cfg(not(unix))]
    let _ = c;
}
