//! The `host` backend's all-reduce: the ranks form a ring (rank r sends to r+1, rank W−1 to rank 0) and the
//! buffer travels in chunks, so no process carries more than twice the buffer and none carries everyone's.
//! Chunk k's partial sum starts at rank 0 and picks up each rank's part in rank order ((g0 + g1) + g2 …, the
//! order one process accumulating its micro-batches adds in); rank W−1 then holds the total and sends it on
//! round the ring to ranks 0 … W−2. Every rank ends with the same bits. Chunks are pipelined: rank r forwards
//! chunk k while rank r−1 is already sending chunk k+1. Sends go through a writer thread, so a rank never blocks
//! writing while its predecessor waits for it to read (with blocking writes the ring would deadlock once the
//! socket buffers fill).

use std::io::{BufReader, BufWriter, Read, Write};
use std::net::TcpStream;
use std::sync::mpsc;
use std::time::Duration;

use candle_core::{DType, Device, Tensor};

use super::{net, Collective};
use crate::error::{Result, TrainError};

/// Elements per chunk: large enough that per-frame costs vanish, small enough to pipeline.
const CHUNK: usize = 1 << 18;

const PARTIAL: u8 = 1;
const TOTAL: u8 = 2;

/// One rank's place in the ring: a stream from its predecessor, a writer thread to its successor.
pub struct RingCollective {
    rank: usize,
    world: usize,
    links: Option<Links>,
    timeout: Duration,
}

struct Links {
    prev: BufReader<TcpStream>,
    prev_addr: String,
    tx: mpsc::Sender<Vec<u8>>,
    next_addr: String,
    writer: Option<std::thread::JoinHandle<std::io::Result<()>>>,
}

impl RingCollective {
    /// World size 1: every all-reduce is the identity.
    pub fn alone() -> Self {
        Self { rank: 0, world: 1, links: None, timeout: Duration::ZERO }
    }

    /// `prev`: the connection from rank r−1; `next`: the one to rank r+1 (both already checked by the
    /// rendezvous). `timeout`: how long a rank waits for its predecessor's next frame.
    pub fn new(rank: usize, world: usize, prev: TcpStream, next: TcpStream, timeout: Duration) -> Result<Self> {
        let addr = |s: &TcpStream| s.peer_addr().map(|a| a.to_string()).unwrap_or_else(|_| "?".into());
        let (prev_addr, next_addr) = (addr(&prev), addr(&next));
        for s in [&prev, &next] {
            let _ = s.set_nodelay(true);
        }
        prev.set_read_timeout(Some(timeout)).map_err(|e| net("socket", e))?;
        next.set_write_timeout(Some(timeout)).map_err(|e| net("socket", e))?;
        let (tx, rx) = mpsc::channel::<Vec<u8>>();
        let writer = std::thread::Builder::new()
            .name(format!("ring-send-{rank}"))
            .spawn(move || {
                let mut w = BufWriter::with_capacity(1 << 20, next);
                for frame in rx {
                    w.write_all(&frame)?;
                    w.flush()?;
                }
                Ok(())
            })
            .map_err(|e| net("ring writer thread", e))?;
        Ok(Self { rank, world, links: Some(Links { prev: BufReader::with_capacity(1 << 20, prev), prev_addr, tx, next_addr, writer: Some(writer) }), timeout })
    }

    fn prev_rank(&self) -> usize {
        (self.rank + self.world - 1) % self.world
    }
    fn next_rank(&self) -> usize {
        (self.rank + 1) % self.world
    }

    /// The error for a frame that did not come from rank r−1.
    fn lost_prev(&self, e: std::io::Error) -> TrainError {
        let (p, addr) = (self.prev_rank(), self.links.as_ref().map_or("?", |l| l.prev_addr.as_str()));
        let why = match e.kind() {
            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => {
                format!("nothing from rank {p} ({addr}) for {} s (MVSPLAT360_DIST_TIMEOUT): a rank hangs or its machine is unreachable", self.timeout.as_secs())
            }
            std::io::ErrorKind::UnexpectedEof | std::io::ErrorKind::ConnectionReset => {
                format!("rank {p} ({addr}) left the run (it failed or was stopped; its own message says why)")
            }
            _ => format!("rank {p} ({addr}): {e}"),
        };
        TrainError::Dist(format!("rank {}: {why}", self.rank))
    }

    fn send(&mut self, frame: Vec<u8>) -> Result<()> {
        let (rank, next) = (self.rank, self.next_rank());
        let l = self.links.as_mut().expect("links");
        if l.tx.send(frame).is_ok() {
            return Ok(());
        }
        // The writer stopped: say why.
        let why = match l.writer.take().map(|h| h.join()) {
            Some(Ok(Err(e))) => e.to_string(),
            _ => "the connection closed".into(),
        };
        Err(TrainError::Dist(format!("rank {rank}: sending to rank {next} ({}): {why} (it failed or was stopped?)", l.next_addr)))
    }

    /// The next frame from rank r−1, which must be `phase` of chunk `k` of a `total`-element buffer of `kind`.
    fn recv(&mut self, kind: u8, phase: u8, total: u64, k: u32, len: usize, elem: usize) -> Result<Vec<u8>> {
        let mut head = [0u8; 18];
        let r = &mut self.links.as_mut().expect("links").prev;
        if let Err(e) = read_full(r, &mut head) {
            return Err(self.lost_prev(e));
        }
        let (fk, fp) = (head[0], head[1]);
        let ft = u64::from_le_bytes(head[2..10].try_into().expect("8"));
        let fc = u32::from_le_bytes(head[10..14].try_into().expect("4"));
        let fl = u32::from_le_bytes(head[14..18].try_into().expect("4")) as usize;
        if fk != kind || ft != total {
            return Err(TrainError::Dist(format!(
                "rank {}: rank {} all-reduces {ft} values of kind {fk} where this rank has {total} of kind {kind}: the ranks run different configs or code",
                self.rank,
                self.prev_rank()
            )));
        }
        if fp != phase || fc != k || fl != len {
            return Err(TrainError::Dist(format!("rank {}: out-of-order frame from rank {} (phase {fp}, chunk {fc})", self.rank, self.prev_rank())));
        }
        let mut p = vec![0u8; len * elem];
        let r = &mut self.links.as_mut().expect("links").prev;
        if let Err(e) = read_full(r, &mut p) {
            return Err(self.lost_prev(e));
        }
        Ok(p)
    }

    fn all_reduce<T: Elem>(&mut self, v: &mut [T]) -> Result<()> {
        if self.world == 1 {
            return Ok(());
        }
        let (rank, world) = (self.rank, self.world);
        let total = v.len() as u64;
        let chunks = v.len().div_ceil(CHUNK).max(1);
        let n = v.len();
        let range = move |k: usize| k * CHUNK..((k + 1) * CHUNK).min(n);
        for k in 0..chunks {
            let r = range(k);
            if rank > 0 {
                let p = self.recv(T::KIND, PARTIAL, total, k as u32, r.len(), T::SIZE)?;
                for (x, c) in v[r.clone()].iter_mut().zip(p.chunks_exact(T::SIZE)) {
                    // The ranks before this one first: rank order.
                    *x = T::from_le(c).add(*x);
                }
            }
            let phase = if rank == world - 1 { TOTAL } else { PARTIAL };
            self.send(frame(T::KIND, phase, total, k as u32, &v[r]))?;
        }
        if rank == world - 1 {
            return Ok(());
        }
        for k in 0..chunks {
            let r = range(k);
            let p = self.recv(T::KIND, TOTAL, total, k as u32, r.len(), T::SIZE)?;
            for (x, c) in v[r.clone()].iter_mut().zip(p.chunks_exact(T::SIZE)) {
                *x = T::from_le(c);
            }
            if rank + 2 < world {
                self.send(frame(T::KIND, TOTAL, total, k as u32, &v[r]))?;
            }
        }
        Ok(())
    }
}

impl Drop for RingCollective {
    fn drop(&mut self) {
        // Let the writer drain what is queued (the successor may still need it), then close.
        if let Some(mut l) = self.links.take() {
            drop(l.tx);
            if let Some(h) = l.writer.take() {
                let _ = h.join();
            }
        }
    }
}

impl Collective for RingCollective {
    fn rank(&self) -> usize {
        self.rank
    }
    fn world(&self) -> usize {
        self.world
    }
    fn all_reduce_f64(&mut self, v: &mut [f64]) -> Result<()> {
        self.all_reduce(v)
    }
    fn all_reduce_tensor(&mut self, t: &Tensor) -> Result<Tensor> {
        let mut host: Vec<f32> = t.to_dtype(DType::F32)?.flatten_all()?.to_device(&Device::Cpu)?.to_vec1()?;
        self.all_reduce(&mut host)?;
        Ok(Tensor::from_vec(host, t.elem_count(), &Device::Cpu)?.reshape(t.dims())?.to_device(t.device())?)
    }
}

/// `read_exact` that survives a signal landing during the wait (a stop request must not end the run).
fn read_full(r: &mut impl Read, mut buf: &mut [u8]) -> std::io::Result<()> {
    while !buf.is_empty() {
        match r.read(buf) {
            Ok(0) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
            Ok(n) => buf = &mut buf[n..],
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

fn frame<T: Elem>(kind: u8, phase: u8, total: u64, k: u32, v: &[T]) -> Vec<u8> {
    let mut f = Vec::with_capacity(18 + v.len() * T::SIZE);
    f.push(kind);
    f.push(phase);
    f.extend_from_slice(&total.to_le_bytes());
    f.extend_from_slice(&k.to_le_bytes());
    f.extend_from_slice(&(v.len() as u32).to_le_bytes());
    for x in v {
        x.put_le(&mut f);
    }
    f
}

trait Elem: Copy {
    const KIND: u8;
    const SIZE: usize;
    fn from_le(b: &[u8]) -> Self;
    fn put_le(self, out: &mut Vec<u8>);
    fn add(self, o: Self) -> Self;
}

impl Elem for f32 {
    const KIND: u8 = 0;
    const SIZE: usize = 4;
    fn from_le(b: &[u8]) -> Self {
        f32::from_le_bytes(b.try_into().expect("4 bytes"))
    }
    fn put_le(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes())
    }
    fn add(self, o: Self) -> Self {
        self + o
    }
}

impl Elem for f64 {
    const KIND: u8 = 1;
    const SIZE: usize = 8;
    fn from_le(b: &[u8]) -> Self {
        f64::from_le_bytes(b.try_into().expect("8 bytes"))
    }
    fn put_le(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes())
    }
    fn add(self, o: Self) -> Self {
        self + o
    }
}
