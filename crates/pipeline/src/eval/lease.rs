//! Per-scene leases in `--out/scenes/`, so that any number of processes on one output folder (cluster ranks,
//! array jobs on several nodes, a rerun next to a running job) render each scene once, with no rendezvous.
//!
//! A lease is the file `KEY.lease-G` created exclusively (`O_EXCL`, which NFS honours too), holding the owner's
//! record ([`Owner`]: pid, host, start time); its mtime is the owner's heartbeat, refreshed while it holds the
//! lease. The scene's current lease is its highest generation G. It is stale when its owner is on this host and
//! dead (gone, a zombie, or its pid now another process's: [`Owner::state`]; taken over at once), or when its
//! heartbeat is older than [`STALE_AFTER`] (an owner on another host that stopped). Taking over creates
//! generation G + 1 exclusively, so of several processes that find the same stale lease exactly one wins.
//! A lease is removed once its scene's record (or failure) is written.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime};

pub use mvsplat360_dataset::owner::Owner;
use mvsplat360_dataset::owner::State;

/// How often a holder refreshes its leases.
pub const HEARTBEAT: Duration = Duration::from_secs(20);
/// A lease whose heartbeat is older is stale, whoever holds it.
pub const STALE_AFTER: Duration = Duration::from_secs(180);

/// A lease's owner whose record is not written yet, or is garbled.
fn unknown() -> Owner {
    Owner { pid: 0, host: "?".into(), start: None }
}

/// The outcome of [`Leases::claim`].
#[derive(Debug, PartialEq, Eq)]
pub enum Claim {
    /// This process holds the scene now.
    Mine,
    /// A live process holds it.
    Held(Owner),
}

/// The leases this process holds in one folder, refreshed by a background thread while it lives.
pub struct Leases {
    dir: PathBuf,
    held: Arc<Mutex<BTreeSet<PathBuf>>>,
    stop: Arc<std::sync::atomic::AtomicBool>,
}

fn lease_files(dir: &Path, key: &str) -> Vec<(u64, PathBuf)> {
    let prefix = format!("{key}.lease-");
    let mut v: Vec<(u64, PathBuf)> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let g = name.strip_prefix(&prefix)?.parse::<u64>().ok()?;
            Some((g, e.path()))
        })
        .collect();
    v.sort();
    v
}

impl Leases {
    pub fn new(dir: &Path) -> Self {
        let held: Arc<Mutex<BTreeSet<PathBuf>>> = Arc::default();
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (h, s) = (held.clone(), stop.clone());
        std::thread::spawn(move || {
            let tick = Duration::from_millis(250);
            let mut waited = Duration::ZERO;
            while !s.load(std::sync::atomic::Ordering::Relaxed) {
                std::thread::sleep(tick);
                waited += tick;
                if waited >= HEARTBEAT {
                    waited = Duration::ZERO;
                    for p in h.lock().unwrap_or_else(|e| e.into_inner()).iter() {
                        if let Ok(f) = std::fs::File::options().write(true).open(p) {
                            let _ = f.set_modified(SystemTime::now());
                        }
                    }
                }
            }
        });
        Self { dir: dir.to_path_buf(), held, stop }
    }

    /// Takes `key` when no live process holds it (never blocks).
    pub fn claim(&self, key: &str) -> std::io::Result<Claim> {
        self.claim_with(key, STALE_AFTER)
    }

    fn claim_with(&self, key: &str, stale_after: Duration) -> std::io::Result<Claim> {
        let current = lease_files(&self.dir, key).pop();
        let next = match &current {
            None => 0,
            Some((g, path)) => {
                let text = std::fs::read_to_string(path).unwrap_or_default();
                let owner = Owner::parse(&text);
                let age = std::fs::metadata(path).and_then(|m| m.modified()).ok().and_then(|t| SystemTime::now().duration_since(t).ok());
                // Just created and not yet written: its creator is alive.
                let dead_here = owner.as_ref().is_some_and(|o| !o.is_me() && o.state() == State::Dead);
                let expired = age.is_some_and(|a| a > stale_after);
                if !(dead_here || expired) {
                    return Ok(Claim::Held(owner.unwrap_or_else(unknown)));
                }
                g + 1
            }
        };
        let path = self.dir.join(format!("{key}.lease-{next}"));
        match std::fs::File::options().write(true).create_new(true).open(&path) {
            Ok(mut f) => {
                use std::io::Write;
                let me = Owner::me();
                f.write_all(format!("{}\n", me.record()).as_bytes())?;
                self.held.lock().unwrap_or_else(|e| e.into_inner()).insert(path);
                // Older generations are dead weight now.
                for (g, p) in lease_files(&self.dir, key) {
                    if g < next {
                        let _ = std::fs::remove_file(p);
                    }
                }
                Ok(Claim::Mine)
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                let text = std::fs::read_to_string(&path).unwrap_or_default();
                Ok(Claim::Held(Owner::parse(&text).unwrap_or_else(unknown)))
            }
            Err(e) => Err(e),
        }
    }

    /// Gives `key` up (its record or failure is written).
    pub fn release(&self, key: &str) {
        let mut held = self.held.lock().unwrap_or_else(|e| e.into_inner());
        for (_, p) in lease_files(&self.dir, key) {
            if held.remove(&p) {
                let _ = std::fs::remove_file(&p);
            }
        }
    }
}

impl Drop for Leases {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        for p in std::mem::take(&mut *self.held.lock().unwrap_or_else(|e| e.into_inner())) {
            let _ = std::fs::remove_file(p);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mvsplat360_dataset::owner::host_name;

    #[test]
    fn one_holder_and_takeover_of_dead_or_expired_owners() {
        let d = tempfile::tempdir().unwrap();
        let a = Leases::new(d.path());
        let b = Leases::new(d.path());
        assert_eq!(a.claim("s1").unwrap(), Claim::Mine);
        // Another claimant (here in the same process, so not "dead"): held, by this pid.
        assert_eq!(b.claim("s1").unwrap(), Claim::Held(Owner::me()));
        a.release("s1");
        assert!(lease_files(d.path(), "s1").is_empty());
        assert_eq!(b.claim("s1").unwrap(), Claim::Mine);
        b.release("s1");

        // A dead owner on this host (a pid beyond the kernel's maximum; the older `HOST PID` form): taken over at
        // once, as generation 1.
        std::fs::write(d.path().join("s2.lease-0"), format!("{} 4294967295\n", host_name())).unwrap();
        assert_eq!(a.claim("s2").unwrap(), Claim::Mine);
        let files: Vec<u64> = lease_files(d.path(), "s2").into_iter().map(|x| x.0).collect();
        assert_eq!(files, [1]);
        // A live process on this host (the test's parent) under another start time: its pid was reused, the
        // owner is dead.
        let pid = std::os::unix::process::parent_id();
        if let Ok(Some(st)) = mvsplat360_dataset::owner::proc_stat(pid) {
            let boot = mvsplat360_dataset::owner::boot_id().unwrap_or("");
            std::fs::write(d.path().join("s4.lease-0"), format!("{pid} {} {boot}:{}\n", host_name(), st.start_ticks + 1)).unwrap();
            assert_eq!(a.claim("s4").unwrap(), Claim::Mine);
            std::fs::write(d.path().join("s5.lease-0"), format!("{pid} {} {boot}:{}\n", host_name(), st.start_ticks)).unwrap();
            assert!(matches!(a.claim("s5").unwrap(), Claim::Held(o) if o.pid == pid));
        }
        // A live owner on another host: held until its heartbeat is older than the limit.
        std::fs::write(d.path().join("s3.lease-4"), "node-b 77\n").unwrap();
        assert_eq!(a.claim("s3").unwrap(), Claim::Held(Owner { host: "node-b".into(), pid: 77, start: None }));
        let old = SystemTime::now() - Duration::from_secs(10);
        std::fs::File::options().write(true).open(d.path().join("s3.lease-4")).unwrap().set_modified(old).unwrap();
        assert_eq!(a.claim_with("s3", Duration::from_secs(5)).unwrap(), Claim::Mine);
        assert_eq!(lease_files(d.path(), "s3").into_iter().map(|x| x.0).collect::<Vec<_>>(), [5]);
        // Dropping the holder removes what it holds.
        drop(a);
        assert!(lease_files(d.path(), "s2").is_empty() && lease_files(d.path(), "s3").is_empty());
    }

    #[test]
    fn of_many_racing_for_a_stale_lease_one_wins() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("s.lease-0"), format!("{} 4294967295\n", host_name())).unwrap();
        let dir = d.path().to_path_buf();
        let wins: usize = (0..8)
            .map(|_| {
                let dir = dir.clone();
                std::thread::spawn(move || {
                    let l = Leases::new(&dir);
                    let won = l.claim("s").unwrap() == Claim::Mine;
                    // Keep the lease while the others try.
                    std::thread::sleep(Duration::from_millis(200));
                    std::mem::forget(l);
                    won as usize
                })
            })
            .collect::<Vec<_>>()
            .into_iter()
            .map(|h| h.join().unwrap())
            .sum();
        assert_eq!(wins, 1);
    }
}
