//! Rendezvous: rank 0 listens at the run's address (MASTER_ADDR and a port, [`super::Rank`]); every other rank
//! connects (retrying until the timeout, as ranks start in any order), says who it is, which backend and which
//! config it runs, and where its ring listener is. When all have joined, rank 0 answers each with the ring's
//! addresses, a token that only this run's ranks know (a stray connection is refused) and, for NCCL, the unique
//! id it made. Then the `host` ranks connect their ring ([`ring`]); NCCL does its own bootstrap from the id.

use std::io::{Read, Write};
use std::net::{IpAddr, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use super::{net, Backend, Rank, ENV_PORT, ENV_TIMEOUT};
use crate::error::{Result, TrainError};

const MAGIC: &[u8; 8] = b"MVS360R1";
const OK: u8 = 0;
const REFUSED: u8 = 1;

/// What a rank knows once everyone has joined.
pub struct Joined {
    /// Ring listener addresses, by rank (`host` backend with more than one rank).
    pub peers: Vec<String>,
    pub token: u64,
    /// The NCCL unique id (empty for `host`).
    pub nccl_id: Vec<u8>,
    /// This rank's ring listener.
    pub ring: Option<TcpListener>,
}

/// The IPv4 (else first) address `host:port` names.
pub fn resolve(addr: &str) -> Result<SocketAddr> {
    let all: Vec<SocketAddr> = addr.to_socket_addrs().map_err(|e| net(&format!("rendezvous address {addr}"), e))?.collect();
    all.iter().find(|a| a.is_ipv4()).or(all.first()).copied().ok_or_else(|| net(&format!("rendezvous address {addr}"), "names no address"))
}

/// Joins the run: rank 0 serves, the others connect. `ring_ip`: where this rank's ring listener binds when not on
/// the interface that reaches rank 0 (`NCCL_SOCKET_IFNAME`). `nccl_id` is called on rank 0 for the NCCL backend.
pub fn join(rank: &Rank, backend: Backend, fingerprint: u64, ring_ip: Option<IpAddr>, nccl_id: impl FnOnce() -> Result<Vec<u8>>) -> Result<Joined> {
    let deadline = Instant::now() + rank.timeout;
    let addr = resolve(&rank.rendezvous)?;
    let wants_ring = backend == Backend::Host && rank.world > 1;
    if rank.rank == 0 {
        let l = TcpListener::bind(addr).map_err(|e| bind_error(rank, addr, e))?;
        let ring = if wants_ring { Some(bind_ring(ring_ip.unwrap_or(addr.ip()))?) } else { None };
        let nccl_id = if backend == Backend::Nccl { nccl_id()? } else { Vec::new() };
        let token: u64 = rand::random();
        let own = Hello { rank: 0, world: rank.world, backend: backend as u8, fingerprint, ring: ring_addr(ring.as_ref())? };
        let peers = serve(rank, &l, &own, token, &nccl_id, deadline)?;
        return Ok(Joined { peers, token, nccl_id, ring });
    }
    let mut s = connect_until(addr, deadline).map_err(|e| {
        TrainError::Dist(format!(
            "rank {}: could not reach rank 0 at {} ({addr}) within {} s: {e}; is rank 0 running there and the port open? \
             (MASTER_ADDR, MASTER_PORT, {ENV_PORT}, {ENV_TIMEOUT})",
            rank.rank,
            rank.rendezvous,
            rank.timeout.as_secs()
        ))
    })?;
    // The interface that routes to rank 0 is the one the ring uses, unless told otherwise.
    let local = s.local_addr().map_err(|e| net("socket", e))?.ip();
    let ring = if wants_ring { Some(bind_ring(ring_ip.unwrap_or(local))?) } else { None };
    let hello = Hello { rank: rank.rank, world: rank.world, backend: backend as u8, fingerprint, ring: ring_addr(ring.as_ref())? };
    let lost = |e: std::io::Error| TrainError::Dist(format!("rank {}: rendezvous with rank 0 at {addr}: {e}", rank.rank));
    hello.write(&mut s).map_err(lost)?;
    // Rank 0 answers when the last rank has joined.
    s.set_read_timeout(Some(deadline.saturating_duration_since(Instant::now()) + Duration::from_secs(10))).map_err(lost)?;
    let mut m = [0u8; 9];
    s.read_exact(&mut m).map_err(lost)?;
    if &m[..8] != MAGIC {
        return Err(lost(std::io::Error::other("the answer is not a rendezvous (another program listens there?)")));
    }
    if m[8] == REFUSED {
        let why = read_str(&mut s).map_err(lost)?;
        return Err(TrainError::Dist(format!("rank {}: rank 0 ({addr}) ended the rendezvous: {why}", rank.rank)));
    }
    let token = read_u64(&mut s).map_err(lost)?;
    let n = read_u32(&mut s).map_err(lost)? as usize;
    if n != rank.world {
        return Err(lost(std::io::Error::other(format!("{n} peers for {} ranks", rank.world))));
    }
    let peers = (0..n).map(|_| read_str(&mut s)).collect::<std::io::Result<Vec<_>>>().map_err(lost)?;
    let nccl_id = read_bytes(&mut s).map_err(lost)?;
    Ok(Joined { peers, token, nccl_id, ring })
}

/// The `host` ring: this rank's connection from rank r−1 and to rank r+1.
pub fn ring(rank: &Rank, j: &Joined) -> Result<(TcpStream, TcpStream)> {
    let deadline = Instant::now() + rank.timeout;
    let (r, w) = (rank.rank, rank.world);
    let (next, prev) = ((r + 1) % w, (r + w - 1) % w);
    let at = &j.peers[next];
    let mut out = connect_until(resolve(at)?, deadline).map_err(|e| {
        TrainError::Dist(format!(
            "rank {r}: could not reach rank {next}'s ring listener at {at} within {} s: {e} (a firewall between the machines?)",
            rank.timeout.as_secs()
        ))
    })?;
    let mut hs = j.token.to_le_bytes().to_vec();
    hs.extend_from_slice(&(r as u32).to_le_bytes());
    out.write_all(&hs).map_err(|e| net(&format!("rank {r}: ring handshake with rank {next} at {at}"), e))?;
    let l = j.ring.as_ref().expect("a ring listener");
    l.set_nonblocking(true).map_err(|e| net("socket", e))?;
    loop {
        match l.accept() {
            Ok((mut s, _)) => {
                let _ = s.set_nonblocking(false);
                let _ = s.set_read_timeout(Some(Duration::from_secs(10)));
                let mut b = [0u8; 12];
                if s.read_exact(&mut b).is_ok()
                    && u64::from_le_bytes(b[..8].try_into().expect("8")) == j.token
                    && u32::from_le_bytes(b[8..].try_into().expect("4")) as usize == prev
                {
                    let _ = s.set_read_timeout(None);
                    return Ok((s, out));
                }
                // Not this run's rank r−1: ignore it.
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if Instant::now() >= deadline {
                    return Err(TrainError::Dist(format!(
                        "rank {r}: rank {prev} did not connect its ring to {} within {} s",
                        ring_addr(Some(l))?,
                        rank.timeout.as_secs()
                    )));
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            Err(e) => return Err(net(&format!("rank {r}: ring accept"), e)),
        }
    }
}

struct Hello {
    rank: usize,
    world: usize,
    backend: u8,
    fingerprint: u64,
    ring: String,
}

impl Hello {
    fn write(&self, s: &mut TcpStream) -> std::io::Result<()> {
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&(self.rank as u32).to_le_bytes());
        b.extend_from_slice(&(self.world as u32).to_le_bytes());
        b.push(self.backend);
        b.extend_from_slice(&self.fingerprint.to_le_bytes());
        put_str(&mut b, &self.ring);
        s.write_all(&b)
    }
    fn read(s: &mut TcpStream) -> std::io::Result<Self> {
        let mut m = [0u8; 8];
        s.read_exact(&mut m)?;
        if &m != MAGIC {
            return Err(std::io::Error::other("not a rank of this program"));
        }
        let rank = read_u32(s)? as usize;
        let world = read_u32(s)? as usize;
        let mut b = [0u8; 1];
        s.read_exact(&mut b)?;
        Ok(Self { rank, world, backend: b[0], fingerprint: read_u64(s)?, ring: read_str(s)? })
    }
}

fn backend_name(b: u8) -> &'static str {
    match b {
        x if x == Backend::Host as u8 => "host",
        x if x == Backend::Nccl as u8 => "nccl",
        _ => "?",
    }
}

/// Rank 0: accepts the other ranks until all have joined or the deadline passes; the ring addresses by rank.
fn serve(rank: &Rank, l: &TcpListener, own: &Hello, token: u64, nccl_id: &[u8], deadline: Instant) -> Result<Vec<String>> {
    let world = rank.world;
    let mut joined: Vec<Option<(TcpStream, Hello)>> = (0..world).map(|_| None).collect();
    let mut count = 1;
    l.set_nonblocking(true).map_err(|e| net("socket", e))?;
    let refuse = |s: &mut TcpStream, why: &str| {
        let mut b = MAGIC.to_vec();
        b.push(REFUSED);
        put_str(&mut b, why);
        let _ = s.write_all(&b);
    };
    let refuse_all = |joined: &mut Vec<Option<(TcpStream, Hello)>>, why: &str| {
        for (s, _) in joined.iter_mut().flatten() {
            refuse(s, why);
        }
        TrainError::Dist(format!("rank 0: {why}"))
    };
    while count < world {
        match l.accept() {
            Ok((mut s, from)) => {
                let _ = s.set_nonblocking(false);
                let _ = s.set_read_timeout(Some(Duration::from_secs(10)));
                let Ok(h) = Hello::read(&mut s) else { continue };
                let why = if h.world != world {
                    Some(format!("rank {} ({from}) was started as one of {} ranks, rank 0 as one of {world}", h.rank, h.world))
                } else if h.rank == 0 || h.rank >= world || joined[h.rank].is_some() {
                    Some(format!("two processes claim rank {} ({from}); every rank must be started once", h.rank))
                } else if h.backend != own.backend {
                    Some(format!("rank {} ({from}) uses --dist-backend {}, rank 0 {}", h.rank, backend_name(h.backend), backend_name(own.backend)))
                } else if h.fingerprint != own.fingerprint {
                    Some(format!("rank {} ({from}) runs another config than rank 0 (every rank must read the same config)", h.rank))
                } else {
                    None
                };
                if let Some(why) = why {
                    refuse(&mut s, &why);
                    return Err(refuse_all(&mut joined, &why));
                }
                let r = h.rank;
                joined[r] = Some((s, h));
                count += 1;
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if Instant::now() >= deadline {
                    let missing: Vec<String> = (1..world).filter(|&r| joined[r].is_none()).map(|r| r.to_string()).collect();
                    let why = format!(
                        "rank(s) {} of {world} did not join at {} within {} s ({ENV_TIMEOUT}): are they started, with MASTER_ADDR naming this machine?",
                        missing.join(", "),
                        rank.rendezvous,
                        rank.timeout.as_secs()
                    );
                    return Err(refuse_all(&mut joined, &why));
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            Err(e) => return Err(net("rank 0: accepting ranks", e)),
        }
    }
    let mut peers = vec![own.ring.clone()];
    peers.extend(joined.iter().skip(1).map(|j| j.as_ref().expect("joined").1.ring.clone()));
    let mut b = MAGIC.to_vec();
    b.push(OK);
    b.extend_from_slice(&token.to_le_bytes());
    b.extend_from_slice(&(world as u32).to_le_bytes());
    for p in &peers {
        put_str(&mut b, p);
    }
    b.extend_from_slice(&(nccl_id.len() as u32).to_le_bytes());
    b.extend_from_slice(nccl_id);
    for (r, (s, _)) in joined.iter_mut().enumerate().filter_map(|(r, j)| Some((r, j.as_mut()?))) {
        s.write_all(&b).map_err(|e| net(&format!("rank 0: answering rank {r}"), e))?;
    }
    Ok(peers)
}

fn bind_error(rank: &Rank, addr: SocketAddr, e: std::io::Error) -> TrainError {
    let why = match e.kind() {
        std::io::ErrorKind::AddrNotAvailable => {
            format!("{} is not an address of this machine, where rank 0 runs: MASTER_ADDR must name rank 0's host", addr.ip())
        }
        std::io::ErrorKind::AddrInUse => format!(
            "port {} is in use (under torchrun MASTER_PORT is torchrun's own, and training takes MASTER_PORT + 1): set {ENV_PORT} to a free port",
            addr.port()
        ),
        _ => e.to_string(),
    };
    TrainError::Dist(format!("rank 0: listening for the other ranks at {} ({addr}): {why}", rank.rendezvous))
}

fn bind_ring(ip: IpAddr) -> Result<TcpListener> {
    TcpListener::bind((ip, 0)).map_err(|e| net(&format!("listening for the ring on {ip}"), e))
}

fn ring_addr(l: Option<&TcpListener>) -> Result<String> {
    l.map(|l| l.local_addr().map(|a| a.to_string()).map_err(|e| net("socket", e))).transpose().map(Option::unwrap_or_default)
}

/// Connects, retrying while nothing listens yet (ranks start in any order), until `deadline`.
fn connect_until(addr: SocketAddr, deadline: Instant) -> std::io::Result<TcpStream> {
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match TcpStream::connect_timeout(&addr, left.clamp(Duration::from_millis(100), Duration::from_secs(5))) {
            Ok(s) => return Ok(s),
            Err(e) if Instant::now() >= deadline => return Err(e),
            Err(_) => std::thread::sleep(Duration::from_millis(100)),
        }
    }
}

fn put_str(b: &mut Vec<u8>, s: &str) {
    b.extend_from_slice(&(s.len() as u32).to_le_bytes());
    b.extend_from_slice(s.as_bytes());
}

fn read_u32(s: &mut impl Read) -> std::io::Result<u32> {
    let mut b = [0u8; 4];
    s.read_exact(&mut b)?;
    Ok(u32::from_le_bytes(b))
}

fn read_u64(s: &mut impl Read) -> std::io::Result<u64> {
    let mut b = [0u8; 8];
    s.read_exact(&mut b)?;
    Ok(u64::from_le_bytes(b))
}

fn read_bytes(s: &mut impl Read) -> std::io::Result<Vec<u8>> {
    let n = read_u32(s)? as usize;
    if n > 1 << 16 {
        return Err(std::io::Error::other(format!("a field of {n} bytes")));
    }
    let mut b = vec![0u8; n];
    s.read_exact(&mut b)?;
    Ok(b)
}

fn read_str(s: &mut impl Read) -> std::io::Result<String> {
    String::from_utf8(read_bytes(s)?).map_err(|_| std::io::Error::other("not UTF-8"))
}
