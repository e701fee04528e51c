//! Ranks: where a process stands among the processes of one run ([`Place::from_env`]), whichever launcher started
//! it — the project's own `--world-size N` (below: one program runs itself again as N ranks, waits for them,
//! forwards an interrupt and stops the others when one fails), torchrun, SLURM's srun or Open MPI's mpirun — and
//! which GPU it takes ([`Place::gpu`]) — and where ranks that must meet find rank 0 ([`Rendezvous::from_vars`]:
//! training; `eval` needs no rendezvous). What the ranks share beyond that (a gradient hub, an NCCL id) is the
//! caller's, passed as extra environment.

use std::net::IpAddr;
use std::process::{Child, Command, ExitStatus};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

pub const ENV_RANK: &str = "MVSPLAT360_DIST_RANK";
pub const ENV_WORLD: &str = "MVSPLAT360_DIST_WORLD";
/// `host:port` of rank 0's rendezvous; set by this program's own launcher, and wins over MASTER_ADDR/MASTER_PORT.
pub const ENV_ADDR: &str = "MVSPLAT360_DIST_ADDR";
/// The rendezvous port under an outside launcher (default: MASTER_PORT, under torchrun MASTER_PORT + 1).
pub const ENV_PORT: &str = "MVSPLAT360_DIST_PORT";
/// Seconds a rank waits for the rendezvous and for each collective (default [`DEFAULT_TIMEOUT`]).
pub const ENV_TIMEOUT: &str = "MVSPLAT360_DIST_TIMEOUT";
/// PyTorch's default process-group timeout; it must outlast rank 0's checkpoint writes, which the others wait out.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(1800);

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
    /// The rendezvous variables are missing or wrong (the message names the variable and the fix).
    #[error("{0}")]
    Rendezvous(String),
}

/// Which launcher started this process as a rank.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Launcher {
    /// This program's own `--world-size N` (one machine).
    Project,
    /// `torchrun --no-python … mvsplat360 …`.
    Torchrun,
    /// `srun mvsplat360 …` inside a SLURM job step.
    Slurm,
    /// Open MPI's `mpirun`.
    Mpi,
}

impl Launcher {
    pub fn name(self) -> &'static str {
        match self {
            Self::Project => "--world-size",
            Self::Torchrun => "torchrun",
            Self::Slurm => "srun",
            Self::Mpi => "mpirun",
        }
    }
}

/// This process's place among the ranks of a launch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Place {
    pub rank: usize,
    pub world: usize,
    /// Rank among the ranks on this machine, and how many run here (where the launcher says).
    pub local_rank: usize,
    pub local_world: Option<usize>,
    pub launcher: Launcher,
}

impl Place {
    /// The launcher's variables, when this process is a rank (None when it is not).
    pub fn from_env() -> Result<Option<Self>, LaunchError> {
        Self::from_vars(&|k| std::env::var(k).ok())
    }

    /// [`Place::from_env`] over any variable lookup. The project's own variables first (its ranks may run under a
    /// cluster's job), then torchrun's (which wins over SLURM's when torchrun runs inside a job), then SLURM's
    /// inside a job step only (the batch script itself, without `SLURM_STEP_ID`, is not a rank), then Open MPI's.
    pub fn from_vars(get: &dyn Fn(&str) -> Option<String>) -> Result<Option<Self>, LaunchError> {
        let num = |name: &str| -> Result<Option<usize>, LaunchError> {
            match get(name) {
                None => Ok(None),
                Some(v) => v.trim().parse::<usize>().map(Some).map_err(|_| LaunchError::Io(format!("{name}: `{v}` is not a number"))),
            }
        };
        let need = |name: &str, launcher: &str| -> Result<usize, LaunchError> {
            num(name)?.ok_or_else(|| LaunchError::Io(format!("{name} is not set, though {launcher} started this process")))
        };
        let place = if let Some(rank) = num(ENV_RANK)? {
            let world = need(ENV_WORLD, "this program's launcher")?;
            Self { rank, world, local_rank: rank, local_world: Some(world), launcher: Launcher::Project }
        } else if let Some(rank) = num("RANK")?.filter(|_| get("WORLD_SIZE").is_some()) {
            let world = need("WORLD_SIZE", "torchrun")?;
            let local_rank = need("LOCAL_RANK", "torchrun")?;
            Self { rank, world, local_rank, local_world: num("LOCAL_WORLD_SIZE")?, launcher: Launcher::Torchrun }
        } else if get("SLURM_STEP_ID").is_some() && get("SLURM_PROCID").is_some() {
            let rank = need("SLURM_PROCID", "srun")?;
            let world = need("SLURM_NTASKS", "srun")?;
            let local_rank = need("SLURM_LOCALID", "srun")?;
            let node = num("SLURM_NODEID")?.unwrap_or(0);
            let local_world = get("SLURM_STEP_TASKS_PER_NODE").or_else(|| get("SLURM_TASKS_PER_NODE")).and_then(|v| tasks_on_node(&v, node));
            Self { rank, world, local_rank, local_world, launcher: Launcher::Slurm }
        } else if let Some(rank) = num("OMPI_COMM_WORLD_RANK")? {
            let world = need("OMPI_COMM_WORLD_SIZE", "mpirun")?;
            let local_rank = need("OMPI_COMM_WORLD_LOCAL_RANK", "mpirun")?;
            // No rendezvous address here: `eval` needs none, and training's rendezvous asks for its own.
            Self { rank, world, local_rank, local_world: num("OMPI_COMM_WORLD_LOCAL_SIZE")?, launcher: Launcher::Mpi }
        } else {
            return Ok(None);
        };
        if place.world == 0 || place.rank >= place.world {
            return Err(LaunchError::Io(format!("{}: rank {} of world size {}", place.launcher.name(), place.rank, place.world)));
        }
        if place.local_world.is_some_and(|l| place.local_rank >= l) {
            return Err(LaunchError::Io(format!(
                "{}: local rank {} of {} on this machine",
                place.launcher.name(),
                place.local_rank,
                place.local_world.unwrap_or(0)
            )));
        }
        Ok(Some(place))
    }

    /// Whether the ranks span more than one machine, as far as the launcher says (more ranks than run here).
    pub fn multi_node(&self) -> bool {
        self.local_world.is_some_and(|l| l < self.world)
    }

    /// The GPU index this rank uses among the `visible` ones: the only one when the launcher gave each rank its own
    /// (`srun --gpus-per-task=1`, or `CUDA_VISIBLE_DEVICES` set per rank), else the local rank's when the whole
    /// machine is visible to each rank; `first` (from `--device cuda:N`) offsets the project's own ranks, which
    /// share one machine.
    pub fn gpu(&self, visible: usize, first: usize) -> Result<usize, LaunchError> {
        if self.launcher == Launcher::Project {
            return Ok(first + self.rank);
        }
        let local_world = self.local_world.unwrap_or(self.local_rank + 1);
        match visible {
            0 => Err(LaunchError::Io(format!("rank {}: no GPU is visible to this process (CUDA_VISIBLE_DEVICES)", self.rank))),
            1 => Ok(0),
            v if v >= local_world => Ok(self.local_rank),
            v => Err(LaunchError::Io(format!(
                "rank {} (local rank {} of {local_world}): {v} GPUs are visible, neither one per rank nor one for each of the {local_world} ranks here; \
                 give each rank one GPU (srun --gpus-per-task=1) or every rank all of them",
                self.rank, self.local_rank
            ))),
        }
    }
}

/// Where the ranks of a run meet: rank 0's `host:port`, and how long each waits there and in each collective.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Rendezvous {
    pub addr: String,
    pub timeout: Duration,
}

impl Rendezvous {
    /// Read for `place`: [`ENV_ADDR`] (this program's launcher), else `MASTER_ADDR` and the port [`ENV_PORT`], else
    /// `MASTER_PORT` — plus one under torchrun, whose own store holds `MASTER_PORT`. A multi-node place whose
    /// address is loopback on every machine is refused, naming the variable.
    pub fn from_vars(place: &Place, get: &dyn Fn(&str) -> Option<String>) -> Result<Self, LaunchError> {
        let who = place.launcher.name();
        let err = |what: &str, msg: String| LaunchError::Rendezvous(format!("{what}: {msg}"));
        // mpirun passes no rendezvous address of its own; the others are started by scripts that set one.
        let hint = if place.launcher == Launcher::Mpi {
            "mpirun passes none: start it as `mpirun -x MASTER_ADDR=<rank 0's host> -x MASTER_PORT=<free port> …`"
        } else {
            "scripts/slurm/train.sbatch sets them from `scontrol show hostnames`"
        };
        // The address and the variable it came from, as given.
        let (var, given, addr) = match get(ENV_ADDR) {
            Some(a) => (ENV_ADDR, a.rsplit_once(':').map_or(a.as_str(), |(h, _)| h).to_string(), a),
            None => {
                let host = get("MASTER_ADDR").filter(|h| !h.trim().is_empty()).ok_or_else(|| {
                    err(who, format!("MASTER_ADDR is not set: training ranks meet at rank 0's host; set MASTER_ADDR and MASTER_PORT ({hint})"))
                })?;
                let port = match get(ENV_PORT) {
                    Some(p) => p.trim().parse::<u16>().map_err(|_| err(ENV_PORT, format!("`{p}` is not a port")))?,
                    None => {
                        let p = get("MASTER_PORT").ok_or_else(|| err(who, format!("MASTER_PORT is not set (rank 0's rendezvous port; {hint})")))?;
                        let p = p.trim().parse::<u16>().map_err(|_| err("MASTER_PORT", format!("`{p}` is not a port")))?;
                        if place.launcher == Launcher::Torchrun {
                            p.checked_add(1).ok_or_else(|| err("MASTER_PORT", format!("{p} + 1 is not a port; set {ENV_PORT}")))?
                        } else {
                            p
                        }
                    }
                };
                let host = host.trim();
                let addr = if host.contains(':') && !host.starts_with('[') { format!("[{host}]:{port}") } else { format!("{host}:{port}") };
                ("MASTER_ADDR", host.to_string(), addr)
            }
        };
        if place.multi_node() && loopback_everywhere(&given) {
            return Err(err(
                who,
                format!(
                    "{var} is {given}, a loopback address (this very machine on every node), but the {} ranks run on more than one \
                     machine ({} here): the others could never reach rank 0; set {var} to rank 0's host name or address as the other \
                     machines reach it ({hint})",
                    place.world,
                    place.local_world.unwrap_or(0)
                ),
            ));
        }
        let timeout = match get(ENV_TIMEOUT) {
            None => DEFAULT_TIMEOUT,
            Some(t) => match t.trim().parse::<f64>() {
                Ok(s) if s > 0.0 && s.is_finite() => Duration::from_secs_f64(s),
                _ => return Err(err(ENV_TIMEOUT, format!("`{t}` is not a number of seconds"))),
            },
        };
        Ok(Self { addr, timeout })
    }
}

/// Whether `host` (a name or an address, IPv6 bracketed or not) is a loopback address on every machine:
/// `localhost` (and Debian's `ip6-localhost`/`ip6-loopback`), 127.0.0.0/8, `::1`. Machine-specific names are not
/// resolved: Debian maps a machine's own name to 127.0.1.1 there, yet the other machines reach it by that name.
pub fn loopback_everywhere(host: &str) -> bool {
    let h = host.trim().trim_start_matches('[').trim_end_matches(']').trim_end_matches('.').to_ascii_lowercase();
    ["localhost", "ip6-localhost", "ip6-loopback"].contains(&h.as_str())
        || h.ends_with(".localhost")
        || h.parse::<IpAddr>().is_ok_and(|ip| ip.to_canonical().is_loopback())
}

/// How many GPUs this process may use: `CUDA_VISIBLE_DEVICES`'s count when set (empty = none), else `count()`.
pub fn visible_gpus(get: &dyn Fn(&str) -> Option<String>, count: impl FnOnce() -> usize) -> usize {
    match get("CUDA_VISIBLE_DEVICES") {
        Some(v) => v.split(',').filter(|s| !s.trim().is_empty() && s.trim() != "-1").count(),
        None => count(),
    }
}

/// SLURM's compressed tasks-per-node list (`2(x3),1`: 2 tasks on each of nodes 0–2, then 1) at node `node`.
fn tasks_on_node(list: &str, node: usize) -> Option<usize> {
    let mut at = 0;
    for part in list.split(',') {
        let (n, reps) = match part.split_once("(x") {
            Some((n, r)) => (n.trim().parse().ok()?, r.trim_end_matches(')').parse::<usize>().ok()?),
            None => (part.trim().parse().ok()?, 1),
        };
        if node < at + reps {
            return Some(n);
        }
        at += reps;
    }
    None
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

#[cfg(test)]
mod tests {
    use super::*;

    fn place(vars: &[(&str, &str)]) -> Result<Option<Place>, LaunchError> {
        let m: std::collections::HashMap<String, String> = vars.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        Place::from_vars(&|k| m.get(k).cloned())
    }

    const SLURM_STEP: [(&str, &str); 6] =
        [("SLURM_JOB_ID", "77"), ("SLURM_STEP_ID", "0"), ("SLURM_PROCID", "9"), ("SLURM_NTASKS", "16"), ("SLURM_LOCALID", "1"), ("SLURM_NODEID", "1")];

    #[test]
    fn places_from_each_launcher() {
        assert_eq!(place(&[]).unwrap(), None);
        let p = place(&[(ENV_RANK, "2"), (ENV_WORLD, "4")]).unwrap().unwrap();
        assert_eq!((p.rank, p.world, p.launcher), (2, 4, Launcher::Project));
        let torch = [("RANK", "5"), ("WORLD_SIZE", "8"), ("LOCAL_RANK", "1"), ("LOCAL_WORLD_SIZE", "4"), ("MASTER_ADDR", "n0"), ("MASTER_PORT", "29500")];
        let p = place(&torch).unwrap().unwrap();
        assert_eq!((p.rank, p.world, p.local_rank, p.local_world, p.launcher), (5, 8, 1, Some(4), Launcher::Torchrun));
        // torchrun inside a SLURM job step: torchrun's numbers.
        let both: Vec<_> = torch.iter().chain(SLURM_STEP.iter()).copied().collect();
        assert_eq!(place(&both).unwrap().unwrap().launcher, Launcher::Torchrun);
        let mut slurm = SLURM_STEP.to_vec();
        slurm.push(("SLURM_STEP_TASKS_PER_NODE", "8(x2)"));
        let p = place(&slurm).unwrap().unwrap();
        assert_eq!((p.rank, p.world, p.local_rank, p.local_world, p.launcher), (9, 16, 1, Some(8), Launcher::Slurm));
        // The batch script (no step) is not a rank.
        let batch: Vec<_> = SLURM_STEP.iter().filter(|(k, _)| *k != "SLURM_STEP_ID").copied().collect();
        assert_eq!(place(&batch).unwrap(), None);
        let mpi = [("OMPI_COMM_WORLD_RANK", "3"), ("OMPI_COMM_WORLD_SIZE", "4"), ("OMPI_COMM_WORLD_LOCAL_RANK", "1"), ("OMPI_COMM_WORLD_LOCAL_SIZE", "2")];
        // mpirun passes no rendezvous address, and a place needs none (`eval`; training's rendezvous asks).
        let p = place(&mpi).unwrap().unwrap();
        assert_eq!((p.rank, p.world, p.local_rank, p.local_world, p.launcher), (3, 4, 1, Some(2), Launcher::Mpi));
        assert!(p.multi_node());
        let with: Vec<_> = mpi.iter().copied().chain([("MASTER_ADDR", "n0"), ("MASTER_PORT", "29600")]).collect();
        assert_eq!(place(&with).unwrap().unwrap(), p);
    }

    #[test]
    fn multi_node_when_fewer_ranks_run_here_than_in_all() {
        let p = |local_world: Option<usize>, launcher| Place { rank: 0, world: 8, local_rank: 0, local_world, launcher };
        assert!(p(Some(4), Launcher::Torchrun).multi_node());
        assert!(!p(Some(8), Launcher::Slurm).multi_node());
        assert!(!p(Some(8), Launcher::Project).multi_node());
        // The launcher did not say: not known to span machines.
        assert!(!p(None, Launcher::Mpi).multi_node());
    }

    #[test]
    fn bad_places_are_refused_by_name() {
        let e = place(&[("RANK", "x"), ("WORLD_SIZE", "2")]).unwrap_err().to_string();
        assert!(e.contains("RANK: `x` is not a number"), "{e}");
        let e = place(&[("RANK", "0"), ("WORLD_SIZE", "2")]).unwrap_err().to_string();
        assert!(e.contains("LOCAL_RANK is not set"), "{e}");
        let e = place(&[("RANK", "2"), ("WORLD_SIZE", "2"), ("LOCAL_RANK", "0")]).unwrap_err().to_string();
        assert!(e.contains("rank 2 of world size 2"), "{e}");
    }

    #[test]
    fn slurm_tasks_per_node_lists() {
        assert_eq!(tasks_on_node("4", 0), Some(4));
        assert_eq!(tasks_on_node("2(x3),1", 2), Some(2));
        assert_eq!(tasks_on_node("2(x3),1", 3), Some(1));
        assert_eq!(tasks_on_node("2(x3),1", 4), None);
    }

    #[test]
    fn gpus_one_per_rank_or_the_whole_machine() {
        let torch = |local: usize| Place { rank: 4 + local, world: 8, local_rank: local, local_world: Some(4), launcher: Launcher::Torchrun };
        assert_eq!(torch(3).gpu(1, 0).unwrap(), 0);
        assert_eq!(torch(3).gpu(4, 0).unwrap(), 3);
        assert_eq!(torch(3).gpu(8, 0).unwrap(), 3);
        let e = torch(3).gpu(2, 0).unwrap_err().to_string();
        assert!(e.contains("2 GPUs are visible") && e.contains("--gpus-per-task=1"), "{e}");
        assert!(torch(0).gpu(0, 0).unwrap_err().to_string().contains("no GPU is visible"));
        let own = Place { rank: 2, world: 4, local_rank: 2, local_world: Some(4), launcher: Launcher::Project };
        assert_eq!(own.gpu(8, 3).unwrap(), 5);
        let env = |v: &'static str| move |k: &str| (k == "CUDA_VISIBLE_DEVICES").then(|| v.to_string());
        assert_eq!(visible_gpus(&env("0,1,2"), || 8), 3);
        assert_eq!(visible_gpus(&env(""), || 8), 0);
        assert_eq!(visible_gpus(&|_| None, || 8), 8);
    }
}
