//! Rendezvous: rank 0 listens at the run's port (MASTER_ADDR and a port, [`super::Rank`]); every other rank
//! connects (retrying until the timeout, as ranks start in any order), says who it is, which backend and which
//! config it runs, and where its ring listener is. When all have joined, rank 0 answers each with the ring's
//! addresses, a token that only this run's ranks know (a stray connection is refused) and, for NCCL, the unique
//! id it made. Then the `host` ranks connect their ring ([`ring`]); NCCL does its own bootstrap from the id.
//!
//! Rank 0's listeners, and every ring listener unless `NCCL_SOCKET_IFNAME` names an interface, are bound to the
//! wildcard address (of MASTER_ADDR's family): what MASTER_ADDR resolves to on rank 0's machine need not be where
//! the others reach it (Debian's `/etc/hosts` maps a machine's own name to 127.0.1.1). A wildcard ring listener
//! is handed out as rank 0 saw its rank: at the address its rendezvous connection came from, or — on rank 0's
//! machine, come over loopback — at the address where each peer reached rank 0 ([`ring_for`]).

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
        let l = listen(rank, addr)?;
        let ring = if wants_ring { Some(bind_ring(ring_ip, addr.ip())?) } else { None };
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
    // Rank 0 fills in where the others reach this rank's ring (the address it saw this connection come from).
    let local = s.local_addr().map_err(|e| net("socket", e))?.ip();
    let ring = if wants_ring { Some(bind_ring(ring_ip, local)?) } else { None };
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
    let mut joined: Vec<Option<Peer>> = (0..world).map(|_| None).collect();
    let mut count = 1;
    l.set_nonblocking(true).map_err(|e| net("socket", e))?;
    let refuse = |s: &mut TcpStream, why: &str| {
        let mut b = MAGIC.to_vec();
        b.push(REFUSED);
        put_str(&mut b, why);
        let _ = s.write_all(&b);
    };
    let refuse_all = |joined: &mut Vec<Option<Peer>>, why: &str| {
        for p in joined.iter_mut().flatten() {
            refuse(&mut p.stream, why);
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
                // Both ends as the kernel reports them; an IPv4 peer of an IPv6 listener as IPv4.
                let via = s.local_addr().map(|a| a.ip().to_canonical()).map_err(|e| net("rank 0: socket", e))?;
                let r = h.rank;
                joined[r] = Some(Peer { stream: s, hello: h, from: from.ip().to_canonical(), via });
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
    let joined: Vec<Peer> = joined.into_iter().skip(1).map(|j| j.expect("joined")).collect();
    // Rank q's ring as seen by a rank that reached rank 0 at `via` (None: rank 0 itself).
    let peers_for = |via: Option<IpAddr>| -> Vec<String> {
        std::iter::once(ring_for(&own.ring, None, via)).chain(joined.iter().map(|p| ring_for(&p.hello.ring, Some(p.from), via))).collect()
    };
    for (r, p) in joined.iter().enumerate().map(|(i, p)| (i + 1, p)) {
        let mut b = MAGIC.to_vec();
        b.push(OK);
        b.extend_from_slice(&token.to_le_bytes());
        b.extend_from_slice(&(world as u32).to_le_bytes());
        for a in peers_for(Some(p.via)) {
            put_str(&mut b, &a);
        }
        b.extend_from_slice(&(nccl_id.len() as u32).to_le_bytes());
        b.extend_from_slice(nccl_id);
        (&p.stream).write_all(&b).map_err(|e| net(&format!("rank 0: answering rank {r}"), e))?;
    }
    Ok(peers_for(None))
}

/// A rank that has joined: its connection, what it said, where it came from and where it reached rank 0.
struct Peer {
    stream: TcpStream,
    hello: Hello,
    from: IpAddr,
    via: IpAddr,
}

/// Where a rank's ring listener that said `advertised` is reached by another rank. A concrete address stands
/// (`NCCL_SOCKET_IFNAME`); a wildcard one is filled in: `from`, the address the listener's rank came from to
/// rank 0 (None for rank 0 itself), when that is another machine's; else — the listener is on rank 0's machine —
/// `via`, the address at which the asking rank reached rank 0 (None: rank 0 asks, and `from` or loopback serves).
fn ring_for(advertised: &str, from: Option<IpAddr>, via: Option<IpAddr>) -> String {
    let Ok(a) = advertised.parse::<SocketAddr>() else { return advertised.to_string() };
    if !a.ip().is_unspecified() {
        return advertised.to_string();
    }
    let ip = match (from, via) {
        (Some(f), _) if !f.is_loopback() => f,
        (_, Some(v)) => v,
        (Some(f), None) => f,
        (None, None) if a.is_ipv4() => IpAddr::V4(std::net::Ipv4Addr::LOCALHOST),
        (None, None) => IpAddr::V6(std::net::Ipv6Addr::LOCALHOST),
    };
    SocketAddr::new(ip, a.port()).to_string()
}

/// Rank 0's rendezvous listener: on every address at MASTER_ADDR's port, once MASTER_ADDR is known to name this
/// machine (else the others would knock at another one until their timeout).
fn listen(rank: &Rank, addr: SocketAddr) -> Result<TcpListener> {
    TcpListener::bind((addr.ip(), 0)).map_err(|e| bind_error(rank, addr, e))?;
    let any = SocketAddr::new(unspecified(addr.ip()), addr.port());
    TcpListener::bind(any).map_err(|e| bind_error(rank, any, e))
}

fn unspecified(like: IpAddr) -> IpAddr {
    match like {
        IpAddr::V4(_) => IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED),
        IpAddr::V6(_) => IpAddr::V6(std::net::Ipv6Addr::UNSPECIFIED),
    }
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

/// The ring listener: on `ring_ip` (`NCCL_SOCKET_IFNAME`) when given, else on every address of `family`'s kind.
fn bind_ring(ring_ip: Option<IpAddr>, family: IpAddr) -> Result<TcpListener> {
    let ip = ring_ip.unwrap_or(unspecified(family));
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dist::{Collective, RingCollective};
    use mvsplat360_pipeline::launch::{Launcher, Place};

    fn rank(r: usize, at: &str, port: u16) -> Rank {
        let place = Place { rank: r, world: 2, local_rank: r, local_world: Some(2), launcher: Launcher::Torchrun };
        Rank { rank: r, world: 2, place, rendezvous: format!("{at}:{port}"), timeout: Duration::from_secs(20) }
    }

    /// Joins as `r` and sums over the ring: what it was handed out, its ring listener, the sum.
    fn run(r: Rank) -> Result<(Vec<String>, SocketAddr, f64)> {
        let j = join(&r, Backend::Host, 7, None, || Ok(Vec::new()))?;
        let own = j.ring.as_ref().expect("a ring").local_addr().map_err(|e| net("socket", e))?;
        let (prev, next) = ring(&r, &j)?;
        let mut c = RingCollective::new(r.rank, r.world, prev, next, r.timeout)?;
        let mut v = [r.rank as f64 + 1.0];
        c.all_reduce_f64(&mut v)?;
        Ok((j.peers, own, v[0]))
    }

    /// As on Debian: MASTER_ADDR, rank 0's own name, resolves to 127.0.1.1 on its machine, while rank 1 reaches
    /// that machine at another address (127.0.0.3 stands for the LAN address): rank 0 listens on every address,
    /// and hands out its ring at the address rank 1 came to.
    #[test]
    fn rank_0_listens_on_the_wildcard_address_and_hands_out_the_address_reached() {
        let port = TcpListener::bind("0.0.0.0:0").unwrap().local_addr().unwrap().port();
        let r0 = std::thread::spawn(move || run(rank(0, "127.0.1.1", port)).map_err(|e| e.to_string()));
        let (peers1, ring1, sum1) = run(rank(1, "127.0.0.3", port)).unwrap();
        let (peers0, ring0, sum0) = r0.join().unwrap().unwrap();
        assert_eq!((sum0, sum1), (3.0, 3.0));
        assert!(ring0.ip().is_unspecified() && ring1.ip().is_unspecified(), "{ring0} {ring1}");
        assert_eq!(peers1[0], format!("127.0.0.3:{}", ring0.port()));
        let at: SocketAddr = peers0[1].parse().unwrap();
        assert!(at.ip().is_loopback() && at.port() == ring1.port(), "{peers0:?}");
        // Where MASTER_ADDR is not this machine's, rank 0 says so at once.
        let e = join(&rank(0, "192.0.2.1", port), Backend::Host, 7, None, || Ok(Vec::new())).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("not an address of this machine"), "{e}");
    }

    #[test]
    fn ring_addresses_each_rank_can_reach() {
        let ip = |s: &str| Some(s.parse::<IpAddr>().unwrap());
        // Rank 0's wildcard ring: where the asking rank reached it.
        assert_eq!(ring_for("0.0.0.0:4000", None, ip("10.0.0.1")), "10.0.0.1:4000");
        // A rank on another machine: where it came from, for everyone.
        assert_eq!(ring_for("0.0.0.0:4001", ip("10.0.0.7"), ip("10.0.0.1")), "10.0.0.7:4001");
        assert_eq!(ring_for("0.0.0.0:4001", ip("10.0.0.7"), None), "10.0.0.7:4001");
        // A rank beside rank 0 that came over loopback (127.0.1.1): where the asking rank reached rank 0's machine.
        assert_eq!(ring_for("0.0.0.0:4002", ip("127.0.1.1"), ip("10.0.0.1")), "10.0.0.1:4002");
        assert_eq!(ring_for("0.0.0.0:4002", ip("127.0.1.1"), None), "127.0.1.1:4002");
        assert_eq!(ring_for("[::]:4003", ip("::1"), ip("fd00::1")), "[fd00::1]:4003");
        // NCCL_SOCKET_IFNAME's address stands.
        assert_eq!(ring_for("192.168.5.5:4004", ip("10.0.0.7"), ip("10.0.0.1")), "192.168.5.5:4004");
        assert_eq!(ring_for("", None, ip("10.0.0.1")), "");
    }
}
