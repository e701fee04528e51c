//! Data parallelism as PyTorch DDP: one process per device (a *rank*), each drawing its own micro-batches; after
//! every step's backward the gradients (and the logged losses) are summed over the ranks, so every rank applies
//! the same clipped Adam step and the weights stay identical. With `world` ranks and `accumulate = k`, a step
//! equals a single process's step with `accumulate = world·k`: rank r's micro-batch m is global micro-batch
//! `r·k + m` (same examples) and every loss is divided by `world·k` (same scaling).
//!
//! Backends: `nccl` (GPUs; candle's `nccl` feature, this crate's `nccl` feature) and `host` (TCP through the
//! launching process, gradients through host memory; any device — the CPU, or GPUs without NCCL, as PyTorch's
//! gloo). [`launch`] starts the ranks as child processes of one binary with the pipeline's launcher
//! (`mvsplat360_pipeline::launch`, which `eval --world-size` uses too) and passes each its place and link through
//! the environment ([`ENV_RANK`] …); a child finds them with [`Rank::from_env`].

use std::io::{BufReader, BufWriter, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::process::Command;
use std::sync::atomic::AtomicBool;

use candle_core::{DType, Device, Tensor};

use crate::error::{Result, TrainError};

pub use mvsplat360_pipeline::launch::{ENV_RANK, ENV_WORLD};
/// `host` backend: the launcher's address (`127.0.0.1:PORT`).
pub const ENV_HUB: &str = "MVSPLAT360_DIST_HUB";
/// `nccl` backend: the NCCL unique id made by the launcher, hex.
pub const ENV_NCCL_ID: &str = "MVSPLAT360_DIST_NCCL_ID";

/// `--dist-backend`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Backend {
    /// NCCL on CUDA devices, host on the CPU.
    #[default]
    Auto,
    Host,
    Nccl,
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
         README, GPU) or pass --dist-backend host",
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
    pub link: Link,
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Link {
    /// `host`: the hub's address.
    Hub(String),
    /// `nccl`: the unique id, hex.
    NcclId(String),
}

impl Rank {
    /// The launcher's variables, when this process is a rank (None when it is not).
    pub fn from_env() -> Result<Option<Self>> {
        let Some(place) = mvsplat360_pipeline::launch::Place::from_env().map_err(|e| net("launcher", e))? else { return Ok(None) };
        if place.launcher != mvsplat360_pipeline::launch::Launcher::Project && place.world == 1 {
            return Ok(None);
        }
        if place.launcher != mvsplat360_pipeline::launch::Launcher::Project {
            return Err(net(
                place.launcher.name(),
                format!(
                    "this process is rank {} of {} under {}, but training across separately started processes has no rendezvous yet; \
                     train on one machine with `train --world-size N` (evaluation does run under {})",
                    place.rank,
                    place.world,
                    place.launcher.name(),
                    place.launcher.name()
                ),
            ));
        }
        let (rank, world) = (place.rank, place.world);
        let link = match (std::env::var(ENV_HUB), std::env::var(ENV_NCCL_ID)) {
            (Ok(a), _) => Link::Hub(a),
            (_, Ok(id)) => Link::NcclId(id),
            _ => return Err(net(ENV_HUB, format!("neither {ENV_HUB} nor {ENV_NCCL_ID} is set"))),
        };
        Ok(Some(Self { rank, world, link }))
    }
}

/// A fresh NCCL unique id (hex), as the launcher makes for its ranks.
#[cfg(feature = "nccl")]
pub fn nccl_unique_id() -> Result<String> {
    nccl::new_id_hex()
}

/// Sums over the ranks.
pub trait Collective {
    fn rank(&self) -> usize;
    fn world(&self) -> usize;
    /// Every rank passes the same length; each gets the sum, added in rank order.
    fn all_reduce_f64(&mut self, v: &mut [f64]) -> Result<()>;
    /// A 1-D f32 tensor of the same length on every rank → the sum, on the tensor's device.
    fn all_reduce_tensor(&mut self, t: &Tensor) -> Result<Tensor>;
}

/// Joins the run described by `rank`, with `dev` this rank's device.
pub fn connect(rank: &Rank, dev: &Device) -> Result<Box<dyn Collective>> {
    match &rank.link {
        Link::Hub(addr) => Ok(Box::new(HostCollective::connect(addr, rank.rank, rank.world)?)),
        Link::NcclId(id) => {
            #[cfg(feature = "nccl")]
            {
                Ok(Box::new(nccl::NcclCollective::connect(id, rank.rank, rank.world, dev)?))
            }
            #[cfg(not(feature = "nccl"))]
            {
                let _ = (id, dev);
                Err(no_nccl())
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------- host backend

const KIND_F32: u8 = 0;
const KIND_F64: u8 = 1;

/// A rank's connection to the launcher's hub.
pub struct HostCollective {
    rank: usize,
    world: usize,
    r: BufReader<TcpStream>,
    w: BufWriter<TcpStream>,
}

impl HostCollective {
    pub fn connect(addr: &str, rank: usize, world: usize) -> Result<Self> {
        let s = TcpStream::connect(addr).map_err(|e| net(&format!("rank {rank}: connecting to the launcher at {addr}"), e))?;
        let _ = s.set_nodelay(true);
        let mut w = BufWriter::new(s.try_clone().map_err(|e| net("socket", e))?);
        w.write_all(&(rank as u32).to_le_bytes())
            .and_then(|_| w.write_all(&(world as u32).to_le_bytes()))
            .and_then(|_| w.flush())
            .map_err(|e| net("handshake", e))?;
        Ok(Self { rank, world, r: BufReader::new(s), w })
    }

    fn round(&mut self, kind: u8, payload: &[u8]) -> Result<Vec<u8>> {
        let lost = |e: std::io::Error| net(&format!("rank {}: lost the launcher (another rank failed or was stopped)", self.rank), e);
        write_frame(&mut self.w, kind, payload).map_err(lost)?;
        let (k, back) = read_frame(&mut self.r).map_err(lost)?.ok_or_else(|| lost(std::io::ErrorKind::UnexpectedEof.into()))?;
        if k != kind || back.len() != payload.len() {
            return Err(net("host all-reduce", "the ranks sent different amounts (they run different configs?)"));
        }
        Ok(back)
    }
}

impl Collective for HostCollective {
    fn rank(&self) -> usize {
        self.rank
    }
    fn world(&self) -> usize {
        self.world
    }
    fn all_reduce_f64(&mut self, v: &mut [f64]) -> Result<()> {
        let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        let back = self.round(KIND_F64, &bytes)?;
        for (x, c) in v.iter_mut().zip(back.chunks_exact(8)) {
            *x = f64::from_le_bytes(c.try_into().expect("8 bytes"));
        }
        Ok(())
    }
    fn all_reduce_tensor(&mut self, t: &Tensor) -> Result<Tensor> {
        let host: Vec<f32> = t.to_dtype(DType::F32)?.to_device(&Device::Cpu)?.to_vec1()?;
        let bytes: Vec<u8> = host.iter().flat_map(|x| x.to_le_bytes()).collect();
        let back = self.round(KIND_F32, &bytes)?;
        let sum: Vec<f32> = back.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))).collect();
        Ok(Tensor::from_vec(sum, host.len(), &Device::Cpu)?.to_device(t.device())?)
    }
}

fn write_frame(w: &mut impl Write, kind: u8, payload: &[u8]) -> std::io::Result<()> {
    w.write_all(&[kind])?;
    w.write_all(&(payload.len() as u64).to_le_bytes())?;
    w.write_all(payload)?;
    w.flush()
}

/// None at a clean end of stream (the rank finished).
fn read_frame(r: &mut impl Read) -> std::io::Result<Option<(u8, Vec<u8>)>> {
    let mut kind = [0u8; 1];
    loop {
        // A stop signal landing during the wait must not end the run (read_exact retries by itself).
        match r.read(&mut kind) {
            Ok(0) => return Ok(None),
            Ok(_) => break,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        }
    }
    let mut n = [0u8; 8];
    r.read_exact(&mut n)?;
    let n = u64::from_le_bytes(n) as usize;
    if n > 1 << 34 {
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidData, format!("frame of {n} bytes")));
    }
    let mut p = vec![0u8; n];
    r.read_exact(&mut p)?;
    Ok(Some((kind[0], p)))
}

/// The launcher's side of the host backend: accepts `world` ranks, then answers every round with the sum of
/// what the ranks sent, added in rank order. Returns when every rank has closed its connection; an error (and
/// every connection closed, so that no rank waits forever) when one leaves mid-run or the ranks disagree.
pub fn serve_hub(listener: TcpListener, world: usize) -> Result<()> {
    let mut conns: Vec<Option<(BufReader<TcpStream>, BufWriter<TcpStream>)>> = (0..world).map(|_| None).collect();
    for _ in 0..world {
        let (s, _) = listener.accept().map_err(|e| net("hub accept", e))?;
        let _ = s.set_nodelay(true);
        let mut r = BufReader::new(s.try_clone().map_err(|e| net("socket", e))?);
        let mut hs = [0u8; 8];
        r.read_exact(&mut hs).map_err(|e| net("hub handshake", e))?;
        let rank = u32::from_le_bytes(hs[..4].try_into().expect("4")) as usize;
        let w = u32::from_le_bytes(hs[4..].try_into().expect("4")) as usize;
        if w != world || rank >= world || conns[rank].is_some() {
            return Err(net("hub handshake", format!("rank {rank} of {w} joined a run of {world} ranks")));
        }
        conns[rank] = Some((r, BufWriter::new(s)));
    }
    let mut conns: Vec<_> = conns.into_iter().map(|c| c.expect("every rank joined")).collect();
    loop {
        let mut frames = Vec::with_capacity(world);
        for (rank, (r, _)) in conns.iter_mut().enumerate() {
            frames.push((rank, read_frame(r)));
        }
        if frames.iter().all(|(_, f)| matches!(f, Ok(None))) {
            return Ok(());
        }
        let mut got = Vec::with_capacity(world);
        for (rank, f) in frames {
            match f {
                Ok(Some(x)) => got.push(x),
                Ok(None) => return Err(net("hub", format!("rank {rank} left the run early"))),
                Err(e) => return Err(net(&format!("hub: rank {rank}"), e)),
            }
        }
        let (kind, len) = (got[0].0, got[0].1.len());
        if got.iter().any(|(k, p)| *k != kind || p.len() != len) {
            return Err(net("hub", "the ranks sent different amounts (they run different configs?)"));
        }
        let parts = got.iter().map(|(_, p)| p.as_slice());
        let sum: Vec<u8> = match kind {
            KIND_F32 => sum_le(parts, f32::from_le_bytes, f32::to_le_bytes),
            KIND_F64 => sum_le(parts, f64::from_le_bytes, f64::to_le_bytes),
            k => return Err(net("hub", format!("unknown frame kind {k}"))),
        };
        for (rank, (_, w)) in conns.iter_mut().enumerate() {
            write_frame(w, kind, &sum).map_err(|e| net(&format!("hub: rank {rank}"), e))?;
        }
    }
}

/// Element-wise sum of little-endian buffers of one number type, added in the order given.
fn sum_le<'a, T: std::ops::AddAssign + Copy, const N: usize>(
    mut parts: impl Iterator<Item = &'a [u8]>,
    from: fn([u8; N]) -> T,
    to: fn(T) -> [u8; N],
) -> Vec<u8> {
    let read = |c: &[u8]| from(c.try_into().expect("N bytes"));
    let mut acc: Vec<T> = parts.next().map(|p| p.chunks_exact(N).map(read).collect()).unwrap_or_default();
    for p in parts {
        for (a, c) in acc.iter_mut().zip(p.chunks_exact(N)) {
            *a += read(c);
        }
    }
    acc.into_iter().flat_map(to).collect()
}

// ---------------------------------------------------------------------------------------------- launcher

/// How the ranks of [`launch`] run.
pub struct LaunchSpec {
    pub world: usize,
    /// Resolved (`Host` or `Nccl`).
    pub backend: Backend,
    /// On the CPU the ranks share the cores: each gets `RAYON_NUM_THREADS` = cores / world unless set.
    pub cpu: bool,
}

/// Starts `spec.world` ranks, `command(r)` each with its place and the backend's link in the environment, and
/// waits for them (`mvsplat360_pipeline::launch::launch`: inherited stdout and stderr, one SIGTERM forwarded
/// when `stop` turns true — each rank finishes its step, rank 0 writes a checkpoint —, the others killed when
/// one fails). `Err(Interrupted)` when the ranks stopped on request.
pub fn launch(spec: &LaunchSpec, command: impl FnMut(usize) -> Command, stop: &AtomicBool) -> Result<()> {
    use mvsplat360_pipeline::launch::{self as l, LaunchError};
    let world = spec.world;
    if world == 0 {
        return Err(flag("--world-size", "must be at least 1"));
    }
    let mut env: Vec<(String, String)> = Vec::new();
    let hub = match spec.backend {
        Backend::Nccl => {
            #[cfg(feature = "nccl")]
            env.push((ENV_NCCL_ID.into(), nccl::new_id_hex()?));
            #[cfg(not(feature = "nccl"))]
            return Err(no_nccl());
            #[cfg(feature = "nccl")]
            None
        }
        _ => {
            let l = TcpListener::bind("127.0.0.1:0").map_err(|e| net("launcher: listening on 127.0.0.1", e))?;
            env.push((ENV_HUB.into(), l.local_addr().map_err(|e| net("launcher", e))?.to_string()));
            Some(std::thread::spawn(move || serve_hub(l, world)))
        }
    };
    let interrupted = match l::launch(&l::LaunchSpec { world, cpu: spec.cpu, env }, command, stop) {
        Ok(()) => false,
        Err(LaunchError::Interrupted) => true,
        Err(e @ LaunchError::Failed(_)) => return Err(TrainError::Dist(e.to_string())),
        Err(LaunchError::Io(m)) => return Err(net("launcher", m)),
    };
    if let Some(h) = hub {
        // Every rank exited: the hub has seen every connection close.
        match h.join() {
            Ok(Err(e)) if !interrupted => return Err(e),
            Err(_) => return Err(net("launcher", "the hub thread panicked")),
            _ => {}
        }
    }
    if interrupted {
        return Err(TrainError::Interrupted);
    }
    Ok(())
}

/// Runs this program again as `world` ranks with its arguments unchanged (each finds its place with
/// [`Rank::from_env`]) and waits for them; `cuda`: the ranks train on GPUs.
pub fn launch_self(world: usize, backend: Backend, cuda: bool, stop: &AtomicBool) -> Result<()> {
    let exe = std::env::current_exe().map_err(|e| net("launcher: this program's path", e))?;
    let args: Vec<std::ffi::OsString> = std::env::args_os().skip(1).collect();
    let spec = LaunchSpec { world, backend: backend.resolve(cuda)?, cpu: !cuda };
    launch(
        &spec,
        |_| {
            let mut c = Command::new(&exe);
            c.args(&args);
            c
        },
        stop,
    )
}

// ---------------------------------------------------------------------------------------------- nccl backend

#[cfg(feature = "nccl")]
mod nccl {
    use std::sync::Arc;

    use candle_core::backend::BackendStorage;
    use candle_core::cuda_backend::cudarc::nccl::safe::{Comm, Id, ReduceOp};
    use candle_core::{CpuStorage, CudaStorage, CustomOp1, DType, Device, Layout, Shape, Tensor};

    use super::{net, Collective};
    use crate::error::Result;

    pub fn new_id_hex() -> Result<String> {
        let id = Id::new().map_err(|e| net("NCCL unique id", format!("{e:?}")))?;
        Ok(id.internal().iter().map(|&c| format!("{:02x}", c as u8)).collect())
    }

    /// Comm holds a raw communicator; each rank is one process that uses it from its training thread only.
    struct Shared(Comm);
    unsafe impl Send for Shared {}
    unsafe impl Sync for Shared {}

    pub struct NcclCollective {
        comm: Arc<Shared>,
        dev: Device,
    }

    impl NcclCollective {
        pub fn connect(hex: &str, rank: usize, world: usize, dev: &Device) -> Result<Self> {
            let bytes: Vec<u8> = (0..hex.len() / 2).filter_map(|i| u8::from_str_radix(hex.get(2 * i..2 * i + 2)?, 16).ok()).collect();
            if bytes.len() != 128 {
                return Err(net(super::ENV_NCCL_ID, "not a 128-byte hex id"));
            }
            let mut internal = [0 as std::ffi::c_char; 128];
            for (d, s) in internal.iter_mut().zip(&bytes) {
                *d = *s as std::ffi::c_char;
            }
            let Device::Cuda(cuda) = dev else { return Err(net("nccl", "the rank's device is not a GPU")) };
            let comm = Comm::from_rank(cuda.cuda_stream(), rank, world, Id::uninit(internal))
                .map_err(|e| net(&format!("rank {rank}: NCCL init"), format!("{e:?}")))?;
            Ok(Self { comm: Arc::new(Shared(comm)), dev: dev.clone() })
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
            let r: Vec<f64> = t.apply_op1_no_bwd(&AllReduce(self.comm.clone()))?.to_vec1()?;
            v.copy_from_slice(&r);
            Ok(())
        }
        fn all_reduce_tensor(&mut self, t: &Tensor) -> Result<Tensor> {
            Ok(t.to_dtype(DType::F32)?.contiguous()?.apply_op1_no_bwd(&AllReduce(self.comm.clone()))?)
        }
    }
}
