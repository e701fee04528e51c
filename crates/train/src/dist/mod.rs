//! Data parallelism as PyTorch DDP: one process per device (a *rank*), each drawing its own micro-batches; after
//! every step's backward the gradients (and the logged losses) are summed over the ranks, so every rank applies
//! the same clipped Adam step and the weights stay identical. With `world` ranks and `accumulate = k`, a step
//! equals a single process's step with `accumulate = world·k`: rank r's micro-batch m is global micro-batch
//! `r·k + m` (same examples) and every loss is divided by `world·k` (same scaling).
//!
//! Ranks come from any launcher `mvsplat360_pipeline::launch::Place` knows: this program's own `--world-size N`
//! ([`launch`], one machine), torchrun, srun, mpirun. They meet at rank 0 ([`rendezvous`]: MASTER_ADDR and a
//! port, see [`Rank::from_vars`]), which hands out the ring's addresses or the NCCL id. Backends: `nccl` (GPUs;
//! this crate's `nccl` feature) and `host` (a TCP ring through host memory, [`ring`]; any device — the CPU, or
//! GPUs without NCCL, as PyTorch's gloo). Every collective has a timeout ([`ENV_TIMEOUT`]): a dead or unreachable
//! rank stops the others with an error naming it instead of a hang.

pub mod rendezvous;
pub mod ring;

use std::net::IpAddr;
use std::process::Command;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use candle_core::{Device, Tensor};
use mvsplat360_pipeline::compute::DeviceSpec;
use mvsplat360_pipeline::launch::{Launcher, Place, Rendezvous};

use crate::error::{Result, TrainError};

pub use mvsplat360_pipeline::launch::{DEFAULT_TIMEOUT, ENV_ADDR, ENV_PORT, ENV_RANK, ENV_TIMEOUT, ENV_WORLD};
pub use ring::RingCollective;
/// `--dist-backend`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(u8)]
pub enum Backend {
    /// NCCL on CUDA devices, host on the CPU.
    #[default]
    Auto = 0,
    Host = 1,
    Nccl = 2,
}

impl std::str::FromStr for Backend {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            "host" => Ok(Self::Host),
            "nccl" => Ok(Self::Nccl),
            _ => Err(format!("`{s}` is not a backend: use auto, host or nccl")),
        }
    }
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Auto => "auto",
            Self::Host => "host",
            Self::Nccl => "nccl",
        })
    }
}

impl Backend {
    /// The backend `Auto` stands for on `device`; an error naming the fix when it cannot run there.
    pub fn resolve(self, cuda: bool) -> Result<Self> {
        let b = match self {
            Self::Auto if cuda => Self::Nccl,
            Self::Auto => Self::Host,
            b => b,
        };
        if b == Self::Nccl && !cuda {
            return Err(flag("--dist-backend", "nccl reduces GPU tensors only; use --device cuda or --dist-backend host"));
        }
        if b == Self::Nccl && !cfg!(feature = "nccl") {
            return Err(no_nccl());
        }
        Ok(b)
    }
}

/// What a build without the `nccl` feature says when asked for NCCL.
fn no_nccl() -> TrainError {
    flag(
        "--dist-backend",
        "this binary was built without NCCL: build with `--features nccl` (NCCL's library at build and run time; \
         docs/gpu.md) or pass --dist-backend host",
    )
}

fn flag(name: &str, msg: &str) -> TrainError {
    TrainError::Config { path: name.into(), msg: msg.into() }
}

fn net(what: &str, e: impl std::fmt::Display) -> TrainError {
    TrainError::Dist(format!("{what}: {e}"))
}

/// This process's place in a data-parallel run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Rank {
    pub rank: usize,
    pub world: usize,
    /// Where its launcher put it (which GPU it takes).
    pub place: Place,
    /// `host:port` of rank 0's rendezvous.
    pub rendezvous: String,
    /// For the rendezvous and for each collective.
    pub timeout: Duration,
}

impl Rank {
    /// The launcher's variables, when this process is a rank of more than one (None otherwise).
    pub fn from_env() -> Result<Option<Self>> {
        Self::from_vars(&|k| std::env::var(k).ok())
    }

    /// [`Rank::from_env`] over any variable lookup: the place and the rendezvous as
    /// `mvsplat360_pipeline::launch` reads them.
    pub fn from_vars(get: &dyn Fn(&str) -> Option<String>) -> Result<Option<Self>> {
        let Some(place) = Place::from_vars(get).map_err(|e| net("launcher", e))? else { return Ok(None) };
        if place.launcher != Launcher::Project && place.world == 1 {
            return Ok(None);
        }
        let r = Rendezvous::from_vars(&place, get).map_err(|e| TrainError::Dist(e.to_string()))?;
        Ok(Some(Self { rank: place.rank, world: place.world, place, rendezvous: r.addr, timeout: r.timeout }))
    }

    /// This rank's device for `--device`: its own GPU ([`Place::gpu`]), the CPU unchanged.
    pub fn device(&self, spec: DeviceSpec) -> Result<DeviceSpec> {
        match spec {
            DeviceSpec::Cuda(first) => {
                let visible = mvsplat360_pipeline::launch::visible_gpus(&|k| std::env::var(k).ok(), mvsplat360_pipeline::compute::cuda_device_count);
                Ok(DeviceSpec::Cuda(self.place.gpu(visible, first).map_err(|e| net("--device", e))?))
            }
            d => Ok(d),
        }
    }
}

/// Sums over the ranks.
pub trait Collective {
    fn rank(&self) -> usize;
    fn world(&self) -> usize;
    /// Every rank passes the same length; each gets the sum, added in rank order.
    fn all_reduce_f64(&mut self, v: &mut [f64]) -> Result<()>;
    /// An f32 tensor of the same shape on every rank → the sum, on the tensor's device.
    fn all_reduce_tensor(&mut self, t: &Tensor) -> Result<Tensor>;
}

/// Joins the run `rank` belongs to with `backend` (resolved), `fingerprint` naming its config (ranks with other
/// configs are refused), `dev` this rank's device.
pub fn connect(rank: &Rank, backend: Backend, fingerprint: u64, dev: &Device) -> Result<Box<dyn Collective>> {
    let ring_ip = if backend == Backend::Host { socket_ifname_ip(std::env::var("NCCL_SOCKET_IFNAME").ok().as_deref())? } else { None };
    #[cfg(feature = "nccl")]
    let make_id = nccl::new_id;
    #[cfg(not(feature = "nccl"))]
    let make_id = || Err(no_nccl());
    let j = rendezvous::join(rank, backend, fingerprint, ring_ip, make_id)?;
    match backend {
        Backend::Nccl => {
            #[cfg(feature = "nccl")]
            {
                Ok(Box::new(nccl::NcclCollective::connect(&j.nccl_id, rank.rank, rank.world, dev, rank.timeout)?))
            }
            #[cfg(not(feature = "nccl"))]
            {
                let _ = (dev, j);
                Err(no_nccl())
            }
        }
        _ if rank.world == 1 => Ok(Box::new(RingCollective::alone())),
        _ => {
            let (prev, next) = rendezvous::ring(rank, &j)?;
            Ok(Box::new(RingCollective::new(rank.rank, rank.world, prev, next, rank.timeout)?))
        }
    }
}

/// Every rank passes the same number of words; an error naming the ranks whose words differ from rank 0's
/// (`what` says what the words stand for). An all-gather through the sum: each rank fills its own slot.
pub fn check_agreement(c: &mut dyn Collective, words: &[u32], what: &str) -> Result<()> {
    let (r, w, n) = (c.rank(), c.world(), words.len());
    let mut v = vec![0f64; w * n];
    for (d, &x) in v[r * n..(r + 1) * n].iter_mut().zip(words) {
        *d = x as f64;
    }
    c.all_reduce_f64(&mut v)?;
    let slot = |i: usize| &v[i * n..(i + 1) * n];
    let differ: Vec<String> = (1..w).filter(|&i| slot(i) != slot(0)).map(|i| i.to_string()).collect();
    if differ.is_empty() {
        Ok(())
    } else {
        Err(TrainError::Dist(format!("rank(s) {} differ from rank 0 in {what}", differ.join(", "))))
    }
}

/// The IPv4 address of the first interface `NCCL_SOCKET_IFNAME` selects (NCCL's syntax: comma-separated name
/// prefixes, `=` for exact names, a leading `^` to exclude), None when unset. The `host` ring listens there.
fn socket_ifname_ip(spec: Option<&str>) -> Result<Option<IpAddr>> {
    let Some(spec) = spec.map(str::trim).filter(|s| !s.is_empty()) else { return Ok(None) };
    let ifs = interfaces();
    let pick = ifs.iter().find(|(name, ip)| !ip.is_unspecified() && ifname_matches(spec, name)).map(|(_, ip)| IpAddr::V4(*ip));
    match pick {
        Some(ip) => Ok(Some(ip)),
        None => Err(net(
            "NCCL_SOCKET_IFNAME",
            format!(
                "`{spec}` selects none of this machine's IPv4 interfaces ({})",
                ifs.iter().map(|(n, ip)| format!("{n} {ip}")).collect::<Vec<_>>().join(", ")
            ),
        )),
    }
}

fn ifname_matches(spec: &str, name: &str) -> bool {
    let (exclude, list) = match spec.strip_prefix('^') {
        Some(l) => (true, l),
        None => (false, spec),
    };
    let (exact, list) = match list.strip_prefix('=') {
        Some(l) => (true, l),
        None => (false, list),
    };
    let hit = list.split(',').map(str::trim).filter(|p| !p.is_empty()).any(|p| if exact { name == p } else { name.starts_with(p) });
    hit != exclude
}

/// This machine's IPv4 interfaces (name, address).
fn interfaces() -> Vec<(String, std::net::Ipv4Addr)> {
    let mut out = Vec::new();
    #[cfg(unix)]
    unsafe {
        let mut head: *mut libc::ifaddrs = std::ptr::null_mut();
        if libc::getifaddrs(&mut head) != 0 {
            return out;
        }
        let mut p = head;
        while !p.is_null() {
            let a = (*p).ifa_addr;
            if !a.is_null() && (*a).sa_family as i32 == libc::AF_INET {
                let sin = &*(a as *const libc::sockaddr_in);
                let name = std::ffi::CStr::from_ptr((*p).ifa_name).to_string_lossy().into_owned();
                out.push((name, std::net::Ipv4Addr::from(u32::from_be(sin.sin_addr.s_addr))));
            }
            p = (*p).ifa_next;
        }
        libc::freeifaddrs(head);
    }
    out
}

// ---------------------------------------------------------------------------------------------- launcher

/// How the ranks of [`launch`] run.
pub struct LaunchSpec {
    pub world: usize,
    /// On the CPU the ranks share the cores: each gets `RAYON_NUM_THREADS` = cores / world unless set.
    pub cpu: bool,
}

/// Starts `spec.world` ranks on this machine, `command(r)` each with its place and the rendezvous (a free port
/// on 127.0.0.1) in the environment, and waits for them (`mvsplat360_pipeline::launch::launch`: inherited stdout
/// and stderr, one SIGTERM forwarded when `stop` turns true — each rank finishes its step, rank 0 writes a
/// checkpoint —, the others killed when one fails). `Err(Interrupted)` when the ranks stopped on request.
pub fn launch(spec: &LaunchSpec, command: impl FnMut(usize) -> Command, stop: &AtomicBool) -> Result<()> {
    use mvsplat360_pipeline::launch::{self as l, LaunchError};
    let world = spec.world;
    if world == 0 {
        return Err(flag("--world-size", "must be at least 1"));
    }
    // Rank 0 listens there; the port is free now and taken again within a second.
    let port =
        std::net::TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).map_err(|e| net("launcher: finding a free port on 127.0.0.1", e))?.port();
    let env = vec![(ENV_ADDR.to_string(), format!("127.0.0.1:{port}"))];
    match l::launch(&l::LaunchSpec { world, cpu: spec.cpu, env }, command, stop) {
        Ok(()) => Ok(()),
        Err(LaunchError::Interrupted) => Err(TrainError::Interrupted),
        Err(e @ LaunchError::Failed(_)) => Err(TrainError::Dist(e.to_string())),
        Err(LaunchError::Io(m)) => Err(net("launcher", m)),
        Err(LaunchError::Rendezvous(m)) => Err(TrainError::Dist(m)),
    }
}

/// Runs this program again as `world` ranks with its arguments unchanged (each finds its place with
/// [`Rank::from_env`]) and waits for them; `cuda`: the ranks train on GPUs.
pub fn launch_self(world: usize, backend: Backend, cuda: bool, stop: &AtomicBool) -> Result<()> {
    // Refused here, before any rank starts, when the backend cannot run.
    backend.resolve(cuda)?;
    let exe = std::env::current_exe().map_err(|e| net("launcher: this program's path", e))?;
    let args: Vec<std::ffi::OsString> = std::env::args_os().skip(1).collect();
    launch(
        &LaunchSpec { world, cpu: !cuda },
        |_| {
            let mut c = Command::new(&exe);
            c.args(&args);
            c
        },
        stop,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rank(vars: &[(&str, &str)]) -> Result<Option<Rank>> {
        let m: std::collections::HashMap<String, String> = vars.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        Rank::from_vars(&|k| m.get(k).cloned())
    }

    #[test]
    fn rendezvous_address_per_launcher() {
        let torch = [("RANK", "1"), ("WORLD_SIZE", "2"), ("LOCAL_RANK", "1"), ("MASTER_ADDR", "node0"), ("MASTER_PORT", "29500")];
        let r = rank(&torch).unwrap().unwrap();
        // torchrun's store holds MASTER_PORT.
        assert_eq!((r.rank, r.world, r.rendezvous.as_str(), r.timeout), (1, 2, "node0:29501", DEFAULT_TIMEOUT));
        let with: Vec<_> = torch.iter().copied().chain([(ENV_PORT, "40000"), (ENV_TIMEOUT, "2.5")]).collect();
        let r = rank(&with).unwrap().unwrap();
        assert_eq!((r.rendezvous.as_str(), r.timeout), ("node0:40000", Duration::from_millis(2500)));
        let slurm = [
            ("SLURM_STEP_ID", "0"),
            ("SLURM_PROCID", "3"),
            ("SLURM_NTASKS", "4"),
            ("SLURM_LOCALID", "1"),
            ("MASTER_ADDR", "fe80::1"),
            ("MASTER_PORT", "29500"),
        ];
        assert_eq!(rank(&slurm).unwrap().unwrap().rendezvous, "[fe80::1]:29500");
        let e = rank(&slurm[..4]).unwrap_err().to_string();
        assert!(e.contains("MASTER_ADDR is not set") && e.contains("train.sbatch"), "{e}");
        let own = rank(&[(ENV_RANK, "0"), (ENV_WORLD, "2"), (ENV_ADDR, "127.0.0.1:5000"), ("MASTER_ADDR", "x"), ("MASTER_PORT", "1")]).unwrap().unwrap();
        assert_eq!(own.rendezvous, "127.0.0.1:5000");
        // One rank under an outside launcher is a plain process.
        assert_eq!(rank(&[("RANK", "0"), ("WORLD_SIZE", "1"), ("LOCAL_RANK", "0")]).unwrap(), None);
        let bad: Vec<_> = torch.iter().copied().chain([(ENV_TIMEOUT, "soon")]).collect();
        assert!(rank(&bad).unwrap_err().to_string().contains("MVSPLAT360_DIST_TIMEOUT"));
        let bad: Vec<_> = torch.iter().copied().filter(|(k, _)| *k != "MASTER_PORT").chain([("MASTER_PORT", "65535")]).collect();
        assert!(rank(&bad).unwrap_err().to_string().contains(ENV_PORT));
    }

    #[test]
    fn mpirun_ranks_are_told_how_to_pass_the_rendezvous() {
        let mpi = [("OMPI_COMM_WORLD_RANK", "1"), ("OMPI_COMM_WORLD_SIZE", "2"), ("OMPI_COMM_WORLD_LOCAL_RANK", "1")];
        let e = rank(&mpi).unwrap_err().to_string();
        assert!(e.contains("MASTER_ADDR is not set") && e.contains("mpirun -x MASTER_ADDR="), "{e}");
        let e = rank(&[mpi[0], mpi[1], mpi[2], ("MASTER_ADDR", "n0")]).unwrap_err().to_string();
        assert!(e.contains("MASTER_PORT is not set") && e.contains("-x MASTER_PORT="), "{e}");
        let r = rank(&[mpi[0], mpi[1], mpi[2], ("MASTER_ADDR", "n0"), ("MASTER_PORT", "29600")]).unwrap().unwrap();
        assert_eq!(r.rendezvous, "n0:29600");
    }

    #[test]
    fn a_loopback_master_addr_across_machines_is_refused() {
        // torchrun, 2 of 4 ranks here: more than one machine.
        let two_nodes = |addr: &'static str| {
            [("RANK", "2"), ("WORLD_SIZE", "4"), ("LOCAL_RANK", "0"), ("LOCAL_WORLD_SIZE", "2"), ("MASTER_ADDR", addr), ("MASTER_PORT", "29500")]
        };
        for addr in ["localhost", "LOCALHOST.", "127.0.0.1", "127.0.1.1", "::1", "[::1]", "::ffff:127.0.0.1", "ip6-localhost"] {
            let e = rank(&two_nodes(addr)).unwrap_err().to_string();
            assert!(e.contains(&format!("MASTER_ADDR is {addr}, a loopback address")), "{addr}: {e}");
            assert!(e.contains("4 ranks") && e.contains("2 here"), "{e}");
        }
        // A machine's own name (127.0.1.1 there on Debian, its address elsewhere) and real addresses are fine.
        for addr in ["node0", "10.0.0.1", "fe80::1", "localhost-node"] {
            assert!(rank(&two_nodes(addr)).is_ok(), "{addr}");
        }
        // One machine: loopback is right.
        let one = [("RANK", "1"), ("WORLD_SIZE", "2"), ("LOCAL_RANK", "1"), ("LOCAL_WORLD_SIZE", "2"), ("MASTER_ADDR", "localhost"), ("MASTER_PORT", "1")];
        assert_eq!(rank(&one).unwrap().unwrap().rendezvous, "localhost:2");
        // srun, 16 tasks on 2 nodes; this program's own variable is named when it is the one.
        let slurm = [
            ("SLURM_STEP_ID", "0"),
            ("SLURM_PROCID", "9"),
            ("SLURM_NTASKS", "16"),
            ("SLURM_LOCALID", "1"),
            ("SLURM_NODEID", "1"),
            ("SLURM_STEP_TASKS_PER_NODE", "8(x2)"),
            (ENV_ADDR, "127.0.0.1:5000"),
        ];
        let e = rank(&slurm).unwrap_err().to_string();
        assert!(e.contains("MVSPLAT360_DIST_ADDR is 127.0.0.1") && e.contains("16 ranks"), "{e}");
    }

    #[test]
    fn socket_ifname_syntax() {
        assert!(ifname_matches("eth", "eth0"));
        assert!(ifname_matches("ib,eth", "eth1"));
        assert!(!ifname_matches("=eth", "eth0"));
        assert!(ifname_matches("=eth0", "eth0"));
        assert!(!ifname_matches("^lo,docker", "lo"));
        assert!(ifname_matches("^lo,docker", "ens5"));
        assert_eq!(socket_ifname_ip(Some("=lo")).unwrap(), Some(IpAddr::V4(std::net::Ipv4Addr::LOCALHOST)));
        let e = socket_ifname_ip(Some("=no-such-if")).unwrap_err().to_string();
        assert!(e.contains("no-such-if") && e.contains("lo 127.0.0.1"), "{e}");
    }
}

// ---------------------------------------------------------------------------------------------- nccl backend

#[cfg(feature = "nccl")]
mod nccl {
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::Arc;
    use std::time::{Duration, Instant};

    use candle_core::backend::BackendStorage;
    use candle_core::cuda_backend::cudarc::nccl::safe::{Comm, Id, ReduceOp};
    use candle_core::{CpuStorage, CudaStorage, CustomOp1, DType, Device, Layout, Shape, Tensor};

    use super::{net, Collective};
    use crate::error::Result;

    pub fn new_id() -> Result<Vec<u8>> {
        let id = Id::new().map_err(|e| net("NCCL unique id", format!("{e:?}")))?;
        Ok(id.internal().iter().map(|&c| c as u8).collect())
    }

    /// Comm holds a raw communicator; each rank is one process that uses it from its training thread only.
    struct Shared(Comm);
    unsafe impl Send for Shared {}
    unsafe impl Sync for Shared {}

    pub struct NcclCollective {
        comm: Arc<Shared>,
        dev: Device,
        watch: Watchdog,
    }

    /// NCCL waits forever for a peer that died: a collective (or the init) that outlasts the timeout ends this
    /// process with an error instead, as PyTorch's NCCL watchdog does.
    struct Watchdog {
        since_ms: Arc<AtomicU64>,
        t0: Instant,
    }

    impl Watchdog {
        fn new(rank: usize, timeout: Duration) -> Self {
            let since_ms = Arc::new(AtomicU64::new(0));
            let (s, t0) = (since_ms.clone(), Instant::now());
            std::thread::spawn(move || loop {
                std::thread::sleep(Duration::from_millis(500));
                let at = s.load(Ordering::SeqCst);
                if at > 0 && t0.elapsed().as_millis() as u64 > at + timeout.as_millis() as u64 {
                    eprintln!(
                        "error: rank {rank}: an NCCL collective waited more than {} s ({}): a rank died or hangs, or its machine is unreachable",
                        timeout.as_secs(),
                        super::ENV_TIMEOUT
                    );
                    std::process::exit(1);
                }
            });
            Self { since_ms, t0 }
        }
        fn guard<T>(&self, f: impl FnOnce() -> T) -> T {
            self.since_ms.store(self.t0.elapsed().as_millis() as u64 + 1, Ordering::SeqCst);
            let r = f();
            self.since_ms.store(0, Ordering::SeqCst);
            r
        }
    }

    impl NcclCollective {
        pub fn connect(bytes: &[u8], rank: usize, world: usize, dev: &Device, timeout: Duration) -> Result<Self> {
            if bytes.len() != 128 {
                return Err(net("NCCL unique id", format!("{} bytes from rank 0 where NCCL makes 128", bytes.len())));
            }
            let mut internal = [0 as std::ffi::c_char; 128];
            for (d, s) in internal.iter_mut().zip(bytes) {
                *d = *s as std::ffi::c_char;
            }
            let Device::Cuda(cuda) = dev else { return Err(net("nccl", "the rank's device is not a GPU")) };
            let watch = Watchdog::new(rank, timeout);
            let comm = watch
                .guard(|| Comm::from_rank(cuda.cuda_stream(), rank, world, Id::uninit(internal)))
                .map_err(|e| net(&format!("rank {rank}: NCCL init"), format!("{e:?}")))?;
            Ok(Self { comm: Arc::new(Shared(comm)), dev: dev.clone(), watch })
        }
    }

    struct AllReduce(Arc<Shared>);

    impl CustomOp1 for AllReduce {
        fn name(&self) -> &'static str {
            "nccl-all-reduce"
        }
        fn cpu_fwd(&self, _: &CpuStorage, _: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
            candle_core::bail!("NCCL reduces GPU tensors only")
        }
        fn cuda_fwd(&self, s: &CudaStorage, l: &Layout) -> candle_core::Result<(CudaStorage, Shape)> {
            let Some((a, b)) = l.contiguous_offsets() else { candle_core::bail!("nccl all-reduce needs a contiguous tensor") };
            let err = |e| candle_core::Error::Msg(format!("NCCL all-reduce: {e:?}"));
            let out = match s.dtype() {
                DType::F32 => {
                    let src = s.as_cuda_slice::<f32>()?.slice(a..b);
                    let mut dst = s.device.alloc_zeros::<f32>(b - a)?;
                    self.0 .0.all_reduce(&src, &mut dst, &ReduceOp::Sum).map_err(err)?;
                    CudaStorage::wrap_cuda_slice(dst, s.device.clone())
                }
                DType::F64 => {
                    let src = s.as_cuda_slice::<f64>()?.slice(a..b);
                    let mut dst = s.device.alloc_zeros::<f64>(b - a)?;
                    self.0 .0.all_reduce(&src, &mut dst, &ReduceOp::Sum).map_err(err)?;
                    CudaStorage::wrap_cuda_slice(dst, s.device.clone())
                }
                d => candle_core::bail!("nccl all-reduce of {d:?}"),
            };
            Ok((out, l.shape().clone()))
        }
    }

    impl Collective for NcclCollective {
        fn rank(&self) -> usize {
            self.comm.0.rank()
        }
        fn world(&self) -> usize {
            self.comm.0.world_size()
        }
        fn all_reduce_f64(&mut self, v: &mut [f64]) -> Result<()> {
            let t = Tensor::from_slice(v, v.len(), &self.dev)?;
            let comm = self.comm.clone();
            let r: Vec<f64> = self.watch.guard(|| t.apply_op1_no_bwd(&AllReduce(comm))?.to_vec1())?;
            v.copy_from_slice(&r);
            Ok(())
        }
        fn all_reduce_tensor(&mut self, t: &Tensor) -> Result<Tensor> {
            let (comm, dev) = (self.comm.clone(), self.dev.clone());
            // Waited for here, so that the watchdog sees a collective that never completes.
            Ok(self.watch.guard(|| {
                let r = t.to_dtype(DType::F32)?.contiguous()?.apply_op1_no_bwd(&AllReduce(comm))?;
                dev.synchronize()?;
                Ok::<_, candle_core::Error>(r)
            })?)
        }
    }
}
